"""Spherical Gaussian fit of the rough dielectric BTDF and BRDF lobes (de Rousiers 2012, sec. 3.1).

For a view direction at polar angle ``theta_o`` from the normal of one interface, relative
index ``eta`` (the index on the far side over the index on the view side: ``ior`` when
entering glass, ``1 / ior`` when leaving it), roughness ``alpha`` and NDF (Beckmann or GGX),
the transmitted lobe ``f_t(w_o, w_i) |cos theta_i|`` over incident directions ``w_i`` is
replaced by one spherical Gaussian (the paper's eq. 8)::

    SG(w) = a * exp(k * (dot(p, w) - 1))

stored in a table ``T(theta_o, eta, alpha) -> (a, k, p)`` (eq. 9). The reflected lobe
(rough front reflection) is fitted the same way.

The table is fitted offline (moment matching of energy, axis and sharpness over a
deterministic quadrature of microfacet normals, plus an L2-optimal second sharpness) by
:mod:`torchrefract.optics.sg_fit`; this module holds the table, its storage and cache, and
the lookups a render makes.

Table layout and conventions (``SGTable.data``: float32, shape ``(2, 2, T, E, A, 4)``):

- dims: distribution (0 beckmann, 1 ggx), lobe (0 transmit, 1 reflect), ``theta_o``,
  ``eta``, ``alpha``; channels :data:`CHANNELS` = ``(energy, log_sharpness,
  axis_polar_angle, log_sharpness_l2)``.
- ``theta_o``: uniform in ``[0, 90]`` degrees (the last node holds the grazing limit,
  evaluated at ``cos theta_o = 1e-4``). ``eta``: log-spaced in ``[1/3, 3]``, contains 1
  exactly and every ``1/eta`` of its nodes. ``alpha``: log-spaced in ``[1e-3, 1]``.
- axis: with the view direction ``w_o = (sin theta_o, 0, cos theta_o)`` in the interface's
  frame (``z`` = normal on the view side) the lobe axis is
  ``(-sin t, 0, -cos t)`` for transmission and ``(-sin t, 0, cos t)`` for reflection, with
  ``t`` the stored signed angle: ``t = theta_t`` (Snell) and ``t = theta_o`` (mirror) for
  smooth surfaces. :func:`lobe_axis` builds the 3D axis from it.
- TIR: where the transmitted energy is below :data:`ENERGY_EPS` (beyond the critical angle
  for ``eta < 1`` and small ``alpha``: all microfacets reflect totally) the transmit entry
  stores energy exactly 0 (so amplitude 0) and carries the sharpness and axis of the
  nearest smaller ``theta_o`` that transmits, so lookups stay continuous. Rough surfaces do
  transmit some light beyond the critical angle (microfacets tilted towards the viewer);
  that energy is kept. For ``eta == 1`` the reflect entry has energy 0 and the shape of
  the Fresnel-free microfacet reflection lobe; the transmit lobe is a Dirac
  (sharpness :data:`K_MAX`) whose energy is below 1 by the masking-shadowing loss.

Lookup: :func:`sg_lookup` interpolates (energy, log k, sin of the axis angle) trilinearly
in ``(theta_o, log eta, log alpha)`` and is differentiable w.r.t. all three. The sine is
interpolated rather than the angle because Snell's law is linear in it: near critical
angles and across ``eta`` nodes this cuts the axis interpolation error of sharp lobes
from up to 4.5 to 0.8 degrees (measured at cell centres for alpha = 1e-3). For
``alpha < 1e-3`` it keeps the energy and axis of ``alpha = 1e-3`` and extrapolates
``k ∝ 1/alpha^2`` (the small-roughness asymptote), capped at :data:`K_MAX`; for
``alpha > 1`` it clamps.

Example:
    >>> import torch
    >>> from torchrefract.optics.sgfit import load_sg_table, sg_lookup
    >>> table = load_sg_table()                      # shipped file (or cached / built once)
    >>> a, k, t, e = sg_lookup(table, torch.tensor([0.8]), torch.tensor([1.5]),
    ...                        torch.tensor([0.1]), "beckmann")
"""

from __future__ import annotations

import functools
import logging
import math
import sys
from pathlib import Path

import torch

from torchrefract.kernels.index import broadcast_shape
from torchrefract.optics import microfacet as mf
from torchrefract.optics.sg_fit import build_sg_table
from torchrefract.optics.sg_table import (
    K_MAX,
    K_MIN,
    LOBES,
    SHIPPED_TABLE,
    SGTable,
    SGTableSpec,
    read_sg_table,
    save_sg_table,
)
from torchrefract.optics.smooth import dot, fresnel_dielectric

log = logging.getLogger(__name__)

def default_cache_dir() -> Path:
    """The current settings' cache folder (:func:`torchrefract.settings.cache_folder`)."""
    from torchrefract.settings import cache_folder  # noqa: PLC0415

    return cache_folder()


@functools.lru_cache(maxsize=4)
def _load_cached(spec: SGTableSpec, cache_dir: str) -> SGTable:
    """The cached table (load_sg_table took the shipped one where it is ``spec``'s), else a
    table fitted now and cached."""
    if spec == SGTableSpec() and SHIPPED_TABLE.is_file():
        log.warning("%s was built for another spec; ignoring it", SHIPPED_TABLE)
    path = Path(cache_dir) / f"sg_table_{spec.key()}.npz"
    if path.is_file():
        try:
            return read_sg_table(path)
        except (OSError, ValueError, KeyError) as exc:
            log.warning("ignoring unreadable SG table cache %s (%s)", path, exc)
    msg = (f"torchrefract: building the spherical Gaussian BTDF table (spec key "
           f"{spec.key()}); this happens once and takes several minutes on a CPU "
           f"(the default spec: ~6 min on 1 core); it will be cached at {path}")
    log.warning(msg)
    print(msg, file=sys.stderr, flush=True)
    table = build_sg_table(spec, device="cuda" if torch.cuda.is_available() else "cpu")
    try:
        save_sg_table(table, path)
    except OSError as exc:
        log.warning("could not cache the SG table at %s (%s)", path, exc)
    print(f"torchrefract: SG table built in {table.build_seconds:.1f} s", file=sys.stderr)
    return table


def load_sg_table(spec: SGTableSpec | None = None, cache_dir: str | Path | None = None
                  ) -> SGTable:
    """The SG table for ``spec``: the shipped file, else the on-disk cache, else built.

    Building prints (stderr) and logs a warning first, then caches the result under
    ``cache_dir`` (default :func:`default_cache_dir`) as ``sg_table_<key>.npz``. Loaded
    tables are memoized per process.

    Args:
        spec: table parameters (default: the shipped table's).
        cache_dir: where built tables are cached.

    Returns:
        :class:`SGTable` on the CPU.
    """
    spec = SGTableSpec() if spec is None else spec
    shipped = _shipped(spec)  # (the kernels ask for it several times a render)
    if shipped is not None:
        return shipped
    return _load_cached(spec, str(cache_dir or default_cache_dir()))


@functools.lru_cache(maxsize=4)
def _shipped(spec: SGTableSpec) -> SGTable | None:
    """The shipped table where it is ``spec``'s, else None (no cache folder needed)."""
    if spec == SGTableSpec() and SHIPPED_TABLE.is_file():
        table = read_sg_table(SHIPPED_TABLE)
        if table.spec == spec:
            return table
    return None


# --------------------------------------------------------------------------------------
# Lookup
# --------------------------------------------------------------------------------------

def _safe_acos01(c: torch.Tensor) -> torch.Tensor:
    """acos on [0, 1] with a finite gradient at 1: asin(sqrt(1 - c^2)) above c = 0.5.

    Not ``atan2``: torch's vectorized atan2 and its scalar loop tail round differently, so a
    pixel's value would depend on where it falls in the batch (a sample rendered alone and
    in a batch would differ in the last bit); ``asin`` and ``acos`` do not.
    """
    c = c.clamp(0.0, 1.0)
    s2 = (1.0 - c * c).clamp(min=torch.finfo(c.dtype).eps ** 2)
    # each branch's argument is clamped to its own range, so the unused one has a finite
    # gradient too (torch.where would turn inf * 0 into NaN)
    return torch.where(c > 0.5, torch.asin(torch.sqrt(s2).clamp(max=0.9)),
                       torch.acos(c.clamp(max=0.5)))


def _coordinates(table: SGTable, cos_theta_o, eta, alpha, distribution):
    """Broadcast the lookup's arguments; ``grid_sample`` coordinates (1, P, 1, 1, 3), the
    shape, the distribution index per point, log alpha, dtype and device."""
    tensors = [x for x in (cos_theta_o, eta, alpha) if isinstance(x, torch.Tensor)]
    ref = tensors[0] if tensors else torch.zeros(())
    dtype = ref.dtype if ref.dtype.is_floating_point else torch.get_default_dtype()
    for x in tensors:
        if x.dtype.is_floating_point:
            dtype = torch.promote_types(dtype, x.dtype)
    dev = ref.device
    c = torch.as_tensor(cos_theta_o, dtype=dtype, device=dev)
    e = torch.as_tensor(eta, dtype=dtype, device=dev)
    a = torch.as_tensor(alpha, dtype=dtype, device=dev)
    if isinstance(distribution, torch.Tensor):
        d_idx = distribution.to(device=dev, dtype=torch.long)
    else:
        d_idx = torch.tensor(1 if mf._is_ggx(distribution) else 0, device=dev)
    shape = broadcast_shape(c.shape, e.shape, a.shape, d_idx.shape)
    c, e, a, d_idx = (t.expand(shape) for t in (c, e, a, d_idx))

    spec = table.spec
    # grid_sample coordinates in [-1, 1] (align_corners: -1 and 1 are the end nodes):
    # x = log alpha, y = log eta, z = theta_o; clamped to the table (zero gradient outside)
    theta = _safe_acos01(c)
    z = theta.clamp(0.0, 0.5 * math.pi) * (4.0 / math.pi) - 1.0
    le_max = math.log(spec.eta_max)
    y = torch.log(e.clamp(1.0 / spec.eta_max, spec.eta_max)) / le_max
    la0, la1 = math.log(spec.alpha_min), math.log(spec.alpha_max)
    log_a = torch.log(a.clamp(min=mf.ALPHA_MIN))
    x = (log_a.clamp(la0, la1) - la0) * (2.0 / (la1 - la0)) - 1.0
    grid = torch.stack([x, y, z], -1).reshape(1, -1, 1, 1, 3)  # (1, P, 1, 1, 3)
    return grid, shape, d_idx, log_a, dtype, dev


#: Points per thread below which a table lookup stays one ``grid_sample`` call.
_SPLIT_MIN_POINTS = 16384


def _trilinear(vol: torch.Tensor, grid: torch.Tensor) -> torch.Tensor:
    """``grid_sample`` of one (C, T, E, A) volume at (1, P, 1, 1, 3) coordinates -> (C, P)
    (trilinear, border padding, aligned corners).

    torch's CPU kernel for 5-D inputs runs one thread per batch item, so a single batch
    item of P points runs on one core; the points are split into one batch item per
    thread over the same volume (expanded, not copied). Each point's arithmetic is the
    same, so the values are the same, bit for bit; gradients flow as before."""
    p = grid.shape[1]
    k = min(torch.get_num_threads(), p // _SPLIT_MIN_POINTS)
    if k < 2:
        v = torch.nn.functional.grid_sample(vol[None], grid, mode="bilinear",
                                            padding_mode="border", align_corners=True)
        return v.reshape(vol.shape[0], p)
    m = -(-p // k)  # points per chunk; the last chunk is padded with the first point
    g = grid.reshape(p, 3)
    if m * k > p:
        g = torch.cat([g, g[:1].expand(m * k - p, 3)])
    v = torch.nn.functional.grid_sample(vol[None].expand(k, *vol.shape),
                                        g.view(k, m, 1, 1, 3), mode="bilinear",
                                        padding_mode="border", align_corners=True)
    return v.reshape(k, vol.shape[0], m).permute(1, 0, 2).reshape(vol.shape[0], m * k)[:, :p]


def _per_distribution(distribution, d_idx: torch.Tensor, sample) -> torch.Tensor:
    """``sample(d)`` for the distribution(s) present: one lookup when every point has the
    same one (the usual batch), both blended by ``torch.where`` otherwise."""
    if not isinstance(distribution, torch.Tensor):
        return sample(int(d_idx.reshape(-1)[0]) if d_idx.numel() else 0)
    flat = d_idx.reshape(-1)
    if flat.numel() == 0 or bool((flat == flat[0]).all()):
        return sample(int(flat[0]) if flat.numel() else 0)
    return torch.where((d_idx != 0)[..., None], sample(1), sample(0))


def sg_energies(table: SGTable, cos_theta_o: torch.Tensor | float, eta: torch.Tensor | float,
                alpha: torch.Tensor | float, distribution: str | torch.Tensor = "beckmann"
                ) -> tuple[torch.Tensor, torch.Tensor]:
    """The transmitted and reflected lobes' energies only (``sg_lookup(...)[3]`` of both
    lobes, interpolated identically), in one trilinear pass over a 2-channel volume."""
    return _energy_lookup(table, cos_theta_o, eta, alpha, distribution, change=False)


def _energy_lookup(table: SGTable, cos_theta_o, eta, alpha, distribution, change: bool
                   ) -> tuple[torch.Tensor, torch.Tensor]:
    """Trilinear lookup of both lobes' energies (``change``: less their value at the
    smallest roughness, :meth:`SGTable.energy_change_volume`)."""
    grid, shape, d_idx, _, dtype, dev = _coordinates(table, cos_theta_o, eta, alpha,
                                                     distribution)
    # (2, 2, T, E, A): distribution, lobe
    vol = table.energy_change_volume(dtype, dev) if change else table.energy_volume(dtype, dev)

    def sample(d: int) -> torch.Tensor:
        return _trilinear(vol[d], grid).t().reshape(*shape, 2)

    out = _per_distribution(distribution, d_idx, sample)
    if not change:
        out = out.clamp(min=0.0)
    return out[..., 0], out[..., 1]


def sg_lookup(table: SGTable, cos_theta_o: torch.Tensor | float, eta: torch.Tensor | float,
              alpha: torch.Tensor | float, distribution: str | torch.Tensor = "beckmann",
              lobe: str = "transmit", sharpness: str = "moment"
              ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Interpolated SG parameters of one interface, batched over any shape.

    Trilinear in ``(theta_o, log eta, log alpha)`` of (energy, log k, sin of the axis
    angle); the amplitude follows from energy and sharpness. Differentiable w.r.t. ``cos_theta_o``,
    ``eta`` and ``alpha`` (piecewise linear: gradients jump at table nodes).

    Args:
        table: from :func:`load_sg_table`.
        cos_theta_o: (...) cosine of the view direction with the normal on the view side,
            clamped to [0, 1].
        eta: (...) far-side index over view-side index, clamped to the table's range
            (``[1/3, 3]`` by default).
        alpha: (...) roughness; below the table's smallest value, energy and axis are held
            and ``k`` grows as ``1 / alpha^2`` (capped at :data:`K_MAX`); above, clamped.
        distribution: ``"beckmann"``, ``"ggx"``, or an integer / bool tensor broadcastable
            to the others (0 = beckmann, 1 = ggx).
        lobe: ``"transmit"`` or ``"reflect"``.
        sharpness: ``"moment"`` (the paper's moment matching, default) or ``"l2"`` (the
            sharpness minimizing the L2 distance to the true lobe at the same energy and
            axis: much sharper for GGX, whose heavy tails dominate the moments).

    Returns:
        amplitude: (...) ``a`` of ``a exp(k (p.w - 1))``.
        sharpness: (...) ``k``.
        axis_polar_angle: (...) signed angle ``t`` of the axis (module docstring; build
            the vector with :func:`lobe_axis`).
        energy: (...) integral of the lobe (transmittance or reflectance; 0 under TIR).
    """
    if lobe not in LOBES:
        raise ValueError(f"lobe must be 'transmit' or 'reflect', got {lobe!r}")
    if sharpness not in ("moment", "l2"):
        raise ValueError(f"sharpness must be 'moment' or 'l2', got {sharpness!r}")
    grid, shape, d_idx, log_a, dtype, dev = _coordinates(table, cos_theta_o, eta, alpha,
                                                         distribution)
    la0 = math.log(table.spec.alpha_min)

    l_idx = LOBES.index(lobe)
    vol = table.volume(dtype, dev, sharpness)  # (2 * 2, 3, T, E, A)

    def sample(d: int) -> torch.Tensor:  # trilinear, one fused kernel -> (..., 3)
        return _trilinear(vol[d * 2 + l_idx], grid).t().reshape(*shape, 3)

    out = _per_distribution(distribution, d_idx, sample)
    energy, log_k, sin_angle = out.unbind(-1)
    angle = torch.asin(sin_angle.clamp(-1.0 + 1e-7, 1.0 - 1e-7))
    # alpha below the table: k ~ 1 / alpha^2 (the lobe width is proportional to alpha).
    log_k = log_k + 2.0 * (la0 - log_a).clamp(min=0.0)
    k = torch.exp(log_k.clamp(math.log(K_MIN), math.log(K_MAX)))
    energy = energy.clamp(min=0.0)
    amplitude = energy * k / (2.0 * math.pi * -torch.expm1(-2.0 * k))
    return amplitude, k, angle, energy


def interface_energies(table: SGTable, cos_theta_o: torch.Tensor, eta: torch.Tensor,
                       alpha: torch.Tensor, distribution: str | torch.Tensor,
                       fresnel: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Transmitted and reflected energy of a rough interface with an exact smooth limit.

    The smooth Fresnel split ``(1 - F, F)`` plus what the roughness changes in the table's
    energies: ``E(alpha) - E(alpha_table_min)`` for each lobe (the directional albedo of
    the Walter BSDF, the split-sum "DFG" term of real-time engines for reflection and its
    counterpart for transmission). The change is 0 for ``alpha`` at or below the table's
    smallest roughness, so a smooth surface gets exact Fresnel; a rough one loses what the
    single-scattering microfacet model loses to masking-shadowing (Mitsuba's
    ``roughdielectric`` loses the same).

    Args:
        table: from :func:`load_sg_table`.
        cos_theta_o: (...) cosine of the incident direction with the normal on its side.
        eta: (...) far-side index over incident-side index.
        alpha: (...) roughness.
        distribution: as :func:`sg_lookup`.
        fresnel: (...) the exact smooth reflectance at ``cos_theta_o`` (1 under TIR).

    Returns:
        e_t, e_r: (...) energies, each >= 0, ``e_t + e_r <= 1`` up to the table's error.
    """
    d_t, d_r = _energy_lookup(table, cos_theta_o, eta, alpha, distribution, change=True)
    fade = matched_fade(eta)
    t = (1.0 - fresnel + fade * d_t).clamp(min=0.0)
    r = (fresnel + fade * d_r).clamp(min=0.0)
    return t, r


#: Weights of the three distinct cosines of :func:`spread_cosines`.
SPREAD_WEIGHTS = (0.25, 0.25, 0.5)


def spread_cosines(cos_theta: torch.Tensor, var: torch.Tensor) -> torch.Tensor:
    """Incident cosines of a four-point quadrature of a lobe of directions arriving at an
    interface (ours): the light reaching an exit comes from the entry's transmitted lobe,
    not along its axis, and an interface's energies bend sharply with the angle (total
    internal reflection, grazing masking), so they are averaged over the lobe.

    The lobe, an SG (von Mises-Fisher) of sharpness ``k = 1 / var`` around an axis at
    ``acos(cos_theta)`` from the normal, is replaced by four directions at the angle ``r``
    from the axis, two in the plane of incidence (towards and away from the normal) and two
    across it, each of weight 1/4; ``sin^2 r = E[sin^2 theta] = 2 A(k) / k`` with
    ``A(k) = coth k - 1/k`` (the vMF's mean cosine) matches the lobe's second moments. The
    two out-of-plane points share one cosine, so there are three: ``cos(theta - r)``,
    ``cos(theta + r)`` and ``cos theta cos r`` (weights :data:`SPREAD_WEIGHTS`; average
    values over them with :func:`spread_mean`). For a flat exit (a slab) the tangent plane
    is exact; on a sphere a ray tilted by ``delta`` meets the exit at an angle changed by
    ``delta`` too, so the same holds to first order. Measured against Monte Carlo of
    Mitsuba's ``roughdielectric`` through a slab (IOR 1.5, Beckmann 0.3-1.0, the exit's
    ``tir: conserve`` weight): within 0.015 (alpha <= 0.5) and 0.03 (alpha 1) from normal to
    grazing incidence, where the axis alone is off by up to 0.06 and the sharp refracted
    ray by up to 0.18 (alpha 0.5; 0.28 at alpha 1).

    Args:
        cos_theta: (...) cosine of the lobe's axis with the normal on its side.
        var: (...) the lobe's per-axis angular variance ``1 / k`` (0: a single ray).

    Returns:
        (3, ...) cosines in [0, 1] (0: the point misses the interface, grazing).
    """
    k = 1.0 / var.clamp(min=1e-12)
    small = k < 0.1
    ks = torch.where(small, torch.ones_like(k), k)  # a safe value in the unused branch
    mean_cos = torch.where(small, k / 3.0 - k ** 3 / 45.0, 1.0 / torch.tanh(ks) - 1.0 / ks)
    s2 = (2.0 * mean_cos / k).clamp(1e-12, 1.0)  # E[sin^2 theta] = sin^2 r
    ray = var <= 0  # a single ray: its own cosine, exactly
    sr = torch.where(ray, torch.zeros_like(s2), torch.sqrt(s2))
    cr = torch.where(ray, torch.ones_like(s2), torch.sqrt((1.0 - s2).clamp(min=0.0)))
    c = cos_theta.clamp(-1.0, 1.0)
    s = torch.sqrt((1.0 - c * c).clamp(min=1e-12))
    return torch.stack([c * cr + s * sr, c * cr - s * sr, c * cr]).clamp(0.0, 1.0)


def spread_mean(values: torch.Tensor) -> torch.Tensor:
    """(...) the weighted mean over the leading axis of (3, ...) values taken at
    :func:`spread_cosines`."""
    a, b, c = SPREAD_WEIGHTS
    return a * values[0] + b * values[1] + c * values[2]


def spread_interface_energies(table: SGTable, cos_theta_o: torch.Tensor, var: torch.Tensor,
                              n_ratio: torch.Tensor, alpha: torch.Tensor,
                              distribution: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`interface_energies` (exact Fresnel at each direction) averaged over a lobe of
    arriving directions of variance ``var`` around the axis at ``cos_theta_o``
    (:func:`spread_cosines`); all arguments (N,). ``n_ratio``: incident-side over far-side
    index (Fresnel's argument; the table's ``eta`` is its inverse).

    Returns:
        e_t, e_r: (N,) averaged energies.
    """
    cs = spread_cosines(cos_theta_o, var)  # (3, N)
    e_t, e_r = interface_energies(table, cs, (1.0 / n_ratio).expand_as(cs),
                                  alpha.expand_as(cs), distribution.expand_as(cs),
                                  fresnel_dielectric(cs, n_ratio))
    return spread_mean(e_t), spread_mean(e_r)


#: Width of the fade of the roughness's energy change near an index-matched interface:
#: full from ``|ln eta| = ln(1 + MATCHED_FADE)`` on (:func:`matched_fade`).
MATCHED_FADE = 0.1


def matched_fade(eta: torch.Tensor | float) -> torch.Tensor:
    """Weight in [0, 1] of the roughness's energy change at relative index ``eta``.

    At ``eta = 1`` there is no interface: a rough surface bends no ray and the light the
    single-scattering model loses to masking-shadowing (the microfacets' shadows, light that
    in truth goes on unchanged) is an artefact of the model; Mitsuba's ``roughdielectric``
    rejects ``eta = 1`` and loses it at ``1.0001`` (furnace mean 0.974 at alpha 0.5). The
    change is faded in with a smoothstep of ``|ln eta|`` over ``[0, ln 1.1]``, so an
    index-matched object is invisible and the image is a smooth function of the IOR at 1
    (zero slope there); from IOR 1.1 on the model is Mitsuba's.
    """
    x = torch.as_tensor(eta).log().abs() / math.log1p(MATCHED_FADE)
    x = x.clamp(0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)


def lobe_axis(view: torch.Tensor, normal: torch.Tensor, axis_polar_angle: torch.Tensor,
              lobe: str = "transmit") -> torch.Tensor:
    """3D unit axis of a lobe from the table's signed polar angle.

    Args:
        view: (..., 3) unit direction towards the viewer (the table's ``w_o``).
        normal: (..., 3) unit normal on the view side (``dot(view, normal) >= 0``).
        axis_polar_angle: (...) from :func:`sg_lookup`.
        lobe: ``"transmit"`` (axis on the far side) or ``"reflect"``.

    Returns:
        (..., 3) ``-sin(t) u -/+ cos(t) n`` with ``u`` the unit tangential part of ``view``
        (any tangent at normal incidence, where ``t = 0``).
    """
    vt = view - dot(view, normal)[..., None] * normal
    n2 = dot(vt, vt)[..., None]
    ok = n2 > 1e-24
    # fallback tangent: any vector orthogonal to the normal
    alt = torch.where((normal[..., :1].abs() < 0.9), torch.tensor([1.0, 0.0, 0.0]).to(normal),
                      torch.tensor([0.0, 1.0, 0.0]).to(normal))
    alt = alt - dot(alt, normal)[..., None] * normal
    u = torch.where(ok, vt / torch.sqrt(torch.where(ok, n2, torch.ones_like(n2))),
                    alt / alt.norm(dim=-1, keepdim=True))
    sign = -1.0 if lobe == "transmit" else 1.0
    t = axis_polar_angle[..., None]
    return -torch.sin(t) * u + sign * torch.cos(t) * normal


def sg_eval(direction: torch.Tensor, axis: torch.Tensor, sharpness: torch.Tensor,
            amplitude: torch.Tensor) -> torch.Tensor:
    """``a exp(k (dot(p, w) - 1))`` (eq. 8), computed as ``a exp(-k |p - w|^2 / 2)`` for accuracy.

    Args:
        direction: (..., 3) unit ``w``.
        axis: (..., 3) unit ``p``.
        sharpness: (...) ``k``.
        amplitude: (...) ``a``.

    Returns:
        (...) value.
    """
    d = direction - axis
    return amplitude * torch.exp(-0.5 * sharpness * dot(d, d))

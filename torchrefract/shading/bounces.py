"""Internal reflections: light reflected back inside at an exit interface, bounce by bounce.

A two-interface method stops at the first exit: the part of the light that the exit
interface reflects back inside (its Fresnel reflectance, all of it under total internal
reflection) is lost, the largest error left on glass (issue #6). Here that part is followed:

    at each interface met from inside, with throughput w arriving there,
        leaving   w (1 - F)  looked up in the environment (refracted direction / lobe)
        reflected w F        marched inside to the next interface (the front-face layer
                             seen from inside, or the back-face layer again:
                             :func:`torchrefract.kernels.march.march_inside`), attenuated by
                             exp(-sigma s) over the segment's length s

until the bounce budget is spent. The interface model (what leaves, what is reflected, the
lobe's width) belongs to the method and comes in as a ``shade`` function; this module owns
the loop, the bookkeeping and the compaction: every bounce runs only on the rays still
alive, so a few TIR-trapped pixels never cost a full-frame pass.

Budget (``internal_bounces``): an integer K (0 = the papers' two interfaces), or ``auto``:
a ray continues while its reflected throughput (max over RGB) exceeds
``bounce_tolerance``, up to ``max_internal_bounces``. At the last interface the method's
own end rule applies (``tir: conserve``, the default, lets what the interface reflects
leave there too, times :func:`escape_fraction`, the bounces not followed summed in closed
form; ``tir: clamp`` lets TIR light leave at the critical angle); everything else not
followed is recorded as residual throughput (the ``bounce_residual`` pass), so energy can
be audited: in a white furnace without absorption, image + (1 - F_entry) residual = 1 per
pixel for smooth glass (with ``clamp``; ``conserve`` leaves no residual).
Rays lost by the march (they leave the frame or both layers) leave along their current
direction (the environment there), never garbage.

``bounce_rays: 4`` splits the first internal reflection into four rays around its lobe
(:func:`split_lobe`), each followed on its own with a quarter of the throughput: they read
the lobe's spread from the geometry, not only from its variance, and where one ray would
cross a fold or a near miss of the march at once, four cross it one at a time, in four
smaller steps.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Callable

import numpy as np
import torch

from torchrefract.checks import ConfigError, check_number, where
from torchrefract.geometry.gbuffer import GBuffer, interpolate
from torchrefract.kept import KeptByIdentity
from torchrefract.kernels.index import put_, take
from torchrefract.kernels.march import camera_planes, march_inside
from torchrefract.optics.smooth import tangent_frame
from torchrefract.options import option

AUTO = "auto"


def _check_bounces(value, key: str, source: str | None):
    """An integer >= 0 or ``auto``."""
    if value == AUTO:
        return value
    if isinstance(value, str):
        raise ConfigError(f"{where(source, key)}: expected an integer >= 0 or 'auto', "
                          f"got {value!r}")
    return check_number(value, key, source, minimum=0, maximum=64, integer=True)


@dataclass(frozen=True)
class BounceSettings:
    """``method_options`` shared by the methods that follow internal reflections."""

    internal_bounces: int | str = option(0, check=_check_bounces)
    """Internal reflections followed: 0 (two interfaces), 1, 2, ... or ``auto``."""
    bounce_tolerance: float = option(0.01, minimum=0.0, maximum=1.0)
    """``auto``: a ray stops once its reflected throughput (max over RGB) is at most this."""
    max_internal_bounces: int = option(16, minimum=1, maximum=64, integer=True)
    """``auto``: the most internal reflections followed."""
    bounce_march_steps: int = option(16, minimum=1, maximum=4096, integer=True)
    """Coarse samples of each internal segment's march."""
    bounce_rays: int = option(1, choices=(1, 4))
    """Rays the first internal reflection is split into (1 or 4): four rays around the
    reflected lobe's ray carry half its variance (:func:`split_lobe`), each followed with a
    quarter of the throughput."""

    @property
    def enabled(self) -> bool:
        return self.internal_bounces == AUTO or self.internal_bounces > 0

    @property
    def limit(self) -> int:
        """Interfaces followed after the first exit at most: K, or the cap under ``auto``."""
        return self.max_internal_bounces if self.internal_bounces == AUTO \
            else int(self.internal_bounces)

    @property
    def tolerance(self) -> float:
        """The throughput a ray stops at: ``bounce_tolerance`` under ``auto``, 0 for K."""
        return self.bounce_tolerance if self.internal_bounces == AUTO else 0.0


def split_lobe(t: torch.Tensor, var: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Four rays standing for a lobe of axis ``t`` (M, 3) and per-axis angular variance
    ``var`` (M,): the axis tilted by +-s along two tangents, s = sqrt(var), so the four
    directions' per-axis second moment is var / 2; each ray keeps the other half.

    Returns (M * 4, 3) unit directions (the four of ray i at rows 4i .. 4i + 3) and their
    (M * 4,) variance."""
    u, v = tangent_frame(t)
    s = var.clamp(min=0.0).sqrt()[:, None, None]
    off = t.new_tensor([[1.0, 0.0], [-1.0, 0.0], [0.0, 1.0], [0.0, -1.0]])  # (4, 2)
    d = t[:, None] + s * (off[None, :, :1] * u[:, None] + off[None, :, 1:] * v[:, None])
    d = torch.nn.functional.normalize(d, dim=-1).reshape(-1, 3)
    return d, (0.5 * var).repeat_interleave(4)


@dataclass(frozen=True)
class Arrival:
    """Rays arriving from inside at an interface (M of them, compacted).

    Attributes:
        pix: (M,) index of the object pixel (path) each ray belongs to.
        batch: (M,) scene index.
        p: (M, 3) the point on the interface (where the ray was lost: its last point).
        t: (M, 3) unit direction of travel (inside the object).
        normal: (M, 3) unit outward shading normal at ``p`` (zeros where not found).
        uv: (M, 2) texture coordinates at ``p``.
        found: (M,) the interface was found (False: the march lost the ray).
        w: (M, 3) throughput arriving (absorption included).
        var: (M,) angular variance of the lobe carried (per axis, radians^2; 0 = a ray).
    """

    pix: torch.Tensor
    batch: torch.Tensor
    p: torch.Tensor
    t: torch.Tensor
    normal: torch.Tensor
    uv: torch.Tensor
    found: torch.Tensor
    w: torch.Tensor
    var: torch.Tensor

    def take(self, sel: torch.Tensor) -> "Arrival":
        return Arrival(**{k: getattr(self, k)[sel] for k in self.__dataclass_fields__})


@dataclass(frozen=True)
class Shading:
    """What a method's interface model returns for M arrivals.

    Attributes:
        radiance: (M, 3) light leaving the object there, throughput included.
        direction: (M, 3) unit direction of the internally reflected part.
        reflectance: (M,) fraction of the arriving throughput reflected inside (0 where the
            ray was lost or left entirely).
        var: (M,) angular variance of the reflected lobe.
    """

    radiance: torch.Tensor
    direction: torch.Tensor
    reflectance: torch.Tensor
    var: torch.Tensor


ShadeFn = Callable[[Arrival, int, bool], Shading]
"""shade(arrivals, k, last): the method's interface model at the k-th interface met from
inside (0: the first exit, where all N paths arrive in order); ``last`` is True at the
final interface of the budget (the method's end rule applies there)."""


@dataclass(frozen=True)
class BounceResult:
    """radiance (N, 3) leaving through all interfaces met from inside; bounces (N,) internal
    reflections followed per path; residual (N,) throughput (mean over RGB) not followed;
    alive (K+1,) rays arriving at each interface (index 0: the first exit)."""

    radiance: torch.Tensor
    bounces: torch.Tensor
    residual: torch.Tensor
    alive: list[int]


def follow(g: GBuffer, first: Arrival, shade: ShadeFn, absorption: torch.Tensor,
           settings: BounceSettings, n_paths: int, refine: int = 8) -> BounceResult:
    """Shade the first exit interface and follow the internal reflections from there.

    Args:
        g: the G-buffer (both layers are marched).
        first: the rays arriving at their first exit (one per object pixel).
        shade: the method's interface model.
        absorption: (B, 3) absorption coefficient per scene.
        settings: the bounce budget.
        n_paths: N, the number of paths (``pix`` indexes them).
        refine: bisection steps of each internal march.
    """
    limit, tol = settings.limit, settings.tolerance
    dtype = first.w.dtype
    out = torch.zeros(n_paths, 3, dtype=dtype)
    bounces = torch.zeros(n_paths, dtype=dtype)
    residual = torch.zeros(n_paths, dtype=dtype)
    alive_counts = []
    cur = first
    share = torch.ones(first.pix.shape[0], dtype=dtype)  # each ray's part of its path
    k = 0
    planes = None
    while cur.pix.numel() > 0:
        alive_counts.append(int(cur.pix.numel()))
        last = k >= limit
        sh = shade(cur, k, last)
        out.index_add_(0, cur.pix, sh.radiance.to(dtype))
        w_next = cur.w * sh.reflectance[:, None]
        go = cur.found & (w_next.amax(-1) > tol) & (sh.reflectance > 0)
        if last:
            go = torch.zeros_like(go)
        stop = ~go
        residual.index_add_(0, cur.pix[stop], w_next[stop].mean(-1))
        if not bool(go.any()):
            break
        sel = go.nonzero(as_tuple=True)[0]
        nxt = cur.take(sel)
        t = take(sh.direction, sel)
        w_sel, var_sel, share = take(w_next, sel), take(sh.var, sel), take(share, sel)
        if k == 0 and settings.bounce_rays > 1:  # the first internal reflection, split
            t, var_sel = split_lobe(t, var_sel)
            rep = torch.arange(sel.numel()).repeat_interleave(4)
            nxt = nxt.take(rep)
            w_sel, share = take(w_sel, rep) * 0.25, take(share, rep) * 0.25
        if planes is None:  # the slab between the layers, built once for every bounce
            planes = camera_planes(g, both=True)
        ex = march_inside(g, nxt.batch, nxt.p, t, steps=settings.bounce_march_steps,
                          refine=refine, planes=planes)
        dist = torch.where(ex.found, ex.dist, torch.zeros_like(ex.dist))
        att = torch.exp(-absorption[nxt.batch] * dist[:, None])
        uv = interpolate(ex.bary, take(g.meshes.tri_uvs, ex.tri.clamp(min=0)))
        bounces.index_add_(0, nxt.pix, share)
        cur = replace(nxt, p=torch.where(ex.found[:, None], ex.position, nxt.p), t=t,
                      normal=ex.normal, uv=uv, found=ex.found, w=w_sel * att, var=var_sel)
        k += 1
    return BounceResult(radiance=out, bounces=bounces, residual=residual, alive=alive_counts)


def bounce_passes(g: GBuffer, idx: torch.Tensor, res) -> dict[str, torch.Tensor]:
    """``bounces`` (internal reflections followed) and ``bounce_residual`` (throughput left
    inside, mean over RGB) per pixel, (B, H, W, 1)."""
    b, h, w = g.shape
    out = {k: torch.zeros(b * h * w) for k in ("bounces", "bounce_residual")}
    if res is not None:
        put_(out["bounces"], idx, res.bounces.float())
        put_(out["bounce_residual"], idx, res.residual.float())
    return {k: v.view(b, h, w, 1) for k, v in out.items()}


def escape_fraction(table, ior: torch.Tensor, distribution: torch.Tensor, alpha: torch.Tensor,
                    batch: torch.Tensor, nodes: int = 16, grid: int = 41) -> torch.Tensor:
    """Fraction of the light reflected back inside that eventually leaves the object: the
    bounces not followed, summed in closed form (``tir: conserve``'s end rule).

    Light trapped inside meets interface after interface; at each, a fraction T leaves,
    R is reflected on and L = 1 - T - R is lost to the single-scattering microfacet model's
    masking-shadowing (absorption aside). Summing the geometric series, a unit of trapped
    light leaves with T (1 + R + R^2 + ...) = T / (T + L). T and L are the interface's
    energies averaged over the directions of the trapped light, taken as isotropic inside
    (the flux on the interface is then cosine-weighted: ``nodes`` Gauss-Legendre nodes in
    cos theta). A smooth surface loses nothing (L = 0): all trapped light leaves, so a smooth
    object conserves energy in a white furnace; a rough one keeps what Mitsuba's
    ``roughdielectric`` keeps over many bounces. L is measured from the table's smooth
    limit, so it is exactly 0 at alpha = 0.

    Args:
        table: the SG table (:func:`torchrefract.optics.sgfit.load_sg_table`).
        ior: (B,) index inside per scene; distribution: (B,) 0 beckmann, 1 ggx.
        alpha: (N,) roughness at each interface point; batch: (N,) its scene.
        nodes: quadrature nodes in cos theta; grid: roughness nodes in [0, 1] per scene,
            interpolated linearly (the fraction is smooth in alpha).

    Returns:
        (N,) fraction in [0, 1]; differentiable w.r.t. ``ior`` and ``alpha``.
    """
    esc = escape_grid(table, ior, distribution, alpha.dtype, nodes, grid)  # (B, grid)
    pos = alpha.clamp(0.0, 1.0) * (grid - 1)
    i0 = pos.floor().long().clamp(max=grid - 2)
    f = pos - i0
    return esc[batch, i0] * (1.0 - f) + esc[batch, i0 + 1] * f


def escape_grid(table, ior: torch.Tensor, distribution: torch.Tensor, dtype: torch.dtype,
                nodes: int = 16, grid: int = 41) -> torch.Tensor:
    """(B, grid) :func:`escape_fraction` of each scene at ``grid`` roughness nodes uniform in
    [0, 1] (the first at the table's smallest), which it interpolates linearly.

    Without a gradient through ``ior``, each scene's row is computed alone (its values do
    not depend on the batch's other scenes) and kept (per table, IOR and its dtype,
    distribution, dtype and grid; the last 64): a batch's scenes mostly share their
    material, and a row is ~700 table lookups (~1.2 ms a batch)."""
    if ior.requires_grad and torch.is_grad_enabled():
        return _escape_rows(table, ior, distribution, dtype, nodes, grid)
    rows = []
    for i, d in zip(ior.tolist(), distribution.tolist()):
        key = (i, ior.dtype, d, dtype, nodes, grid)
        row = _escape_kept.get(table, key)
        if row is None:
            row = _escape_kept.put(table, key, _escape_rows(
                table, torch.tensor([i], dtype=ior.dtype),
                torch.tensor([d], dtype=distribution.dtype), dtype, nodes, grid)[0])
        rows.append(row)
    return torch.stack(rows).to(ior.device)


_escape_kept = KeptByIdentity(64)
"""escape_grid's rows: per table and (IOR, its dtype, distribution, dtype, nodes, grid)."""


def _escape_rows(table, ior: torch.Tensor, distribution: torch.Tensor, dtype: torch.dtype,
                 nodes: int, grid: int) -> torch.Tensor:
    """:func:`escape_grid`'s rows, computed."""
    from torchrefract.optics.sgfit import sg_energies  # noqa: PLC0415

    x, w = np.polynomial.legendre.leggauss(nodes)
    mu = torch.as_tensor(0.5 * (x + 1.0), dtype=dtype)
    wt = torch.as_tensor(0.5 * w, dtype=dtype) * 2.0 * mu  # cos-weighted, sums to 1
    a_grid = torch.linspace(0.0, 1.0, grid, dtype=dtype)
    a_grid = torch.cat([a_grid.new_full((1,), table.spec.alpha_min), a_grid[1:]])
    shape = (ior.shape[0], grid, nodes)
    args = (mu.expand(shape), (1.0 / ior)[:, None, None].expand(shape),
            a_grid[None, :, None].expand(shape), distribution[:, None, None].expand(shape))
    e_t, e_r = sg_energies(table, *args)
    e_t, e_r = (e_t * wt).sum(-1), (e_r * wt).sum(-1)  # (B, grid)
    loss = 1.0 - e_t - e_r
    loss = (loss - loss[:, :1]).clamp(min=0.0)  # 0 at the smooth limit
    esc = e_t / (e_t + loss).clamp(min=1e-6)
    return torch.where(loss > 0, esc, torch.ones_like(esc))


__all__ = ["AUTO", "Arrival", "BounceResult", "BounceSettings", "Shading", "bounce_passes",
           "escape_fraction", "escape_grid", "follow"]

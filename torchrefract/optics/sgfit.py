"""Spherical Gaussian fit of the rough dielectric BTDF and BRDF lobes (de Rousiers 2012, sec. 3.1).

For a view direction at polar angle ``theta_o`` from the normal of one interface, relative
index ``eta`` (the index on the far side over the index on the view side: ``ior`` when
entering glass, ``1 / ior`` when leaving it), roughness ``alpha`` and NDF (Beckmann or GGX),
the transmitted lobe ``f_t(w_o, w_i) |cos theta_i|`` over incident directions ``w_i`` is
replaced by one spherical Gaussian (the paper's eq. 8)::

    SG(w) = a * exp(k * (dot(p, w) - 1))

stored in a table ``T(theta_o, eta, alpha) -> (a, k, p)`` (eq. 9). The reflected lobe
(rough front reflection) is fitted the same way.

Fit (moment matching, as sec. 4.1 describes: "scaling, mean and variance"). With the lobe
``L(w)`` (the BSDF of :mod:`torchrefract.optics.microfacet` times ``|cos|``, *without* the
radiance compression factor, so that a smooth interface transmits ``1 - F``):

- energy ``E = integral L(w) dw`` (the lobe's total transmittance or reflectance);
- mean vector ``m = integral w L(w) dw / E``; an SG over the sphere has mean resultant
  length ``|m| = coth(k) - 1/k``, solved for ``k`` by bisection (vectorized, float64);
- axis ``p = m / |m|``, which lies in the plane of incidence; stored as a signed polar
  angle (below);
- amplitude ``a = E k / (2 pi (1 - exp(-2k)))`` so the SG integrates to ``E``.

The moments are integrals over microfacet normals ``m`` (Walter et al. 2007: for every
``m``, the refracted / reflected direction and the weight ``(1-F or F) G D |w.m| / |cos|``).
Instead of random importance samples they use a fixed deterministic rule in the
coordinates ``x = log(tan(theta_m) / alpha)`` and ``phi_m`` (a midpoint grid in ``x`` whose
offset shifts by the golden ratio from one ``phi`` column to the next), because:
(1) GGX lobes have heavy tails, and the second moment that sets ``k`` converges slowly
with NDF importance sampling (measured: 4096 scrambled-Sobol samples of Walter's sampler
left ``k`` off by factors of 1.3 to 3.3 for GGX and by 2-3% for Beckmann; the log-tan grid,
5-13k nodes, agrees with a 40x finer grid to 1e-5 away from total internal reflection);
(2) a deterministic rule makes the table a smooth, reproducible function of its
parameters. Only the half circle ``phi in [0, pi]`` is integrated (mirror symmetry about
the plane of incidence).

A second sharpness is stored beside the moment-matched one: the ``k`` minimizing the L2
distance between SG and lobe at the same energy and axis (``sg_lookup(...,
sharpness="l2")``). For Beckmann both agree within a few percent; for GGX the moments are
dominated by the tails and the moment-matched SG's peak is 2-5x too low (relative L2 error
0.52-0.84 for alpha < 0.4 at theta_o < 30 degrees, against 0.23 with the L2 sharpness).

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

import dataclasses
import functools
import hashlib
import json
import logging
import math
import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np
import torch

from torchrefract.optics import microfacet as mf
from torchrefract.optics.smooth import dot, fresnel_dielectric

log = logging.getLogger(__name__)

#: Version of the fitting code; part of every table's cache key.
FIT_VERSION = 1
#: Largest sharpness stored (a Dirac lobe, e.g. transmission at ``eta == 1``).
K_MAX = 1e9
#: Smallest sharpness stored.
K_MIN = 1e-3
#: Lobes with less energy than this are treated as absent (TIR; ``eta == 1`` reflection).
ENERGY_EPS = 1e-6
#: ``cos theta_o`` used for the grazing node ``theta_o = 90`` degrees.
COS_GRAZING = 1e-4

DISTRIBUTIONS = ("beckmann", "ggx")
LOBES = ("transmit", "reflect")
CHANNELS = ("energy", "log_sharpness", "axis_polar_angle", "log_sharpness_l2")

DATA_DIR = Path(__file__).resolve().parent.parent / "tables"
SHIPPED_TABLE = DATA_DIR / "sg_table_v1.npz"

_GOLDEN = 0.6180339887498949


@dataclass(frozen=True)
class SGTableSpec:
    """Axes and quadrature of an SG table (every field is part of the cache key).

    Attributes:
        n_theta: nodes of ``theta_o``, uniform in [0, 90] degrees.
        n_eta: nodes of ``eta``, log-spaced in ``[1/eta_max, eta_max]``; odd so 1 is a node.
        eta_max: largest relative index (the smallest is its inverse).
        n_alpha: nodes of ``alpha``, log-spaced in ``[alpha_min, alpha_max]``.
        alpha_min: smallest tabulated roughness.
        alpha_max: largest tabulated roughness.
        quad_h: step of the quadrature in ``x = log(tan(theta_m) / alpha)``.
        quad_nphi: quadrature columns over ``phi_m in [0, pi]``.
        quad_x_min: lower end of ``x`` (the NDF mass below it is < 1e-5).
        quad_tan_max: largest ``tan(theta_m)`` integrated for GGX (Beckmann stops at
            ``x = 2``, where ``D`` is below ``exp(-54)`` of its peak).
    """

    n_theta: int = 48
    n_eta: int = 33
    eta_max: float = 3.0
    n_alpha: int = 24
    alpha_min: float = 1e-3
    alpha_max: float = 1.0
    quad_h: float = 0.1
    quad_nphi: int = 64
    quad_x_min: float = -6.5
    quad_tan_max: float = 1e3

    def __post_init__(self) -> None:
        if self.n_eta % 2 != 1 or self.n_eta < 3:
            raise ValueError(f"SGTableSpec.n_eta must be odd and >= 3, got {self.n_eta}")
        if self.n_theta < 2 or self.n_alpha < 2:
            raise ValueError("SGTableSpec.n_theta and n_alpha must be >= 2")
        if not (self.eta_max > 1.0 and 0.0 < self.alpha_min < self.alpha_max):
            raise ValueError(f"SGTableSpec: bad ranges in {self}")

    def key(self) -> str:
        """Hash of the fields and :data:`FIT_VERSION` (names the cache file)."""
        blob = json.dumps({"fit_version": FIT_VERSION, **dataclasses.asdict(self)},
                          sort_keys=True)
        return hashlib.sha256(blob.encode()).hexdigest()[:16]

    def theta_nodes(self) -> np.ndarray:
        """(T,) polar angles of the view direction, radians."""
        return np.linspace(0.0, 0.5 * math.pi, self.n_theta)

    def eta_nodes(self) -> np.ndarray:
        """(E,) relative indices; node ``E // 2`` is exactly 1, node ``E-1-i`` is ``1/node i``."""
        h = self.n_eta // 2
        low = np.exp(np.linspace(-math.log(self.eta_max), 0.0, h + 1)[:-1])
        return np.concatenate([low, [1.0], (1.0 / low)[::-1]])

    def alpha_nodes(self) -> np.ndarray:
        """(A,) roughness values."""
        return np.exp(np.linspace(math.log(self.alpha_min), math.log(self.alpha_max),
                                  self.n_alpha))


@dataclass
class SGTable:
    """A loaded table. ``data``: float32 ``(2, 2, T, E, A, 4)`` (see the module docstring)."""

    spec: SGTableSpec
    data: torch.Tensor
    build_seconds: float = float("nan")
    _cache: dict = dataclasses.field(default_factory=dict, repr=False, compare=False)

    @property
    def theta(self) -> np.ndarray:
        return self.spec.theta_nodes()

    @property
    def eta(self) -> np.ndarray:
        return self.spec.eta_nodes()

    @property
    def alpha(self) -> np.ndarray:
        return self.spec.alpha_nodes()

    def to(self, device: torch.device | str) -> "SGTable":
        return SGTable(self.spec, self.data.to(device), self.build_seconds)

    def volume(self, dtype: torch.dtype, device: torch.device | str,
               sharpness: str = "moment") -> torch.Tensor:
        """``(2 * 2, 3, T, E, A)`` volumes (index ``2 * distribution + lobe``) of energy,
        log k and sin(axis angle), for ``grid_sample`` (memoized)."""
        key = ("volume", dtype, str(device), sharpness)
        if key not in self._cache:
            ch = (0, 1 if sharpness == "moment" else 3, 2)
            d = self.data.to(dtype=torch.float64)[..., list(ch)].clone()  # (2, 2, T, E, A, 3)
            d[..., 2] = torch.sin(d[..., 2])
            self._cache[key] = d.flatten(0, 1).permute(0, 4, 1, 2, 3).to(
                device=device, dtype=dtype).contiguous()
        return self._cache[key]

    def energy_volume(self, dtype: torch.dtype, device: torch.device | str) -> torch.Tensor:
        """``(2, 2, T, E, A)`` volumes (distribution, lobe) of the energy alone (memoized)."""
        key = ("energy", dtype, str(device))
        if key not in self._cache:
            self._cache[key] = self.data[..., 0].to(device=device, dtype=dtype).contiguous()
        return self._cache[key]

    def energy_change_volume(self, dtype: torch.dtype, device: torch.device | str
                             ) -> torch.Tensor:
        """``(2, 2, T, E, A)``: the energy less its value at the smallest roughness (the first
        node of the last axis), the change the roughness makes (memoized). Interpolation is
        linear, so one lookup of it is the difference of two lookups of the energy."""
        key = ("energy_change", dtype, str(device))
        if key not in self._cache:
            e = self.data[..., 0].to(dtype=torch.float64)
            self._cache[key] = (e - e[..., :1]).to(device=device, dtype=dtype).contiguous()
        return self._cache[key]


# --------------------------------------------------------------------------------------
# Fitting
# --------------------------------------------------------------------------------------

def _quadrature(alpha: float, ggx: bool, spec: SGTableSpec, device=None
                ) -> tuple[torch.Tensor, torch.Tensor]:
    """Nodes ``m`` (N, 3) over the half hemisphere ``m_y >= 0`` and weights ``D(m) dw_m`` (N,).

    Midpoint rule in ``x = log(tan theta_m / alpha)`` times ``phi``; each ``phi`` column
    shifts its ``x`` offsets by the golden ratio so that edges (TIR) are not aligned with
    the grid. The weights are doubled for the mirrored half (``m_y < 0``).
    """
    f64 = torch.float64
    x_lo = spec.quad_x_min
    x_hi = math.log(spec.quad_tan_max / alpha) if ggx else 2.0
    nx = max(8, int(math.ceil((x_hi - x_lo) / spec.quad_h)))
    hx = (x_hi - x_lo) / nx
    nphi = spec.quad_nphi
    i = torch.arange(nx, dtype=f64, device=device)
    j = torch.arange(nphi, dtype=f64, device=device)
    off = torch.frac(0.5 + j * _GOLDEN)
    x = (x_lo + (i[:, None] + off[None, :]) * hx).reshape(-1)  # (nx * nphi,)
    phi = ((j + 0.5) * (math.pi / nphi))[None, :].expand(nx, nphi).reshape(-1)
    t = alpha * torch.exp(x)  # tan theta_m
    c = torch.rsqrt(1.0 + t * t)
    s = t * c
    m = torch.stack([s * torch.cos(phi), s * torch.sin(phi), c], -1)
    d = mf.ndf(c, alpha, "ggx" if ggx else "beckmann", sin2_theta_h=s * s, cutoff=False)
    # dw_m = sin(theta) dtheta dphi, dtheta = tan cos^2 dx  ->  sin^2 cos dx dphi; x2 mirror.
    dw = s * s * c * (hx * math.pi / nphi * 2.0)
    return m, d * dw


def _g1(xy2: torch.Tensor, z2: torch.Tensor, a2: float, ggx: bool) -> torch.Tensor:
    """Smith G1 from squared components (same formulas as :func:`microfacet.smith_g1`,
    without the side test, which callers apply)."""
    t = a2 * xy2 / z2.clamp(min=1e-300)
    if ggx:
        return 2.0 / (1.0 + torch.sqrt(1.0 + t))
    a = torch.rsqrt(t.clamp(min=1e-300))
    ac = a.clamp(max=1.6)
    g = (3.535 * ac + 2.181 * ac * ac) / (1.0 + 2.276 * ac + 2.577 * ac * ac)
    return torch.where(a >= 1.6, torch.ones_like(g), g)


def _lobe_nodes(cos_theta_o: torch.Tensor, eta: torch.Tensor, alpha: float, ggx: bool,
                spec: SGTableSpec, chunk: int):
    """Yield, per chunk of quadrature nodes, the scattered directions and their weights.

    Each item has ``tx, ty, tz, wt`` (T, E, N): transmitted directions and weights
    ``(1 - F) G D |wi.m| / cos_o dw_m``; ``rx, ry, rz`` (T, N) reflected directions, ``br``
    (T, N) the Fresnel-free reflection weights and ``F`` (T, E, N). Sums of ``weight * g(w)``
    over all nodes approximate ``integral g(w) L(w) dw`` (Walter eqs. 14, 17, 20, 21).
    """
    dev = cos_theta_o.device
    f64 = torch.float64
    ct_o = cos_theta_o.to(f64).clamp(COS_GRAZING, 1.0)
    st_o = torch.sqrt(1.0 - ct_o * ct_o)
    eta = eta.to(f64)
    alpha = max(float(alpha), mf.ALPHA_MIN)
    a2 = alpha * alpha
    m_all, ddw_all = _quadrature(alpha, ggx, spec, dev)
    wx, wz = st_o[:, None], ct_o[:, None]  # (T, 1)
    eta3 = eta[None, :, None]  # (1, E, 1)
    inv_eta3 = 1.0 / eta3
    g1i = _g1(wx * wx, wz * wz, a2, ggx)  # (T, 1)
    for k0 in range(0, m_all.shape[0], chunk):
        m = m_all[k0:k0 + chunk]
        mx, my, mz = m[:, 0][None], m[:, 1][None], m[:, 2][None]  # (1, N)
        ddw = ddw_all[k0:k0 + chunk][None]
        wim = (wx * mx + wz * mz).clamp(min=0.0)  # (T, N); wi.m <= 0: G1(wi) = 0
        base = g1i * wim / wz * ddw  # G1(wi) |wi.m| D dw / cos_o   (T, N)
        # reflection: wo = 2 (wi.m) m - wi
        rx, ry, rz = 2 * wim * mx - wx, 2 * wim * my, 2 * wim * mz - wz
        g1r = torch.where(rz > 0, _g1(rx * rx + ry * ry, rz * rz, a2, ggx),
                          torch.zeros_like(rz))
        # Fresnel per eta (view side outside: eta_it = eta), as microfacet.fresnel
        wim3 = wim[:, None, :]  # (T, 1, N)
        cos_t2 = 1.0 - (1.0 - wim3 * wim3) * (inv_eta3 * inv_eta3)  # (T, E, N)
        ctab = torch.sqrt(cos_t2.clamp(min=0.0))
        a_s = (wim3 - eta3 * ctab) / (wim3 + eta3 * ctab).clamp(min=1e-300)
        a_p = (ctab - eta3 * wim3) / (ctab + eta3 * wim3).clamp(min=1e-300)
        F = (0.5 * (a_s * a_s + a_p * a_p)).clamp(0.0, 1.0)
        F = torch.where(wim3 > 0, F, torch.ones_like(F))
        F = torch.where(eta3 == 1.0, torch.zeros_like(F), F)
        # transmission, Mitsuba's refract: wo = m (wi.m / eta + cos_t) - wi / eta with
        # cos_t = -|cos_t|, so that wo.m = cos_t.
        s = wim3 * inv_eta3 - ctab
        tx = mx[:, None] * s - wx[:, :, None] * inv_eta3
        ty = my[:, None] * s
        tz = mz[:, None] * s - wz[:, :, None] * inv_eta3
        g1t = torch.where((tz < 0) & (cos_t2 > 0),
                          _g1(tx * tx + ty * ty, tz * tz, a2, ggx), torch.zeros_like(tz))
        wt = (1.0 - F) * g1t * base[:, None, :]
        yield {"tx": tx, "ty": ty, "tz": tz, "wt": wt, "rx": rx, "ry": ry, "rz": rz,
               "br": base * g1r, "F": F}


def lobe_moments(cos_theta_o: torch.Tensor, eta: torch.Tensor, alpha: float,
                 distribution: str, spec: SGTableSpec = SGTableSpec(),
                 chunk: int = 512) -> dict[str, torch.Tensor]:
    """Energy and first moments of the transmitted and reflected lobes (float64).

    Args:
        cos_theta_o: (T,) cosines of the view direction (clamped to >= 1e-4).
        eta: (E,) relative indices (far side / view side).
        alpha: roughness (one value).
        distribution: ``"beckmann"`` or ``"ggx"``.
        spec: quadrature settings.
        chunk: quadrature nodes processed at once (memory ~ T * E * chunk * 200 bytes).

    Returns:
        dict with ``E_t, mx_t, mz_t`` (T, E), ``E_r, mx_r, mz_r`` (T, E) and the
        Fresnel-free reflection moments ``E_r1, mx_r1, mz_r1`` (T,): unnormalized
        ``integral L``, ``integral w_x L`` and ``integral w_z L``.
    """
    ggx = mf._is_ggx(distribution)
    T, E = cos_theta_o.shape[0], eta.shape[0]
    dev = cos_theta_o.device
    z = torch.zeros(T, E, dtype=torch.float64, device=dev)
    acc = {k: z.clone() for k in ("E_t", "mx_t", "mz_t", "E_r", "mx_r", "mz_r")}
    acc1 = {k: torch.zeros(T, dtype=torch.float64, device=dev)
            for k in ("E_r1", "mx_r1", "mz_r1")}
    for n in _lobe_nodes(cos_theta_o, eta, alpha, ggx, spec, chunk):
        br, F, wt = n["br"], n["F"], n["wt"]
        # reflection sums over nodes: (T, E, N) @ (T, N, 1)
        acc["E_r"] += torch.bmm(F, br[:, :, None])[..., 0]
        acc["mx_r"] += torch.bmm(F, (br * n["rx"])[:, :, None])[..., 0]
        acc["mz_r"] += torch.bmm(F, (br * n["rz"])[:, :, None])[..., 0]
        acc1["E_r1"] += br.sum(-1)
        acc1["mx_r1"] += (br * n["rx"]).sum(-1)
        acc1["mz_r1"] += (br * n["rz"]).sum(-1)
        acc["E_t"] += wt.sum(-1)
        acc["mx_t"] += (wt * n["tx"]).sum(-1)
        acc["mz_t"] += (wt * n["tz"]).sum(-1)
    return {**acc, **acc1}


def sharpness_from_mean_length(one_minus_r: torch.Tensor, iters: int = 80) -> torch.Tensor:
    """Solve ``coth(k) - 1/k = 1 - eps`` for the SG sharpness ``k`` (vectorized bisection).

    Args:
        one_minus_r: (...) ``eps = 1 - |mean|`` in (0, 1).
        iters: bisection steps in ``log k`` over ``[K_MIN, K_MAX]``.

    Returns:
        (...) ``k`` in ``[K_MIN, K_MAX]``.
    """
    eps = one_minus_r.to(torch.float64)
    lo = torch.full_like(eps, math.log(K_MIN))
    hi = torch.full_like(eps, math.log(K_MAX))
    for _ in range(iters):
        mid = 0.5 * (lo + hi)
        k = torch.exp(mid)
        e_mid = 1.0 / k - 2.0 / torch.expm1(2.0 * k)  # 1 - (coth k - 1/k), decreasing in k
        too_wide = e_mid > eps  # need a larger k
        lo = torch.where(too_wide, mid, lo)
        hi = torch.where(too_wide, hi, mid)
    return torch.exp(0.5 * (lo + hi))


def _shape(e: torch.Tensor, mx: torch.Tensor, mz: torch.Tensor, reflect: bool):
    """(log k, signed polar angle) from unnormalized moments."""
    norm = torch.sqrt(mx * mx + mz * mz)
    r = norm / e.clamp(min=1e-300)
    eps = (1.0 - r).clamp(min=0.0)
    k = sharpness_from_mean_length(torch.where(e > 0, eps, torch.ones_like(eps)))
    k = torch.where(eps <= 0.5 / K_MAX, torch.full_like(k, K_MAX), k)
    angle = torch.atan2(-mx, mz if reflect else -mz)
    return torch.log(k), angle


_HIST_LO, _HIST_HI, _HIST_BINS = -32.0, 1.5, 200  # log(d^2) histogram of the L2 fit


def _l2_sharpness(hist_w: torch.Tensor, hist_wd: torch.Tensor, logk_mom: torch.Tensor
                  ) -> torch.Tensor:
    """log k minimizing ``integral (SG_k - L)^2`` at fixed energy and axis.

    ``L`` is summarized by a histogram over ``d^2 = |w - p|^2`` (weights ``hist_w`` and
    weighted ``d^2`` sums ``hist_wd``, (..., B)); ``integral SG_k L = a_k sum_b W_b
    exp(-k d_b^2 / 2)`` and ``integral SG_k^2 = a_k^2 pi (1 - exp(-4k)) / k``. A coarse
    search over ``k_mom * 2^(j/2)``, ``j = -4..24``, then a fine one (1/16 octave) around
    the best, refined by a parabola in ``log k``.
    """
    energy = hist_w.sum(-1, keepdim=True)  # (..., 1)
    d2 = hist_wd / hist_w.clamp(min=1e-300)  # (..., B)
    lo, hi = math.log(K_MIN), math.log(K_MAX)

    def cost(logk: torch.Tensor) -> torch.Tensor:  # (..., J) -> (..., J)
        k = torch.exp(logk)
        amp = energy * k / (2 * math.pi * -torch.expm1(-2 * k))
        cross = (hist_w[..., None, :] * torch.exp(-0.5 * k[..., None] * d2[..., None, :])).sum(-1)
        return amp * amp * math.pi * -torch.expm1(-4 * k) / k - 2 * amp * cross

    octave = math.log(2.0)
    coarse = torch.arange(-4, 25, dtype=torch.float64, device=hist_w.device) * (octave / 2)
    logk = (logk_mom[..., None] + coarse).clamp(lo, hi)
    best = logk.gather(-1, cost(logk).argmin(-1, keepdim=True))  # (..., 1)
    fine_step = octave / 16
    fine = torch.arange(-8, 9, dtype=torch.float64, device=hist_w.device) * fine_step
    logk = (best + fine).clamp(lo, hi)
    c = cost(logk)
    jb = c.argmin(-1, keepdim=True).clamp(1, fine.numel() - 2)
    c0, c1, c2 = (c.gather(-1, jb + o)[..., 0] for o in (-1, 0, 1))
    den = c0 - 2 * c1 + c2
    shift = torch.where(den > 0, 0.5 * (c0 - c2) / den.clamp(min=1e-300),
                        torch.zeros_like(den)).clamp(-1, 1)
    return (logk.gather(-1, jb)[..., 0] + shift * fine_step).clamp(lo, hi)


def _histogram(d2: torch.Tensor, w: torch.Tensor, out_w: torch.Tensor, out_wd: torch.Tensor
               ) -> None:
    """Accumulate ``w`` and ``w d2`` over log-spaced bins of ``d2`` (last dim reduced)."""
    step = (_HIST_HI - _HIST_LO) / _HIST_BINS
    b = ((torch.log(d2.clamp(min=1e-300)) - _HIST_LO) / step).floor().clamp(0, _HIST_BINS - 1)
    b = b.to(torch.long)
    out_w.scatter_add_(-1, b, w)
    out_wd.scatter_add_(-1, b, w * d2)


def fit_entries(theta: np.ndarray | torch.Tensor, eta: np.ndarray | torch.Tensor,
                alpha: float, distribution: str, spec: SGTableSpec = SGTableSpec(),
                chunk: int = 512) -> torch.Tensor:
    """Fit both lobes for all ``theta`` x ``eta`` at one ``alpha`` (the table's code path).

    Two passes over the quadrature: moments (energy, axis, moment-matched ``k``), then a
    histogram of squared distances to the axis for the L2-optimal ``k``.

    Args:
        theta: (T,) view polar angles in radians, increasing (the TIR fill walks along it).
        eta: (E,) relative indices.
        alpha: roughness.
        distribution: ``"beckmann"`` or ``"ggx"``.
        spec: quadrature settings.
        chunk: quadrature nodes per step.

    Returns:
        (2, T, E, 4) float64: lobe (transmit, reflect); channels :data:`CHANNELS`.
    """
    theta = torch.as_tensor(np.asarray(theta), dtype=torch.float64)
    eta = torch.as_tensor(np.asarray(eta), dtype=torch.float64, device=theta.device)
    ggx = mf._is_ggx(distribution)
    mom = lobe_moments(torch.cos(theta), eta, alpha, distribution, spec, chunk)
    # transmission
    e_t = mom["E_t"]
    logk_t, ang_t = _shape(e_t, mom["mx_t"], mom["mz_t"], reflect=False)
    valid_t = e_t >= ENERGY_EPS
    # reflection; where the F-weighted energy vanishes (eta == 1) use the Fresnel-free shape
    e_r = mom["E_r"]
    logk_r, ang_r = _shape(e_r, mom["mx_r"], mom["mz_r"], reflect=True)
    logk_1, ang_1 = _shape(mom["E_r1"], mom["mx_r1"], mom["mz_r1"], reflect=True)
    valid_r = e_r >= ENERGY_EPS
    logk_r = torch.where(valid_r, logk_r, logk_1[:, None].expand_as(logk_r))
    ang_r = torch.where(valid_r, ang_r, ang_1[:, None].expand_as(ang_r))

    # second pass: distance histograms around the axes -> L2-optimal sharpness
    T, E = e_t.shape
    hw = torch.zeros(2, T, E, _HIST_BINS, dtype=torch.float64, device=theta.device)
    hwd = torch.zeros_like(hw)
    ptx, ptz = -torch.sin(ang_t)[..., None], -torch.cos(ang_t)[..., None]  # (T, E, 1)
    prx, prz = -torch.sin(ang_r)[..., None], torch.cos(ang_r)[..., None]
    f_or_1 = torch.where(valid_r[..., None], 1.0, 0.0)
    for n in _lobe_nodes(torch.cos(theta), eta, alpha, ggx, spec, chunk):
        d2 = (n["tx"] - ptx) ** 2 + n["ty"] ** 2 + (n["tz"] - ptz) ** 2
        _histogram(d2, n["wt"], hw[0], hwd[0])
        rx, ry, rz = n["rx"][:, None], n["ry"][:, None], n["rz"][:, None]  # (T, 1, N)
        d2 = (rx - prx) ** 2 + ry ** 2 + (rz - prz) ** 2
        w_r = (n["F"] * f_or_1 + (1.0 - f_or_1)) * n["br"][:, None]
        _histogram(d2, w_r, hw[1], hwd[1])
    l2_t = torch.stack([_l2_sharpness(hw[0, i], hwd[0, i], logk_t[i]) for i in range(T)])
    l2_r = torch.stack([_l2_sharpness(hw[1, i], hwd[1, i], logk_r[i]) for i in range(T)])

    e_t = torch.where(valid_t, e_t, torch.zeros_like(e_t))
    e_r = torch.where(valid_r, e_r, torch.zeros_like(e_r))
    # TIR fill: carry the last transmitting theta's shape forward (theta increasing).
    for i in range(1, T):
        for ch in (logk_t, ang_t, l2_t):
            ch[i] = torch.where(valid_t[i], ch[i], ch[i - 1])
    return torch.stack([torch.stack([e_t, logk_t, ang_t, l2_t], -1),
                        torch.stack([e_r, logk_r, ang_r, l2_r], -1)], 0)


def fit_error(theta: np.ndarray | torch.Tensor, eta: np.ndarray | torch.Tensor, alpha: float,
              distribution: str, lobe: str = "transmit", fitted: torch.Tensor | None = None,
              spec: SGTableSpec = SGTableSpec(), chunk: int = 256,
              k_scales: Sequence[float] = (), sharpness: str = "moment"
              ) -> dict[str, torch.Tensor]:
    """How well the SG represents the true lobe, per entry (for reports; not used in renders).

    ``rel_l2 = sqrt(integral (SG - L)^2 / integral L^2)`` over the sphere, with ``L`` the
    true lobe evaluated by :func:`microfacet.eval` (importance mode) at the quadrature's
    scattered directions, and ``integral SG^2 = a^2 pi (1 - exp(-4k)) / k``.

    Args:
        theta: (T,) view polar angles (radians).
        eta: (E,) relative indices.
        alpha: roughness.
        distribution: ``"beckmann"`` or ``"ggx"``.
        lobe: ``"transmit"`` or ``"reflect"``.
        fitted: (T, E, C) channels (:data:`CHANNELS`) of that lobe; default: fitted now.
        spec: quadrature settings.
        chunk: quadrature nodes per step.
        k_scales: also report ``rel_l2`` with the sharpness multiplied by each factor
            (amplitude rescaled to keep the energy), as ``rel_l2_scaled`` (S, T, E).
        sharpness: ``"moment"`` or ``"l2"``: which stored sharpness to score; the other
            one is scored too and returned as ``rel_l2_other``.

    Returns:
        dict with ``rel_l2`` (T, E) (NaN where the lobe has no energy), ``hemisphere``
        (T, E): the SG's energy fraction on the lobe's own side of the surface,
        ``rel_l2_scaled`` (S, T, E) and ``rel_l2_other`` (T, E).
    """
    ggx = mf._is_ggx(distribution)
    theta = torch.as_tensor(np.asarray(theta), dtype=torch.float64)
    eta = torch.as_tensor(np.asarray(eta), dtype=torch.float64)
    l_idx = LOBES.index(lobe)
    if fitted is None:
        fitted = fit_entries(theta, eta, alpha, distribution, spec)[l_idx]
    fitted = fitted.to(torch.float64)
    k_ch = 1 if sharpness == "moment" else 3
    energy, k, ang = fitted[..., 0], torch.exp(fitted[..., k_ch]), fitted[..., 2]
    k_other = torch.exp(fitted[..., 4 - k_ch])
    sign = -1.0 if lobe == "transmit" else 1.0
    px, pz = -torch.sin(ang), sign * torch.cos(ang)  # (T, E)
    scales = torch.tensor([1.0, *k_scales], dtype=torch.float64)  # (S,)
    ks = torch.cat([k[None] * scales[:, None, None], k_other[None]], 0)  # (S + 1, T, E)
    amp = energy[None] * ks / (2 * math.pi * -torch.expm1(-2 * ks))
    ct_o = torch.cos(theta).clamp(COS_GRAZING, 1.0)
    wi = torch.stack([torch.sqrt(1 - ct_o ** 2), torch.zeros_like(ct_o), ct_o], -1)
    f2 = torch.zeros_like(energy)
    sgf = torch.zeros_like(ks)
    for n in _lobe_nodes(torch.cos(theta), eta, alpha, ggx, spec, chunk):
        if lobe == "transmit":
            wo = torch.stack([n["tx"], n["ty"], n["tz"]], -1)  # (T, E, N, 3)
            w = n["wt"]
        else:
            wo = torch.stack([n["rx"], n["ry"], n["rz"]], -1)[:, None].expand(
                -1, eta.shape[0], -1, -1)
            w = n["F"] * n["br"][:, None]
        f = mf.eval(wi[:, None, None, :], wo, alpha, eta[None, :, None], distribution,
                    radiance=False)
        f2 += (w * f).sum(-1)
        d2 = (wo[..., 0] - px[..., None]) ** 2 + wo[..., 1] ** 2 + (wo[..., 2] - pz[..., None]) ** 2
        sgf += (w[None] * torch.exp(-0.5 * ks[..., None] * d2[None])).sum(-1) * amp
    sg2 = amp ** 2 * math.pi * -torch.expm1(-4 * ks) / ks
    rel = torch.sqrt((sg2 - 2 * sgf + f2[None]).clamp(min=0.0) / f2[None])
    rel = torch.where(energy[None] > 0, rel, torch.full_like(rel, float("nan")))
    return {"rel_l2": rel[0], "rel_l2_scaled": rel[1:-1], "rel_l2_other": rel[-1],
            "hemisphere": sg_hemisphere_fraction(k, sign * torch.cos(ang))}


def sg_hemisphere_fraction(k: torch.Tensor, axis_z: torch.Tensor, n: int = 96) -> torch.Tensor:
    """Fraction of a normalized SG's mass with ``sign(w_z) == sign(axis_z)`` (Gauss quadrature).

    Args:
        k: (...) sharpness.
        axis_z: (...) z component of the unit axis.
        n: quadrature order per dimension.

    Returns:
        (...) fraction in [0, 1].
    """
    k = k.to(torch.float64)[..., None, None]
    cz = axis_z.to(torch.float64).abs()[..., None, None]
    sz = torch.sqrt((1 - cz * cz).clamp(min=0))
    # mass on cos(psi) = u is k exp(k (u - 1)) / (1 - exp(-2k)) du; sample u by its inverse CDF
    # (midpoints in q), azimuth uniform: w_z = u cz + sqrt(1 - u^2) cos(phi) sz.
    q = (torch.arange(n, dtype=torch.float64) + 0.5) / n
    u = 1.0 + torch.log1p(-q[:, None] * -torch.expm1(-2.0 * k)) / k  # (..., n, 1)
    u = u.clamp(-1.0, 1.0)
    phi = (torch.arange(n, dtype=torch.float64) + 0.5) / n * 2 * math.pi
    wz = u * cz + torch.sqrt((1 - u * u).clamp(min=0)) * torch.cos(phi) * sz
    return (wz > 0).to(torch.float64).mean((-1, -2))


def build_sg_table(spec: SGTableSpec = SGTableSpec(), *,
                   eta_indices: Sequence[int] | None = None,
                   alpha_indices: Sequence[int] | None = None,
                   distributions: Sequence[str] = DISTRIBUTIONS,
                   device: str | torch.device = "cpu", verbose: bool = False) -> SGTable:
    """Fit the whole table (or a sub-table of some ``eta`` / ``alpha`` nodes; all ``theta``).

    Args:
        spec: axes and quadrature.
        eta_indices: subset of the ``eta`` nodes (default all).
        alpha_indices: subset of the ``alpha`` nodes (default all).
        distributions: subset of ``("beckmann", "ggx")``; the result keeps the full
            distribution axis, with NaN where not built.
        device: where to compute (float64); CUDA is much faster, results agree to float32.
        verbose: print progress.

    Returns:
        :class:`SGTable`; a sub-table has ``data`` of shape ``(2, 2, T, len(eta_indices),
        len(alpha_indices), 4)`` and is meant for comparisons.
    """
    t0 = time.perf_counter()
    theta = spec.theta_nodes()
    eta_all, alpha_all = spec.eta_nodes(), spec.alpha_nodes()
    ei = list(range(len(eta_all))) if eta_indices is None else list(eta_indices)
    ai = list(range(len(alpha_all))) if alpha_indices is None else list(alpha_indices)
    eta_t = torch.as_tensor(eta_all[ei], dtype=torch.float64, device=device)
    theta_t = torch.as_tensor(theta, dtype=torch.float64, device=device)
    out = torch.full((2, 2, len(theta), len(ei), len(ai), len(CHANNELS)), float("nan"),
                     dtype=torch.float64)
    for d_name in distributions:
        d = DISTRIBUTIONS.index(mf._is_ggx(d_name) and "ggx" or "beckmann")
        for j, a_idx in enumerate(ai):
            fit = fit_entries(theta_t, eta_t, float(alpha_all[a_idx]), DISTRIBUTIONS[d], spec)
            out[d, :, :, :, j, :] = fit.cpu()
            if verbose:
                print(f"  {DISTRIBUTIONS[d]:8s} alpha={alpha_all[a_idx]:.4g} "
                      f"({time.perf_counter() - t0:.1f} s)", flush=True)
    return SGTable(spec, out.to(torch.float32), time.perf_counter() - t0)


# --------------------------------------------------------------------------------------
# Storage and caching
# --------------------------------------------------------------------------------------

def save_sg_table(table: SGTable, path: str | Path) -> Path:
    """Write a table as a compressed ``.npz`` (float32 data, axes, spec, key)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + f".tmp{os.getpid()}.npz")
    np.savez_compressed(
        tmp, data=table.data.cpu().numpy().astype(np.float32),
        theta=table.theta, eta=table.eta, alpha=table.alpha,
        spec=json.dumps(dataclasses.asdict(table.spec)), key=table.spec.key(),
        fit_version=FIT_VERSION, build_seconds=table.build_seconds,
        distributions=np.array(DISTRIBUTIONS), lobes=np.array(LOBES),
        channels=np.array(CHANNELS))
    os.replace(tmp, path)
    return path


def read_sg_table(path: str | Path) -> SGTable:
    """Read a table written by :func:`save_sg_table` (no key check)."""
    with np.load(path, allow_pickle=False) as z:
        spec = SGTableSpec(**json.loads(str(z["spec"])))
        data = torch.from_numpy(np.array(z["data"], dtype=np.float32))
        secs = float(z["build_seconds"]) if "build_seconds" in z else float("nan")
        if str(z["key"]) != spec.key():
            raise ValueError(f"{path}: stored key {z['key']} does not match its spec "
                             f"({spec.key()}; fitting code version {FIT_VERSION})")
    return SGTable(spec, data, secs)


def default_cache_dir() -> Path:
    """The current settings' cache folder (:func:`torchrefract.settings.cache_folder`)."""
    from torchrefract.settings import cache_folder  # noqa: PLC0415

    return cache_folder()


@functools.lru_cache(maxsize=4)
def _load_cached(spec: SGTableSpec, cache_dir: str) -> SGTable:
    if spec == SGTableSpec() and SHIPPED_TABLE.is_file():
        table = read_sg_table(SHIPPED_TABLE)
        if table.spec == spec:
            return table
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
    return _load_cached(spec, str(cache_dir or default_cache_dir()))


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
    shape = torch.broadcast_shapes(c.shape, e.shape, a.shape, d_idx.shape)
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

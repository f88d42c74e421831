"""Offline fitting of the spherical Gaussian table of :mod:`torchrefract.optics.sgfit`
(de Rousiers 2012, sec. 3.1): ``scripts/build_sg_table.py`` builds the shipped table with
it, ``scripts/plot_sg_fit.py`` reports its error; a render only needs it when no table for
its spec is shipped or cached.

Fit (moment matching, as sec. 4.1 describes: "scaling, mean and variance"). With the lobe
``L(w)`` (the BSDF of :mod:`torchrefract.optics.microfacet` times ``|cos|``, *without* the
radiance compression factor, so that a smooth interface transmits ``1 - F``):

- energy ``E = integral L(w) dw`` (the lobe's total transmittance or reflectance);
- mean vector ``m = integral w L(w) dw / E``; an SG over the sphere has mean resultant
  length ``|m| = coth(k) - 1/k``, solved for ``k`` by bisection (vectorized, float64);
- axis ``p = m / |m|``, which lies in the plane of incidence; stored as a signed polar
  angle (:mod:`torchrefract.optics.sgfit`);
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
"""

from __future__ import annotations

import math
import time
from typing import Sequence

import numpy as np
import torch

from torchrefract.optics import microfacet as mf
from torchrefract.optics.sg_table import (
    CHANNELS,
    COS_GRAZING,
    DISTRIBUTIONS,
    ENERGY_EPS,
    K_MAX,
    K_MIN,
    LOBES,
    SGTable,
    SGTableSpec,
)

_GOLDEN = 0.6180339887498949


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

"""Rough dielectric microfacet BSDF (Walter et al. 2007), matching Mitsuba 3 ``roughdielectric``.

Everything is expressed in the local shading frame: ``z`` is the macro-surface normal, and
directions are unit vectors pointing *away* from the surface point. As in Mitsuba 3:

- ``wi`` is the direction the path arrives from (towards the camera in radiance transport),
  ``wo`` the other direction (towards the light). ``wi.z > 0`` means ``wi`` lies outside.
- ``eta = int_ior / ext_ior`` (1.5 for glass in air). Where ``wi.z < 0`` (``wi`` inside) the
  relative index seen by the path is ``1 / eta``; every function swaps to it as Mitsuba does.
- :func:`eval` returns the BSDF value times ``|cos theta_o|`` (Mitsuba's ``bsdf.eval``): the
  BRDF for ``wi.z * wo.z > 0`` and the BTDF otherwise. In ``radiance`` mode (default,
  Mitsuba's ``TransportMode::Radiance``) the BTDF includes the solid-angle compression
  factor ``1 / eta_eff^2``; with ``radiance=False`` it is Walter's eq. 21 as written, whose
  integral over ``wo`` is the fraction of the energy arriving from ``wi`` that is
  transmitted (``1 - F`` for a smooth interface). The adjoint relation
  ``eval(wi, wo, radiance=True) / |wo.z| == eval(wo, wi, radiance=False) / |wi.z|`` holds.
- Masking-shadowing is Smith's separable ``G = G1(wi, m) G1(wo, m)`` (Walter eq. 23). For
  Beckmann, ``G1`` is Walter's rational approximation (eq. 27, < 0.35% from the exact eq. 26)
  exactly as Mitsuba evaluates it; ``exact_beckmann_g1=True`` in :func:`smith_g1` gives eq. 26.
- ``alpha`` is clamped to at least :data:`ALPHA_MIN` = 1e-4 (Mitsuba clamps the same).

Sampling (:func:`sample`) importance-samples the microfacet normal and picks reflection or
refraction with probability ``F`` (Walter sec. 5.3). Two samplers, both mapping the same
uniforms to the same directions as Mitsuba (same formulas, evaluated in the input dtype;
``sin theta_m`` comes from ``tan theta_m`` for precision at tiny alpha):

- ``sample_visible=False`` (default): Walter's NDF sampling (eqs. 28 and 35 for the normal's
  polar angle, uniform azimuth) of ``D(m) cos theta_m`` with Walter's widened roughness
  ``alpha * (1.2 - 0.2 sqrt|cos theta_i|)`` (his sec. 5.3 trick against large weights).
  The returned ``weight`` is exactly ``eval / pdf``, i.e. it includes ``D(m) / D_wide(m)``.
  Mitsuba 3.9's own ``sample`` omits that ratio (its weight is ``G |wi.m| / (|cos_i| cos_m)``),
  so with ``sample_visible: false`` Mitsuba's ``sample`` and ``eval``/``pdf`` disagree by the
  factor ``D / D_wide``; the tests check both facts.
- ``sample_visible=True``: visible-normal sampling as Mitsuba implements it (Heitz and d'Eon
  2014; GGX through the concentric disk map, Beckmann through a 3-step Newton inversion).
  Then ``weight = G1(wo, m)`` (times the radiance factor). For Beckmann the inversion
  samples the visible normals of the exact Smith ``G1`` while ``pdf`` uses eq. 27, so
  (as in Mitsuba) the two differ by up to 0.35%.

All functions are pure, batched over any leading shape (inputs broadcast), differentiable
(no NaN gradients at grazing angles, total internal reflection or ``alpha = 1e-4``), and work
in float32 and float64.

Example:
    >>> import torch
    >>> from torchrefract import microfacet as mf
    >>> wi = torch.tensor([[0.3, 0.0, 0.9539392]], dtype=torch.float64)
    >>> u = torch.tensor([[0.5, 0.3, 0.7]], dtype=torch.float64)
    >>> wo, weight, pdf = mf.sample(wi, 0.3, 1.5, "ggx", u)
    >>> torch.allclose(weight, mf.eval(wi, wo, 0.3, 1.5, "ggx") / pdf)
    True

References:
    B. Walter, S. Marschner, H. Li, K. Torrance. Microfacet Models for Refraction through
    Rough Surfaces. EGSR 2007. Equation numbers below refer to this paper.
"""

from __future__ import annotations

import math
from typing import Literal

import torch

from torchrefract.kernels.index import broadcast_shape
from torchrefract.optics.smooth import dot

Distribution = Literal["beckmann", "ggx"]

#: Smallest roughness; smaller values are clamped (as Mitsuba 3 does).
ALPHA_MIN = 1e-4

_INV_SQRT_PI = 1.0 / math.sqrt(math.pi)


# --------------------------------------------------------------------------------------
# Small helpers
# --------------------------------------------------------------------------------------

def _is_ggx(distribution: str) -> bool:
    d = str(distribution).lower()
    if d == "ggx":
        return True
    if d == "beckmann":
        return False
    raise ValueError(f"distribution must be 'beckmann' or 'ggx', got {distribution!r}")


def _tensor(x: torch.Tensor | float, like: torch.Tensor) -> torch.Tensor:
    return torch.as_tensor(x, dtype=like.dtype, device=like.device)


def _alpha(alpha: torch.Tensor | float, like: torch.Tensor) -> torch.Tensor:
    return _tensor(alpha, like).clamp(min=ALPHA_MIN)


def _dot(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    return dot(a, b)


def _mulsign(x: torch.Tensor, s: torch.Tensor) -> torch.Tensor:
    """``x`` with the sign of ``s`` (``s = 0`` counts as positive, like drjit's mulsign)."""
    return torch.where(s >= 0, x, -x)


def _safe_sqrt(x: torch.Tensor) -> torch.Tensor:
    """sqrt(max(x, 0)) with a finite gradient at 0 (the gradient there is set to 0)."""
    pos = x > 0
    return torch.where(pos, torch.sqrt(torch.where(pos, x, torch.ones_like(x))),
                       torch.zeros_like(x))


def _nonzero(x: torch.Tensor) -> torch.Tensor:
    """``x`` where ``|x| > eps`` else 1: a denominator for branches that ``torch.where``
    discards (keeps their gradients finite; the kept branches never get that close to 0)."""
    return torch.where(x.abs() > torch.finfo(x.dtype).eps, x, torch.ones_like(x))


def _normalize(v: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Unit vector and a mask of vectors with a usable length (zero vectors give (0, 0, 1))."""
    n2 = (v * v).sum(-1)
    ok = n2 > torch.finfo(v.dtype).eps ** 2 * 1e4
    n = torch.sqrt(torch.where(ok, n2, torch.ones_like(n2)))
    ez = torch.zeros_like(v)
    ez[..., 2] = 1.0
    return torch.where(ok[..., None], v / n[..., None], ez), ok


# --------------------------------------------------------------------------------------
# Roughness conversions
# --------------------------------------------------------------------------------------

def alpha_from_blinn_phong(kappa: torch.Tensor | float) -> torch.Tensor | float:
    """Beckmann/GGX ``alpha`` equivalent to a Blinn-Phong exponent (Walter sec. 5.2).

    ``alpha = sqrt(2 / (kappa + 2))`` (the inverse of ``kappa = 2 / alpha^2 - 2``).

    Args:
        kappa: (...) Blinn-Phong exponent, ``>= 0`` (the paper's ``kappa_gamma^D``).

    Returns:
        (...) alpha, same type as ``kappa``.
    """
    if isinstance(kappa, torch.Tensor):
        return torch.sqrt(2.0 / (kappa + 2.0))
    return math.sqrt(2.0 / (float(kappa) + 2.0))


def blinn_phong_from_alpha(alpha: torch.Tensor | float) -> torch.Tensor | float:
    """Blinn-Phong exponent ``kappa = 2 / alpha^2 - 2`` (inverse of :func:`alpha_from_blinn_phong`).

    Args:
        alpha: (...) roughness in ``(0, 1]`` (clamped to at least :data:`ALPHA_MIN`).

    Returns:
        (...) kappa, same type as ``alpha``.
    """
    if isinstance(alpha, torch.Tensor):
        a = alpha.clamp(min=ALPHA_MIN)
        return 2.0 / (a * a) - 2.0
    a = max(float(alpha), ALPHA_MIN)
    return 2.0 / (a * a) - 2.0


# --------------------------------------------------------------------------------------
# Normal distribution, masking-shadowing, Fresnel
# --------------------------------------------------------------------------------------

def ndf(cos_theta_h: torch.Tensor, alpha: torch.Tensor | float, distribution: Distribution,
        sin2_theta_h: torch.Tensor | None = None, cutoff: bool = True) -> torch.Tensor:
    """Microfacet normal distribution ``D(m)`` (per unit solid angle of ``m``).

    Beckmann (Walter eq. 25): ``exp(-tan^2 / alpha^2) / (pi alpha^2 cos^4)``.
    GGX (Walter eq. 33): ``alpha^2 / (pi cos^4 (alpha^2 + tan^2)^2)``.
    Both are zero for ``cos_theta_h <= 0`` (the ``chi^+`` factor). Normalized so that
    ``integral D(m) cos(theta_m) dm = 1``.

    Args:
        cos_theta_h: (...) cosine between ``m`` and the macro normal.
        alpha: (...) roughness (broadcastable), clamped to >= 1e-4.
        distribution: ``"beckmann"`` or ``"ggx"``.
        sin2_theta_h: optional (...) ``m_x^2 + m_y^2``; pass it when ``m`` is known, since
            ``1 - cos^2`` loses all precision for tiny alpha in float32.
        cutoff: zero values with ``D cos < 1e-20`` as Mitsuba does (avoids denormals).

    Returns:
        (...) D, same dtype as ``cos_theta_h``.
    """
    ggx = _is_ggx(distribution)
    c = cos_theta_h
    a2 = _alpha(alpha, c) ** 2
    pos = c > 0
    c2 = torch.where(pos, c * c, torch.ones_like(c))
    s2 = (1.0 - c2) if sin2_theta_h is None else sin2_theta_h
    s2 = s2.clamp(min=0.0)
    if ggx:
        # 1 / (pi a^2 (sin^2/a^2 + cos^2)^2), Mitsuba's form of eq. 33
        d = 1.0 / (math.pi * a2 * (s2 / a2 + c2) ** 2)
    else:
        small = s2 < 80.0 * a2 * c2  # exponent < 80; exp(-80) ~ 2e-35: 0 beyond (0 gradient)
        c2s = torch.where(small, c2, torch.ones_like(c2))
        e = torch.where(small, s2 / (a2 * c2s), torch.zeros_like(c2))
        d = torch.where(small, torch.exp(-e) / (math.pi * a2 * c2s * c2s), torch.zeros_like(e))
    keep = pos & (d * c > 1e-20) if cutoff else pos
    return torch.where(keep, d, torch.zeros_like(d))


def _ndf_vec(m: torch.Tensor, alpha: torch.Tensor, ggx: bool) -> torch.Tensor:
    return ndf(m[..., 2], alpha, "ggx" if ggx else "beckmann",
               sin2_theta_h=m[..., 0] ** 2 + m[..., 1] ** 2)


def smith_g1(v: torch.Tensor, m: torch.Tensor, alpha: torch.Tensor | float,
             distribution: Distribution, exact_beckmann_g1: bool = False) -> torch.Tensor:
    """Smith masking term ``G1(v, m)`` for one direction.

    With ``a = 1 / (alpha tan theta_v)``:
    Beckmann, Walter eq. 27 (the rational approximation Mitsuba uses):
    ``(3.535 a + 2.181 a^2) / (1 + 2.276 a + 2.577 a^2)`` for ``a < 1.6``, else 1;
    or eq. 26 with ``exact_beckmann_g1``: ``2 / (1 + erf(a) + exp(-a^2) / (a sqrt(pi)))``.
    GGX, Walter eq. 34: ``2 / (1 + sqrt(1 + alpha^2 tan^2 theta_v))``.
    The ``chi^+((v.m) / (v.n))`` factor makes it 0 where ``v`` sees the back of ``m``.

    Args:
        v: (..., 3) unit direction (either hemisphere).
        m: (..., 3) unit microfacet normal (upper hemisphere).
        alpha: (...) roughness, clamped to >= 1e-4.
        distribution: ``"beckmann"`` or ``"ggx"``.
        exact_beckmann_g1: use eq. 26 (erf) instead of eq. 27 for Beckmann.

    Returns:
        (...) G1 in [0, 1].
    """
    ggx = _is_ggx(distribution)
    a_ = _alpha(alpha, v)
    xy2 = v[..., 0] ** 2 + v[..., 1] ** 2
    vz = v[..., 2].abs()
    # Written without tan = xy / z so that grazing directions keep finite gradients.
    if ggx:
        # 2 / (1 + sqrt(1 + alpha^2 tan^2)) = 2 |z| / (|z| + sqrt(z^2 + alpha^2 xy^2))
        den = vz + torch.sqrt(vz * vz + a_ * a_ * xy2)
        g = 2.0 * vz / torch.where(den > 0, den, torch.ones_like(den))
    else:
        pos = xy2 > 0
        xy = torch.sqrt(torch.where(pos, xy2, torch.ones_like(xy2)))
        a = vz / (a_ * xy)  # 1 / (alpha tan theta_v)
        a_c = a.clamp(max=1.6)
        if exact_beckmann_g1:
            a_s = a.clamp(min=1e-30)
            g = 2.0 / (1.0 + torch.erf(a_s) + torch.exp(-a_s * a_s) * _INV_SQRT_PI / a_s)
        else:
            g = torch.where(a >= 1.6, torch.ones_like(a),
                            (3.535 * a_c + 2.181 * a_c * a_c)
                            / (1.0 + 2.276 * a_c + 2.577 * a_c * a_c))
    g = torch.where(xy2 == 0, torch.ones_like(g), g)  # normal incidence: no masking
    return torch.where(_dot(v, m) * v[..., 2] <= 0, torch.zeros_like(g), g)


def fresnel(cos_theta_i: torch.Tensor, eta: torch.Tensor | float
            ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Exact unpolarized dielectric Fresnel reflectance with Mitsuba's sign conventions.

    Walter eq. 22 (equivalent to the textbook s/p amplitudes used here).

    Args:
        cos_theta_i: (...) signed cosine between the incident direction and the (micro)
            normal; negative means the direction is inside, and ``1 / eta`` is used.
        eta: (...) ``int_ior / ext_ior``.

    Returns:
        F: (...) reflectance in [0, 1] (1 under total internal reflection and at
            ``cos = 0``, 0 when ``eta == 1``).
        cos_theta_t: (...) signed cosine of the refracted direction (opposite sign to
            ``cos_theta_i``; 0 under TIR).
        eta_it: (...) relative index along the direction of travel (``eta`` or ``1/eta``).
        eta_ti: (...) ``1 / eta_it``.
    """
    c = cos_theta_i
    eta = _tensor(eta, c)
    outside = c >= 0
    eta_it = torch.where(outside, eta, 1.0 / eta)
    eta_ti = torch.where(outside, 1.0 / eta, eta)
    cos_t2 = 1.0 - (1.0 - c * c) * eta_ti * eta_ti
    ci = c.abs()
    ct = _safe_sqrt(cos_t2)
    a_s = (ci - eta_it * ct) / (ci + eta_it * ct).clamp(min=torch.finfo(c.dtype).tiny)
    a_p = (ct - eta_it * ci) / (ct + eta_it * ci).clamp(min=torch.finfo(c.dtype).tiny)
    f = 0.5 * (a_s * a_s + a_p * a_p)
    matched = eta == 1.0
    f = torch.where(ci == 0, torch.ones_like(f), f)
    f = torch.where(matched, torch.zeros_like(f), f).clamp(0.0, 1.0)
    cos_t = torch.where(c >= 0, -ct, ct)
    return f, cos_t, eta_it, eta_ti


def _reflect(wi: torch.Tensor, m: torch.Tensor) -> torch.Tensor:
    """Mirror ``wi`` about ``m`` (Walter eq. 39): ``2 (wi.m) m - wi``."""
    return 2.0 * _dot(wi, m)[..., None] * m - wi


def _refract(wi: torch.Tensor, m: torch.Tensor, cos_t: torch.Tensor,
             eta_ti: torch.Tensor) -> torch.Tensor:
    """Refract ``wi`` through ``m`` (Walter eq. 40, Mitsuba's form)."""
    return m * (_dot(wi, m) * eta_ti + cos_t)[..., None] - wi * eta_ti[..., None]


# --------------------------------------------------------------------------------------
# BSDF evaluation and density
# --------------------------------------------------------------------------------------

def _half_vector(wi: torch.Tensor, wo: torch.Tensor, eta: torch.Tensor):
    """Generalized half vector: reflection eq. 13, transmission eq. 16 (``-(eta_i i + eta_o o)``).

    Returns (m, ok, reflect, eta_e): m in the upper hemisphere, ``ok`` where it is
    defined, the reflection mask and the relative index seen from ``wi``'s side.
    """
    ci, co = wi[..., 2], wo[..., 2]
    reflect = ci * co > 0
    eta_e = torch.where(ci > 0, eta, 1.0 / eta)
    h = wi + wo * torch.where(reflect, torch.ones_like(eta_e), eta_e)[..., None]
    m, ok = _normalize(h)
    m = m * torch.where(m[..., 2] >= 0, 1.0, -1.0)[..., None]
    return m, ok, reflect, eta_e


def _broadcast(wi, wo, alpha, eta):
    shape = broadcast_shape(wi.shape[:-1], wo.shape[:-1], alpha.shape, eta.shape)
    return (wi.expand(*shape, 3), wo.expand(*shape, 3), alpha.expand(shape), eta.expand(shape))


def eval(wi: torch.Tensor, wo: torch.Tensor, alpha: torch.Tensor | float,
         eta: torch.Tensor | float, distribution: Distribution, *,
         radiance: bool = True) -> torch.Tensor:
    """BSDF value times ``|cos theta_o|`` (Mitsuba's ``roughdielectric.eval``).

    Reflection (``wi.z * wo.z > 0``), Walter eq. 20:
    ``F D G / (4 |cos_i| |cos_o|)``. Transmission, Walter eq. 21 in relative-index form:
    ``|wi.m| |wo.m| eta^2 (1 - F) D G / (|cos_i| |cos_o| (wi.m + eta wo.m)^2)``, times
    ``1 / eta^2`` in radiance mode; ``m`` is the half vector of eq. 13 or eq. 16 and ``eta``
    the relative index seen from ``wi`` (``1 / eta`` where ``wi`` is inside).

    Args:
        wi: (..., 3) unit direction in the shading frame (``wi.z != 0``).
        wo: (..., 3) unit direction.
        alpha: (...) roughness, clamped to >= 1e-4.
        eta: (...) ``int_ior / ext_ior``.
        distribution: ``"beckmann"`` or ``"ggx"``.
        radiance: include the ``1 / eta^2`` radiance compression (Mitsuba's default
            transport mode); ``False`` gives the importance / energy-fraction form.

    Returns:
        (...) ``f(wi, wo) |wo.z|``; 0 where ``wi.z == 0`` or the half vector is undefined
        (index-matched straight-through transmission, a Dirac peak).
    """
    ggx = _is_ggx(distribution)
    alpha, eta = _alpha(alpha, wi), _tensor(eta, wi)
    wi, wo, alpha, eta = _broadcast(wi, wo, alpha, eta)
    ci = wi[..., 2]
    m, ok, reflect, eta_e = _half_vector(wi, wo, eta)
    d = _ndf_vec(m, alpha, ggx)
    dist = "ggx" if ggx else "beckmann"
    wim, wom = _dot(wi, m), _dot(wo, m)
    f = fresnel(wim, eta)[0]
    g = smith_g1(wi, m, alpha, dist) * smith_g1(wo, m, alpha, dist)
    ci_abs = torch.where(ci != 0, ci.abs(), torch.ones_like(ci))
    val_r = f * d * g / (4.0 * ci_abs)
    den = wim + eta_e * wom
    den2 = _nonzero(den * den)
    scale = 1.0 / (eta_e * eta_e) if radiance else torch.ones_like(eta_e)
    val_t = (scale * (1.0 - f) * d * g * eta_e * eta_e * wim * wom / (ci_abs * den2)).abs()
    val = torch.where(reflect, val_r, val_t)
    return torch.where(ok & (ci != 0), val, torch.zeros_like(val))


def _sampling_alpha(alpha: torch.Tensor, ci: torch.Tensor, sample_visible: bool) -> torch.Tensor:
    if sample_visible:
        return alpha
    # Walter et al. sec. 5.3: widen the sampled lobe to keep the weights small.
    return alpha * (1.2 - 0.2 * _safe_sqrt(ci.abs()))


def _microfacet_pdf(wi_up: torch.Tensor, m: torch.Tensor, alpha: torch.Tensor, ggx: bool,
                    sample_visible: bool) -> torch.Tensor:
    """Density of the sampled microfacet normal per solid angle of ``m``."""
    d = _ndf_vec(m, alpha, ggx)
    if sample_visible:
        g1 = smith_g1(wi_up, m, alpha, "ggx" if ggx else "beckmann")
        cz = wi_up[..., 2]
        return d * g1 * _dot(wi_up, m).abs() / torch.where(cz != 0, cz, torch.ones_like(cz))
    return d * m[..., 2]


def pdf(wi: torch.Tensor, wo: torch.Tensor, alpha: torch.Tensor | float,
        eta: torch.Tensor | float, distribution: Distribution, *,
        sample_visible: bool = False) -> torch.Tensor:
    """Solid-angle density of :func:`sample` producing ``wo`` (Mitsuba's ``pdf``).

    ``p(wo) = p_m(m) * (F or 1 - F) * |d omega_m / d omega_o|`` with the Jacobians
    ``1 / (4 |wo.m|)`` (Walter eq. 14) and ``eta^2 |wo.m| / (wi.m + eta wo.m)^2`` (eq. 17);
    ``p_m = D_wide(m) cos theta_m`` (NDF sampling with the widened alpha) or
    ``D(m) G1(wi, m) |wi.m| / |cos_i|`` (visible normals).

    Args:
        wi, wo: (..., 3) unit directions.
        alpha: (...) roughness (>= 1e-4).
        eta: (...) ``int_ior / ext_ior``.
        distribution: ``"beckmann"`` or ``"ggx"``.
        sample_visible: density of the visible-normal sampler instead of the NDF sampler.

    Returns:
        (...) density per steradian; 0 where the micro and macro surfaces disagree on the
        side (as in Mitsuba).
    """
    ggx = _is_ggx(distribution)
    alpha, eta = _alpha(alpha, wi), _tensor(eta, wi)
    wi, wo, alpha, eta = _broadcast(wi, wo, alpha, eta)
    ci, co = wi[..., 2], wo[..., 2]
    m, ok, reflect, eta_e = _half_vector(wi, wo, eta)
    wim, wom = _dot(wi, m), _dot(wo, m)
    active = ok & (ci != 0) & (wim * ci > 0) & (wom * co > 0)
    wom_s = _nonzero(wom)
    den = wim + eta_e * wom
    den2 = _nonzero(den * den)
    dwh = torch.where(reflect, 1.0 / (4.0 * wom_s), eta_e * eta_e * wom / den2)
    a_s = _sampling_alpha(alpha, ci, sample_visible)
    wi_up = wi * torch.where(ci >= 0, 1.0, -1.0)[..., None]
    prob = _microfacet_pdf(wi_up, m, a_s, ggx, sample_visible)
    f = fresnel(wim, eta)[0]
    prob = prob * torch.where(reflect, f, 1.0 - f)
    out = prob * dwh.abs()
    return torch.where(active, out, torch.zeros_like(out))


# --------------------------------------------------------------------------------------
# Sampling
# --------------------------------------------------------------------------------------

def sample_microfacet_normal(alpha: torch.Tensor, u1: torch.Tensor, u2: torch.Tensor,
                             distribution: Distribution) -> tuple[torch.Tensor, torch.Tensor]:
    """Sample ``m`` with density ``D(m) cos theta_m`` (Walter eqs. 28 and 35, isotropic).

    Beckmann: ``tan^2 theta_m = -alpha^2 log(1 - u1)``; GGX:
    ``tan^2 theta_m = alpha^2 u1 / (1 - u1)``; ``phi_m = 2 pi u2``.

    Args:
        alpha: (...) roughness (already clamped / widened).
        u1, u2: (...) uniforms in [0, 1).
        distribution: ``"beckmann"`` or ``"ggx"``.

    Returns:
        m: (..., 3) unit normal; pdf: (...) ``D(m) cos theta_m`` per steradian.
    """
    ggx = _is_ggx(distribution)
    u1 = u1.clamp(0.0, 1.0 - torch.finfo(u1.dtype).eps)
    a2 = alpha * alpha
    if ggx:
        tan2 = a2 * u1 / (1.0 - u1)
    else:
        tan2 = -a2 * torch.log1p(-u1)
    cos_t = torch.rsqrt(1.0 + tan2)
    sin_t = _safe_sqrt(tan2) * cos_t  # accurate for tiny alpha (1 - cos^2 is not)
    phi = (2.0 * math.pi) * u2
    m = torch.stack([torch.cos(phi) * sin_t, torch.sin(phi) * sin_t, cos_t], -1)
    pdf_m = ndf(cos_t, alpha, distribution, sin2_theta_h=sin_t * sin_t) * cos_t
    return m, pdf_m


def _square_to_disk_concentric(u1: torch.Tensor, u2: torch.Tensor):
    """Shirley-Chiu concentric map (Mitsuba's branch-free variant)."""
    x, y = 2.0 * u1 - 1.0, 2.0 * u2 - 1.0
    q13 = x.abs() < y.abs()
    r = torch.where(q13, y, x)
    rp = torch.where(q13, x, y)
    r_s = torch.where(r != 0, r, torch.ones_like(r))
    phi = 0.25 * math.pi * rp / r_s
    phi = torch.where(q13, 0.5 * math.pi - phi, phi)
    phi = torch.where((x == 0) & (y == 0), torch.zeros_like(phi), phi)
    return r * torch.cos(phi), r * torch.sin(phi)


def _sample_visible_11(cos_i: torch.Tensor, u1: torch.Tensor, u2: torch.Tensor, ggx: bool):
    """Slopes of the visible normals of the unit-roughness distribution (Mitsuba's code)."""
    if ggx:
        px, py = _square_to_disk_concentric(u1, u2)
        s = 0.5 * (1.0 + cos_i)
        py = _safe_sqrt(1.0 - px * px) * (1.0 - s) + py * s
        z = _safe_sqrt(1.0 - px * px - py * py)
        sin_i = _safe_sqrt(1.0 - cos_i * cos_i)
        # the denominator vanishes only on the disk's rim (u on the square's border)
        norm = 1.0 / (sin_i * py + cos_i * z).clamp(min=1e-12)
        return (cos_i * py - sin_i * z) * norm, px * norm
    # Beckmann: numerical inversion (3 Newton steps) in the erf domain, as in Mitsuba.
    sin_i = _safe_sqrt(1.0 - cos_i * cos_i)
    tan_i = sin_i / cos_i
    big = sin_i > 1e-12
    cot_i = torch.where(big, cos_i / torch.where(big, sin_i, torch.ones_like(sin_i)),
                        torch.full_like(sin_i, 1e12))
    maxval = torch.erf(cot_i)
    u1 = u1.clamp(1e-6, 1.0 - 1e-6)
    u2 = u2.clamp(1e-6, 1.0 - 1e-6)
    x = maxval - (maxval + 1.0) * torch.erf(torch.sqrt(-torch.log(u1)))
    tail = torch.where(cot_i < 30.0, tan_i * torch.exp(-cot_i.clamp(max=30.0) ** 2),
                       torch.zeros_like(tan_i))
    u1 = u1 * (1.0 + maxval + _INV_SQRT_PI * tail)
    for _ in range(3):
        slope = torch.erfinv(x)
        value = 1.0 + x + _INV_SQRT_PI * tan_i * torch.exp(-slope * slope) - u1
        deriv = 1.0 - slope * tan_i
        x = x - value / deriv
    return torch.erfinv(x), torch.erfinv(2.0 * u2 - 1.0)


def sample_visible_normal(wi_up: torch.Tensor, alpha: torch.Tensor, u1: torch.Tensor,
                          u2: torch.Tensor, distribution: Distribution
                          ) -> tuple[torch.Tensor, torch.Tensor]:
    """Sample ``m`` from the visible normals ``D(m) G1(wi, m) |wi.m| / cos_i`` (Heitz, d'Eon 2014).

    Args:
        wi_up: (..., 3) unit direction with ``z > 0``.
        alpha: (...) roughness.
        u1, u2: (...) uniforms.
        distribution: ``"beckmann"`` or ``"ggx"``.

    Returns:
        m: (..., 3); pdf: (...) per steradian of ``m``.
    """
    ggx = _is_ggx(distribution)
    wp, _ = _normalize(torch.stack([alpha * wi_up[..., 0], alpha * wi_up[..., 1],
                                    wi_up[..., 2]], -1))
    s2 = wp[..., 0] ** 2 + wp[..., 1] ** 2
    small = s2 <= 4.0 * torch.finfo(wp.dtype).eps
    inv = torch.rsqrt(torch.where(small, torch.ones_like(s2), s2))
    cos_phi = torch.where(small, torch.ones_like(s2), (wp[..., 0] * inv).clamp(-1, 1))
    sin_phi = torch.where(small, torch.zeros_like(s2), (wp[..., 1] * inv).clamp(-1, 1))
    sx, sy = _sample_visible_11(wp[..., 2], u1, u2, ggx)
    tx = (cos_phi * sx - sin_phi * sy) * alpha
    ty = (sin_phi * sx + cos_phi * sy) * alpha
    m, _ = _normalize(torch.stack([-tx, -ty, torch.ones_like(tx)], -1))
    return m, _microfacet_pdf(wi_up, m, alpha, ggx, True)


def sample(wi: torch.Tensor, alpha: torch.Tensor | float, eta: torch.Tensor | float,
           distribution: Distribution, u: torch.Tensor, *, sample_visible: bool = False,
           radiance: bool = True) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Importance-sample ``wo`` given ``wi`` (Walter sec. 5.3; Mitsuba's ``sample``).

    ``u[..., 0]`` chooses reflection (``u0 <= F(wi.m)``) or refraction, ``u[..., 1:3]``
    sample the microfacet normal (see the module docstring for the two samplers). The
    mapping from ``u`` to ``wo`` and the returned ``pdf`` equal Mitsuba's
    ``bsdf.sample(ctx, si, u0, (u1, u2))`` for the same ``sample_visible`` flag.

    Args:
        wi: (..., 3) unit direction (``wi.z != 0``).
        alpha: (...) roughness, clamped to >= 1e-4.
        eta: (...) ``int_ior / ext_ior``.
        distribution: ``"beckmann"`` or ``"ggx"``.
        u: (..., 3) uniforms in [0, 1).
        sample_visible: sample visible normals instead of ``D cos``.
        radiance: as in :func:`eval`.

    Returns:
        wo: (..., 3) sampled unit direction.
        weight: (...) ``eval(wi, wo) / pdf`` (0 where the sample is invalid: masked,
            wrong side, or ``wi.z == 0``).
        pdf: (...) density of ``wo`` per steradian (Walter eqs. 14 and 17 Jacobians
            times the lobe choice probability).
    """
    ggx = _is_ggx(distribution)
    dist = "ggx" if ggx else "beckmann"
    alpha, eta = _alpha(alpha, wi), _tensor(eta, wi)
    shape = broadcast_shape(wi.shape[:-1], u.shape[:-1], alpha.shape, eta.shape)
    wi, u = wi.expand(*shape, 3), u.to(wi.dtype).expand(*shape, 3)
    alpha, eta = alpha.expand(shape), eta.expand(shape)
    ci = wi[..., 2]
    active = ci != 0
    ez = torch.zeros_like(wi)
    ez[..., 2] = 1.0
    wi_up = torch.where(active[..., None], wi * torch.where(ci >= 0, 1.0, -1.0)[..., None], ez)
    a_s = _sampling_alpha(alpha, ci, sample_visible)
    if sample_visible:
        m, pdf_m = sample_visible_normal(wi_up, a_s, u[..., 1], u[..., 2], dist)
    else:
        m, pdf_m = sample_microfacet_normal(a_s, u[..., 1], u[..., 2], dist)
    active = active & (pdf_m != 0)
    wim = _dot(wi, m)
    f, cos_t, eta_it, eta_ti = fresnel(wim, eta)
    sel_r = u[..., 0] <= f
    p = pdf_m * torch.where(sel_r, f, 1.0 - f)
    wo_r = _reflect(wi, m)
    wo_t = _refract(wi, m, cos_t, eta_ti)
    wo = torch.where(sel_r[..., None], wo_r, wo_t)
    wom = _dot(wo, m)
    wom_s = _nonzero(wom)
    den = wim + eta_it * wom
    den2 = _nonzero(den * den)
    dwh = torch.where(sel_r, 1.0 / (4.0 * wom_s), eta_it * eta_it * wom / den2)
    p = p * dwh.abs()
    # weight = f cos / pdf, simplified analytically (Walter eq. 41 generalised):
    g1o = smith_g1(wo, m, alpha, dist)
    if sample_visible:
        weight = g1o
    else:
        g1i = smith_g1(wi, m, alpha, dist)
        d_ratio = _ndf_vec(m, alpha, ggx) / torch.where(pdf_m > 0, pdf_m, torch.ones_like(pdf_m))
        weight = g1i * g1o * wim.abs() / torch.where(active, ci.abs(), torch.ones_like(ci)) \
            * d_ratio
    if radiance:
        weight = torch.where(sel_r, weight, weight * eta_ti * eta_ti)
    # eval() classifies by the macro side of wo; a lobe that lands on the other side has
    # G1(wo) = 0 already, so weight is 0 there, as eval / pdf would be.
    weight = torch.where(active & (p > 0), weight, torch.zeros_like(weight))
    p = torch.where(active, p, torch.zeros_like(p))
    return wo, weight, p

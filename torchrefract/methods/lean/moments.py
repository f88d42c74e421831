"""LEAN moments of the back layer (Olano and Baker 2010; Dai and Wyman 2012) and their
Gaussian sum reduction into K subdivisions (Runnalls 2007).

Frame. Slopes are taken in each view's camera frame (right, up, forward): a back-face normal
with camera coordinates (n_x, n_y, n_z) has slopes s = (n_x, n_y) / n_z. Back faces look away
from the eye, so n_z > 0 except within a few degrees of the silhouette; n_z is clamped to
``NZ_MIN`` (slopes saturate 78 degrees from the view axis, where the exit is past the critical
angle anyway).

Per back-face pixel (LEAN, Olano and Baker sec. 3): the first moments B = s and the second
moments M = s s^T + Sigma_mu, where Sigma_mu is the microfacet slope covariance of the
pixel's own roughness: alpha^2 / 2 per axis in the tangent plane (a Beckmann slope
distribution; GGX shares its peak), mapped to camera slopes by the Jacobian A of
s(n) (:func:`slope_jacobian`). Each is stored weighted by coverage, together with the
angular microfacet variance alpha^2 / 2, and box-filtered into a mip pyramid: linear
filtering of (w, w B, w M) is exactly the moment-matching merge of Gaussians,
mu = w1 mu1 + w2 mu2, Sigma = w1 Sigma1 + w2 Sigma2 + w1 w2 (mu1 - mu2)(mu1 - mu2)^T (Runnalls
eq. 2; the poster's merge formula is its isotropic trace / 2). At a footprint,
Sigma = M - B B^T is the anisotropic Gaussian NDF of the footprint, roughness and geometry in
one (Olano and Baker eq. 6).

The first three moments of u = alpha^2 go through the mip too: a footprint over a roughness
map then gives the two-point distribution matching its mean, variance and skewness (the
2-node Gaussian quadrature of the roughness over the footprint: standardized nodes
(gamma -+ sqrt(gamma^2 + 4)) / 2, weight -a / (b - a) at b; exact for a two-level map), two
roughness lobes where the poster merges into one (``roughness_lobes``; ours).

Gaussian sum reduction (``gsr``): the normals are first split into K subdivisions of the
hemisphere, sectors of the slope azimuth around the view axis (centered on the image axes so
that facets tilted left/right or up/down fall in different sectors), each with its own
moments through the mip; a footprint then gives K Gaussians (weight, mean, covariance)
instead of their single merge. K = 1 is LEAN.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from torchrefract.geometry.gbuffer import GBuffer
from torchrefract.optics.materials import MaterialBatch
from torchrefract.optics.ndf import build_box_mips, sample_box_mips
from torchrefract.methods.lean.lobes import to_basis
from torchrefract.optics.cov2 import psd2
from torchrefract.optics.smooth import dot, normalize

NZ_MIN = 0.2
"""Smallest camera-z of a back normal used for its slopes (78 degrees off the view axis)."""
FOOTPRINT_TAPS = (-0.375, -0.125, 0.125, 0.375)
"""Taps along the footprint's major extent, in units of it (as ``rousiers``' NDF)."""
CHANNELS = 9
"""Per subdivision: w, w s_x, w s_y, w M_xx, w M_xy, w M_yy, w u, w u^2, w u^3 (u = alpha^2)."""
SLOPE_CHANNELS = 6
"""The first CHANNELS, without the roughness's: a pyramid where the roughness is one value
per view (:func:`lean_mips`)."""


@dataclass(frozen=True)
class Footprint:
    """K Gaussians of normals over the footprints of N pixels.

    Attributes:
        weight: (N, K) share of the footprint's covered area in each subdivision (sum 1
            where anything is covered; all 0 where nothing is).
        normal: (N, K, 3) world mean normal of each (outward; zeros where weight is 0).
        cov: (N, K, 2, 2) angular covariance of the normals (radians^2, roughness excluded)
            in the tangent basis (u, v) of ``normal``.
        u, v: (N, K, 3) that basis (world).
        var_mu: (N, K) mean angular microfacet variance (alpha^2 / 2) of the subdivision.
        alpha2: (N, K, 2) the two alpha^2 nodes matching the roughness over the footprint
            and alpha2_w (N, K, 2) their weights (module docstring).
        coverage: (N,) covered fraction of the footprint.
    """

    weight: torch.Tensor
    normal: torch.Tensor
    cov: torch.Tensor
    u: torch.Tensor
    v: torch.Tensor
    var_mu: torch.Tensor
    alpha2: torch.Tensor
    alpha2_w: torch.Tensor
    coverage: torch.Tensor


def camera_basis(g: GBuffer) -> torch.Tensor:
    """(B, 3, 3) rows right, up, forward of each view (world)."""
    return g.proj[:, 3:12].reshape(-1, 3, 3)


def slopes(n_cam: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Slopes (..., 2) of unit camera-space normals (..., 3), n_z clamped to ``NZ_MIN``;
    returns the slopes and the normal they stand for (unit, clamped)."""
    nz = n_cam[..., 2:3].clamp(min=NZ_MIN)
    xy = n_cam[..., :2]
    # keep the normal unit where n_z was raised: scale its xy part down
    r = xy.norm(dim=-1, keepdim=True)
    xy = xy * torch.where(r > 1e-12, torch.sqrt((1.0 - nz * nz).clamp(min=0.0)) / r.clamp(
        min=1e-12), torch.ones_like(r)).clamp(max=1.0)
    n = torch.cat([xy, nz], -1)
    return xy / nz, n


def slope_jacobian(n_cam: torch.Tensor, u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """(..., 2, 2) A = d s / d(angles along u, v) at unit camera normals n (..., 3) with
    tangent basis u, v: ds = (dn_xy n_z - n_xy dn_z) / n_z^2, dn = u or v."""
    nz = n_cam[..., 2:3].clamp(min=NZ_MIN)
    cols = [(t[..., :2] * nz - n_cam[..., :2] * t[..., 2:3]) / (nz * nz) for t in (u, v)]
    return torch.stack(cols, -1)


def _tangents(n: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """A tangent basis of unit normals (..., 3) that turns smoothly with them: u along the
    camera's right axis projected onto the tangent plane (n_z >= NZ_MIN keeps it defined)."""
    ex = torch.zeros_like(n)
    ex[..., 0] = 1.0
    u = normalize(ex - n[..., :1] * n)
    return u, torch.cross(n, u, dim=-1)


def sector(s: torch.Tensor, k: int) -> torch.Tensor:
    """Subdivision index (...,) of slopes (..., 2): K sectors of the slope's azimuth, the
    first centered on the camera's right axis."""
    if k == 1:
        return torch.zeros(s.shape[:-1], dtype=torch.long)
    phi = torch.atan2(s[..., 1], s[..., 0]) + math.pi / k  # sector 0 centered on phi = 0
    return torch.floor(phi.remainder(2.0 * math.pi) / (2.0 * math.pi / k)).long().clamp(0, k - 1)


def lean_mips(g: GBuffer, materials: MaterialBatch, k: int, roughness: bool = True
              ) -> tuple[torch.Tensor, ...]:
    """The back layer's LEAN moments per subdivision (module docstring), box-filtered:
    levels of (B, H_l, W_l, K * CHANNELS); without ``roughness`` the first SLOPE_CHANNELS
    of each subdivision only (one roughness per view: :func:`footprint_sums` gives its
    moments)."""
    b, h, w = g.shape
    basis = camera_basis(g)  # (B, 3, 3)
    n_world = g.back.normal  # (B, H, W, 3), outward
    n_cam = torch.einsum("bij,bhwj->bhwi", basis, n_world)
    s, n_c = slopes(n_cam)
    u, v = _tangents(n_c)
    a = slope_jacobian(n_c, u, v)  # (B, H, W, 2, 2)
    flat_b = torch.arange(b).repeat_interleave(h * w)
    alpha = materials.roughness_at(flat_b, g.back.uv.reshape(-1, 2)).view(b, h, w)
    u = alpha * alpha
    var_mu = 0.5 * u  # angular microfacet variance per axis
    sig = var_mu[..., None, None] * (a @ a.transpose(-1, -2))  # A (var I) A^T
    m = s[..., :, None] * s[..., None, :] + sig
    wgt = g.back.mask.to(s.dtype)
    ch = torch.stack([torch.ones_like(wgt), s[..., 0], s[..., 1], m[..., 0, 0], m[..., 0, 1],
                      m[..., 1, 1], u, u * u, u * u * u], -1) * wgt[..., None]
    c = CHANNELS if roughness else SLOPE_CHANNELS
    sec = sector(s, k)
    out = torch.zeros(b, h, w, k, c, dtype=s.dtype)
    out.scatter_(3, sec[..., None, None].expand(b, h, w, 1, c), ch[..., None, :c])
    return build_box_mips(out.view(b, h, w, k * c))


def footprint_sums(mips: tuple[torch.Tensor, ...], k: int, bi: torch.Tensor,
                   xy_c: torch.Tensor, major: torch.Tensor, ext: torch.Tensor,
                   level: torch.Tensor, alpha: torch.Tensor | None = None) -> torch.Tensor:
    """The moment sums (N, K, CHANNELS) over each pixel's footprint: the mips read at
    ``level`` (the footprint's minor extent) with taps along its major extent (the
    anisotropic part, as :func:`torchrefract.methods.rousiers.cone.back_ndf` does); the
    roughness moments at its center only, as ``rousiers``' coverage ratios (measured closer
    on the roughness-map globes: docs/decisions_lean.md). Mips without roughness channels
    (:func:`lean_mips`, ``roughness`` False) take them from each pixel's one roughness
    ``alpha`` (N,): w u, w u^2, w u^3 with u = alpha^2, what the center's give then."""
    n = bi.shape[0]
    c = mips[0].shape[-1] // k
    along_x = (ext[:, 0] >= ext[:, 1])[:, None]
    acc = torch.zeros(n, k * c, dtype=xy_c.dtype)
    for o in FOOTPRINT_TAPS:
        zero = torch.zeros_like(major)
        shift = torch.where(along_x, torch.stack([o * major, zero], -1),
                            torch.stack([zero, o * major], -1))
        acc = acc + sample_box_mips(mips, bi, xy_c + shift, level)
    acc = acc.view(n, k, c) / len(FOOTPRINT_TAPS)
    if c == SLOPE_CHANNELS:
        u = (alpha * alpha)[:, None, None]
        return torch.cat([acc, acc[..., :1] * torch.cat([u, u * u, u * u * u], -1)], -1)
    center = sample_box_mips(mips, bi, xy_c, level).view(n, k, CHANNELS)
    # the roughness moments, rescaled to the taps' covered weight so that w stays theirs
    scale = acc[..., :1] / center[..., :1].clamp(min=1e-12)
    rough = torch.where(center[..., :1] > 1e-9, center[..., 6:] * scale, acc[..., 6:])
    return torch.cat([acc[..., :6], rough], -1)


def gaussians(g: GBuffer, bi: torch.Tensor, acc: torch.Tensor) -> Footprint:
    """The K Gaussians of normals of moment sums ``acc`` (N, K, CHANNELS) (a footprint's,
    :func:`footprint_sums`; summed over K: their merge, Runnalls eq. 2): per subdivision
    Sigma = M / w - B B^T converted from slopes to angles at the mean normal (A^-1 Sigma A^-T)
    with the mean microfacet variance taken out (the exit's own roughness lobe carries it)."""
    cov_w = acc[..., 0]  # (N, K) covered fraction per subdivision
    total = cov_w.sum(-1)
    wk = cov_w / total.clamp(min=1e-12)[:, None]
    mean = acc[..., 1:] / cov_w.clamp(min=1e-12)[..., None]  # (N, K, 6)
    bx, by = mean[..., 0], mean[..., 1]
    sxx = mean[..., 2] - bx * bx
    sxy = mean[..., 3] - bx * by
    syy = mean[..., 4] - by * by
    sig_s = torch.stack([torch.stack([sxx, sxy], -1), torch.stack([sxy, syy], -1)], -2)
    n_cam = normalize(torch.stack([bx, by, torch.ones_like(bx)], -1))
    u_c, v_c = _tangents(n_cam)
    a = slope_jacobian(n_cam, u_c, v_c)  # (N, K, 2, 2)
    a_inv = torch.linalg.inv(a)
    var_mu = 0.5 * mean[..., 5]
    alpha2, alpha2_w = two_point(mean[..., 5], mean[..., 6], mean[..., 7])
    cov = a_inv @ sig_s @ a_inv.transpose(-1, -2)
    cov = psd2(0.5 * (cov + cov.transpose(-1, -2))
               - var_mu[..., None, None] * torch.eye(2, dtype=cov.dtype))
    basis = camera_basis(g)[bi]  # (N, 3, 3): world = basis^T cam
    to_world = lambda c: torch.einsum("nji,nkj->nki", basis, c)  # noqa: E731
    valid = (cov_w > 1e-6)[..., None]
    normal = torch.where(valid, to_world(n_cam), torch.zeros_like(n_cam))
    return Footprint(weight=torch.where(total[:, None] > 1e-6, wk, torch.zeros_like(wk)),
                     normal=normal, cov=torch.where(valid[..., None], cov, torch.zeros_like(cov)),
                     u=to_world(u_c), v=to_world(v_c), var_mu=torch.where(
                         valid[..., 0], var_mu, torch.zeros_like(var_mu)),
                     alpha2=alpha2, alpha2_w=alpha2_w,
                     coverage=total.clamp(max=1.0))


def reads_no_moments(subdivisions: int, spread: str, has_maps: bool) -> bool:
    """Whether a render's footprints are :func:`uniform_footprint` (no moments pyramid is
    built or read): ``lean`` (one subdivision) with ``spread: rays`` and one roughness per
    view. The tensor code and the fused kernel both ask here."""
    return subdivisions == 1 and spread == "rays" and not has_maps


def uniform_footprint(alpha: torch.Tensor) -> Footprint:
    """The merged Gaussian (K = 1) of any footprint where the roughness ``alpha`` (N,) is
    one value (no roughness map): the mip's roughness moments are that value's own, w u / w
    = alpha^2 (what :func:`gaussians` gives, to its rounding), so no pyramid is read.
    Weight 1 (a pixel whose exit is found reads the roughness there); the normal, basis and
    covariance zero: ``spread: rays`` reads the merged Gaussian's roughness alone (its lobe
    sits at the exact exit normal)."""
    n = alpha.shape[0]
    a2 = (alpha * alpha)[:, None]
    z3 = alpha.new_zeros(n, 1, 3)
    return Footprint(weight=alpha.new_ones(n, 1), normal=z3, cov=alpha.new_zeros(n, 1, 2, 2),
                     u=z3, v=z3, var_mu=0.5 * a2, alpha2=torch.stack([a2, a2], -1),
                     alpha2_w=torch.full((n, 1, 2), 0.5, dtype=alpha.dtype,
                                         device=alpha.device),
                     coverage=alpha.new_ones(n))


SEPARATION = (3.0, 10.0)
"""Trace ratios between (subdivisions' spread about their mean) and within (their own
spread) where a footprint starts and ends counting as several lobes: one Gaussian blob cut
into sectors gives ~1.8, a uniform disc of normals (a curved surface) ~2.6, distinct flat
facets grow without bound."""


def separation(fp: Footprint) -> torch.Tensor:
    """(N,) in [0, 1]: how clearly the footprint's normals form separate groups rather than
    one blob cut into sectors (``SEPARATION``, smoothstep of the trace ratio, continuous as
    the object moves). ``gsr`` with ``spread: rays`` blends from the merged lobe to its
    subdivisions' lobes by this much, so a curved surface keeps one lobe (the poster's
    ghosting) and a crease splits."""
    w = fp.weight
    n_bar = normalize((w[..., None] * fp.normal).sum(1))
    t1, t2 = (t[:, None] for t in _tangents(n_bar))
    o = torch.stack([dot(fp.normal, t1), dot(fp.normal, t2)], -1)
    o = o - (w[..., None] * o).sum(1, keepdim=True)
    between = (w * (o * o).sum(-1)).sum(-1)
    cov = to_basis(fp.cov, fp.u, fp.v, t1, t2)  # each subdivision's, in n_bar's plane
    within = (w * (cov[..., 0, 0] + cov[..., 1, 1])).sum(-1)
    ratio = between / within.clamp(min=1e-10)
    lo, hi = SEPARATION
    x = ((ratio - lo) / (hi - lo)).clamp(0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)


def two_point(m1: torch.Tensor, m2: torch.Tensor, m3: torch.Tensor
              ) -> tuple[torch.Tensor, torch.Tensor]:
    """Nodes (..., 2) and weights (..., 2) of the two-point distribution with raw moments
    m1, m2, m3 (module docstring; float64 inside: the central moments cancel). Where the
    variance vanishes both nodes are the mean with weights 1/2."""
    m1d, m2d, m3d = (x.double() for x in (m1, m2, m3))
    var = (m2d - m1d * m1d).clamp(min=1e-30)  # above 0: a finite gradient at a uniform map
    sd = torch.sqrt(var)
    mu3 = m3d - 3.0 * m1d * m2d + 2.0 * m1d ** 3
    spread = sd > 1e-6 * m1d.abs().clamp(min=1e-12)
    gamma = torch.where(spread, mu3 / (sd ** 3).clamp(min=1e-300), torch.zeros_like(sd))
    root = torch.sqrt(gamma * gamma + 4.0)
    a, b = 0.5 * (gamma - root), 0.5 * (gamma + root)
    q = -a / (b - a)
    nodes = torch.stack([m1d + sd * a, m1d + sd * b], -1).clamp(min=0.0)
    weights = torch.stack([1.0 - q, q], -1)
    return nodes.to(m1.dtype), weights.to(m1.dtype)


__all__ = ["CHANNELS", "Footprint", "NZ_MIN", "SLOPE_CHANNELS", "camera_basis",
           "footprint_sums", "gaussians", "lean_mips", "reads_no_moments", "sector",
           "separation", "slope_jacobian", "slopes", "two_point", "uniform_footprint"]

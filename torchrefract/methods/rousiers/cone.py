"""Steps 2 and 3: cone tracing (sec. 4.3) and the back layer over its footprint (sec. 4.2).

Four rays at theta_b (eq. 12) around the front lobe's axis p_t1 bound 75% of the lobe; they
and the axis are marched through the back-face buffer (``cone_rays: march``, the paper) or
intersected with the tangent plane at the axis' exit (``plane``). The screen positions of
the four exits give the footprint. Over it the back layer is read: the NDF mip (Toksvig,
eq. 11) for ``spread: paper`` / ``paper+front``, the exit normals of the four rays for
``rays``, the roughness levels' coverage for a roughness map (sec. 5.1).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from torchrefract.geometry.gbuffer import GBuffer
from torchrefract.kernels.cone import footprint as _footprint, ray_spread as _ray_spread
from torchrefract.kernels import native
from torchrefract.kernels.index import put_, take, where_true
from torchrefract.kernels.march import (
    Exit,
    camera_coordinates,
    camera_planes,
    frame_back,
    march_back,
)
from torchrefract.methods.rousiers.options import RousiersOptions
from torchrefract.optics.materials import MaterialBatch
from torchrefract.optics.ndf import (
    KAPPA_MAX,
    build_box_mips,
    build_ndf_mips,
    kappa_from_length,
    sample_box_mips,
    sample_mips,
)
from torchrefract.optics.smooth import dot, normalize, tangent_frame

# The backends' one call each (``_footprint``, ``_ray_spread``) is looked up in this module at
# every call, so a test can record what the cone tracing passes them.


def bounding_angle(k: torch.Tensor) -> torch.Tensor:
    """theta_b = acos(0.25^(1 / (k + 1))), the cone holding 75% of an SG lobe (eq. 12).

    Computed as 2 asin(sqrt((1 - x) / 2)) with 1 - x = -expm1(-ln 4 / (k + 1)): the same
    angle, accurate and with a finite gradient for sharp lobes (acos' diverges at 1).
    """
    one_minus = -torch.expm1(-math.log(4.0) / (k + 1.0))
    return 2.0 * torch.asin(torch.sqrt(0.5 * one_minus))


@dataclass
class Cone:
    """The traced cone of N pixels.

    Attributes:
        ex: the axis' exit (``march_back``).
        dirs: (N, 4, 3) the bounding rays; ok4 (N, 4) their exits found; n4 (N, 4, 3) their
            exit normals (``None`` for ``cone_rays: plane`` until read from the back layer).
        xy: (N, 4, 2) the exits' pixel coordinates (the axis' where not found); xy_c (N, 2)
            the axis exit's.
        ext: (N, 2) the footprint's extent in pixels (at least 1); major / minor its
            larger / smaller; level = log2(minor), the mip level read.
        sub: (N,) the raw minor extent clamped to [0, 1]: 1 once the footprint spans a pixel.
        exact_n: (N, 3) the axis' exit normal (p_t1 where not found).
    """

    ex: Exit
    dirs: torch.Tensor
    ok4: torch.Tensor
    n4: torch.Tensor | None
    xy: torch.Tensor
    xy_c: torch.Tensor
    ext: torch.Tensor
    major: torch.Tensor
    minor: torch.Tensor
    level: torch.Tensor
    sub: torch.Tensor
    exact_n: torch.Tensor


def trace_cone(g: GBuffer, bi: torch.Tensor, p1: torch.Tensor, p_t1: torch.Tensor,
               k_t1: torch.Tensor, options: RousiersOptions) -> Cone:
    """Step 2: march the axis p_t1 from the front hits p1, find the four bounding rays'
    exits (eq. 12) and their screen footprint."""
    planes = camera_planes(g)  # built once for the axis and the bounding rays
    c_p1, c_t1 = camera_coordinates(g, bi, p1, p_t1)
    ex = march_back(g, bi, p1, p_t1, steps=options.march_steps, refine=options.refine_steps,
                    planes=planes, camera=(c_p1, c_t1))
    theta_b = bounding_angle(k_t1)[:, None]
    u, v = tangent_frame(p_t1)
    cos_b, sin_b = torch.cos(theta_b), torch.sin(theta_b)
    dirs = torch.stack([cos_b * p_t1 + sin_b * s * a
                        for a in (u, v) for s in (1.0, -1.0)], 1)  # (N, 4, 3)
    if options.cone_rays == "march":
        q, ok4, n4 = _march_bounding(g, bi, p1, dirs, u, v, cos_b, sin_b, c_p1, c_t1, planes,
                                     options)
    else:
        q, ok4, n4 = _on_tangent_plane(p1, p_t1, dirs, ex)
    # Footprint in pixels: screen bounding box of the four exits.
    xy, xy_c, ext_raw = _footprint(q, ok4, ex.position, g.proj, bi)
    ext = ext_raw.clamp(min=1.0)
    minor = ext.min(-1).values
    # A footprint smaller than a pixel sees less of the surface than the finest NDF texel:
    # its normal spread shrinks with its area (variance ~ extent^2), down to the exact exit
    # normal of a specular ray. Without this a smooth object would be blurred by the
    # pixel grid itself.
    sub = ext_raw.min(-1).values.clamp(0.0, 1.0)
    exact_n = torch.where(ex.found[:, None], ex.normal, p_t1)
    return Cone(ex=ex, dirs=dirs, ok4=ok4, n4=n4, xy=xy, xy_c=xy_c, ext=ext,
                major=ext.max(-1).values, minor=minor, level=torch.log2(minor), sub=sub,
                exact_n=exact_n)


def _march_bounding(g, bi, p1, dirs, u, v, cos_b, sin_b, c_p1, c_t1, planes,
                    options: RousiersOptions):
    """The four bounding rays marched from p1 (the paper): exits q (N, 4, 3), found ok4
    (N, 4), exit normals n4 (N, 4, 3)."""
    n = p1.shape[0]
    # The bounding rays start at p1 with directions combining p_t1, u and v: their
    # camera coordinates combine those of the axis (no per-ray camera transform).
    _, c_u = camera_coordinates(g, bi, p1, u)
    _, c_v = camera_coordinates(g, bi, p1, v)
    cb, sb = cos_b.detach(), sin_b.detach()
    c_dirs = torch.stack([cb * c_t1 + sb * s * c for c in (c_u, c_v)
                          for s in (1.0, -1.0)], 1)  # (N, 4, 3)
    ex4 = march_back(g, bi.repeat_interleave(4), p1.repeat_interleave(4, 0),
                     dirs.reshape(-1, 3), steps=options.cone_march_steps,
                     refine=options.cone_refine_steps, planes=planes,
                     camera=(c_p1.repeat_interleave(4, 0), c_dirs.reshape(-1, 3)))
    return ex4.position.view(n, 4, 3), ex4.found.view(n, 4), ex4.normal.view(n, 4, 3)


def _on_tangent_plane(p1, p_t1, dirs, ex: Exit):
    """The four bounding rays intersected with the tangent plane at the axis' exit
    (``cone_rays: plane``): exits q, found ok4; their normals are read later."""
    pn = torch.where(ex.found[:, None], ex.normal, p_t1)
    denom = dot(dirs, pn[:, None, :])
    s = dot(ex.position - p1, pn)[..., None] / denom.clamp(min=1e-6)
    q = p1[:, None, :] + s[..., None] * dirs
    ok4 = (denom > 1e-6) & ex.found[:, None]
    return q, ok4, None


def back_ndf(g: GBuffer, cone: Cone, bi: torch.Tensor
             ) -> tuple[torch.Tensor, torch.Tensor]:
    """Step 3 (sec. 4.2-4.3): the back layer's NDF over the footprint, as the proxy exit
    normal n_bar (N, 3) and kappa_G (N,) (eq. 11).

    The mip level comes from the footprint's minor extent and four taps along its major
    extent average the anisotropic part (a box-filtered stand-in for the paper's
    anisotropic ``textureGrad``)."""
    n = bi.shape[0]
    major, ext, ex, exact_n = cone.major, cone.ext, cone.ex, cone.exact_n
    mips = build_ndf_mips(g.back.normal, g.back.mask, g.back.depth)
    along_x = (ext[:, 0] >= ext[:, 1])[:, None]
    offsets = torch.tensor([-0.375, -0.125, 0.125, 0.375])
    vec = torch.zeros(n, 3)
    cov = torch.zeros(n)
    for o in offsets:
        shift = torch.where(along_x, torch.stack([o * major, torch.zeros_like(major)], -1),
                            torch.stack([torch.zeros_like(major), o * major], -1))
        nd, nl, nc = sample_mips(mips, bi, cone.xy_c + shift, cone.level)
        vec = vec + nd * (nl * nc)[:, None]
        cov = cov + nc
    mean = vec / cov.clamp(min=1e-12)[:, None]
    length = mean.norm(dim=-1)
    have_ndf = ex.found & (cov > 1e-6) & (length > 1e-6)
    ndf_n = mean / length.clamp(min=1e-12)[:, None]
    # Proxy direction: over a footprint of a few pixels the exact exit normal (its
    # center) is a better estimate of the mean normal than bilinear taps of pixel-sized
    # texels (the footprint is symmetric, so curvature changes the mean only to second
    # order); from 4 pixels on, the mip's mean over the footprint takes over.
    w_ndf = (torch.log2(cone.minor) / 2.0).clamp(0.0, 1.0)[:, None]
    n_bar = torch.where(have_ndf[:, None],
                        normalize(w_ndf * ndf_n + (1.0 - w_ndf) * exact_n), exact_n)
    kappa_g = torch.where(have_ndf,
                          kappa_from_length(length) / (cone.sub * cone.sub).clamp(min=1e-12),
                          torch.full_like(length, KAPPA_MAX)).clamp(max=KAPPA_MAX)
    return n_bar, kappa_g


def geometric_variance(g: GBuffer, cone: Cone, bi: torch.Tensor, p_t1: torch.Tensor,
                       ior: torch.Tensor, fallback: torch.Tensor) -> torch.Tensor:
    """``spread: rays``: the bounding rays (75% of the front lobe, eq. 12) refracted out at
    their own exit normals; their angles to the central exit direction measure how the
    front lobe maps through the object (a flat slab magnifies it by the exit refraction, a
    ball lens focuses it): the per-axis variance (N,) they add to the exit lobe
    (:func:`torchrefract.kernels.cone.ray_spread`); ``fallback`` where no bounding ray found
    its exit."""
    n4, ok4 = bounding_normals(g, cone, bi)
    return _ray_spread(p_t1, cone.exact_n, cone.dirs, n4, ok4, ior, fallback)


def bounding_normals(g: GBuffer, cone: Cone, bi: torch.Tensor
                     ) -> tuple[torch.Tensor, torch.Tensor]:
    """The bounding rays' exit normals (N, 4, 3) and which were found (N, 4): marched
    (``cone_rays: march``) or, for ``plane``, the back layer's at the exits' pixels."""
    n4, ok4 = cone.n4, cone.ok4
    if n4 is None:
        _, h, w = g.shape
        n = bi.shape[0]
        xy = cone.xy
        flat = bi[:, None] * (h * w) + (xy[..., 1].floor().clamp(0, h - 1).long() * w
                                        + xy[..., 0].floor().clamp(0, w - 1).long())
        n4 = take(g.back.normal.reshape(-1, 3), flat.reshape(-1)).view(n, 4, 3)
        ok4 = ok4 & take(g.back.mask.reshape(-1), flat.reshape(-1)).view(n, 4)
    return n4, ok4


def level_values(materials: MaterialBatch, n: int) -> torch.Tensor:
    """(B, n) roughness levels spanning each scene's roughness_range (or its uniform value)."""
    t = torch.linspace(0.0, 1.0, n)
    lo, hi = materials.roughness_range.unbind(-1)  # (B,)
    vals = lo[:, None] + t[None, :] * (hi - lo)[:, None]
    uniform = torch.tensor([m is None for m in materials.roughness_maps])
    return torch.where(uniform[:, None], materials.roughness[:, None].expand_as(vals), vals)


def level_coverage(g: GBuffer, materials: MaterialBatch, n: int) -> torch.Tensor:
    """(B, H, W, n) per back-layer pixel of the frame footprints are measured in (``g``'s
    own, or in a sparse pass the one-sample frame: :func:`frame_back`): its roughness as
    hat weights on the n levels (linear between the two nearest), zero where the back
    layer is empty."""
    back = frame_back(g)
    uv, mask = back.uv, back.mask
    out = native.level_coverage(materials.roughness, materials.roughness_maps,
                                materials.roughness_range, uv, mask, n)
    if out is not None:  # the same values in one kernel call
        return out
    b, h, w = mask.shape
    on = where_true(mask.reshape(-1))  # the back layer's pixels (the rest: zero)
    bi = on // (h * w)
    alpha = materials.roughness_at(bi, take(uv.reshape(-1, 2), on))
    lo, hi = take(materials.roughness_range, bi).unbind(-1)
    pos = ((alpha - lo) / (hi - lo).clamp(min=1e-12)).clamp(0.0, 1.0) * (n - 1)
    idx = torch.arange(n, dtype=pos.dtype)
    wts = (1.0 - (pos[:, None] - idx[None, :]).abs()).clamp(min=0.0)  # (K, n)
    out = torch.zeros((b * h * w, n), dtype=wts.dtype)
    return put_(out, on, wts).view(b, h, w, n)


def coverage_mips(g: GBuffer, materials: MaterialBatch, n_levels: int
                  ) -> tuple[torch.Tensor, tuple[torch.Tensor, ...]]:
    """The roughness levels (B, L) and the box mips of their coverage over the back layer
    (:func:`level_coverage`), for :func:`footprint_coverage` (and the fused kernel). In a
    sparse pass, made once for the one-sample frame (kept in ``Marched.derived`` with the
    materials they were made for) and read by its samples' pass too."""
    m = g.marched
    shared = m is not None and m.frame_back is not None
    kept = m.derived.get("coverage_mips") if shared else None
    if kept is not None and kept[0] is materials and kept[1] == n_levels:
        return kept[2]
    out = level_values(materials, n_levels), build_box_mips(
        level_coverage(g, materials, n_levels))
    if shared:
        m.derived["coverage_mips"] = (materials, n_levels, out)
    return out


def footprint_coverage(g: GBuffer, materials: MaterialBatch, n_levels: int, bi: torch.Tensor,
                       cone: Cone, mips: tuple | None = None
                       ) -> tuple[torch.Tensor, torch.Tensor]:
    """Spatially varying roughness at the exit (sec. 5.1): the roughness levels (B, L) and
    their coverage ratios over the footprint (N, L), carried through the mips like the NDF
    and read at the same level (``mips``: :func:`coverage_mips`, where built already)."""
    levels, cover = mips if mips is not None else coverage_mips(g, materials, n_levels)
    c = sample_box_mips(cover, bi, cone.xy_c, cone.level)  # (N, L)
    return levels, c / c.sum(-1, keepdim=True).clamp(min=1e-12)


__all__ = ["Cone", "back_ndf", "bounding_angle", "bounding_normals", "coverage_mips",
           "footprint_coverage", "geometric_variance", "level_coverage",
           "level_values", "trace_cone"]

"""Adaptive sampling (issue #28, "model no more than a scene needs"), on by default
(``RenderSettings(adaptive=False)``: every sub-pixel shaded). With n x n samples per pixel,
a method that shades its samples alone (``Method.shades_samples``: ``specular``,
``prefiltered``, ``rousiers``' and ``lean``'s defaults, ``sh``) is supersampled sparsely,
from a one-sample G-buffer (:mod:`torchrefract.geometry.subsamples`); the plan here serves
the others (the frame read around a sample: ``gsr``, ``lean``'s moments pyramid,
``rousiers``' other cones and spreads; matte passes; a GPU). With it, all n x n sub-pixels of a
pixel are shaded only where they can differ; elsewhere one sample at the pixel's center
stands for them. With one sample, a lattice of pixels is shaded and the pixels between are
interpolated where the image is smooth (last paragraph).

A pixel's sub-pixels can differ where the G-buffer changes inside it: a silhouette or a
layer's edge (the front or back coverage differs among them), a fold (their front or back
shading normals differ by more than ``normal_tol`` in 1 - cos), or a step of the back layer
(its depth differs by more than ``depth_tol`` relative), or a smooth surface (roughness
below ``smooth_alpha``: a sharp refraction shows the environment's detail inside the
pixel). Such pixels are shaded at every
sub-pixel as the uniform n x n sampling does. In the others the first sub-pixel is replaced
by the exact sample through the pixel's center (the center ray intersected with that
sub-pixel's front triangle: position, distance, depth, shading normal, UV), shaded alone,
and its radiance and passes stand for the other sub-pixels in the box filter
(result.plan_box): the image of a pixel whose G-buffer is smooth inside it, at a quarter
of the shading (n = 2). The center samples get the lattice below too: a uniform pixel
between uniform lattice pixels waits on their center samples.
The back layer, which the marches read, stays the n x n one; the center sample lies on
the sub-pixel triangle its ray hits (the most inside of the pixel's). What the G-buffer cannot show
(a TIR boundary, a sharp feature of the environment seen through a smooth pixel) shows in
the radiance: after the first pass a pixel shaded once whose neighbourhood's radiances
spread by more than ``REFINE_RTOL`` is shaded at its other sub-pixels too (:func:`refine`).

At one sample per pixel (:func:`lattice`, :func:`fill`, csrc/lattice.c) the same idea runs
the other way: the object pixels of the 2x2 lattice (even row and column) are shaded
first; a pixel between lattice pixels whose G-buffer agrees with theirs (the tests above,
and roughness at least ``smooth_alpha``) waits, and is then the mean of their radiances
where those agree within ``LATTICE_RTOL``, else it is shaded in a further pass over the
image so far; near the tolerances it is shaded and blended with the mean
(``BLEND_FROM``), so the image changes continuously with the scene. Where the image is
smooth over several pixels the even pixels are first a level of their own, waiting on the
pixels of stride 4, and before it those on the pixels of stride 8 (``COARSEST``), where
enough of a level's pixels could wait (``COARSE_SHARE``); where little could wait there is
no lattice (``FINE_SHARE``). The
shaded pixels are the full render's; the others are interpolated where the image is smooth
(measured: docs/decisions.md, "Adaptive shading at one sample per pixel").
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import torch

from torchrefract.geometry.gbuffer import GBuffer, interpolate, intersect_triangles
from torchrefract.kernels import native
from torchrefract.kernels.index import put_, take, where_true
from torchrefract.optics.smooth import dot, normalize

NORMAL_TOL = 1e-2
"""1 - cos of the largest angle between a pixel's sub-pixel normals it shades once (~8 deg)."""
DEPTH_TOL = 0.05
"""The largest relative step of the back layer's depth inside a pixel it shades once."""
SMOOTH_ALPHA = 0.02
"""Below this roughness every sub-pixel is shaded: a sharp refraction resolves the
environment's detail inside a pixel, which the G-buffer does not show (measured on the
smooth sphere: docs/decisions.md, "Adaptive supersampling")."""
LATTICE_RTOL = 0.2
"""The spread (max - min per channel, over their mean luminance + 1e-3) of a waiting
pixel's lattice neighbours' radiances from which it is shaded (fit on the validation set's
fit half: docs/decisions.md, "Adaptive shading at one sample per pixel"); halved at the
coarser level."""
BLEND_FROM = 0.5
"""The lattice's tolerances (NORMAL_TOL, DEPTH_TOL, SMOOTH_ALPHA, LATTICE_RTOL) are where
a waiting pixel stops being its neighbours' mean alone: up to 1 / BLEND_FROM times them it
is shaded too and blended with the mean (smoothstep), beyond it is shaded alone. So the
image changes continuously with the scene instead of by a pixel's whole interpolation
error where a measure crosses its tolerance, and the pixels shaded are those shaded before
the blend existed (docs/decisions.md, "Adaptive shading on by default")."""
FINE_SHARE = 0.0
"""Below this share of a view's object pixels waiting, its lattice is not used (one full
pass). 0: a view switches only where no pixel could wait, so that its image does not jump
as the share crosses a threshold (a view's camera or object moving); 0.4 saved ~5% on a
detailed view (the bunny at 256x256, 0.35 waiting)."""
COARSE_SHARE = 0.5
"""The share of a view's object pixels at a level's lattice (stride 2 s for the level at
stride s) that must be able to wait on the pixels of stride 4 s for that coarser level to
be planned (0: wherever any can; see FINE_SHARE)."""
COARSEST = 4
"""The stride of the coarsest level planned (the levels: strides COARSEST, ..., 2, 1). A
level at stride 8 interpolates over 16 pixels: on the rough sphere at 512 and 1024 pixels
it bought under 2% of the frame and doubled the interpolation's error against the full
render (docs/decisions.md, "The lattice's levels coarsen while enough pixels can
wait")."""
REFINE_RTOL = 1.6
"""With n x n samples: a pixel shaded once whose 3x3 neighbourhood of such pixels'
radiances spreads (max - min in a channel) by more than this times their mean luminance
(+ 1e-3) is shaded at every sub-pixel after all (:func:`refine`): the TIR boundaries and
sharp environment detail that the G-buffer does not show. Fit on the validation set's fit
half (docs/decisions.md, "Adaptive 2x2 refined where the radiance spreads")."""


@dataclass(frozen=True)
class Plan:
    """Which pixels are shaded once: ``uniform`` (B, H/n, W/n) bool, for a G-buffer of
    supersampling n; ``lattice``: the levels over the uniform pixels' center samples
    (:func:`lattice` with ``uniform``), or None."""

    uniform: torch.Tensor
    n: int
    lattice: Lattice | None = None


def _subs(x: torch.Tensor, n: int) -> list[torch.Tensor]:
    """The n*n strided views (B, H/n, W/n, ...) of a (B, H, W, ...) tensor, one per
    sub-pixel position of a pixel, row-major (no copies)."""
    return [x[:, i::n, j::n] for i in range(n) for j in range(n)]


def _uniform_torch(g: GBuffer, alpha: torch.Tensor, n: int, smooth_alpha: float,
                   normal_tol: float, depth_tol: float) -> torch.Tensor:
    """The tensor code of csrc/lattice.c's uniform pixels (:func:`plan`): (B, H/n, W/n)."""
    fm, bm = _subs(g.front.mask, n), _subs(g.back.mask, n)
    fn, bn, bd = _subs(g.front.normal, n), _subs(g.back.normal, n), _subs(g.back.depth, n)
    uniform = fm[0].clone()  # covered (empty pixels cost nothing) and smooth inside
    tol = depth_tol * bd[0].abs()
    for k in range(1, n * n):
        uniform &= (fm[k] == fm[0]) & (bm[k] == bm[0])
        uniform &= (1.0 - dot(fn[k], fn[0]) <= normal_tol) & (1.0 - dot(bn[k], bn[0]) <= normal_tol)
        uniform &= (bd[k] - bd[0]).abs() <= tol
    for a in _subs(alpha.expand(g.shape), n):
        uniform &= a >= smooth_alpha
    return uniform


def _shade_torch(front_mask: torch.Tensor, uniform: torch.Tensor,
                 region: torch.Tensor | None) -> torch.Tensor:
    """The tensor code of csrc/lattice.c's sub-pixels to shade (:func:`plan`): (B, H, W)
    covered (and in ``region``), but a uniform pixel at its first sub-pixel only."""
    shade = front_mask.clone() if region is None else front_mask & region
    for v in _subs(shade, front_mask.shape[1] // uniform.shape[1])[1:]:
        v &= ~uniform  # (strided views: in place)
    return shade


def plan(g: GBuffer, center_dirs: torch.Tensor, alpha: torch.Tensor,
         normal_tol: float = NORMAL_TOL, depth_tol: float = DEPTH_TOL,
         smooth_alpha: float = SMOOTH_ALPHA, region: torch.Tensor | None = None
         ) -> tuple[GBuffer, Plan]:
    """The G-buffer to shade and the plan (module docstring). Writes the center samples
    into ``g``'s front layer and rays (a render's own G-buffer).

    Args:
        g: a G-buffer of supersampling n > 1.
        center_dirs: (B, H/n, W/n, 3) unit rays through the pixels' centers.
        alpha: the front roughness of each sub-pixel, broadcastable to (B, H, W) (per view:
            (B, 1, 1)): a pixel with a sub-pixel smoother than ``smooth_alpha`` is shaded
            at all of them.
        region: (B, H, W) bool, whole pixels: the only sub-pixels shaded (None: all).

    Returns:
        The G-buffer with ``shade`` set (the sub-pixels to shade), and the plan.
    """
    n = g.supersample
    made = native.uniform(g.front.mask, g.back.mask, g.front.normal, g.back.normal,
                          g.back.depth, alpha, n, smooth_alpha, normal_tol, depth_tol, region)
    if made is None:
        uniform = _uniform_torch(g, alpha, n, smooth_alpha, normal_tol, depth_tol)
        shade = _shade_torch(g.front.mask, uniform, region)
    else:
        uniform, shade = made
    _, h, w = g.shape
    if not native.center_samples(g, uniform, center_dirs.contiguous()):
        pb, py, px = uniform.nonzero(as_tuple=True)  # the uniform pixels
        sel = (pb * h + py * n) * w + px * n  # their first sub-pixels, flat
        tris = torch.stack([t[uniform] for t in _subs(g.front.tri, n)], 1)
        _center_samples(g, sel, tris, center_dirs[uniform])
    if region is not None:  # a pixel outside is neither shaded nor waited on
        uniform = uniform & region[:, ::n, ::n]
    return replace(g, shade=shade), Plan(uniform=uniform, n=n)


def refine(plan: Plan, radiance: torch.Tensor, rtol: float | None = None
           ) -> tuple[torch.Tensor, torch.Tensor] | None:
    """After a supersampled plan's passes: its uniform pixels whose 3x3 neighbourhood of
    uniform pixels' radiances (their center samples, at their first sub-pixels) spreads by
    more than ``rtol`` (default REFINE_RTOL; module docstring), to be shaded at every
    sub-pixel (csrc/lattice.c's ``refine``, else :func:`_refine_torch`: the same
    decisions). Returns their (B, H/n, W/n) mask and the (B, H, W) sub-pixels still to
    shade (those after the first; the first too where the lattice interpolated the center
    sample), or None where there are none.

    Args:
        radiance: (B, H, W, 3), the passes' (sub-)pixel radiance.
    """
    more = spread(plan.uniform, radiance, rtol)
    if not bool(more.any()):
        return None
    n = plan.n
    rest = torch.zeros(radiance.shape[:3], dtype=torch.bool, device=radiance.device)
    for v in _subs(rest, n)[1:]:
        v |= more  # (strided views: in place)
    if plan.lattice is not None:  # center samples the lattice interpolated: shaded now
        interpolated = torch.zeros_like(more)
        for level in plan.lattice.levels:
            s = level.stride
            interpolated[:, ::s, ::s] |= (level.status == 3) | (level.status == 5)
        rest[:, ::n, ::n] |= more & interpolated
    return more, rest


def spread(uniform: torch.Tensor, radiance: torch.Tensor, rtol: float | None = None
           ) -> torch.Tensor:
    """:func:`refine`'s test: the pixels of ``uniform`` (B, H/n, W/n) whose 3x3
    neighbourhood of uniform pixels' radiances (at their first sub-pixels of ``radiance``,
    (B, H, W, 3)) spreads by more than ``rtol`` (default REFINE_RTOL) times their mean
    luminance; csrc/lattice.c's ``refine``, else :func:`_refine_torch` (the same decisions)."""
    rtol = REFINE_RTOL if rtol is None else rtol
    more = native.refine(uniform, radiance, rtol)
    if more is None:
        n = radiance.shape[1] // uniform.shape[1]
        more = _refine_torch(uniform, radiance.detach()[:, ::n, ::n], rtol)
    return more


def _refine_torch(uniform: torch.Tensor, first: torch.Tensor, rtol: float) -> torch.Tensor:
    """csrc/lattice.c's ``refine`` in tensor code: ``uniform`` (B, h, w) and each pixel's
    first sub-pixel's radiance ``first`` (B, h, w, 3); the luminances summed down each
    column of the neighbourhood, the columns left to right (the kernel slides them)."""
    b, h, w, _ = first.shape
    u = torch.nn.functional.pad(uniform, (1, 1, 1, 1))
    v = torch.nn.functional.pad(first.permute(0, 3, 1, 2), (1, 1, 1, 1)).permute(0, 2, 3, 1)
    hi = torch.full_like(first, float("-inf"))
    lo = torch.full_like(first, float("inf"))
    total = torch.zeros(b, h, w, dtype=first.dtype, device=first.device)
    count = torch.zeros(b, h, w, dtype=first.dtype, device=first.device)
    bad = torch.zeros(b, h, w, dtype=torch.bool, device=first.device)
    for dx in range(3):
        column = torch.zeros_like(total)
        for dy in range(3):
            on = u[:, dy:dy + h, dx:dx + w]
            q = v[:, dy:dy + h, dx:dx + w]
            hi = torch.where(on[..., None], torch.maximum(hi, q), hi)
            lo = torch.where(on[..., None], torch.minimum(lo, q), lo)
            column = torch.where(on, column + ((q[..., 0] + q[..., 1]) + q[..., 2]) / 3.0,
                                 column)
            count = count + on.to(first.dtype)
            bad |= on & ~torch.isfinite(q).all(-1)
        total = total + column
    d = hi - lo
    spread = torch.maximum(torch.maximum(d[..., 0], d[..., 1]), d[..., 2])
    mean = total / count.clamp(min=1.0) + 1e-3
    return uniform & ~bad & (spread > rtol * mean)


def _center_samples(g: GBuffer, sel: torch.Tensor, tris: torch.Tensor, d: torch.Tensor
                    ) -> None:
    """The sub-pixels ``sel`` (flat) of ``g``'s front layer and rays replaced, in place, by
    the samples along ``d`` (len(sel), 3): each on the one of its pixel's sub-pixel
    triangles ``tris`` (len(sel), n*n) that the center ray hits (the most inside one:
    largest smallest barycentric)."""
    b, h, w = g.shape
    bi = sel // (h * w)
    eye = take(g.eye, bi)
    m = tris.shape[1]
    ts, bs = intersect_triangles(eye[:, None].expand(-1, m, -1), d[:, None].expand(-1, m, -1),
                                 g.meshes.tri_vertices[tris])  # (N, m), (N, m, 3)
    best = bs.amin(-1).argmax(-1)  # the first of equal ones
    pick = torch.arange(len(sel))
    tri, t, bary = tris[pick, best], ts[pick, best], bs[pick, best]
    fwd = take(g.proj[:, 9:12], bi)
    values = {
        "tri": tri,
        "position": eye + t[:, None] * d,
        "dist": t,
        "depth": t * dot(d, fwd),
        "bary": bary,
        "normal": normalize(interpolate(bary, take(g.meshes.tri_normals, tri))),
        "uv": interpolate(bary, take(g.meshes.tri_uvs, tri)),
    }
    for name, v in values.items():  # in place: the render's own layer
        x = getattr(g.front, name)
        x.view(-1, *x.shape[3:])[sel] = v.to(x.dtype)
    g.ray_dir.view(-1, 3)[sel] = d.to(g.ray_dir.dtype)


@dataclass(frozen=True)
class Level:
    """One level of adaptive shading at one sample per pixel (or over a supersampled
    plan's center samples: ``sub``), on the pixels of stride ``stride`` (1: every pixel;
    2: the even rows and columns; 4: a coarser level, COARSEST): ``status`` (B, H/s, W/s)
    uint8 on them, 0 not the object, 1 shaded before the level is filled, 2 waiting for its
    lattice neighbours (csrc/lattice.c; :func:`fill` turns 2 into 3, interpolated, 4,
    shaded in the level's own pass, or 5, shaded there and blended with the
    interpolation), and ``gap`` (B, H/s, W/s) float32: a waiting pixel's G-buffer gap to
    its neighbours, its measures over their tolerances (<= 1; 0 elsewhere)."""

    stride: int
    status: torch.Tensor
    gap: torch.Tensor
    sub: int = 1
    """The G-buffer's sub-pixels per pixel side: the level's pixels are the frame's
    (sub-)pixels of stride ``stride * sub`` (a supersampled G-buffer: the uniform pixels'
    center samples, at each pixel's first sub-pixel)."""

    @property
    def frame_stride(self) -> int:
        return self.stride * self.sub


@dataclass(frozen=True)
class Lattice:
    """Adaptive shading at one sample per pixel (or over a supersampled plan's center
    samples): its levels, coarsest first (the even pixels' level, where it pays, then
    every pixel's)."""

    levels: tuple[Level, ...]


def _neighbours(idx: torch.Tensor, h: int, w: int
                ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Each flat pixel's lattice neighbours (N, 4) (the two of a pixel between two lattice
    pixels repeated), whether it has four, and whether it has any inside the frame (False
    for a lattice pixel, and one on the last row or column without its second)."""
    x, y = idx % w, (idx // w) % h
    ox, oy = (x % 2) == 1, (y % 2) == 1
    diag = ox & oy
    step = torch.where(ox, torch.ones_like(idx), torch.full_like(idx, w))
    n0 = torch.where(diag, idx - w - 1, idx - step)
    n1 = torch.where(diag, idx - w + 1, idx + step)
    n2 = torch.where(diag, idx + w - 1, n0)
    n3 = torch.where(diag, idx + w + 1, n1)
    valid = (ox | oy) & ~(ox & (x + 1 >= w)) & ~(oy & (y + 1 >= h))
    return torch.stack([n0, n1, n2, n3], 1), diag, valid


def _inv_tol(tol: torch.Tensor | float) -> torch.Tensor:
    """The float32 reciprocal of a tolerance (below 1e-30 taken as 1e-30; csrc/lattice.c's
    inv_tol): a measure times it is the measure over the tolerance."""
    tol = torch.as_tensor(tol, dtype=torch.float32)
    return 1.0 / tol.clamp(min=1e-30)


def _lattice_torch(fm, bm, fn, bn, bd, alpha, alpha_min: float, normal_tol: float,
                   depth_tol: float, uniform: torch.Tensor | None = None
                   ) -> tuple[torch.Tensor, torch.Tensor]:
    """The tensor code of csrc/lattice.c's plan: (B, H, W) uint8 status and float32 gap
    (:class:`Level`); ``uniform`` (B, H, W) bool: the pixels that may wait or be waited on
    (None: all)."""
    b, h, w = fm.shape
    n = b * h * w
    status = torch.zeros(n, dtype=torch.uint8, device=fm.device)
    gap_out = torch.zeros(n, device=fm.device)
    obj = where_true(fm.reshape(-1))
    status[obj] = 1
    nb, _, valid = _neighbours(obj, h, w)
    nb = nb.clamp(0, n - 1)  # out of the frame only where not valid
    al = alpha.expand(b, h, w).reshape(-1).float()
    fmf, bmf, bdf = fm.reshape(-1), bm.reshape(-1), bd.reshape(-1)
    fnf, bnf = fn.reshape(-1, 3), bn.reshape(-1, 3)
    p_bm, p_bd = take(bmf, obj), take(bdf, obj)
    p_fn, p_bn = take(fnf, obj), take(bnf, obj)
    tol = depth_tol * p_bd.abs()
    wait = valid.clone()
    uf = None if uniform is None else uniform.reshape(-1)
    if uf is not None:
        wait &= take(uf, obj)
    inv_n, inv_d = _inv_tol(normal_tol), _inv_tol(tol)
    alpha_min = torch.tensor(alpha_min, dtype=torch.float32)
    gap = alpha_min * _inv_tol(take(al, obj))
    for k in range(4):
        q = nb[:, k]
        wait &= take(fmf, q) & (take(bmf, q) == p_bm)
        if uf is not None:
            wait &= take(uf, q)
        gap = torch.maximum(gap, alpha_min * _inv_tol(take(al, q)))
        gap = torch.maximum(gap, (1.0 - dot(take(fnf, q), p_fn)) * inv_n)
        back = torch.maximum((1.0 - dot(take(bnf, q), p_bn)) * inv_n,
                             (take(bdf, q) - p_bd).abs() * inv_d)
        gap = torch.where(p_bm, torch.maximum(gap, back), gap)
    wait &= gap <= 1.0
    sel = where_true(wait)
    status[take(obj, sel)] = 2
    gap_out[take(obj, sel)] = take(gap, sel)
    return status.view(b, h, w), gap_out.view(b, h, w)


def _plan(fm, bm, fn, bn, bd, alpha, smooth_alpha: float, normal_tol: float,
          depth_tol: float, stride: int = 1, uniform: torch.Tensor | None = None
          ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """A level's status and gap over the (B, H, W) layers' pixels of stride ``stride``
    (csrc/lattice.c, reading them in place; else the tensor code on copies), and its
    :func:`_counts`; ``uniform``: on the level's pixels, those that may wait or be waited
    on (None: all)."""
    tols = (smooth_alpha, normal_tol, depth_tol)
    out = native.lattice_plan(fm, bm, fn, bn, bd, alpha, *tols, stride=stride,
                              uniform=uniform)
    if out is not None:
        return out
    if stride > 1:
        on = (slice(None), slice(None, None, stride), slice(None, None, stride))
        if alpha.shape[1:] == fm.shape[1:]:  # per pixel (else per view)
            alpha = alpha[on].contiguous()
        fm, bm, fn, bn, bd = (x[on].contiguous() for x in (fm, bm, fn, bn, bd))
    status, gap = _lattice_torch(fm, bm, fn, bn, bd, alpha, *tols, uniform=uniform)
    return status, gap, _counts(status)


def _counts(status: torch.Tensor) -> torch.Tensor:
    """(B, 2) int64: each view's object pixels (status > 0) and waiting pixels (status 2)
    of a (B, H, W) plan."""
    flat = status.flatten(1)
    return torch.stack([(flat > 0).sum(1), (flat == 2).sum(1)], 1)


def lattice(g: GBuffer, alpha: torch.Tensor, normal_tol: float = NORMAL_TOL,
            depth_tol: float = DEPTH_TOL, smooth_alpha: float = SMOOTH_ALPHA,
            coarse_share: float | None = None, uniform: torch.Tensor | None = None,
            region: torch.Tensor | None = None) -> tuple[GBuffer, Lattice | None]:
    """The G-buffer of the first pass (``shade``) and the plan, for a G-buffer of one
    sample per pixel (module docstring). Each view decides alone, so that a batch's images
    are those of its views rendered alone (and of any chunking): a view where under
    FINE_SHARE of the object pixels could wait shades every pixel at once; every other
    view's pixels wait on its even pixels, and where at least ``coarse_share`` (default
    COARSE_SHARE) of its even object pixels can themselves wait on the pixels of stride 4
    (smooth regions spanning several pixels), a level on the even pixels comes first; and
    so on up to COARSEST (a level at stride 4 where enough of those can wait on stride 8).
    The first pass shades what no level lets wait; ``g`` and None where no view waits at all.
    A waiting pixel is rough and so are its lattice neighbours, which an earlier pass
    shades: each pass has a rough pixel where the full pass has one (the methods' switch
    of the rough interfaces' energies, :func:`torchrefract.tiles.shade`).

    A supersampled G-buffer after :func:`plan` (``uniform``: its uniform pixels, whose
    first sub-pixels hold their center samples) gets the same levels over those center
    samples: only a uniform pixel waits, and only on uniform lattice neighbours (a
    non-uniform pixel is shaded at every sub-pixel; its first sub-pixel is not a center
    sample); ``g.shade`` (the plan's) then loses the waiting ones.

    Args:
        alpha: the front roughness, per (sub-)pixel (B, H, W) or per view (B, 1, 1).
        region: (B, H, W) bool: the only (sub-)pixels shaded (None: all). The levels see
            the object only there, so a pixel inside never waits on one outside.
    """
    n = g.supersample
    if n > 1 and uniform is None:
        raise ValueError("adaptive.lattice: a supersampled G-buffer needs its plan's uniform "
                         "pixels")
    share = COARSE_SHARE if coarse_share is None else coarse_share
    front = g.front.mask if region is None else g.front.mask & region
    # the (sub-)pixels shaded so far (the plan's, or the object's), in the region
    shaded = front if g.shade is None else (g.shade if region is None else g.shade & region)
    layers = (front, g.back.mask, g.front.normal, g.back.normal, g.back.depth)
    # the plan's tolerances: where blending ends (BLEND_FROM)
    tol = (smooth_alpha * BLEND_FROM, normal_tol / BLEND_FROM, depth_tol / BLEND_FROM)
    status, gap, counts = _plan(*layers, alpha, *tol, stride=n, uniform=uniform)
    views = _waits(counts, FINE_SHARE)
    if not any(views):  # every pixel shaded (in the region only)
        return (g if region is None else replace(g, shade=shaded)), None
    _no_wait(status, views)
    levels = [Level(1, status, gap, sub=n)]
    stride = 2
    while stride <= COARSEST:  # a coarser level on the last one's lattice, where it pays
        status, gap, counts = _plan(*layers, alpha, *tol, stride=stride * n, uniform=None
                                    if uniform is None else uniform[:, ::stride, ::stride])
        views = [v and w for v, w in zip(views, _waits(counts, share))]
        if not any(views):
            break
        _no_wait(status, views)
        levels.insert(0, Level(stride, status, gap, sub=n))
        stride *= 2
    # the first pass: the (sub-)pixels shaded so far, less the levels' waiting pixels
    first = shaded.clone(memory_format=torch.contiguous_format)
    for level in levels:
        _clear_waiting(first, level.status, level.frame_stride)
    return replace(g, shade=first), Lattice(levels=tuple(levels))


def _clear_waiting(first: torch.Tensor, status: torch.Tensor, stride: int) -> None:
    """In place: a level's waiting pixels out of the first pass's (B, H, W) mask ``first``,
    ``first[:, ::stride, ::stride] &= status != 2`` (csrc/index.c where it runs)."""
    if not native.clear_waiting(first, status, stride):
        first[:, ::stride, ::stride] &= status != 2


def waiting(level: Level) -> bool:
    """Whether any pixel of ``level`` still waits (:func:`fill` not run on it yet; a level
    of :func:`lattice` starts with at least one, and a fused kernel that fills the levels
    itself, ``GBuffer.lattice``, fills them all: the first, the smallest, tells). A fill
    turns every waiting pixel (2) into 3-5, so the largest status tells, in one reduction
    without a mask."""
    return level.status.numel() > 0 and int(level.status.max()) == 2


def _waits(counts: torch.Tensor, share: float) -> list[bool]:
    """Per view, from a level's (B, 2) counts of object and waiting pixels: whether some
    pixels wait, and at least ``share`` of its object pixels (Python numbers: a render
    takes these decisions a few times, and tiny tensor ops cost ~5 us each)."""
    return [waiting > 0 and waiting >= share * objects for objects, waiting in counts.tolist()]


def _no_wait(status: torch.Tensor, views: list[bool]) -> None:
    """In place: the (B, H, W) status of every view not in ``views`` (B bools) without
    waiting pixels (its object pixels shaded in the first pass)."""
    for i, v in enumerate(views):
        if not v:
            status[i].clamp_(max=1)


def _mean(v: torch.Tensor, four: torch.Tensor) -> torch.Tensor:
    """(N, C) mean of the neighbours' values v (N, 4, C): of four, or of the first two."""
    s = v[:, 0] + v[:, 1]
    return torch.where(four[:, None], ((s + v[:, 2]) + v[:, 3]) * 0.25, s * 0.5)


def _fill_torch(status: torch.Tensor, gap: torch.Tensor, weight: torch.Tensor,
                flat: torch.Tensor, rtol: float, blend_from: float,
                passes: list[torch.Tensor] = ()) -> None:
    """The tensor code of csrc/lattice.c's fill, in place on ``status`` (B, H, W), ``weight``
    (B, H, W; written at status 5), ``flat`` (B*H*W, 3) and each of ``passes`` (B*H*W, C),
    with the plan's ``gap`` (B, H, W)."""
    _, h, w = status.shape
    st = status.view(-1)
    idx = where_true(st == 2)
    nb, four, _ = _neighbours(idx, h, w)
    v = take(flat, nb.reshape(-1)).view(-1, 4, 3)
    mean = _mean(v, four)
    lum = ((mean[:, 0] + mean[:, 1]) + mean[:, 2]) / 3.0 + 1e-3
    rel = (v.amax(1) - v.amin(1)) / lum[:, None]
    finite = torch.isfinite(rel).all(-1)
    t = torch.maximum(take(gap.view(-1), idx), rel.nan_to_num(float("inf")).amax(-1) / rtol)
    ok = finite & (t < 1.0)
    soft = ok & (t > blend_from)
    sel = where_true(ok)
    done, nb, four = take(idx, sel), take(nb, sel), take(four, sel)
    put_(flat, done, take(mean, sel))
    for x in passes:
        put_(x, done, _mean(take(x, nb.reshape(-1)).view(len(done), 4, x.shape[-1]), four))
    ss = where_true(soft)
    u = (take(t, ss) - blend_from) / (torch.ones((), dtype=t.dtype) - blend_from)
    put_(weight.view(-1), take(idx, ss), u * u * (3.0 - 2.0 * u))
    st[idx] = torch.where(soft, 5, torch.where(ok, 3, 4)).to(st.dtype)


def fill_rtol(level: Level, blend_from: float = BLEND_FROM) -> float:
    """The spread of a waiting pixel's neighbours' radiances over their luminance from which
    it is shaded alone (where blending ends): LATTICE_RTOL over the level's stride (the
    error of a mean over twice the spacing grows faster than the neighbours' spread), over
    ``blend_from``. :func:`fill`'s default, and csrc/lattice.c's (shading.fused)."""
    return LATTICE_RTOL / level.stride / blend_from


def fill(level: Level, radiance: torch.Tensor, passes: dict[str, torch.Tensor],
         rtol: float | None = None, blend_from: float | None = None
         ) -> tuple[torch.Tensor, dict[str, torch.Tensor], torch.Tensor | None,
                    tuple[torch.Tensor, torch.Tensor] | None]:
    """After the passes before ``level``: each of its waiting pixels its lattice
    neighbours' mean where their radiances agree, in ``radiance`` (B, H, W, 3) and the
    method's ``passes`` (B, H, W, C) (``level.status`` in place). Returns the radiance,
    the passes, the (B, H, W) mask of the pixels the level's own pass shades (None: none),
    and of those the ones to blend with their mean (:func:`merge`): their flat (B*H*W)
    indices and smoothstep weights (None: none). ``rtol``: where blending ends, default
    :func:`fill_rtol` (``blend_from``: default BLEND_FROM)."""
    blend_from = BLEND_FROM if blend_from is None else blend_from
    rtol = fill_rtol(level, blend_from) if rtol is None else rtol
    b, h, w, _ = radiance.shape
    radiance = radiance.contiguous()
    passes = {k: v.contiguous() for k, v in passes.items()}
    s = level.frame_stride
    on = (slice(None), slice(None, None, s), slice(None, None, s))
    # the level's pixels, contiguous (copies at a stride above 1, written back below)
    sub = radiance if s == 1 else radiance[on].contiguous()
    psub = {k: (v if s == 1 else v[on].contiguous()) for k, v in passes.items()}
    n = level.status.numel()
    flat = sub.view(-1, 3)
    pflat = [v.view(n, -1) for v in psub.values()]
    weight = torch.zeros(level.status.shape, device=flat.device)
    grad = flat.requires_grad or any(v.requires_grad for v in pflat)
    if grad or not native.lattice_fill(level.status, level.gap, weight, flat, rtol,
                                       blend_from, pflat):
        _fill_torch(level.status, level.gap, weight, flat, rtol, blend_from, pflat)
    if s > 1:
        radiance[on] = sub
        for k, v in psub.items():
            passes[k][on] = v
    rest = level.status >= 4
    if not bool(rest.any()):
        return radiance, passes, None, None
    five = where_true(level.status.view(-1) == 5)
    soft = None
    if five.numel():
        hs, ws = level.status.shape[1:]  # the level's pixel (bi, y, x) at (bi, s y, s x)
        full_idx = ((five // (hs * ws)) * h + (five // ws) % hs * s) * w + five % ws * s
        soft = (full_idx, take(weight.view(-1), five))
    if s > 1:
        full = torch.zeros(b, h, w, dtype=torch.bool, device=rest.device)
        full[on] = rest
        rest = full
    return radiance, passes, rest, soft


def merge(radiance: torch.Tensor, passes: dict[str, torch.Tensor], second,
          rest: torch.Tensor, soft: tuple[torch.Tensor, torch.Tensor] | None = None
          ) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """The second pass's radiance (it shaded ``rest`` (B, H, W) over the first's image)
    and the first pass's passes with the second's values at ``rest``; at the pixels of
    ``soft`` (:func:`fill`) the first's value (the mean) plus the weight times the
    difference to the second's."""
    rest = where_true(rest.view(-1))
    out = {}
    for k, v in second.passes.items():
        if k not in passes:
            out[k] = v
            continue
        c = v.shape[-1]
        first = passes[k].reshape(-1, c)
        shaded = v.reshape(-1, c)
        # the blended pixels' means, read before the rest's values overwrite them in place
        mean = take(first, soft[0]) if soft is not None else None
        x = put_(first, rest, take(shaded, rest))
        if soft is not None:
            x = _put(x, soft[0], _blend(mean, take(shaded, soft[0]), soft[1]))
        out[k] = x.view(passes[k].shape)
    rad = second.radiance
    if soft is not None:
        i5, w5 = soft
        flat = rad.reshape(-1, 3)
        mean = take(radiance.reshape(-1, 3), i5)
        rad = _put(flat, i5, _blend(mean, take(flat, i5), w5)).view(rad.shape)
    return rad, {**passes, **out}


def _put(x: torch.Tensor, idx: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """x with rows ``idx`` set to ``v``: in place (the pass's own buffer), or a new tensor
    where a gradient flows through either (autograd keeps x's old values)."""
    if x.requires_grad or v.requires_grad:
        return x.index_put((idx,), v)
    return put_(x, idx, v)


def _blend(mean: torch.Tensor, shaded: torch.Tensor, weight: torch.Tensor) -> torch.Tensor:
    """(N, C) the mean plus ``weight`` (N,) times the way to the shaded value."""
    return mean + weight[:, None] * (shaded - mean)


__all__ = ["BLEND_FROM", "COARSE_SHARE", "COARSEST", "DEPTH_TOL", "FINE_SHARE",
           "LATTICE_RTOL", "NORMAL_TOL", "REFINE_RTOL", "SMOOTH_ALPHA", "Lattice", "Level",
           "Plan", "fill", "fill_rtol", "lattice", "merge", "plan", "refine", "spread",
           "waiting"]

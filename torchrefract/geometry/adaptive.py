"""Adaptive supersampling: all n x n sub-pixels of a pixel are shaded only where they can
differ; elsewhere one sample at the pixel's center stands for them (issue #28, "model no
more than a scene needs"). Opt-in: ``RenderSettings(adaptive=True)``.

A pixel's sub-pixels can differ where the G-buffer changes inside it: a silhouette or a
layer's edge (the front or back coverage differs among them), a fold (their front or back
shading normals differ by more than ``normal_tol`` in 1 - cos), or a step of the back layer
(its depth differs by more than ``depth_tol`` relative), or a smooth surface (roughness
below ``smooth_alpha``: a sharp refraction shows the environment's detail inside the
pixel). Such pixels are shaded at every
sub-pixel as the uniform n x n sampling does. In the others the first sub-pixel is replaced
by the exact sample through the pixel's center (the center ray intersected with that
sub-pixel's front triangle: position, distance, depth, shading normal, UV), shaded alone,
and its radiance and passes are copied to the other sub-pixels before the box filter: the
image of a pixel whose G-buffer is smooth inside it, at a quarter of the shading (n = 2).
The back layer, which the marches read, stays the n x n one; the center sample lies on
the sub-pixel triangle its ray hits (the most inside of the pixel's). What the G-buffer cannot show
(a TIR boundary, a sharp feature of the environment seen through a smooth pixel) is not
detected: there one sample stands for the pixel.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import torch

from torchrefract.geometry.gbuffer import GBuffer, interpolate, intersect_triangles
from torchrefract.kernels.index import take
from torchrefract.optics.smooth import dot, normalize

NORMAL_TOL = 1e-2
"""1 - cos of the largest angle between a pixel's sub-pixel normals it shades once (~8 deg)."""
DEPTH_TOL = 0.05
"""The largest relative step of the back layer's depth inside a pixel it shades once."""
SMOOTH_ALPHA = 0.02
"""Below this roughness every sub-pixel is shaded: a sharp refraction resolves the
environment's detail inside a pixel, which the G-buffer does not show (measured on the
smooth sphere: docs/decisions.md, "Adaptive supersampling")."""


@dataclass(frozen=True)
class Plan:
    """Which pixels are shaded once: ``uniform`` (B, H/n, W/n) bool, for a G-buffer of
    supersampling n."""

    uniform: torch.Tensor
    n: int


def _subs(x: torch.Tensor, n: int) -> list[torch.Tensor]:
    """The n*n strided views (B, H/n, W/n, ...) of a (B, H, W, ...) tensor, one per
    sub-pixel position of a pixel, row-major (no copies)."""
    return [x[:, i::n, j::n] for i in range(n) for j in range(n)]


def plan(g: GBuffer, center_dirs: torch.Tensor, alpha: torch.Tensor,
         normal_tol: float = NORMAL_TOL, depth_tol: float = DEPTH_TOL,
         smooth_alpha: float = SMOOTH_ALPHA) -> tuple[GBuffer, Plan]:
    """The G-buffer to shade and the plan (module docstring). Writes the center samples
    into ``g``'s front layer and rays (a render's own G-buffer).

    Args:
        g: a G-buffer of supersampling n > 1.
        center_dirs: (B, H/n, W/n, 3) unit rays through the pixels' centers.
        alpha: the front roughness of each sub-pixel, broadcastable to (B, H, W) (per view:
            (B, 1, 1)): a pixel with a sub-pixel smoother than ``smooth_alpha`` is shaded
            at all of them.

    Returns:
        The G-buffer with ``shade`` set (the sub-pixels to shade), and the plan.
    """
    n = g.supersample
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
    _, h, w = g.shape
    pb, py, px = uniform.nonzero(as_tuple=True)  # the uniform pixels
    sel = (pb * h + py * n) * w + px * n  # their first sub-pixels, flat
    tris = torch.stack([t[uniform] for t in _subs(g.front.tri, n)], 1)
    _center_samples(g, sel, tris, center_dirs[uniform])
    shade = g.front.mask.clone()
    for k, v in enumerate(_subs(shade, n)):
        if k:
            v[uniform] = False
    return replace(g, shade=shade), Plan(uniform=uniform, n=n)


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
    v0, v1, v2 = g.meshes.tri_vertices[tri].unbind(-2)
    values["geo_normal"] = normalize(torch.cross(v1 - v0, v2 - v0, dim=-1))  # by winding
    for name, v in values.items():  # in place: the render's own layer
        x = getattr(g.front, name)
        x.view(-1, *x.shape[3:])[sel] = v.to(x.dtype)
    g.ray_dir.view(-1, 3)[sel] = d.to(g.ray_dir.dtype)


def spread(p: Plan, radiance: torch.Tensor, passes: dict[str, torch.Tensor]
           ) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """Each uniform pixel's first sub-pixel copied to its others: radiance (B, H, W, 3) and
    the method's passes (B, H, W, C), in place."""
    for x in (radiance, *passes.values()):
        subs = _subs(x, p.n)
        v0 = subs[0][p.uniform]
        for v in subs[1:]:
            v[p.uniform] = v0
    return radiance, passes


__all__ = ["DEPTH_TOL", "NORMAL_TOL", "SMOOTH_ALPHA", "Plan", "plan", "spread"]

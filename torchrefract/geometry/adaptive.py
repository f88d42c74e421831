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

from torchrefract.geometry.gbuffer import GBuffer, Layer, interpolate, intersect_triangles
from torchrefract.kernels.index import take
from torchrefract.optics.smooth import dot, normalize

NORMAL_TOL = 1e-2
"""1 - cos of the largest angle between a pixel's sub-pixel normals it shades once (~8 deg)."""
DEPTH_TOL = 0.05
"""The largest relative step of the back layer's depth inside a pixel it shades once."""
SMOOTH_ALPHA = 0.02
"""Below this roughness every sub-pixel is shaded: a sharp refraction resolves the
environment's detail inside a pixel, which the G-buffer does not show (the smooth sphere
with two internal bounces: one sample per pixel there lost 0.005 of FLIP against the truth
that uniform 2x2 sampling gains)."""


@dataclass(frozen=True)
class Plan:
    """Which pixels are shaded once: ``uniform`` (B, H/n, W/n) bool, for a G-buffer of
    supersampling n."""

    uniform: torch.Tensor
    n: int


def _blocks(x: torch.Tensor, n: int) -> torch.Tensor:
    """(B, H, W, ...) -> (B, H/n, W/n, n*n, ...): each pixel's sub-pixels, row-major."""
    b, h, w = x.shape[:3]
    rest = x.shape[3:]
    y = x.reshape(b, h // n, n, w // n, n, *rest).transpose(2, 3)
    return y.reshape(b, h // n, w // n, n * n, *rest)


def _first(n: int, shape: tuple[int, int, int]) -> torch.Tensor:
    """(B, H, W) bool: the first sub-pixel of every pixel."""
    b, h, w = shape
    first = torch.zeros(n, n, dtype=torch.bool)
    first[0, 0] = True
    return first.repeat(h // n, w // n)[None].expand(b, h, w)


def plan(g: GBuffer, center_dirs: torch.Tensor, alpha: torch.Tensor,
         normal_tol: float = NORMAL_TOL, depth_tol: float = DEPTH_TOL,
         smooth_alpha: float = SMOOTH_ALPHA) -> tuple[GBuffer, Plan]:
    """The G-buffer to shade and the plan (module docstring).

    Args:
        g: a G-buffer of supersampling n > 1.
        center_dirs: (B, H/n, W/n, 3) unit rays through the pixels' centers.
        alpha: (B, H, W) the front roughness of each sub-pixel: a pixel with a sub-pixel
            smoother than ``smooth_alpha`` is shaded at all of them.

    Returns:
        The G-buffer with the center samples in the uniform pixels' first sub-pixels and
        ``shade`` set (the sub-pixels to shade), and the plan.
    """
    n = g.supersample
    fm, bm = _blocks(g.front.mask, n), _blocks(g.back.mask, n)
    same = (fm == fm[..., :1]).all(-1) & (bm == bm[..., :1]).all(-1)
    for lay in (g.front, g.back):
        nb = _blocks(lay.normal, n)
        same &= (1.0 - dot(nb, nb[..., :1, :])).amax(-1) <= normal_tol
    bd = _blocks(g.back.depth, n)
    same &= ((bd - bd[..., :1]).abs().amax(-1) <= depth_tol * bd[..., 0].abs())
    same &= _blocks(alpha, n).amin(-1) >= smooth_alpha
    uniform = same & fm[..., 0]  # covered and smooth inside (empty pixels cost nothing)
    first = _first(n, g.shape)
    up = uniform.repeat_interleave(n, 1).repeat_interleave(n, 2)  # (B, H, W)
    sel = (up & first).reshape(-1).nonzero(as_tuple=True)[0]
    front, ray_dir = _center_samples(g, sel, _blocks(g.front.tri, n)[uniform],
                                     center_dirs[uniform])
    shade = g.front.mask & (first | ~up)
    return replace(g, front=front, ray_dir=ray_dir, shade=shade), Plan(uniform=uniform, n=n)


def _center_samples(g: GBuffer, sel: torch.Tensor, tris: torch.Tensor, d: torch.Tensor
                    ) -> tuple[Layer, torch.Tensor]:
    """The front layer and rays with the sub-pixels ``sel`` (flat) replaced by the samples
    along ``d`` (len(sel), 3): each on the one of its pixel's sub-pixel triangles ``tris``
    (len(sel), n*n) that the center ray hits (the most inside one: largest smallest
    barycentric)."""
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
    fields = {}
    v0, v1, v2 = g.meshes.tri_vertices[tri].unbind(-2)
    values["geo_normal"] = normalize(torch.cross(v1 - v0, v2 - v0, dim=-1))  # by winding
    for name in ("mask", "tri", "position", "dist", "depth", "bary", "geo_normal", "normal",
                 "uv"):
        x = getattr(g.front, name)
        if name in values:
            x = x.clone()
            x.reshape(-1, *x.shape[3:])[sel] = values[name].to(x.dtype)
        fields[name] = x
    ray_dir = g.ray_dir.clone()
    ray_dir.reshape(-1, 3)[sel] = d.to(ray_dir.dtype)
    return Layer(**fields), ray_dir


def spread(p: Plan, radiance: torch.Tensor, passes: dict[str, torch.Tensor]
           ) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """Each uniform pixel's first sub-pixel copied to its others: radiance (B, H, W, 3) and
    the method's passes (B, H, W, C), in place where they allow it."""
    def fill(x: torch.Tensor) -> torch.Tensor:
        xb = _blocks(x, p.n)  # a copy (the transpose), filled and put back
        xb[p.uniform] = xb[p.uniform][:, :1].expand_as(xb[p.uniform])
        b, hh, ww = p.uniform.shape
        return xb.reshape(b, hh, ww, p.n, p.n, *x.shape[3:]).transpose(2, 3).reshape(x.shape)

    return fill(radiance), {k: fill(v) for k, v in passes.items()}


__all__ = ["DEPTH_TOL", "NORMAL_TOL", "SMOOTH_ALPHA", "Plan", "plan", "spread"]

"""Pinhole camera of SCENE_SPEC.md: frame, per-pixel ray directions, projection.

Pixel (i, j), column i from the left and row j from the top, has its center at
(i + 0.5, j + 0.5); with forward f, right r = f x up, true up u = r x f, t = tan(yfov/2),
a = width / height:
``d = normalize(f + (2(i+0.5)/W - 1) t a r + (1 - 2(j+0.5)/H) t u)``.
With ``samples_per_pixel = n`` the image is rendered at (n H, n W) sub-pixel centers and
box-filtered back, which is exactly the n x n stratified grid of sub-pixel centers.
"""

from __future__ import annotations

import functools
import math

import numpy as np
import torch

from torchrefract.kernels import native
from torchrefract.optics.smooth import dot
from torchrefract.scene.model import Camera


def camera_frame(cam: Camera) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Eye, right, true up, forward as float64 (3,) arrays (Mitsuba ``look_at``)."""
    return tuple(np.array(a) for a in _camera_frame_cached(cam))  # callers may write to theirs


def camera_frame_floats(cam: Camera) -> tuple[tuple[float, float, float], ...]:
    """:func:`camera_frame` as tuples of Python floats (kept for the last cameras; the
    same values)."""
    return _camera_frame_cached(cam)


def _unit(v: tuple[float, float, float]) -> tuple[float, float, float]:
    """v over its length, the length as ``np.linalg.norm`` takes it for a float64 (3,)."""
    n = math.sqrt((v[0] * v[0] + v[1] * v[1]) + v[2] * v[2])
    return (v[0] / n, v[1] / n, v[2] / n)


def _cross(a: tuple[float, ...], b: tuple[float, ...]) -> tuple[float, float, float]:
    """``np.cross`` of two 3-vectors (the same products and differences)."""
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


@functools.lru_cache(maxsize=64)
def _camera_frame_cached(cam: Camera) -> tuple[tuple[float, float, float], ...]:
    """:func:`camera_frame` as tuples, kept for the last cameras: a render asks for each
    view's frame several times (rays, projection, the passes' matrices). Python floats,
    not numpy: the same float64 operations (each rounded once, no fused multiply-adds), at
    a tenth of numpy's cost for 3-vectors (a dataset's views are new in every batch)."""
    eye = tuple(float(x) for x in cam.eye)
    f = _unit(tuple(float(t) - e for t, e in zip(cam.target, eye)))
    r = _unit(_cross(f, tuple(float(x) for x in cam.up)))
    return eye, r, _cross(r, f), f


def screen_scale(cam: Camera) -> tuple[float, float]:
    """t = tan(yfov / 2) and the aspect a = width / height (module docstring's ray)."""
    return math.tan(math.radians(cam.yfov_deg) / 2.0), cam.width / cam.height


def camera_pose(cam: Camera) -> np.ndarray:
    """4x4 camera-to-world matrix in OpenGL convention (camera looks down -Z)."""
    eye, r, u, f = camera_frame(cam)
    pose = np.eye(4)
    pose[:3, 0], pose[:3, 1], pose[:3, 2], pose[:3, 3] = r, u, -f, eye
    return pose


def pixel_rays(cam: Camera, supersample: int = 1) -> torch.Tensor:
    """Unit ray directions through the (sub-)pixel centers.

    Args:
        cam: the camera.
        supersample: n; rays go through the n x n sub-pixel centers of each pixel.

    Returns:
        (n H, n W, 3) float32 world directions, row 0 at the top.

    Example:
        >>> d = pixel_rays(Camera(width=4, height=2))
        >>> d.shape
        torch.Size([2, 4, 3])
    """
    return views_pixel_rays([cam], supersample)[0]


def views_pixel_rays(cams: list[Camera] | tuple[Camera, ...], supersample: int = 1,
                     rows: tuple[int, int] | None = None) -> torch.Tensor:
    """:func:`pixel_rays` of views of one size, (B, n H, n W, 3), in one buffer (``rows``:
    only the sub-pixel rows [r0, r1), a strip of a large frame): the native kernel
    (csrc/gbuffer.c, the same bits) where it runs, else :func:`pixel_rays_rows` per view.
    Computed every time, not kept: a dataset's views are new in every batch, and the
    kernel is cheap beside the rest of a view (docs/benchmarks.md, "eleventh sitting")."""
    n = supersample
    c0 = cams[0]
    if any((c.width, c.height) != (c0.width, c0.height) for c in cams):
        raise ValueError("views_pixel_rays needs cameras of one width and height; got "
                         f"{sorted({(c.width, c.height) for c in cams})}")
    r0, r1 = (0, c0.height * n) if rows is None else rows
    out = native.pixel_rays(_ray_frames(cams), c0.height * n, c0.width * n, r0, r1)
    if out is not None:
        return out
    return torch.stack([pixel_rays_rows(cam, n, r0, r1) for cam in cams])


def _ray_frames(cams: list[Camera] | tuple[Camera, ...]) -> torch.Tensor:
    """(B, 11) float64 per view: forward, right, up, t and a (the ray kernels' frames)."""
    frames = []
    for cam in cams:
        _, r, u, f = _camera_frame_cached(cam)
        frames.append([*f, *r, *u, *screen_scale(cam)])
    return torch.tensor(frames, dtype=torch.float64)


def pixel_rays_rows(cam: Camera, supersample: int, r0: int, r1: int) -> torch.Tensor:
    """The rows [r0, r1) of :func:`pixel_rays` (the same values), (r1 - r0, n W, 3): a
    strip of a frame too large to hold whole (:mod:`torchrefract.large`). Not kept."""
    n = supersample
    h, w = cam.height * n, cam.width * n
    _, r, u, f = (torch.tensor(v, dtype=torch.float64) for v in _camera_frame_cached(cam))
    t, a = screen_scale(cam)
    # x depends on the column only, y on the row only: (f + x r) per column and y u per row,
    # added once over the image (each element's operations and order unchanged)
    # pixel indices as float64 (exact integers; kornia's create_meshgrid gave the same, and
    # its import cost every process memory: docs/decisions.md, "Peak memory")
    cols = torch.arange(w, dtype=torch.float64)[None, :, None]  # (1, w, 1)
    rows = torch.arange(r0, r1, dtype=torch.float64)[:, None, None]  # (r1 - r0, 1, 1)
    return _unit_rays(f, r, u, cols, rows, w, h, t, a)  # (r1 - r0, w, 3)


def _unit_rays(f: torch.Tensor, r: torch.Tensor, u: torch.Tensor, cols: torch.Tensor,
               rows: torch.Tensor, w: int, h: int, t, a) -> torch.Tensor:
    """The module docstring's ray through (sub-)pixel columns ``cols`` and rows ``rows``
    (float64, broadcast with the frame's f, r, u (..., 3) and its t, a) of a w x h grid,
    normalized and rounded to float32: ``(f + x r) + y u``, each in float64."""
    x = (2.0 * (cols + 0.5) / w - 1.0) * t * a
    y = (1.0 - 2.0 * (rows + 0.5) / h) * t
    d = (f + x * r) + y * u
    return (d / d.norm(dim=-1, keepdim=True)).to(torch.float32)


def subpixel_rays(cams: list[Camera] | tuple[Camera, ...], supersample: int,
                  rows: torch.Tensor, cols: torch.Tensor) -> torch.Tensor:
    """The rays of :func:`pixel_rays` at chosen sub-pixels of views of one size: ``rows``,
    ``cols`` (B, M) int64 coordinates on each view's n x n sub-pixel grid -> (B, M, 3)
    float32, by :func:`pixel_rays_rows`' float64 operations (sparse supersampling's
    samples, :mod:`torchrefract.geometry.subsamples`): the native kernel where it runs."""
    n = supersample
    fr = _ray_frames(cams)
    h, w = cams[0].height * n, cams[0].width * n
    out = native.rays_at(fr, h, w, rows, cols)  # csrc/gbuffer.c, the same bits
    if out is not None:
        return out
    fr = fr[:, None]  # (B, 1, 11)
    return _unit_rays(fr[..., 0:3], fr[..., 3:6], fr[..., 6:9], cols.double()[..., None],
                      rows.double()[..., None], w, h, fr[..., 9:10], fr[..., 10:11])


def projection_params(cam: Camera) -> torch.Tensor:
    """Packed camera for batched projection: (16,) float32.

    Layout: eye (3), right (3), up (3), forward (3), t*a, t, width, height, where
    t = tan(yfov/2), a = width/height.
    """
    return torch.tensor(packed_camera(cam), dtype=torch.float32)


def packed_camera(cam: Camera, supersample: int = 1) -> list[float]:
    """:func:`projection_params` as float64 Python numbers, its width and height those of
    the n x n sub-pixel grid (``supersample``): many views' rows become one tensor at once."""
    eye, r, u, f = _camera_frame_cached(cam)
    t, a = screen_scale(cam)
    return [*eye, *r, *u, *f, t * a, t, float(cam.width * supersample),
            float(cam.height * supersample)]


def project(points: torch.Tensor, params: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Project world points to continuous pixel coordinates.

    Args:
        points: (B, ..., 3) world positions.
        params: (B, 16) from :func:`projection_params` (width/height may be scaled by the
            supersampling factor).

    Returns:
        xy: (B, ..., 2) pixel coordinates (x to the right, y down; centers at +0.5).
        z: (B, ...) distance along the forward axis (negative behind the camera).
    """
    b = points.shape[0]
    shape = (b,) + (1,) * (points.dim() - 2)
    p = params.view(b, 16)
    eye, r, u, f = (p[:, i:i + 3].view(*shape, 3) for i in (0, 3, 6, 9))
    ta, t, w, h = (p[:, 12 + i].view(shape) for i in range(4))
    rel = points - eye
    z = dot(rel, f)
    zs = torch.where(z.abs() > 1e-12, z, torch.full_like(z, 1e-12))
    x = dot(rel, r) / (zs * ta)  # in [-1, 1] across the image
    y = dot(rel, u) / (zs * t)
    px = (x + 1.0) * 0.5 * w
    py = (1.0 - y) * 0.5 * h
    return torch.stack([px, py], -1), z

"""Sparse supersampling (issue #28, "model no more than a scene needs"). With n x n samples
per pixel and adaptive shading (the default), a method that shades its samples alone
(``Method.shades_samples``) renders the one-sample image (the G-buffer through the pixel
centers, shaded with :func:`~torchrefract.geometry.adaptive.lattice`) and replaces the
pixels whose samples can differ by the box filter of their n x n sub-pixel samples,
shaded from a G-buffer of those samples alone (:func:`gather`). No frame-sized buffer is
made at the sub-pixels but the rasterized ids (4 bytes a sub-pixel and layer), which both
passes march through (:func:`marched`), as the n x n render does.

A pixel is supersampled (:func:`edges`, csrc/lattice.c) where
- the rasterized coverage of its sub-pixels differs among them or from its center's, in
  either layer: a silhouette or a layer's edge inside it (the n x n render's own test);
  or its sub-pixels see triangles that fold against each other (``FACE_TOL``): a crease
  inside it;
- its center's front or back shading normal differs from a neighbour's (3x3, both
  covered) by more than ``NORMAL_TOL`` (1 - cos), or its back depth by more than
  ``DEPTH_TOL`` relative: a fold or a step (the n x n plan's tolerances inside a pixel,
  scaled to neighbours a pixel apart);
- its roughness is below ``adaptive.SMOOTH_ALPHA`` (a sharp refraction resolves the
  environment's detail inside the pixel);
and after the one-sample pass, where the radiances of its 3x3 neighbourhood of pixels
not picked so far spread by more than ``adaptive.REFINE_RTOL`` (:func:`adaptive.refine`'s
test: a TIR boundary, a sharp feature of the environment).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F

from torchrefract.geometry import adaptive
from torchrefract.geometry.camera import subpixel_rays
from torchrefract.geometry.gbuffer import GBuffer, _layer
from torchrefract.kernels import native
from torchrefract.kernels.march import Marched, plane_table
from torchrefract.optics.smooth import dot
from torchrefract.scene.model import Camera


NORMAL_TOL = 4 * adaptive.NORMAL_TOL
"""1 - cos between neighbouring pixel centers' normals above which a pixel is picked: the
n x n plan's tolerance between a pixel's sub-pixels (at most ~0.7 pixel apart), scaled to
centers twice as far (up to ~1.4 pixel: a smooth normal field turns twice the angle, and
1 - cos grows with its square)."""
DEPTH_TOL = 2 * adaptive.DEPTH_TOL
"""The relative step of the back depth between neighbouring pixel centers above which a
pixel is picked: the plan's, scaled the same way (a smooth slope changes twice as much)."""

FACE_TOL = 4 * adaptive.NORMAL_TOL
"""1 - cos between the face normals of two triangles seen inside one pixel (its
sub-pixels' rasterized ids) above which it is picked where they fold (:func:`_folds`): a
crease finer than the pixel (grooves), which neighbouring centers may not see. Triangles
whose shading normals meet at a common corner are a smooth surface however their faces
turn (a coarse mesh's neighbours)."""


FOLDS = (NORMAL_TOL, FACE_TOL)
"""The fold test's tolerances (:func:`_folds`), for the sub-pixel flags
(``gbuffer.build_sparse``)."""


@dataclass(frozen=True)
class Samples:
    """The sub-pixel samples of the picked pixels.

    Attributes:
        g: their G-buffer, (B, n K, n) for K pixels a view at most: pixel slot k of view b
            holds its n x n sub-pixels at rows [n k, n k + n), so that the box filter over
            n x n blocks gives (B, K, 1) pixels; slots past a view's pixels are empty.
        pixels: (B, K) int64 the pixel of each slot (y W + x in its view), -1 past a view's.
    """

    g: GBuffer
    pixels: torch.Tensor


def _changes(x: torch.Tensor, n: int) -> torch.Tensor:
    """(B, H, W) bool: the pixels whose n x n sub-pixels of ``x`` (B, n H, n W) bool are not
    all alike."""
    b, hh, ww = x.shape
    blocks = x.view(b, hh // n, n, ww // n, n)
    return blocks.any(4).any(2) != blocks.all(4).all(2)


def _folds(meshes, a: torch.Tensor, b: torch.Tensor, normal_tol: float, face_tol: float
           ) -> torch.Tensor:
    """(N,) bool: triangles ``a`` fold against triangles ``b`` (N,) (global ids): no
    corner of one lies where one of the other's does with a shading normal within
    ``normal_tol`` of it (there the interpolated normals meet: a smooth mesh's neighbours,
    however its faces turn), and their faces turn by more than ``face_tol``."""
    tv, tn, fn = meshes.tri_vertices, meshes.tri_normals, meshes.face_normals
    same = (tv[a][:, :, None] == tv[b][:, None]).all(-1)  # (N, 3, 3) corner pairs
    smooth = 1.0 - dot(tn[a][:, :, None], tn[b][:, None]) <= normal_tol
    return ~(same & smooth).any(-1).any(-1) & (1.0 - dot(fn[b], fn[a]) > face_tol)


def _edges_torch(g: GBuffer, ids: tuple[torch.Tensor, torch.Tensor], alpha: torch.Tensor,
                 normal_tol: float, depth_tol: float, smooth_alpha: float,
                 face_tol: float) -> torch.Tensor:
    """The tensor code of :func:`edges` (csrc/lattice.c's ``edges``: the same decisions)."""
    b, h, w = g.shape
    n = ids[0].shape[1] // h
    out = torch.zeros(b, h, w, dtype=torch.bool)
    for x, center in ((ids[0], g.front.mask), (ids[1], g.back.mask)):
        sub = x >= 0
        blocks = sub.view(b, h, n, w, n)
        out |= _changes(sub, n) | (blocks[:, :, 0, :, 0] != center)
        tri = x.long().view(b, h, n, w, n)
        first = tri[:, :, :1, :, :1].expand_as(tri)
        other = (tri != first) & (tri >= 0) & (first >= 0)
        fold = torch.zeros_like(other)
        fold[other] = _folds(g.meshes, first[other], tri[other], normal_tol, face_tol)
        out |= fold.any(4).any(2)
    fm, bm = g.front.mask, g.back.mask
    nf, nb, db = g.front.normal, g.back.normal, g.back.depth

    def shifted(x: torch.Tensor, dy: int, dx: int, fill) -> torch.Tensor:
        """x at (y + dy, x + dx), ``fill`` outside the frame."""
        pad = (0, 0) * (x.dim() - 3)
        p = F.pad(x, (*pad, 1, 1, 1, 1), value=fill) if x.dim() == 3 else \
            F.pad(x.movedim(-1, 1), (1, 1, 1, 1), value=fill).movedim(1, -1)
        return p[:, 1 + dy:1 + dy + h, 1 + dx:1 + dx + w]

    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            if dy == 0 and dx == 0:
                continue
            qf, qb = shifted(fm, dy, dx, False) & fm, shifted(bm, dy, dx, False) & bm
            out |= qf & (1.0 - dot(shifted(nf, dy, dx, 0.0), nf) > normal_tol)
            out |= qb & (1.0 - dot(shifted(nb, dy, dx, 0.0), nb) > normal_tol)
            out |= qb & ((shifted(db, dy, dx, 0.0) - db).abs() > depth_tol * db.abs())
    out |= fm & (alpha.expand(b, h, w) < smooth_alpha)
    return out


def edges(g: GBuffer, ids: tuple[torch.Tensor, torch.Tensor], alpha: torch.Tensor,
          region: torch.Tensor | None = None, flags: torch.Tensor | None = None
          ) -> torch.Tensor:
    """The pixels whose samples can differ, by their G-buffer (module docstring): (B, H, W)
    bool for the one-sample G-buffer ``g`` (B, H, W), both layers' rasterized ids on the
    n x n sub-pixel grid ``ids`` (B, n H, n W) and the front roughness ``alpha`` (B, H, W)
    or (B, 1, 1); within ``region`` (B, H, W) where given. ``flags``: the ids' sub-pixel
    flags where the rasterizer made them (``gbuffer.build_sparse`` with :data:`FOLDS`),
    else made here from the ids (``native.sub_flags``)."""
    tols = (NORMAL_TOL, DEPTH_TOL, adaptive.SMOOTH_ALPHA, FACE_TOL)
    if flags is None:
        n = ids[0].shape[1] // g.shape[1]
        flags = native.sub_flags(ids, native.SubTest(n, g.meshes, *FOLDS))
    out = None if flags is None else native.edges(
        g.front.mask, g.back.mask, g.front.normal, g.back.normal, g.back.depth, flags, alpha,
        *tols[:3])
    if out is None:
        out = _edges_torch(g, ids, alpha.detach(), *tols)
    return out if region is None else out & region


def refined(g: GBuffer, picked: torch.Tensor, radiance: torch.Tensor,
            region: torch.Tensor | None = None, rtol: float | None = None,
            background: torch.Tensor | None = None) -> torch.Tensor:
    """``picked`` and the object pixels not picked (within ``region``) whose 3x3
    neighbourhood of such pixels' one-sample radiances (B, H, W, 3) spreads
    (:func:`adaptive.spread`: the n x n plan's refinement test); with ``background``
    (B, H, W) bool, also those of its pixels (not the object's, not picked) whose
    neighbourhood among them spreads (a sphere light's edge in view)."""
    rest = g.front.mask & ~picked
    if region is not None:
        rest &= region
    out = picked | adaptive.spread(rest, radiance, rtol)
    if background is not None:
        out |= adaptive.spread(background & ~g.front.mask & ~picked, radiance, rtol)
    return out


def gather(g: GBuffer, ids: tuple[torch.Tensor, torch.Tensor], cameras: list[Camera],
           picked: torch.Tensor) -> Samples | None:
    """The G-buffer of the picked pixels' n x n sub-pixel samples (:class:`Samples`): the
    exact layers of the rasterized ids ``ids`` (B, n H, n W) int32 there (written in
    place: the samples' exact ids where they are), marching through ``g.marched``
    (:func:`marched` of ``ids``); None where no pixel is picked. ``cameras``: the views'
    at n x n."""
    b, h, w = picked.shape
    n = ids[0].shape[1] // h
    slots = _slots(picked, ids, n)
    if slots is None:
        return None
    pixels, rows, cols, sids, flat, taken = slots
    k = pixels.shape[1]
    dirs = subpixel_rays(cameras, n, rows, cols).view(b, n * k, n, 3)
    # the cameras as the one-sample frame's (g's): what a sample projects is in its pixels
    # (the ``footprint`` pass); the march reads proj's scale only
    eye, proj = g.eye, g.proj
    fwd = proj[:, 9:12].contiguous()
    layers = [_layer(x.view(b, n * k, n), eye, dirs, fwd, g.meshes, back=i == 1)
              for i, x in enumerate(sids)]
    # the marched ids: the samples' exact (repaired) ones where they are
    if not native.put_ids(ids, flat, taken, (layers[0].tri, layers[1].tri)):
        for x, lay in zip(ids, layers):
            x.view(-1).index_copy_(0, flat, lay.tri.view(-1).index_select(0, taken).to(x.dtype))
    return Samples(g=GBuffer(front=layers[0], back=layers[1], ray_dir=dirs, eye=eye, proj=proj,
                             meshes=g.meshes, supersample=n, marched=g.marched),
                   pixels=pixels)


def _slots(picked: torch.Tensor, ids: tuple[torch.Tensor, torch.Tensor], n: int
           ) -> tuple | None:
    """:func:`gather`'s layout of the picked pixels in K slots a view (by csrc/index.c, or
    :func:`_slots_torch`, the same values): ``pixels`` (B, K), -1 past a view's; each
    slot's n x n samples' ``rows`` and ``cols`` on the n x n grid (B, K n n; pixel 0's
    past a view's pixels), both layers' rasterized ids there (int64, -1 past), and the
    samples of picked pixels' ``flat`` index in the ids and ``taken`` index in the slots.
    None where no pixel is picked."""
    made = native.sample_slots(picked, ids, n)
    if made is None:
        return _slots_torch(picked, ids, n)
    if made["pixels"].shape[1] == 0:
        return None
    return (made["pixels"], made["rows"], made["cols"], (made["sid0"], made["sid1"]),
            made["flat"], made["taken"])


def _slots_torch(picked: torch.Tensor, ids: tuple[torch.Tensor, torch.Tensor], n: int
                 ) -> tuple | None:
    """:func:`_slots` in tensor operations (the reference)."""
    b, h, w = picked.shape
    flat = picked.reshape(b, -1).nonzero()  # (N, 2): view, pixel, in order
    if flat.shape[0] == 0:
        return None
    counts = torch.bincount(flat[:, 0], minlength=b)
    k = int(counts.max())
    starts = torch.cumsum(counts, 0) - counts
    slot = torch.arange(flat.shape[0]) - starts[flat[:, 0]]
    pixels = torch.full((b, k), -1, dtype=torch.int64)
    pixels[flat[:, 0], slot] = flat[:, 1]
    p = pixels.clamp(min=0)
    sub = torch.arange(n)
    rows = ((n * (p // w))[:, :, None, None] + sub[:, None]).expand(b, k, n, n).reshape(b, -1)
    cols = ((n * (p % w))[:, :, None, None] + sub).expand(b, k, n, n).reshape(b, -1)
    at = rows * (n * w) + cols  # (B, K n n): the samples on the n x n grid
    empty = (pixels < 0)[:, :, None, None].expand(b, k, n, n).reshape(b, -1)
    taken = (~empty).view(-1).nonzero()[:, 0]  # the samples of picked pixels, flat
    sids = tuple(x.reshape(b, -1).gather(1, at).masked_fill_(empty, -1).long() for x in ids)
    flat = (torch.arange(b)[:, None] * ids[0][0].numel() + at).view(-1).index_select(0, taken)
    return pixels, rows, cols, sids, flat, taken


def marched(g: GBuffer, ids: tuple[torch.Tensor, torch.Tensor]) -> Marched:
    """The layers both passes march (``GBuffer.marched``): the rasterized ids on the
    n x n grid ``ids`` (B, n H, n W) int32, held, not copied (:func:`gather` writes the
    samples' exact ids into them), with the one-sample G-buffer ``g``'s triangle planes.
    The n x n render's marched layers, but for its edge repair where no sample is taken
    (rare: rays within ~1/256 pixel of an edge): a march through the one-sample frame's
    ids would find other exits where a method's result depends on the layers' resolution
    (internal bounces' TIR regions), and the picked pixels' neighbours would not match.
    Both passes measure footprints in the one-sample frame's pixels (the samples keep
    ``g``'s cameras): its back layer goes with them (``Marched.frame_back``)."""
    table, base = plane_table(g.meshes, g.eye, g.proj)
    _, h, w = ids[0].shape
    return Marched(back=ids[1].view(-1), front=ids[0].view(-1), table=table, base=base,
                   h=h, w=w, frame_back=g.back)


__all__ = ["Samples", "edges", "gather", "marched", "refined"]

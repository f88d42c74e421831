"""Exact G-buffers: triangle ids from the visibility passes, attributes from torch.

For every pixel the rasterizer tells only *which* triangle is seen (front layer: nearest
front face; back layer: nearest back face). Torch then intersects the pixel's camera ray
with that triangle (Moller-Trumbore, float64) and interpolates attributes with the exact
barycentrics, so positions, depths and normals carry no 8-bit or depth-buffer quantization.
Where the exact hit falls outside the rasterized triangle (pixel centers on edges, edge-on
triangles), the 3x3 neighbourhood's triangles are tested and the true hit kept.

Layout: channels-last, ``(B, H, W, C)``, where (H, W) is the *rendered* resolution: the
camera resolution times ``samples_per_pixel`` (the G-buffer lives on sub-pixel centers).
Meshes of a batch are concatenated, each distinct mesh once; ``tri`` indexes the
concatenation. Views that repeat within a batch (the same mesh object and camera: a sweep
of materials or environment maps over one view) are rasterized and intersected once and
copied to each of their batch items.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields, replace

import torch
import torch.nn.functional as F

from torchrefract.geometry.camera import packed_camera, views_pixel_rays
from torchrefract.geometry.mesh import MeshData
from torchrefract.geometry.raster import sub_layers, visibility_layers
from torchrefract.kernels import native
from torchrefract.kernels.index import put_, take, where_true
from torchrefract.optics.smooth import dot
from torchrefract.scene.model import Camera


@dataclass(frozen=True)
class MeshBatch:
    """Triangles of B meshes concatenated (float32), each distinct mesh object once (batch
    items showing the same mesh share its faces).

    Attributes:
        tri_vertices: (F, 3, 3) corner positions, F = total faces of the distinct meshes.
        tri_normals: (F, 3, 3) unit corner shading normals.
        tri_uvs: (F, 3, 2) corner UVs (zeros where a mesh has none).
        face_offset: (B,) int64 index of each batch item's mesh's first face.
        num_faces: (B,) int64 faces per mesh.
        tri_neighbors: (F, 3) int64 edge-adjacent faces (batch indices, -1 where none).
        tri_across: (F, 3) int64 the face across the edge opposite each corner (batch
            indices, -1 where none; ``MeshData.across``).
        sphere_center: (B, 3), sphere_radius: (B,) each mesh's ``MeshData.face_sphere``.
        face_normals: (F, 3) unit geometric normals (``MeshData.face_normals``).
    """

    tri_vertices: torch.Tensor
    tri_normals: torch.Tensor
    tri_uvs: torch.Tensor
    face_offset: torch.Tensor
    num_faces: torch.Tensor
    tri_neighbors: torch.Tensor
    tri_across: torch.Tensor
    sphere_center: torch.Tensor
    sphere_radius: torch.Tensor
    face_normals: torch.Tensor

    @staticmethod
    def from_meshes(meshes: list[MeshData]) -> "MeshBatch":
        tv, tn, tu, nb, ac, fn = [], [], [], [], [], []
        first: dict[int, int] = {}  # id(mesh) -> its first face in the concatenation
        offset = 0
        for m in meshes:
            if id(m) in first:
                continue
            first[id(m)] = offset
            tv.append(m.tri_vertices)  # (F_i, 3, 3), kept with the mesh
            tn.append(m.tri_normals)
            tu.append(m.tri_uvs)
            fn.append(m.face_normals)
            nb.append(torch.where(m.neighbors >= 0, m.neighbors + offset, m.neighbors)
                      if offset else m.neighbors)
            ac.append(torch.where(m.across >= 0, m.across + offset, m.across)
                      if offset else m.across)
            offset += m.num_faces
        if offset >= 2 ** 31:  # the layers' ids are int32
            raise ValueError(f"a batch's meshes have {offset} faces; at most 2**31 - 1")
        counts_t = torch.tensor([m.num_faces for m in meshes], dtype=torch.int64)
        offsets = torch.tensor([first[id(m)] for m in meshes], dtype=torch.int64)
        spheres = [m.face_sphere for m in meshes]

        def joined(parts: list[torch.Tensor]) -> torch.Tensor:
            # one mesh: its own tensors, read only (nothing writes a batch's tables)
            return parts[0] if len(parts) == 1 else torch.cat(parts)

        return MeshBatch(joined(tv), joined(tn), joined(tu), offsets, counts_t, joined(nb),
                         joined(ac), torch.stack([c for c, _ in spheres]),
                         torch.stack([r for _, r in spheres]), joined(fn))


@dataclass(frozen=True)
class Layer:
    """One depth layer (front faces or back faces) of a G-buffer.

    Attributes:
        mask: (B, H, W) bool, a face is seen.
        tri: (B, H, W) int32 index into the MeshBatch (-1 where ``mask`` is False).
        position: (B, H, W, 3) exact world position of the hit; None in the back layer
            (:func:`carries_points`).
        dist: (B, H, W) distance from the eye along the pixel ray.
        depth: (B, H, W) camera-space depth (along the forward axis).
        bary: (B, H, W, 3) barycentrics of the hit (may leave [0, 1] by ~1e-6 at edges);
            None in the back layer (:func:`carries_points`).
        normal: (B, H, W, 3) unit interpolated shading normal, outward.
        uv: (B, H, W, 2) interpolated UV.
    Values where ``mask`` is False are zeros.
    """

    mask: torch.Tensor
    tri: torch.Tensor
    position: torch.Tensor | None
    dist: torch.Tensor
    depth: torch.Tensor
    bary: torch.Tensor | None
    normal: torch.Tensor
    uv: torch.Tensor


def carries_points(back: bool) -> bool:
    """Whether a layer (the back one, or the front one) carries its hits' ``position`` and
    ``bary``: the front layer's are read (the shading's entry points, ``sh``'s surface
    lattice, adaptive shading's center samples), the back layer's by nothing (the marches
    find the exits themselves), so they are not made (docs/decisions.md, "Peak memory")."""
    return not back


@dataclass(frozen=True)
class GBuffer:
    """Front and back layers of a batch of B views, plus the rays and cameras.

    Attributes:
        front: nearest front faces.
        back: nearest back faces (first exit of a convex object).
        ray_dir: (B, H, W, 3) unit camera ray per (sub-)pixel center.
        eye: (B, 3) camera positions.
        proj: (B, 16) packed cameras for :func:`torchrefract.geometry.camera.project`,
            with width and height of the rendered (supersampled) grid.
        meshes: the batch's triangles.
        supersample: n; (H, W) = n * (camera height, camera width).
        shade: (B, H, W) bool, the object (sub-)pixels a method shades (None: all of
            ``front.mask``; :mod:`torchrefract.geometry.adaptive` sets fewer).
        canvas: (B*H*W, 3) radiance a method shades its pixels over in place of the
            background (None: the background; adaptive shading's second pass: the
            first pass's image, :func:`torchrefract.shading.background.background`).
        draw_in_place: the method draws over ``canvas`` itself, not over a copy (the
            caller keeps nothing of it: csrc/lattice.c's driver has read the means it
            blends).
        lattice: adaptive shading's levels after this first pass (a
            :class:`torchrefract.geometry.adaptive.Lattice`) that a fused kernel may fill
            and shade itself after shading ``shade`` (:func:`torchrefract.shading.fused._run`;
            a level left with no waiting pixel is done); None: the caller fills them.
        marched: where this G-buffer is a strip of a larger frame (its rows only,
            :mod:`torchrefract.large`), the whole frame's marched layers
            (:class:`torchrefract.kernels.march.Marched`: the march reads them, and their
            ``h``, ``w``, instead of this G-buffer's); None: its own.
        derived: values computed from the layers on first use (the march's camera planes,
            :func:`torchrefract.kernels.march.camera_planes`), keyed with the layers'
            versions; shared by the G-buffers ``dataclasses.replace`` makes of this one
            (a render's tiles and adaptive passes), so they are computed once.
    """

    front: Layer
    back: Layer
    ray_dir: torch.Tensor
    eye: torch.Tensor
    proj: torch.Tensor
    meshes: MeshBatch
    supersample: int
    shade: torch.Tensor | None = None
    canvas: torch.Tensor | None = None
    draw_in_place: bool = False
    lattice: object | None = None
    marched: object | None = None
    derived: dict = field(default_factory=dict, compare=False, repr=False)

    @property
    def shape(self) -> tuple[int, int, int]:
        b, h, w, _ = self.ray_dir.shape
        return b, h, w

    def object_index(self) -> torch.Tensor:
        """(N,) flat (B*H*W) indices of the object (sub-)pixels to shade, in order. Kept in
        ``derived`` with the mask it was found in (held, so its identity cannot be reused)
        and that mask's version: the tiling and the method of one pass ask for it alike."""
        return self._object_pixels()[0]

    def object_views(self) -> torch.Tensor:
        """(N,) the view of each of :meth:`object_index`'s pixels (its index // (H*W)),
        found and kept with it."""
        return self._object_pixels()[1]

    def _object_pixels(self) -> tuple[torch.Tensor, torch.Tensor]:
        """:meth:`object_index` and :meth:`object_views`: in two sweeps of csrc/index.c
        where the native kernels run, else ``nonzero`` and a division."""
        mask = self.front.mask if self.shade is None else self.shade
        kept = self.derived.get("object_index")
        if kept is not None and kept[0] is mask and kept[1] == mask._version:
            return kept[2]
        _, h, w = self.shape
        made = native.mask_index(mask, h * w)
        if made is None:
            idx = mask.reshape(-1).nonzero(as_tuple=True)[0]
            made = idx, idx // (h * w)
        self.derived["object_index"] = (mask, mask._version, made)
        return made


def intersect_triangles(origin: torch.Tensor, direction: torch.Tensor,
                        tri_vertices: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Ray-plane hit of each ray with its triangle (Moller-Trumbore, no inside test).

    Args:
        origin: (..., 3) ray origins.
        direction: (..., 3) ray directions (any length).
        tri_vertices: (..., 3, 3) the triangle of each ray.

    Returns:
        t: (...) ray parameter of the hit with the triangle's plane (inf if parallel).
        bary: (..., 3) barycentrics (w0, w1, w2) of that point.
    """
    v0, v1, v2 = tri_vertices.unbind(-2)
    e1, e2 = v1 - v0, v2 - v0
    p = torch.cross(direction, e2, dim=-1)
    det = dot(e1, p)
    ok = det.abs() > 1e-30
    inv = torch.where(ok, 1.0 / torch.where(ok, det, torch.ones_like(det)),
                      torch.zeros_like(det))
    s = origin - v0
    u = dot(s, p) * inv
    q = torch.cross(s, e1, dim=-1)
    v = dot(direction, q) * inv
    t = dot(e2, q) * inv
    t = torch.where(ok, t, torch.full_like(t, float("inf")))
    return t, torch.stack([1.0 - u - v, u, v], -1)


def interpolate(bary: torch.Tensor, corner_values: torch.Tensor) -> torch.Tensor:
    """Interpolate per-corner attributes with barycentrics clamped to the triangle.

    Args:
        bary: (..., 3) barycentrics (may be slightly outside [0, 1]).
        corner_values: (..., 3, C).

    Returns:
        (..., C)
    """
    w = bary.clamp(min=0.0)
    w = w / (w[..., 0:1] + w[..., 1:2] + w[..., 2:3]).clamp(min=1e-12)
    # per corner, in the order of a sum over the corner axis (same values, less time)
    return (w[..., 0:1] * corner_values[..., 0, :] + w[..., 1:2] * corner_values[..., 1, :]
            + w[..., 2:3] * corner_values[..., 2, :])


def _repair_edge_ids(cand_ids: torch.Tensor, ids: torch.Tensor, pb: torch.Tensor,
                     py: torch.Tensor, px: torch.Tensor, own_min: torch.Tensor,
                     eye: torch.Tensor, dirs: torch.Tensor, meshes: MeshBatch, back: bool,
                     tol: float, keep_tol: float = 1e-3) -> torch.Tensor:
    """Re-pick the triangle where the exact ray misses the rasterized one.

    The rasterizer snaps vertices to a sub-pixel grid, so a pixel center within ~1/256 pixel
    of an edge may get the triangle on the other side; at silhouettes it may cover a pixel
    whose ray misses the object. For those pixels only (exact barycentrics outside the
    rasterized triangle), the ray is tested against the triangles seen in the 3x3 pixel
    neighbourhood and the rasterized triangle's edge neighbours and their edge neighbours,
    and the nearest one really hit, facing the right way for the layer, is kept. If none is
    hit, the rasterized id stays when the miss is tiny (barycentric > -keep_tol: its plane
    is an excellent stand-in) and the pixel becomes empty otherwise (a silhouette miss).

    Args:
        cand_ids: (B, H, W) rasterized ids (neighbourhood source).
        ids: (S,) rasterized ids of the suspect pixels at (pb, py, px); own_min (S,) their
            smallest exact barycentric.

    Returns:
        (S,) repaired ids (-1 for a miss).
    """
    padded = F.pad(cand_ids, (1, 1, 1, 1), value=-1)  # (B, H+2, W+2)
    dy, dx = torch.meshgrid(torch.arange(3), torch.arange(3), indexing="ij")
    pix = padded[pb[:, None], py[:, None] + dy.reshape(1, 9), px[:, None] + dx.reshape(1, 9)]
    ring1 = meshes.tri_neighbors[ids]  # (S, 3)
    ring2 = meshes.tri_neighbors[ring1.clamp(min=0)]  # (S, 3, 3)
    ring2 = torch.where(ring1[..., None] >= 0, ring2, torch.full_like(ring2, -1))
    cand = torch.cat([pix, ring1, ring2.reshape(-1, 9)], 1)  # (S, 21)
    k = cand.shape[1]
    ds = dirs.double()[pb, py, px][:, None, :].expand(-1, k, 3)  # (S, k, 3)
    os_ = eye.double()[pb][:, None, :].expand(-1, k, 3)
    ctv = meshes.tri_vertices[cand.clamp(min=0)].double()  # (S, k, 3, 3)
    t, cb = intersect_triangles(os_, ds, ctv)
    gn = torch.cross(ctv[..., 1, :] - ctv[..., 0, :], ctv[..., 2, :] - ctv[..., 0, :], dim=-1)
    facing = dot(gn, ds)
    facing_ok = facing > 0 if back else facing < 0
    ok = (cand >= 0) & (cb.min(-1).values >= -tol) & (t > 0) & torch.isfinite(t) & facing_ok
    t = torch.where(ok, t, torch.full_like(t, float("inf")))
    best_t, best = t.min(-1)  # (S,)
    chosen = torch.gather(cand, 1, best[:, None])[:, 0]
    fallback = torch.where(own_min > -keep_tol, ids, torch.full_like(ids, -1))
    return torch.where(torch.isfinite(best_t), chosen, fallback)


def _layer(ids: torch.Tensor, eye: torch.Tensor, dirs: torch.Tensor, forward: torch.Tensor,
           meshes: MeshBatch, back: bool, tol: float = 1e-7) -> Layer:
    """ids (B, H, W) global face index or -1; eye (B, 3); dirs (B, H, W, 3).

    Work happens on the covered pixels only (compacted, by flat pixel index), in float64;
    where the native kernel is available (``native.layer``) it does the same, one pixel at
    a time, with the same values.
    """
    fast = native.layer(ids, eye, dirs, forward, meshes.tri_vertices, meshes.tri_normals,
                        meshes.tri_uvs, meshes.tri_neighbors, back, tol, 1e-3,
                        carries_points(back))
    if fast is not None:
        return Layer(**fast)
    return _layer_tensor(ids, eye, dirs, forward, meshes, back, tol)


def _layer_tensor(ids: torch.Tensor, eye: torch.Tensor, dirs: torch.Tensor,
                  forward: torch.Tensor, meshes: MeshBatch, back: bool, tol: float) -> Layer:
    """:func:`_layer` in tensor code: the exact hits of the covered pixels, compacted."""
    b, h, w = ids.shape
    flat_ids = ids.reshape(-1)
    pix = where_true(flat_ids >= 0)  # (N,) covered pixels, flat
    tri = take(flat_ids, pix)
    eye64 = eye.double()
    o = take(eye64, pix // (h * w))  # (N, 3)
    d = take(dirs.reshape(-1, 3), pix).double()  # (N, 3)
    tv = take(meshes.tri_vertices, tri).double()  # (N, 3, 3)
    t, bary = intersect_triangles(o, d, tv)
    own_min = bary.min(-1).values
    sus = where_true(own_min < -tol)
    if sus.numel() > 0:
        sp = take(pix, sus)
        fixed = _repair_edge_ids(ids, take(tri, sus), sp // (h * w), (sp // w) % h, sp % w,
                                 take(own_min, sus), eye, dirs, meshes, back, tol)
        tri = put_(tri.clone(), sus, fixed)
        keep = where_true(tri >= 0)
        pix, tri, o, d = (take(x, keep) for x in (pix, tri, o, d))
        tv = take(meshes.tri_vertices, tri).double()
        t, bary = intersect_triangles(o, d, tv)
    pos = o + t[:, None] * d
    n = interpolate(bary, take(meshes.tri_normals, tri).double())
    n = n / n.norm(dim=-1, keepdim=True).clamp(min=1e-300)
    uv = interpolate(bary, take(meshes.tri_uvs, tri).double())
    depth = t * dot(d, take(forward.double(), pix // (h * w)))

    def scatter(v: torch.Tensor, c: int | None, fill=0.0, dtype=torch.float32):
        out = torch.full((b * h * w,) if c is None else (b * h * w, c), fill, dtype=dtype)
        put_(out, pix, v)
        return out.reshape((b, h, w) if c is None else (b, h, w, c))

    points = carries_points(back)
    return Layer(
        mask=scatter(torch.ones_like(tri, dtype=torch.bool), None, False, torch.bool),
        tri=scatter(tri, None, -1, torch.int32),
        position=scatter(pos, 3) if points else None,
        dist=scatter(t, None),
        depth=scatter(depth, None),
        bary=scatter(bary, 3) if points else None,
        normal=scatter(n, 3),
        uv=scatter(uv, 2),
    )


def view_frames(cams: list[Camera], n: int
                ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Views' eyes (B, 3) and unit forwards (B, 3), float32, and their packed cameras
    (B, 16) (:func:`~torchrefract.geometry.camera.projection_params`) for their n x n
    sub-pixel grids: what the layers and the marches take of a camera."""
    p = torch.tensor([packed_camera(c, n) for c in cams], dtype=torch.float32)
    return p[:, 0:3].contiguous(), p[:, 9:12].contiguous(), p


def _distinct_views(meshes: list[MeshData], cameras: list[Camera]
                    ) -> tuple[list[tuple[int, MeshData, Camera]], list[int]]:
    """Each distinct view (mesh object, camera) once, as (its first batch item, mesh,
    camera), and the distinct view of every batch item."""
    slot: dict[tuple[int, Camera], int] = {}
    views: list[tuple[int, MeshData, Camera]] = []
    inverse = []
    for b, (m, c) in enumerate(zip(meshes, cameras)):
        if (id(m), c) not in slot:
            slot[id(m), c] = len(views)
            views.append((b, m, c))
        inverse.append(slot[id(m), c])
    return views, inverse


def build_gbuffer(meshes: list[MeshData], cameras: list[Camera]) -> GBuffer:
    """Rasterize both layers' ids of each view (``RenderSettings.rasterizer``: the native
    rasterizer, or the OpenGL passes) and build the exact G-buffer.

    Args:
        meshes: B world-space meshes.
        cameras: B cameras with equal width, height and samples_per_pixel.

    Returns:
        GBuffer with (H, W) = samples_per_pixel * (height, width).
    """
    return _build(meshes, cameras, sparse=False)[0]


def build_sparse(meshes: list[MeshData], cameras: list[Camera],
                 folds: tuple[float, float] | None = None
                 ) -> tuple[GBuffer, tuple[torch.Tensor, torch.Tensor], torch.Tensor | None]:
    """Sparse supersampling's G-buffers (:mod:`torchrefract.geometry.subsamples`): the
    exact one-sample G-buffer of cameras taking n x n samples, both layers' rasterized
    ids on their n x n sub-pixel grids (B, n H, n W) int32, -1 where no face is seen (not
    repaired: the samples' layers are), and with ``folds`` (the fold test's normal and
    face tolerances) the pixels' sub-pixel flags (B, H, W) uint8 (``raster.sub_layers``;
    None without, or without the kernels). Two rasterizations: finding the pixel centers'
    triangles among the sub-pixels' instead cost more, and a dense mesh's center may see
    none of them (docs/benchmarks.md, sixteenth sitting)."""
    g, grid = _build(meshes, cameras, sparse=True, folds=folds)
    return g, grid[:2], grid[2]


def _build(meshes: list[MeshData], cameras: list[Camera], sparse: bool,
           folds: tuple[float, float] | None = None) -> tuple[GBuffer, tuple | None]:
    """:func:`build_gbuffer` (``sparse`` False; no ids) or :func:`build_sparse` (its ids
    and flags as one tuple)."""
    if len(meshes) != len(cameras) or not meshes:
        raise ValueError("build_gbuffer needs one camera per mesh and at least one view")
    c0 = cameras[0]
    for c in cameras[1:]:
        if (c.width, c.height, c.samples_per_pixel) != (c0.width, c0.height,
                                                        c0.samples_per_pixel):
            raise ValueError("build_gbuffer: all cameras need the same width, height and "
                             f"samples_per_pixel; got {c0} and {c}")
    n = c0.samples_per_pixel
    batch = MeshBatch.from_meshes(meshes)
    views, inverse = _distinct_views(meshes, cameras)
    drawn, cams = [m for _, m, _ in views], [c for _, _, c in views]
    # both layers' ids of every distinct view, global (the MeshBatch's face indices)
    offsets = [int(batch.face_offset[b]) for b, _, _ in views]
    sub = None
    if sparse:
        if folds is None:
            sub = (*visibility_layers(drawn, cams, n, offsets, dtype=torch.int32), None)
        else:
            sub = sub_layers(drawn, cams, offsets, native.SubTest(n, batch, *folds))
        cams, n = [replace(c, samples_per_pixel=1) for c in cams], 1
    front_ids, back_ids = visibility_layers(drawn, cams, n, offsets)
    dirs_t = views_pixel_rays(cams, n)
    eye_t, fwd_t, proj_t = view_frames(cams, n)
    front = _layer(front_ids, eye_t, dirs_t, fwd_t, batch, back=False)
    back_layer = _layer(back_ids, eye_t, dirs_t, fwd_t, batch, back=True)
    if len(views) < len(meshes):  # copy the distinct views to their batch items
        inv = torch.tensor(inverse, dtype=torch.int64)

        def expand(x: torch.Tensor | None) -> torch.Tensor | None:
            return None if x is None else x.index_select(0, inv)

        front, back_layer = (Layer(**{f.name: expand(getattr(lay, f.name)) for f in fields(Layer)})
                             for lay in (front, back_layer))
        dirs_t, eye_t, proj_t = expand(dirs_t), expand(eye_t), expand(proj_t)
        sub = None if sub is None else tuple(expand(x) for x in sub)
    return GBuffer(front=front, back=back_layer, ray_dir=dirs_t, eye=eye_t, proj=proj_t,
                   meshes=batch, supersample=n), sub

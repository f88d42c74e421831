"""Ray marching in the back-face buffer (Oliveira and Brauwers 2007), exact exit refinement.

A ray that entered the object at P1 travels along T. Sample points X = P1 + s T are
projected into the back-face layer; X has left the object once it lies beyond the back-face
plane seen at its pixel (or projects outside the object's silhouette or the frame). A
uniform coarse search over the chord of the bounding sphere brackets the first crossing,
bisection narrows it, and the exit is the exact intersection of the ray with the back-face
triangle found there (so the exit normal is the triangle's interpolated normal, not a
buffer texel). Vectorized over all rays of a batch; no per-pixel Python.

:func:`march_inside` marches a ray that travels *inside* between the two layers (an
internal reflection, from either surface): X is inside while it lies behind the front-face
plane and in front of the back-face plane at its pixel; the exit is the exact hit with the
triangle of whichever layer was crossed.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields

import torch

from torchrefract.geometry.gbuffer import GBuffer, Layer, interpolate, intersect_triangles
from torchrefract.kernels import native
from torchrefract.kernels.compiled import compile_enabled, kernel
from torchrefract.kernels.index import put_, take, where_true
from torchrefract.optics.smooth import dot
from torchrefract.stages import timed


@dataclass(frozen=True)
class Exit:
    """Where marched rays leave the object.

    Attributes:
        found: (N,) bool, an exit triangle was found.
        position: (N, 3) exit point (P1 where not found).
        normal: (N, 3) unit outward shading normal at the exit (zeros where not found).
        tri: (N,) int64 exit triangle (-1 where not found).
        dist: (N,) distance travelled inside.
        layer: (N,) int64 layer left through: 0 front, 1 back, -1 where not found.
        bary: (N, 3) barycentrics of the exit in ``tri``.
    """

    found: torch.Tensor
    position: torch.Tensor
    normal: torch.Tensor
    tri: torch.Tensor
    dist: torch.Tensor
    layer: torch.Tensor
    bary: torch.Tensor


@dataclass(frozen=True)
class Marched:
    """What a march reads of the frame: the marched layers' triangle ids per (sub-)pixel
    and each view's triangles' planes (issue #27: 4 bytes per sub-pixel and layer instead
    of a plane per sub-pixel, so that a frame of any size can be marched in bounded memory).

    A point with camera coordinates C (right, up, forward from the eye) is beyond the back
    layer at its pixel when that pixel's triangle is missing (-1) or ``dot(n, C) - c > 0``
    with (n, c) = ``table[base[b] + tri]``: the triangle's unit geometric normal turned
    away from the eye, in view b's camera coordinates, and n . (v0 - eye) (the world plane
    n . X = n . v0 without the world point). The front layer's plane faces the eye: the
    same row negated, so there the test is ``c - dot(n, C) > 0``. This is the plane of
    the exact layer the G-buffer holds at that pixel (its hit lies on the triangle's
    plane), up to rounding.

    Attributes:
        back: (B*H*W,) int32 back-face triangle per (sub-)pixel (the exact layer's, after
            the edge repair), -1 where empty.
        front: (B*H*W,) int32 the front layer's, or None (a march of the back layer only).
        table: (R, 4) float32 planes of each view's triangles (camera coordinates).
        base: (B,) int64: view b's triangle t (a MeshBatch index) is row ``base[b] + t``.
        h, w: the frame's (sub-)pixels.
        frame_back: the back layer (B, h, w) of the frame footprints are measured in,
            where the G-buffer marching it is not that frame (sparse supersampling: the
            one-sample frame's, for its scattered samples too), else None: where
            ``rousiers`` reads the roughness levels' coverage around its exits
            (:func:`~torchrefract.methods.rousiers.cone.level_coverage`).
        derived: values computed from ``frame_back`` on first use, for every pass and
            tile that marches this frame (``rousiers``' coverage mips).
    """

    back: torch.Tensor
    front: torch.Tensor | None
    table: torch.Tensor
    base: torch.Tensor
    h: int
    w: int
    frame_back: Layer | None = None
    derived: dict = field(default_factory=dict, compare=False, repr=False)

    def numel(self) -> int:
        """The frame's (sub-)pixels, B*H*W."""
        return self.back.numel()


def frame_back(g: GBuffer) -> Layer:
    """The back layer of the frame ``g``'s footprints are measured in: its own, or in a
    sparse pass (``g`` the one-sample frame or its scattered samples) the one-sample
    frame's (``Marched.frame_back``)."""
    m = g.marched
    return m.frame_back if m is not None and m.frame_back is not None else g.back


def plane_table(meshes, eye: torch.Tensor, proj: torch.Tensor
                ) -> tuple[torch.Tensor, torch.Tensor]:
    """Each view's triangles' planes in its camera coordinates (:class:`Marched`): the
    (R, 4) float32 table and the (B,) int64 row bases. Computed in float64 from the
    vertices (one row per triangle of the view's mesh; views of one mesh and camera share
    their rows).

    Args:
        meshes: the batch's ``MeshBatch``; eye: (B, 3); proj: (B, 16) packed cameras.
    """
    b = eye.shape[0]
    views, bases, seen = [], [], {}  # the distinct views: (batch item, first face, faces)
    at = 0
    eyes, frames = eye.tolist(), proj[:, 3:12].tolist()
    offsets, counts = meshes.face_offset.tolist(), meshes.num_faces.tolist()
    for i in range(b):
        fo, nf = int(offsets[i]), int(counts[i])
        key = (fo, nf, tuple(eyes[i]), tuple(frames[i]))
        if key in seen:
            bases.append(seen[key])
            continue
        views.append((i, fo, nf))
        seen[key] = at - fo
        bases.append(at - fo)
        at += nf
    table = _views_planes(meshes.tri_vertices, views, eye, proj) if views \
        else torch.zeros(0, 4)
    return table.contiguous(), torch.tensor(bases, dtype=torch.int64)


def _views_planes(tv: torch.Tensor, views: list[tuple[int, int, int]], eye: torch.Tensor,
                  proj: torch.Tensor) -> torch.Tensor:
    """:func:`plane_table`'s rows of the distinct ``views`` (batch item, first face, faces),
    one after the other: the native kernel in one call where it runs (the same operations
    in double), else view by view."""
    rows = [i for i, _, _ in views]
    eyes, bases = eye, proj[:, 3:12]
    if rows != list(range(eye.shape[0])):  # (every view distinct, in order: no copies)
        items = torch.tensor(rows, dtype=torch.int64)
        eyes, bases = eye.index_select(0, items), bases.index_select(0, items)
    fast = native.tri_planes(tv, [fo for _, fo, _ in views], [nf for _, _, nf in views],
                             eyes, bases)
    if fast is not None:
        return fast
    return torch.cat([_view_planes(tv[fo:fo + nf], eye[i], proj[i, 3:12])
                      for i, fo, nf in views])


def _view_planes(tv: torch.Tensor, eye: torch.Tensor, basis: torch.Tensor) -> torch.Tensor:
    """:func:`plane_table`'s rows (F, 4) of one view's triangles ``tv`` (F, 3, 3), from its
    eye (3,) and camera basis (9,): the tensor code (the native kernel's reference)."""
    tv = tv.detach().double()  # (F, 3, 3)
    n = torch.cross(tv[:, 1] - tv[:, 0], tv[:, 2] - tv[:, 0], dim=-1)
    n = n / n.norm(dim=-1, keepdim=True).clamp(min=1e-300)
    rel = tv[:, 0] - eye.detach().double()
    away = dot(rel, n)
    n = torch.where((away < 0)[:, None], -n, n)  # away from the eye
    b = basis.detach().double().view(3, 3)  # rows: right, up, forward
    return torch.stack([dot(n, b[0]), dot(n, b[1]), dot(n, b[2]), dot(n, rel)], -1).float()


def camera_planes(g: GBuffer, both: bool = False) -> Marched:
    """The :class:`Marched` layers of ``g``: its back layer (``both``: and its front
    layer) as int32 triangle ids and the views' triangle planes, detached. A strip of a
    larger frame (``g.marched``, :mod:`torchrefract.large`) marches the whole frame's.

    A caller that marches one G-buffer several times (the central and the bounding rays,
    the bounces) builds them once and passes them as ``planes``; they are also kept in
    ``g.derived``, keyed by the inputs' memory and versions (a replaced G-buffer with other
    layers or cameras, or one changed in place, computes its own).
    """
    if g.marched is not None:
        if both and g.marched.front is None:
            raise ValueError("march: this strip's frame holds no front layer (a march "
                             "between the layers needs it)")
        return g.marched
    inputs = tuple((t.data_ptr(), t._version) for t in (g.back.tri, g.front.tri, g.eye,
                                                        g.proj, g.meshes.tri_vertices))
    # both layers serve a march of the back layer alone too
    for b in (True,) if both else (False, True):
        kept = g.derived.get(("camera_planes", b) + inputs)
        if kept is not None:  # computed for this G-buffer already (another tile or pass)
            return kept
    out = _camera_planes(g, both)
    g.derived[("camera_planes", both) + inputs] = out
    return out


def _camera_planes(g: GBuffer, both: bool) -> Marched:
    """:func:`camera_planes`, computed."""
    _, h, w = g.shape
    table, base = plane_table(g.meshes, g.eye, g.proj)
    # the layers' own int32 ids (views: no copy; a layer changed in place gets new planes)
    back = g.back.tri.detach().reshape(-1).to(torch.int32)
    front = g.front.tri.detach().reshape(-1).to(torch.int32) if both else None
    return Marched(back=back, front=front, table=table, base=base, h=h, w=w)


def camera_coordinates(g: GBuffer, batch: torch.Tensor, p: torch.Tensor, t: torch.Tensor
                       ) -> tuple[torch.Tensor, torch.Tensor]:
    """Camera coordinates (right, up, forward; N, 3 each) of points ``p`` (from the eye)
    and of directions ``t`` of rays in views ``batch`` (N,), detached: what the march
    projects. A caller marching rays whose directions are combinations of a few vectors
    (``rousiers``' bounding rays around the lobe axis) combines their coordinates instead
    and passes them to :func:`march_back` as ``camera``."""
    pr = take(g.proj[:, :12], batch)  # (N, 12): eye, then the basis rows
    basis = pr[:, 3:12].view(-1, 3, 3)  # (N, 3, 3) rows: right, up, forward
    # one matrix-vector product per ray each (einsum: the values of a bmm with both
    # vectors stacked, in half its time)
    rel = p.detach() - pr[:, 0:3]
    return (torch.einsum("nij,nj->ni", basis, rel),
            torch.einsum("nij,nj->ni", basis, t.detach()))


class _Projector:
    """Pixel lookups of points p1 + s t along rays, linear in s (precomputed per ray)."""

    def __init__(self, g: GBuffer, batch: torch.Tensor, p1: torch.Tensor, t: torch.Tensor,
                 marched: Marched, camera: tuple[torch.Tensor, torch.Tensor] | None = None):
        self.h, self.w = marched.h, marched.w
        # (N, 3) camera coords of p1 and per unit s
        self.c0, self.ct = camera if camera is not None else camera_coordinates(g, batch, p1, t)
        # pixel x = (cx / (cz ta) + 1) w / 2, y = (1 - cy / (cz t)) h / 2
        self.sx = take(0.5 * self.w / g.proj[:, 12], batch)
        self.sy = take(0.5 * self.h / g.proj[:, 13], batch)
        self.base = batch * (self.h * self.w)
        self.pbase = take(marched.base, batch)  # (N,) each ray's view's plane rows

    def pixels(self, idx: torch.Tensor | None, s: torch.Tensor
               ) -> tuple[torch.Tensor, torch.Tensor]:
        """Flat pixel index and in-frame flag of rays ``idx`` (None: all) at parameters ``s``."""
        def sel(x):
            return x if idx is None else take(x, idx)

        return _pixel_of(sel(self.c0), sel(self.ct), s, sel(self.sx), sel(self.sy),
                         sel(self.base), self.h, self.w)


def _pixel_of_camera(c: torch.Tensor, sx: torch.Tensor, sy: torch.Tensor, base: torch.Tensor,
                     h: int, w: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Flat pixel index (M,) and in-frame flag (M,) of points with camera coordinates c."""
    z = c[:, 2]
    zs = z.clamp(min=1e-12)
    px = torch.floor(c[:, 0] / zs * sx + 0.5 * w)
    py = torch.floor(0.5 * h - c[:, 1] / zs * sy)
    # px, py are whole numbers: in the frame exactly where clamping leaves them unchanged
    # (NaN and inf fail either test), two comparisons fewer than testing both bounds
    pxc, pyc = px.clamp(0, w - 1), py.clamp(0, h - 1)
    inside = (z > 1e-12) & (pxc == px) & (pyc == py)
    flat = base + pyc.long() * w + pxc.long()
    return flat, inside


def _pixel_of(c0: torch.Tensor, ct: torch.Tensor, s: torch.Tensor, sx: torch.Tensor,
              sy: torch.Tensor, base: torch.Tensor, h: int, w: int
              ) -> tuple[torch.Tensor, torch.Tensor]:
    """Flat pixel index (M,) and in-frame flag (M,) of the points at parameters ``s`` (M,)
    of rays with camera coordinates c0 + s ct (``_Projector``'s per-ray terms)."""
    return _pixel_of_camera(c0 + s[:, None] * ct, sx, sy, base, h, w)


def _plane_at(tri: torch.Tensor, flat: torch.Tensor, pbase: torch.Tensor,
              table: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The triangle (M,) int64 seen at pixels ``flat`` of a marched layer (int32, -1 where
    empty) and its plane row (M, 4) of ``table`` (any row where empty)."""
    t = take(tri, flat).long()
    return t, take(table, torch.where(t >= 0, pbase + t, torch.zeros_like(t)))


def _crossed_at(c0, ct, s, sx, sy, base, pbase, back, front, table, h: int, w: int
                ) -> torch.Tensor:
    """(M,) bool: the points c0 + s ct (camera coordinates, M rays) have left the marched
    layer(s) (:class:`Marched`: ``back``, and ``front`` where not None): outside the frame,
    on a pixel where a layer is empty, or beyond its triangle's plane there."""
    c = c0 + s[:, None] * ct  # (M, 3)
    flat, inside = _pixel_of_camera(c, sx, sy, base, h, w)
    tb, pl = _plane_at(back, flat, pbase, table)
    beyond = (tb < 0) | (dot(pl[:, :3], c) - pl[:, 3] > 0)
    if front is not None:  # two layers: also in front of the front face (the row negated)
        tf, pf = _plane_at(front, flat, pbase, table)
        beyond = beyond | (tf < 0) | (pf[:, 3] - dot(pf[:, :3], c) > 0)
    return ~inside | beyond


def _search_eager(c0, ct, s_max, sx, sy, base, pbase, back, front, table, h: int, w: int,
                  steps: int, refine: int) -> tuple[torch.Tensor, torch.Tensor]:
    """The whole search on every ray, without compaction: ``steps`` uniform samples over
    [0, s_max] (the first sample k where a ray has crossed gives lo = s_{k-1}, hi = s_k; a
    ray that never crosses gets lo = hi = s_max), then ``refine`` bisections. The compiled
    form of the march: traced once per (steps, refine), every sample and bisection fuse
    into one pass over the rays that reads each ray's terms once."""
    lo = torch.zeros_like(s_max)
    hi = s_max
    done = torch.zeros_like(s_max, dtype=torch.bool)
    for k in range(1, steps + 1):
        s = s_max * (k / steps)
        crossed = _crossed_at(c0, ct, s, sx, sy, base, pbase, back, front, table, h,
                              w) & ~done
        lo = torch.where(crossed, s_max * ((k - 1) / steps), lo)
        hi = torch.where(crossed, s, hi)
        done = done | crossed
    lo = torch.where(done, lo, s_max)
    for _ in range(refine):
        lo, hi = _bisect_step_eager(lo, hi, c0, ct, sx, sy, base, pbase, back, front,
                                    table, h, w)
    return lo, hi


def _bisect_step_eager(lo, hi, c0, ct, sx, sy, base, pbase, back, front, table, h: int,
                       w: int) -> tuple[torch.Tensor, torch.Tensor]:
    """One bisection of the bracketing intervals [lo, hi] (N,) of all rays."""
    mid = 0.5 * (lo + hi)
    crossed = _crossed_at(c0, ct, mid, sx, sy, base, pbase, back, front, table, h, w)
    return torch.where(crossed, lo, mid), torch.where(crossed, mid, hi)


# The compiled march (where ``accel`` is enabled): the whole search as one kernel.
_search = kernel(_search_eager)


def _bounding_chord(g: GBuffer, batch: torch.Tensor, p1: torch.Tensor, t: torch.Tensor
                    ) -> torch.Tensor:
    """(N,) distance along each ray to where it leaves its mesh's bounding sphere (+1%)."""
    center = take(g.meshes.sphere_center, batch)  # (N, 3)
    radius = take(g.meshes.sphere_radius, batch)  # (N,)
    oc = p1 - center
    bq = dot(oc, t)
    cq = dot(oc, oc) - radius * radius
    return (-bq + torch.sqrt((bq * bq - cq).clamp(min=0.0))).clamp(min=1e-6) * 1.01


def _walk_to_containing(p1, t, tv, across, found, tri, s_exit, bary, s_min, s_max,
                        max_steps: int = 16):
    """Move each exit to the triangle that contains it.

    The triangle read at the crossing pixel is the one seen at the pixel's *center*; where
    triangles are smaller than pixels (or the crossing is near an edge) the ray meets that
    triangle's plane outside it (barycentrics < 0), and its normal would be extrapolated
    (measured on a 48x48 sphere: 90% of exits, normals off by up to 2.8 degrees). Walk
    across the edge opposite the most negative barycentric to the adjacent triangle, until
    the hit is inside; keep the most-inside hit seen. Only the rays that need it are walked.
    """
    eps = -1e-6
    sel = where_true(found & (bary.min(-1).values < eps))
    # The walkers' own state, compacted as they stop (no pass over all rays per step):
    # where each stands, and the smallest barycentric of the best hit kept so far.
    cur_tri, cur_bary = take(tri, sel), take(bary, sel)
    best = cur_bary.min(-1).values
    ps, ts, lo, hi = take(p1, sel), take(t, sel), take(s_min, sel), 1.5 * take(s_max, sel)
    across_flat = across.reshape(-1)
    for _ in range(max_steps):
        if sel.numel() == 0:
            break
        worst = cur_bary.argmin(-1)  # the vertex opposite the edge to cross
        nxt = take(across_flat, cur_tri * 3 + worst)  # the face across (MeshData.across)
        st, bt = intersect_triangles(ps, ts, take(tv, nxt.clamp(min=0)))
        ok = (nxt >= 0) & torch.isfinite(st) & (st > lo) & (st <= hi)
        cur_tri = torch.where(ok, nxt, cur_tri)
        cur_bary = torch.where(ok[:, None], bt, cur_bary)
        score = bt.min(-1).values
        better = ok & (score > best)
        bi = where_true(better)
        upd = take(sel, bi)
        put_(tri, upd, take(nxt, bi))
        put_(s_exit, upd, take(st, bi))
        put_(bary, upd, take(bt, bi))
        best = torch.where(better, score, best)
        keep = where_true(ok & (score < eps))
        if keep.numel() < sel.numel():
            sel, cur_tri, cur_bary, best = (take(x, keep) for x in (sel, cur_tri, cur_bary,
                                                                    best))
            ps, ts, lo, hi = (take(x, keep) for x in (ps, ts, lo, hi))
    return tri, s_exit, bary


@timed("march")
def march_back(g: GBuffer, batch: torch.Tensor, p1: torch.Tensor, t: torch.Tensor,
               steps: int = 64, refine: int = 10, depth_min: torch.Tensor | None = None,
               tile: int = 8, fine_steps: int = 8, planes: Marched | None = None,
               camera: tuple[torch.Tensor, torch.Tensor] | None = None) -> Exit:
    """March rays from entry points to their exit through the back-face layer.

    Without ``depth_min``: ``steps`` uniform samples over the bounding-sphere chord bracket
    the first crossing, then ``refine`` bisections. With ``depth_min`` (the min back-face
    depth of ``tile`` x ``tile`` pixel tiles, from :func:`torchrefract.optics.ndf.build_ndf_mips`),
    empty space is skipped: a coarse sample whose camera depth lies in front of every back
    face of its tile cannot have crossed, so only coarse intervals that may contain the
    crossing are searched with ``fine_steps`` exact plane tests (Oliveira and Brauwers
    2007's min/max acceleration). Either way the exit is then the exact hit with the
    back-face triangle found there.

    Args:
        g: the G-buffer (its back layer is marched).
        batch: (N,) int64 scene index per ray.
        p1: (N, 3) entry points; t: (N, 3) unit directions inside the object.
        steps: coarse samples along the chord of the bounding sphere.
        refine: bisection iterations on the bracketing interval.
        depth_min: optional (B, ceil(H/tile), ceil(W/tile), 1) min back depth per tile
            (+inf where a tile is empty).
        tile: the tile size of ``depth_min`` in pixels (a power of two).
        fine_steps: exact samples inside a coarse interval that may hold the crossing.
        planes: ``camera_planes(g)``, where the caller already has them.
        camera: ``camera_coordinates(g, batch, p1, t)``, where the caller already has them.

    Returns:
        Exit of each ray.
    """
    n = p1.shape[0]
    # The native kernel marches one ray at a time (nothing to keep in cache across rays):
    # all in one pass, without the chunks' concatenation (4 ms per frame on the demo).
    if n <= MARCH_CHUNK or (depth_min is None and native.available()):
        return _march(g, batch, p1, t, steps, refine, depth_min, tile, fine_steps,
                      both=False, planes=planes, camera=camera)
    if planes is None:
        planes = camera_planes(g)
    parts = []
    for i in range(0, n, MARCH_CHUNK):
        sl = slice(i, i + MARCH_CHUNK)
        cam = None if camera is None else (camera[0][sl], camera[1][sl])
        parts.append(_march(g, batch[sl], p1[sl], t[sl], steps, refine, depth_min, tile,
                            fine_steps, both=False, planes=planes, camera=cam))
    return Exit(**{f.name: torch.cat([getattr(e, f.name) for e in parts])
                   for f in fields(Exit)})


MARCH_CHUNK = 1 << 17
"""Rays marched per pass of :func:`march_back`: a march chains many elementwise ops over
(N, 3) tensors, which stay closer to this CPU's 1 MB L2 per core in chunks (the demo's
472k bounding rays at 256x256, batch 8: 277 -> 243 ms single-thread CPU time, best of 5,
in chunks of 2^17). Each ray's exit does not depend on the chunking. Not for the native
kernel, which takes all rays in one pass."""


@timed("march")
def march_inside(g: GBuffer, batch: torch.Tensor, p: torch.Tensor, t: torch.Tensor,
                 steps: int = 32, refine: int = 10, planes: Marched | None = None
                 ) -> Exit:
    """March rays that travel inside the object from a point on its surface (an internal
    reflection at the back or the front surface) to where they meet either layer.

    X is inside while it lies behind the front-face plane and in front of the back-face
    plane of its pixel (the slab between the two layers; where either layer is empty, or
    outside the frame, the ray is lost: ``found`` False). The exit is the exact hit with the
    triangle of the layer whose plane was crossed (``Exit.layer``); hits closer than 1e-4 of
    the chord are ignored (the start's own triangle).

    Args:
        g: the G-buffer; batch: (N,) scene per ray; p: (N, 3) start points on the surface;
        t: (N, 3) unit directions pointing into the object; steps, refine: as
        :func:`march_back`; planes: ``camera_planes(g, both=True)``, where the caller
        already has them.
    """
    return _march(g, batch, p, t, steps, refine, None, 8, 8, both=True, planes=planes)


def _march(g: GBuffer, batch: torch.Tensor, p1: torch.Tensor, t: torch.Tensor, steps: int,
           refine: int, depth_min: torch.Tensor | None, tile: int, fine_steps: int,
           both: bool, planes: Marched | None = None,
           camera: tuple[torch.Tensor, torch.Tensor] | None = None) -> Exit:
    """The march: the backend chosen here (the native kernel where it runs and no tile
    acceleration is asked for, else the tensor code: a bracketing search, then the exact
    hit with the triangle seen at the crossing)."""
    if planes is None:
        planes = camera_planes(g, both)
    elif not isinstance(planes, Marched) or (both and planes.front is None) or (
            g.marched is None and planes.numel() != g.ray_dir[..., 0].numel()):
        raise ValueError(f"march: planes {type(planes).__name__} do not belong to this "
                         f"G-buffer (camera_planes(g, both={both}))")
    front = planes.front if both else None
    # Where each ray crosses is a discrete choice (no gradient); the gradient flows through
    # the exact intersection with the triangle found there (p1 and t below, not detached).
    p1d, td = p1.detach(), t.detach()
    s_max = _bounding_chord(g, batch, p1d, td)
    s_min = 1e-4 * s_max if both else torch.zeros_like(s_max)
    if depth_min is None and native.available():
        ex = _march_native(g, batch, p1, t, p1d, td, s_max, s_min, steps, refine, planes,
                           both, camera)
        if ex is not None:
            return ex
    proj = _Projector(g, batch, p1d, td, planes, camera)
    h, w = planes.h, planes.w
    if depth_min is None and compile_enabled():
        # Compiled: every ray at every sample, search and bisection in one fused pass
        # (cheaper than the compaction below, which pays for gathers the fused pass does
        # not need); the same intervals, so the same exits.
        lo, hi = _search(proj.c0, proj.ct, s_max, proj.sx, proj.sy, proj.base, proj.pbase,
                         planes.back, front, planes.table, h, w, steps, refine)
    else:
        if depth_min is None:
            lo, hi = _search_compacted(proj, planes, front, s_max, steps)
        else:
            lo, hi = _search_tiles(batch, proj, planes, front, s_max, steps, depth_min, tile,
                                   fine_steps)
        for _ in range(refine):
            lo, hi = _bisect_step_eager(lo, hi, proj.c0, proj.ct, proj.sx, proj.sy,
                                        proj.base, proj.pbase, planes.back, front,
                                        planes.table, h, w)
    return _exact_exit(g, p1, t, proj, planes, lo, hi, s_min, s_max, both)


def _march_native(g: GBuffer, batch, p1, t, p1d, td, s_max, s_min, steps: int, refine: int,
                  planes: Marched, both: bool, camera) -> Exit | None:
    """The native kernel (native.py): the same search, candidates and walk as the tensor
    code, one ray at a time; the same triangles, then the same differentiable hit. Where no
    gradient is wanted the kernel also returns the exits' values (the same as _exit's);
    else the hit is taken again here, in torch. None where the kernel did not run."""
    h, w = planes.h, planes.w
    tv = g.meshes.tri_vertices
    c0, ct = camera if camera is not None else camera_coordinates(g, batch, p1d, td)
    grad = not native.no_grad_through(p1, t)
    res = native.march(c0, ct, s_max, s_min, 0.5 * w / g.proj[:, 12],
                       0.5 * h / g.proj[:, 13], batch, planes, both, steps, refine, p1d,
                       td, tv, g.meshes.tri_across,
                       tri_normals=None if grad else g.meshes.tri_normals)
    if res is None:
        return None
    if not grad:
        found, tri, layer, s_exit, bary, normal, pos = res
        return Exit(found=found, position=pos, normal=normal, tri=tri, dist=s_exit,
                    layer=layer, bary=bary)
    found, tri, layer = res
    st, bt = intersect_triangles(p1, t, take(tv, tri.clamp(min=0)))
    s_exit = torch.where(found, st, torch.zeros_like(st))
    bary = torch.where(found[:, None], bt, torch.zeros_like(bt))
    return _exit(g, p1, t, found, tri, s_exit, bary, layer)


def _search_compacted(proj: "_Projector", planes: Marched, front: torch.Tensor | None,
                      s_max: torch.Tensor, steps: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Uniform coarse search over the chord, (lo, hi) brackets of the first crossing; the
    rays that crossed are dropped after each sample. The per-ray quantities the step needs
    are packed so that dropping rays is one gather (instead of one per array)."""
    h, w = planes.h, planes.w
    n = s_max.shape[0]
    lo = torch.zeros(n, dtype=s_max.dtype)
    hi = s_max.clone()
    state = torch.cat([proj.c0, proj.ct, s_max[:, None], proj.sx[:, None],
                       proj.sy[:, None]], 1)  # (N, 9)
    base, pbase = proj.base, proj.pbase
    ids = torch.arange(n)
    last = torch.zeros(n, dtype=s_max.dtype)  # the last s still inside, per active ray
    for k in range(1, steps + 1):
        if ids.numel() == 0:
            break
        s = state[:, 6] * (k / steps)
        crossed = _crossed_at(state[:, 0:3], state[:, 3:6], s, state[:, 7],
                              state[:, 8], base, pbase, planes.back, front, planes.table,
                              h, w)
        if bool(crossed.any()):
            done = where_true(crossed)
            gone = take(ids, done)
            put_(hi, gone, take(s, done))
            put_(lo, gone, take(last, done))
            keep = where_true(~crossed)
            state, base, ids = take(state, keep), take(base, keep), take(ids, keep)
            pbase = take(pbase, keep)
            last = take(s, keep)
        else:
            last = s
    if ids.numel():
        put_(lo, ids, last)
    return lo, hi


def _search_tiles(batch: torch.Tensor, proj: "_Projector", planes: Marched,
                  front: torch.Tensor | None, s_max: torch.Tensor, steps: int,
                  depth_min: torch.Tensor, tile: int, fine_steps: int
                  ) -> tuple[torch.Tensor, torch.Tensor]:
    """The coarse search with empty space skipped (min back depth per tile: Oliveira and
    Brauwers 2007's min/max acceleration): only intervals that may hold the crossing are
    searched with ``fine_steps`` exact plane tests."""
    h, w = planes.h, planes.w
    n = s_max.shape[0]
    lo = torch.zeros(n, dtype=s_max.dtype)
    hi = s_max.clone()
    th, tw = depth_min.shape[1:3]
    dmin = depth_min.reshape(-1)
    active = torch.arange(n)  # rays whose crossing is not bracketed yet
    for k in range(1, steps + 1):
        if active.numel() == 0:
            break
        s0 = s_max[active] * ((k - 1) / steps)
        s1 = s_max[active] * (k / steps)
        # Coarse test at the interval's end: can the ray have crossed by s1?
        c = proj.c0[active] + s1[:, None] * proj.ct[active]  # camera coords
        flat, inside = proj.pixels(active, s1)
        px = flat % w
        py = (flat // w) % h
        tflat = batch[active] * (th * tw) + (py // tile) * tw + (px // tile)
        maybe = ~inside | (c[:, 2] >= dmin[tflat] * (1.0 - 1e-6))
        # Exact search inside the intervals that may hold the crossing.
        idx = active[maybe]
        a, b = s0[maybe], s1[maybe]
        found = torch.zeros(idx.numel(), dtype=torch.bool)
        for j in range(1, fine_steps + 1):
            sj = a + (b - a) * (j / fine_steps)
            cj = _crossed_at(take(proj.c0, idx), take(proj.ct, idx), sj, take(proj.sx, idx),
                             take(proj.sy, idx), take(proj.base, idx),
                             take(proj.pbase, idx), planes.back, front, planes.table, h,
                             w) & ~found
            hi[idx[cj]] = sj[cj]
            found = found | cj
            lo[idx[~found]] = sj[~found]
        lo[active[~maybe]] = s1[~maybe]
        done = torch.zeros(n, dtype=torch.bool)
        done[idx[found]] = True
        active = active[~done[active]]
    return lo, hi


def _exact_exit(g: GBuffer, p1: torch.Tensor, t: torch.Tensor, proj: "_Projector",
                planes: Marched, lo: torch.Tensor, hi: torch.Tensor, s_min: torch.Tensor,
                s_max: torch.Tensor, both: bool) -> Exit:
    """Exact exit: the ray intersected with the crossed layer's triangle at the crossing
    (first choice: the pixel just beyond the crossing; second: the last pixel still
    inside). Two layers: the layer whose plane is crossed farther at ``hi`` first, then the
    other; the first try on every ray at once (no gathers), the others on the rays still
    without an exit; then the walk to the triangle that contains the hit."""
    n = p1.shape[0]
    tv = g.meshes.tri_vertices
    if both:
        flat, _ = proj.pixels(None, hi)
        x = proj.c0 + hi[:, None] * proj.ct  # camera coordinates
        tb, pb = _plane_at(planes.back, flat, proj.pbase, planes.table)
        tf, pf = _plane_at(planes.front, flat, proj.pbase, planes.table)
        # (the front plane faces the eye: its row negated; none where a layer is empty)
        primary_front = (tb >= 0) & (tf >= 0) & (
            (pf[:, 3] - dot(pf[:, :3], x)) > (dot(pb[:, :3], x) - pb[:, 3]))
        tries = [(hi, primary_front), (lo, primary_front), (hi, ~primary_front),
                 (lo, ~primary_front)]
    else:
        back = torch.zeros(n, dtype=torch.bool)
        tries = [(hi, back), (lo, back)]
    tri, s_exit, bary, found, uf = _candidates(g, p1, t, proj, planes, None, *tries[0], s_min,
                                               s_max, both)
    s_exit = torch.where(found, s_exit, torch.zeros_like(s_exit))
    tri = torch.where(found, tri, torch.full_like(tri, -1))
    bary = torch.where(found[:, None], bary, torch.zeros_like(bary))
    layer = torch.where(found, (~uf).long(), torch.full_like(tri, -1))
    # the where above keeps ``found`` for its gradient: the later tries set a copy
    found = found.clone()
    for s_try, use_front in tries[1:]:
        todo = where_true(~found)  # only the rays still without an exit
        if todo.numel() == 0:
            break
        cand, st, bt, ok, uf = _candidates(g, p1, t, proj, planes, todo, s_try, use_front,
                                           s_min, s_max, both)
        oi = where_true(ok)
        hit = take(todo, oi)
        put_(s_exit, hit, take(st, oi))
        put_(tri, hit, take(cand, oi))
        put_(layer, hit, (~take(uf, oi)).long())
        put_(bary, hit, take(bt, oi))
        put_(found, hit, torch.ones_like(hit, dtype=torch.bool))
    tri, s_exit, bary = _walk_to_containing(p1, t, tv, g.meshes.tri_across, found, tri,
                                            s_exit, bary, s_min, s_max)
    return _exit(g, p1, t, found, tri, s_exit, bary, layer)


def _candidates(g: GBuffer, p1, t, proj: "_Projector", planes: Marched,
                todo: torch.Tensor | None, s_try: torch.Tensor, use_front: torch.Tensor,
                s_min, s_max, both: bool):
    """The exit candidates of rays ``todo`` (None: all) at their parameters ``s_try``: the
    triangle seen at that pixel in the chosen layer, and the hit with it."""
    def sel(x):
        return x if todo is None else take(x, todo)

    flat, inside = proj.pixels(todo, sel(s_try))
    uf = sel(use_front)
    if both:
        seen_tri = torch.where(uf, take(planes.front, flat), take(planes.back, flat)).long()
    else:  # the back layer only (use_front is all False)
        seen_tri = take(planes.back, flat).long()
    cand = torch.where(inside & (seen_tri >= 0), seen_tri, torch.full_like(flat, -1))
    st, bt = intersect_triangles(sel(p1), sel(t), take(g.meshes.tri_vertices, cand.clamp(min=0)))
    ok = (cand >= 0) & torch.isfinite(st) & (st > sel(s_min)) & (st <= sel(s_max) * 1.5)
    return cand, st, bt, ok, uf


def _exit(g: GBuffer, p1: torch.Tensor, t: torch.Tensor, found: torch.Tensor,
          tri: torch.Tensor, s_exit: torch.Tensor, bary: torch.Tensor, layer: torch.Tensor
          ) -> Exit:
    """The Exit of rays p1 + s t that leave through triangles ``tri`` at ``s_exit``."""
    normal = interpolate(bary, take(g.meshes.tri_normals, tri.clamp(min=0)))
    normal = normal / normal.norm(dim=-1, keepdim=True).clamp(min=1e-20)
    normal = torch.where(found[:, None], normal, torch.zeros_like(normal))
    pos = p1 + s_exit[:, None] * t
    return Exit(found=found, position=pos, normal=normal, tri=tri, dist=s_exit, layer=layer,
                bary=bary)

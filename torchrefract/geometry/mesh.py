"""Meshes: load with trimesh, apply the scene transform, shading normals, UVs.

Shading normals follow SCENE_SPEC.md: the file's own vertex normals when it has them
(rotated with the object), otherwise trimesh's ``vertex_normals`` computed after the
transform (:mod:`~torchrefract.geometry.vertex_normals`, the same numbers without importing
trimesh). Degenerate triangles are dropped; a mesh that is not watertight loads with a
warning (the two-layer methods assume closed objects). What does not depend on the pose
(the faces kept, watertightness, the edge-neighbour tables) is computed once per file, in
object space, and kept in the cache folder (``mesh/``, keyed by the file's path, time and
size): a new process then reads it without trimesh, whose import (scipy's with it) took
~0.55 s and ~60 MB of a warm start; each transform then only moves positions and normals.
"""

from __future__ import annotations

import functools
import hashlib
import math
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from torchrefract import settings
from torchrefract.checks import ConfigError, file_version
from torchrefract.geometry.vertex_normals import vertex_normals
from torchrefract.output.atomic import atomic_path
from torchrefract.scene.model import Transform


@dataclass(frozen=True)
class MeshData:
    """A triangle mesh in world space (float32, CPU).

    Attributes:
        vertices: (V, 3) world positions.
        faces: (F, 3) int64 vertex indices, counter-clockwise seen from outside.
        normals: (V, 3) unit shading normals.
        uvs: (V, 2) texture coordinates (OpenGL convention) or None.
        watertight: whether every edge is shared by exactly two faces.
        neighbors: (F, 3) int64 faces sharing an edge with each face (-1 where none).
        across: (F, 3) int64 the face across the edge opposite each corner: the first of
            ``neighbors`` without a vertex at that corner's position (-1 where none).
    """

    vertices: torch.Tensor
    faces: torch.Tensor
    normals: torch.Tensor
    uvs: torch.Tensor | None
    watertight: bool
    neighbors: torch.Tensor
    across: torch.Tensor

    @property
    def num_faces(self) -> int:
        return int(self.faces.shape[0])

    @functools.cached_property
    def content_hash(self) -> str:
        """SHA-256 (hex) of the vertices, faces and shading normals: the key of what is
        computed from the mesh's content (``sh``'s tables), hashed once per mesh."""
        h = hashlib.sha256()
        for t, dt in ((self.vertices, np.float32), (self.faces, np.int64),
                      (self.normals, np.float32)):
            a = np.ascontiguousarray(t.numpy().astype(dt))
            h.update(str(a.shape).encode())
            h.update(a.tobytes())
        return h.hexdigest()

    @functools.cached_property
    def tri_vertices(self) -> torch.Tensor:
        """(F, 3, 3) float32 corner positions, gathered once per mesh (the batch's table
        and the face sphere read them)."""
        return self.vertices.index_select(0, self.faces.reshape(-1)).view(-1, 3, 3)

    @functools.cached_property
    def tri_normals(self) -> torch.Tensor:
        """(F, 3, 3) float32 corner shading normals, gathered once per mesh."""
        return self.normals.index_select(0, self.faces.reshape(-1)).view(-1, 3, 3)

    @functools.cached_property
    def face_normals(self) -> torch.Tensor:
        """(F, 3) float32 unit geometric normals (the corners' winding), computed once per
        mesh: sparse supersampling's test of a fold inside a pixel."""
        tv = self.tri_vertices.double()
        n = torch.cross(tv[:, 1] - tv[:, 0], tv[:, 2] - tv[:, 0], dim=-1)
        return (n / n.norm(dim=-1, keepdim=True).clamp(min=1e-300)).float()

    @functools.cached_property
    def tri_uvs(self) -> torch.Tensor:
        """(F, 3, 2) float32 corner UVs (zeros without UVs), gathered once per mesh."""
        if self.uvs is None:
            return torch.zeros(self.num_faces, 3, 2)
        return self.uvs.index_select(0, self.faces.reshape(-1)).view(-1, 3, 2)

    @functools.cached_property
    def face_sphere(self) -> tuple[torch.Tensor, torch.Tensor]:
        """float32 center (3,) and radius () of the sphere around the faces' corners
        (centered on their axis-aligned box), computed once per mesh: the march's bound."""
        v = self.tri_vertices.reshape(-1, 3)
        c = 0.5 * (v.min(0).values + v.max(0).values)
        return c, (v - c).norm(dim=-1).max()

    def bounding_sphere(self) -> tuple[np.ndarray, float]:
        """Center (3,) and radius of the axis-aligned box's circumscribed sphere (computed
        once per mesh: the visibility passes ask for it every view; the center a copy)."""
        c, r = self._bounding_sphere
        return c.copy(), r

    @functools.cached_property
    def _bounding_sphere(self) -> tuple[np.ndarray, float]:
        v = self.vertices.numpy().astype(np.float64)
        lo, hi = v.min(0), v.max(0)
        c = 0.5 * (lo + hi)
        return c, float(np.linalg.norm(v - c, axis=1).max())


def rotation_matrix(rotate_deg: tuple[float, float, float]) -> np.ndarray:
    """R = Rz @ Ry @ Rx for degrees about world X, Y, Z (right-handed), float64 (3, 3)."""
    ax, ay, az = (math.radians(a) for a in rotate_deg)
    cx, sx, cy, sy, cz, sz = (math.cos(ax), math.sin(ax), math.cos(ay), math.sin(ay),
                              math.cos(az), math.sin(az))
    rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    return rz @ ry @ rx


def transform_matrix(t: Transform) -> np.ndarray:
    """4x4 object-to-world matrix: translate @ rotate @ scale (float64)."""
    m = np.eye(4)
    m[:3, :3] = rotation_matrix(t.rotate_deg) * t.scale
    m[:3, 3] = t.translate
    return m


def _load_trimesh(path: str):
    """The file as one ``trimesh.Trimesh`` (imported here: only a mesh not in the cache
    folder needs it)."""
    import trimesh  # noqa: PLC0415

    try:
        # Not force="mesh": trimesh's concatenation there drops the file's own normals.
        loaded = trimesh.load(path, process=False)
        if isinstance(loaded, trimesh.Scene):
            loaded = loaded.to_mesh() if loaded.geometry else None
    except Exception as exc:  # trimesh raises many types for broken files
        raise ConfigError(f"mesh {path!r}: cannot be loaded ({type(exc).__name__}: {exc})") \
            from None
    if not isinstance(loaded, trimesh.Trimesh) or len(loaded.faces) == 0:
        raise ConfigError(f"mesh {path!r}: contains no triangles")
    return loaded


def load_mesh(path: str, transform: Transform = Transform()) -> MeshData:
    """Load a mesh file and place it in world space (cached per path and transform).

    Args:
        path: any file trimesh loads.
        transform: the scene's object transform (scale -> rotate -> translate).

    Returns:
        MeshData in world space.

    Raises:
        ConfigError: unreadable file, no triangles, NaN/Inf vertices, all faces degenerate.
    """
    return _load_mesh_cached(*file_version(path, "mesh"), transform)


@dataclass(frozen=True)
class _Topology:
    """What a mesh file gives independently of its pose (object space, float64): computed
    once per file version, so a sweep over random poses pays only for the transform."""

    verts: np.ndarray           # (V, 3) object-space positions
    faces: np.ndarray           # (F, 3) the faces kept (degenerate ones dropped)
    file_normals: np.ndarray | None
    uvs: np.ndarray | None
    watertight: bool
    neighbors: np.ndarray       # (F, 3) int64
    across: np.ndarray          # (F, 3) int64


_TOPOLOGY_FORMAT = 1
"""Bumped when what _topology computes changes: older cache files are then not read."""


def _topology_file(path: str, mtime: int, size: int) -> Path:
    key = hashlib.sha256(repr((_TOPOLOGY_FORMAT, path, mtime, size)).encode()).hexdigest()
    return settings.cache_folder() / "mesh" / f"topology_{key[:32]}.npz"


@functools.lru_cache(maxsize=16)
def _topology(path: str, _mtime: int, _size: int) -> _Topology:
    """The file's :class:`_Topology`: from the cache folder where it is there (its load's
    warnings given again), else computed and written there (a failed write is skipped)."""
    disk = _topology_file(path, _mtime, _size)
    try:
        with np.load(disk, allow_pickle=False) as z:
            top = _Topology(z["verts"], z["faces"],
                            z["file_normals"] if "file_normals" in z else None,
                            z["uvs"] if "uvs" in z else None, bool(z["watertight"]),
                            z["neighbors"], z["across"])
            notes = [str(w) for w in z["warnings"]]
        for note in notes:
            warnings.warn(note, stacklevel=3)
        return top
    except (OSError, KeyError, ValueError):  # absent, unreadable or of another format
        pass
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        top = _compute_topology(path)
    for w in caught:  # given on, and kept with the file for the next process
        warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
    arrays = {"verts": top.verts, "faces": top.faces, "watertight": np.bool_(top.watertight),
              "neighbors": top.neighbors, "across": top.across,
              "warnings": np.array([str(w.message) for w in caught], dtype=str)}
    if top.file_normals is not None:
        arrays["file_normals"] = top.file_normals
    if top.uvs is not None:
        arrays["uvs"] = top.uvs
    try:
        disk.parent.mkdir(parents=True, exist_ok=True)
        with atomic_path(disk) as tmp, open(tmp, "wb") as fh:
            np.savez(fh, **arrays)
    except OSError:
        pass  # a read-only cache folder: computed again next time
    return top


def _compute_topology(path: str) -> _Topology:
    """:func:`_topology` computed from the file (trimesh)."""
    import trimesh  # noqa: PLC0415

    tm = _load_trimesh(path)
    verts = np.asarray(tm.vertices, dtype=np.float64)
    faces = np.asarray(tm.faces, dtype=np.int64)
    if not np.isfinite(verts).all():
        raise ConfigError(f"mesh {path!r}: vertex positions contain NaN or Inf")
    if faces.min() < 0 or faces.max() >= len(verts):
        raise ConfigError(f"mesh {path!r}: face indices out of range")
    # trimesh keeps normals read from the file in its cache (it has no public flag for it);
    # computed normals would only appear there after an access, which has not happened yet.
    has_normals = "vertex_normals" in tm._cache
    file_normals = np.asarray(tm.vertex_normals, dtype=np.float64) if has_normals else None
    uv = getattr(tm.visual, "uv", None)
    uvs = None if uv is None or len(uv) != len(verts) else np.asarray(uv, dtype=np.float64)

    # Drop degenerate triangles (repeated indices or zero area): they have no normal and
    # would give the visibility pass ids that no exact intersection can reproduce.
    # The test is relative to each triangle's longest edge, so a float32-rounded collinear
    # triangle (a sliver with no defined normal) is caught at any scale (and any pose).
    tri = verts[faces]  # (F, 3, 3)
    area2 = np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    edge2 = np.max(np.stack([((tri[:, i] - tri[:, (i + 1) % 3]) ** 2).sum(-1)
                             for i in range(3)], -1), -1)
    keep = (area2 > 1e-7 * edge2) & (edge2 > 0) & (faces[:, 0] != faces[:, 1]) \
        & (faces[:, 1] != faces[:, 2]) & (faces[:, 0] != faces[:, 2])
    if not keep.any():
        raise ConfigError(f"mesh {path!r}: every triangle is degenerate (zero area)")
    if not keep.all():
        warnings.warn(f"mesh {path!r}: dropped {int((~keep).sum())} degenerate triangles",
                      stacklevel=3)
    faces = faces[keep]
    # Watertight as a surface: vertices split only to carry normals or UVs (a flat-shaded
    # box) still close the volume, so check on a copy with coincident vertices merged.
    closed = trimesh.Trimesh(verts, faces, process=False)
    closed.merge_vertices(merge_tex=True, merge_norm=True)
    watertight = bool(closed.is_watertight)
    if not watertight:
        warnings.warn(f"mesh {path!r} is not watertight: methods that assume a closed object "
                      "may show holes or wrong exits", stacklevel=3)
    adjacency = trimesh.Trimesh(verts, faces, process=False).face_adjacency
    neighbors = face_neighbors(np.asarray(adjacency, dtype=np.int64), len(faces))
    across = across_edges(verts.astype(np.float32)[faces], neighbors)
    return _Topology(verts, faces, file_normals, uvs, watertight, neighbors, across)


@functools.lru_cache(maxsize=16)
def _scaled_normals(path: str, _mtime: int, _size: int, scale: float) -> np.ndarray:
    """The file's computed vertex normals (``vertex_normals``) at ``scale``, unturned: the
    corner angles and face normals of a turned and moved copy are these turned (the same
    values up to rounding, tests/test_mesh.py), so a sweep's new pose costs a product
    instead of the whole computation. Computed at the scale itself, so that what counts
    as a degenerate face is the posed mesh's."""
    top = _topology(path, _mtime, _size)
    return vertex_normals(top.verts * scale, top.faces)


@functools.lru_cache(maxsize=16)
def _load_mesh_cached(path: str, _mtime: int, _size: int, transform: Transform) -> MeshData:
    top = _topology(path, _mtime, _size)
    faces = top.faces
    m = transform_matrix(transform)
    verts = top.verts @ m[:3, :3].T + m[:3, 3]
    if top.file_normals is not None:
        normals = top.file_normals @ rotation_matrix(transform.rotate_deg).T
    else:  # trimesh's, without importing trimesh, turned as the file's would be
        normals = _scaled_normals(path, _mtime, _size, transform.scale) \
            @ rotation_matrix(transform.rotate_deg).T
    n = np.linalg.norm(normals, axis=1, keepdims=True)
    # Vertices used by no kept face (or with a zero normal in the file) get any unit vector;
    # they are never interpolated.
    normals = np.where(n > 1e-12, normals / np.maximum(n, 1e-30), np.array([0.0, 0.0, 1.0]))
    return MeshData(
        vertices=torch.from_numpy(verts.astype(np.float32)),
        faces=torch.from_numpy(faces),
        normals=torch.from_numpy(normals.astype(np.float32)),
        uvs=None if top.uvs is None else torch.from_numpy(top.uvs.astype(np.float32)),
        watertight=top.watertight,
        neighbors=torch.from_numpy(top.neighbors),
        across=torch.from_numpy(top.across),
    )


def face_neighbors(adjacency: np.ndarray, num_faces: int) -> np.ndarray:
    """(F, 3) int64 edge neighbours per face, -1 padded, from trimesh's ``face_adjacency``
    pairs (P, 2): each pair (a, b) lists b for a, then a for b, in the pairs' order, and a
    face keeps its first three (non-manifold edges may list more; three are plenty).

    Vectorized (a loop over the pairs took 40 ms per load of suzanne and 169 of the bunny,
    paid for every new pose in a sweep; now 4 and 16); the same table as that loop
    (tests/test_mesh.py)."""
    neighbors = np.full((num_faces, 3), -1, dtype=np.int64)
    if len(adjacency) == 0:
        return neighbors
    a, b = adjacency[:, 0], adjacency[:, 1]
    src = np.stack([a, b], 1).reshape(-1)  # in the loop's order: (a, b), then (b, a)
    dst = np.stack([b, a], 1).reshape(-1)
    order = np.argsort(src, kind="stable")  # by face, keeping the listing order
    src, dst = src[order], dst[order]
    start = np.searchsorted(src, src, side="left")  # first entry of each face's group
    rank = np.arange(len(src)) - start
    keep = rank < 3
    neighbors[src[keep], rank[keep]] = dst[keep]
    return neighbors


def across_edges(tri_vertices: np.ndarray, neighbors: np.ndarray, tol: float = 1e-6
                 ) -> np.ndarray:
    """(F, 3) the neighbour across the edge opposite each corner of each face.

    For corner k of face f: the first of ``neighbors[f]`` (in order) none of whose corners
    lies within ``tol`` (per axis) of corner k's position, -1 where there is none. By
    position, not vertex index, so that faces meeting at split vertices (normal or UV
    seams) are neighbours too. The walk of the march (``march._walk_to_containing``) crosses
    the edge opposite a barycentric's most negative corner through this table.

    Args:
        tri_vertices: (F, 3, 3) float32 corner positions; neighbors: (F, 3) int64.
    """
    # has[f, j, k]: neighbour j has a vertex at corner k of f (one (j, k) at a time, so
    # that a mesh of F faces needs O(F) temporary memory, not 81 F floats)
    has = np.zeros((len(neighbors), 3, 3), dtype=bool)
    for j in range(3):
        nbv = tri_vertices[np.maximum(neighbors[:, j], 0)]  # (F, 3 corners, 3)
        for k in range(3):
            has[:, j, k] = (np.abs(nbv - tri_vertices[:, None, k, :]).max(-1) < tol).any(-1)
    ok = (neighbors >= 0)[:, :, None] & ~has  # (F, j, k)
    first = ok.argmax(1)  # (F, k): the first neighbour j that qualifies
    across = np.take_along_axis(neighbors, first, 1)
    return np.where(ok.any(1), across, -1).astype(np.int64)

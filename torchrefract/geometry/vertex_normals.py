"""Angle-weighted vertex normals, trimesh's ``Trimesh.vertex_normals`` without trimesh.

A mesh file without normals gets trimesh's vertex normals (SCENE_SPEC.md), computed after
the scene transform, so once per pose. Importing trimesh for them brought scipy and
networkx into every render process (docs/decisions.md, "Peak memory") although the mesh
cache spares trimesh everywhere else. This is the same computation in the same
floating-point operations (trimesh 4.x/5.x ``geometry.weighted_vertex_normals``: face
normals from edge cross products, corner angles, each vertex's sum of angle times face
normal in face order, then unit length), so the normals are bit-identical to trimesh's
(``tests/test_vertex_normals.py`` checks against trimesh itself).
"""

from __future__ import annotations

import numpy as np

_TOL_ZERO = float(np.finfo(np.float64).resolution * 100)  # trimesh's util.TOL_ZERO
_TOL_MERGE = 1e-8  # trimesh's tol.merge: a corner below it makes a degenerate triangle


def _row_dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Per-row dot product as trimesh's ``util.diagonal_dot`` computes it."""
    return np.dot(a * b, [1.0] * a.shape[1])


def _unitize(vectors: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rows scaled to unit length, and which rows were not zero (trimesh's ``unitize``)."""
    norm = np.sqrt(np.dot(vectors * vectors, [1.0] * vectors.shape[1]))
    valid = norm > _TOL_ZERO
    norm[valid] **= -1
    return vectors * norm.reshape((-1, 1)), valid


def _corner_angles(tri: np.ndarray) -> np.ndarray:
    """(F, 3) angle at each corner; all zero for a triangle with a zero corner."""
    u = _unitize(tri[:, 1] - tri[:, 0])[0]
    v = _unitize(tri[:, 2] - tri[:, 0])[0]
    w = _unitize(tri[:, 2] - tri[:, 1])[0]
    out = np.zeros((len(tri), 3), dtype=np.float64)
    out[:, 0] = np.arccos(np.clip(_row_dot(u, v), -1, 1))
    out[:, 1] = np.arccos(np.clip(_row_dot(-u, w), -1, 1))
    out[:, 2] = np.pi - out[:, 0] - out[:, 1]
    out[(out < _TOL_MERGE).any(axis=1), :] = 0.0
    return out


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(V, 3) float64 unit normals of ``vertices`` (V, 3) for ``faces`` (F, 3): each the
    corner-angle-weighted sum of its faces' normals (zero where no valid face uses it)."""
    verts = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    tri = verts[faces]
    edges = tri[:, 1:, :] - tri[:, :2, :]
    unit, valid = _unitize(np.cross(edges[:, 0], edges[:, 1]))
    face_normals = np.zeros((len(faces), 3), dtype=np.float64)
    face_normals[valid] = unit[valid]
    angles = _corner_angles(tri)
    ok = (face_normals ** 2).sum(axis=1) > 0.5
    faces, face_normals, angles = faces[ok], face_normals[ok], angles[ok]
    # Each vertex's contributions added one at a time in face order, starting from zero
    # (scipy's sparse product, which trimesh uses, adds them so; so does bincount, per
    # component, faster than np.add.at).
    contrib = angles.reshape(-1, 1) * np.repeat(face_normals, 3, axis=0)
    idx = faces.reshape(-1)
    summed = np.stack([np.bincount(idx, weights=contrib[:, c], minlength=len(verts))
                       for c in range(3)], axis=1)
    return _unitize(summed)[0]


__all__ = ["vertex_normals"]

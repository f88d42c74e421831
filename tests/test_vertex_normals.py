"""Vertex normals without trimesh: bit-identical to trimesh's ``Trimesh.vertex_normals``."""

from pathlib import Path

import numpy as np
import pytest

from torchrefract.geometry import mesh as mesh_mod
from torchrefract.geometry.vertex_normals import vertex_normals
from torchrefract.scene.model import Transform

trimesh = pytest.importorskip("trimesh")

MESHES = sorted(p for p in (Path(__file__).resolve().parent.parent / "assets" / "meshes").rglob("*")
                if p.suffix in (".ply", ".obj"))
POSES = (Transform(), Transform(scale=0.37, rotate_deg=(10.0, -25.0, 70.0),
                                translate=(0.1, -2.0, 3.5)))


@pytest.mark.parametrize("path", MESHES, ids=lambda p: p.name)
def test_vertex_normals_match_trimesh(path):
    top = mesh_mod._topology(*mesh_mod.file_version(path, "mesh"))
    for pose in POSES:
        m = mesh_mod.transform_matrix(pose)
        verts = top.verts @ m[:3, :3].T + m[:3, 3]
        ours = vertex_normals(verts, top.faces)
        theirs = np.asarray(trimesh.Trimesh(verts, top.faces, process=False).vertex_normals)
        np.testing.assert_array_equal(ours, theirs)


def test_vertex_normals_degenerate_and_unused():
    """A zero-area face counts for nothing; a vertex no face uses gets a zero normal."""
    verts = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [2, 0, 0], [5, 5, 5.0]])
    faces = np.array([[0, 1, 2], [0, 1, 3]])
    ours = vertex_normals(verts, faces)
    theirs = np.asarray(trimesh.Trimesh(verts, faces, process=False).vertex_normals)
    np.testing.assert_array_equal(ours, theirs)
    assert not ours[4].any()

"""Mesh loading: transform order, shading normals, degenerate faces, broken files."""

from __future__ import annotations

import math
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh
from conftest import ASSETS
from trimesh.exchange.ply import export_ply

from torchrefract.checks import ConfigError
from torchrefract.geometry.mesh import load_mesh, rotation_matrix, transform_matrix
from torchrefract.scene.model import Transform

ROOT = Path(__file__).resolve().parents[1]

# An asymmetric tetrahedron (outward winding) so that any wrong axis or order shows.
# Dyadic coordinates: exact in the float32 of a PLY file, so that midpoints are exactly
# collinear after the round trip.
TET_V = np.array([[0.125, 0.25, 0.375], [1.25, 0.125, 0.25], [0.25, 0.875, 0.125],
                  [0.375, 0.5, 1.75]])
TET_F = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])


def write_ply(path: Path, vertices, faces, normals=None) -> str:
    m = trimesh.Trimesh(np.asarray(vertices, float), np.asarray(faces), process=False,
                        vertex_normals=normals)
    path.write_bytes(export_ply(m, vertex_normal=normals is not None))
    return str(path)


def rx(deg):
    a = math.radians(deg)
    return np.array([[1, 0, 0], [0, math.cos(a), -math.sin(a)], [0, math.sin(a), math.cos(a)]])


def ry(deg):
    a = math.radians(deg)
    return np.array([[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]])


def rz(deg):
    a = math.radians(deg)
    return np.array([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]])


def test_transform_is_scale_then_rotate_xyz_then_translate(tmp_path):
    path = write_ply(tmp_path / "tet.ply", TET_V, TET_F)
    t = Transform(scale=2.5, rotate_deg=(30.0, -50.0, 70.0), translate=(1.0, -2.0, 3.0))
    m = load_mesh(path, t)
    r = rz(70.0) @ ry(-50.0) @ rx(30.0)
    want = (2.5 * TET_V) @ r.T + np.array([1.0, -2.0, 3.0])
    assert np.abs(m.vertices.numpy() - want).max() < 1e-5
    # any other composition order is measurably different
    wrong = (2.5 * TET_V) @ (rx(30.0) @ ry(-50.0) @ rz(70.0)).T + np.array([1.0, -2.0, 3.0])
    assert np.abs(m.vertices.numpy() - wrong).max() > 0.1
    # translate is not scaled or rotated
    wrong2 = (2.5 * (TET_V + [1.0, -2.0, 3.0])) @ r.T
    assert np.abs(m.vertices.numpy() - wrong2).max() > 0.1
    assert np.allclose(rotation_matrix((30.0, -50.0, 70.0)), r, atol=1e-12)
    mat = transform_matrix(t)
    assert np.allclose(mat[:3, :3], 2.5 * r) and np.allclose(mat[:3, 3], [1, -2, 3])
    assert np.array_equal(mat[3], [0, 0, 0, 1])
    # faces (and so the outward winding) are untouched by a proper rotation
    assert np.array_equal(m.faces.numpy(), TET_F)


def test_rotation_axes_and_order_by_example(tmp_path):
    # about world X first, then world Y, then Z; right-handed
    path = write_ply(tmp_path / "tet_axes.ply", TET_V, TET_F)
    m = load_mesh(path, Transform(rotate_deg=(90.0, 90.0, 0.0)))
    # X by 90: (x, y, z) -> (x, -z, y); then Y by 90: (x, y, z) -> (z, y, -x)
    x, y, z = TET_V.T
    step1 = np.stack([x, -z, y], 1)
    want = np.stack([step1[:, 2], step1[:, 1], -step1[:, 0]], 1)
    assert np.abs(m.vertices.numpy() - want).max() < 1e-6
    m = load_mesh(path, Transform(rotate_deg=(0.0, 0.0, 90.0)))  # Z by 90: x -> y
    assert np.abs(m.vertices.numpy() - np.stack([-y, x, z], 1)).max() < 1e-6


@pytest.mark.parametrize("mesh", ["spot.ply", "suzanne.ply", "bunny.ply"])
def test_a_new_pose_turns_the_kept_normals_to_the_posed_meshs_own(mesh):
    """A pose's computed normals are the file's at that scale, turned (kept per scale, not
    recomputed per pose): the same float32 values as computing them from the posed
    vertices, for any rotation, translation and scale."""
    from torchrefract.geometry.mesh import _topology, file_version
    from torchrefract.geometry.vertex_normals import vertex_normals

    path = str(ASSETS / "meshes" / mesh)
    top = _topology(*file_version(path, "mesh"))
    assert top.file_normals is None  # computed, not read
    rng = np.random.default_rng(7)
    for _ in range(4):
        t = Transform(scale=float(rng.uniform(0.2, 3.0)),
                      rotate_deg=tuple(float(a) for a in rng.uniform(-180.0, 180.0, 3)),
                      translate=tuple(float(a) for a in rng.uniform(-2.0, 2.0, 3)))
        m = transform_matrix(t)
        posed = vertex_normals(top.verts @ m[:3, :3].T + m[:3, 3], top.faces)
        posed /= np.linalg.norm(posed, axis=1, keepdims=True)
        np.testing.assert_array_equal(load_mesh(path, t).normals.numpy(),
                                      posed.astype(np.float32))


def test_computed_normals_follow_the_transform(tmp_path):
    ico = trimesh.creation.icosphere(subdivisions=2, radius=1.0)
    path = write_ply(tmp_path / "ico.ply", ico.vertices, ico.faces)
    t = Transform(scale=0.7, rotate_deg=(10.0, 20.0, 30.0), translate=(5.0, 0.0, -1.0))
    m = load_mesh(path, t)
    v = m.vertices.numpy().astype(np.float64)
    want = trimesh.Trimesh(v, m.faces.numpy(), process=False).vertex_normals
    n = m.normals.numpy()
    assert np.abs(n - want).max() < 1e-5
    assert np.abs(np.linalg.norm(n, axis=1) - 1.0).max() < 1e-6
    # outward on a sphere around the translated center
    radial = v - np.array([5.0, 0.0, -1.0])
    radial /= np.linalg.norm(radial, axis=1, keepdims=True)
    assert (np.sum(n * radial, axis=1) > 0.98).all()
    assert m.watertight


def test_normals_from_the_file_are_kept_and_rotated(tmp_path):
    ico = trimesh.creation.icosphere(subdivisions=2, radius=1.0)
    inverted = -np.asarray(ico.vertex_normals)  # deliberately inward: must be kept
    path = write_ply(tmp_path / "inverted.ply", ico.vertices, ico.faces, normals=inverted)
    # the file really stores them
    assert b"property float nx" in Path(path).read_bytes()[:400]
    t = Transform(scale=2.0, rotate_deg=(0.0, 90.0, 45.0), translate=(1.0, 2.0, 3.0))
    m = load_mesh(path, t)
    r = rz(45.0) @ ry(90.0) @ rx(0.0)
    want = inverted @ r.T  # rotated, not scaled or translated, still unit
    assert np.abs(m.normals.numpy() - want).max() < 1e-5


def test_obj_normals_from_the_file_are_kept(tmp_path):
    """Same as above for OBJ ``vn`` records."""
    ico = trimesh.creation.icosphere(subdivisions=1, radius=1.0)
    inverted = -np.asarray(ico.vertex_normals)
    lines = [f"v {a:.9f} {b:.9f} {c:.9f}" for a, b, c in ico.vertices]
    lines += [f"vn {a:.9f} {b:.9f} {c:.9f}" for a, b, c in inverted]
    lines += [f"f {a + 1}//{a + 1} {b + 1}//{b + 1} {c + 1}//{c + 1}" for a, b, c in ico.faces]
    path = tmp_path / "inverted.obj"
    path.write_text("\n".join(lines) + "\n")
    m = load_mesh(str(path), Transform())
    assert m.num_faces == len(ico.faces)
    assert np.abs(m.normals.numpy() - inverted).max() < 1e-5


def test_degenerate_triangles_are_dropped_with_a_warning(tmp_path):
    v = np.vstack([TET_V, 0.5 * (TET_V[0] + TET_V[1])])  # vertex 4: midpoint of edge 0-1
    faces = np.vstack([TET_F, [[0, 1, 1],       # repeated index
                               [0, 4, 1],       # zero area: three collinear corners
                               [2, 2, 2]]])     # all the same
    path = write_ply(tmp_path / "degenerate.ply", v, faces)
    with pytest.warns(UserWarning, match=r"degenerate\.ply.*dropped 3 degenerate") as rec:
        m = load_mesh(path, Transform())
    assert m.num_faces == 4
    assert np.array_equal(m.faces.numpy(), TET_F)
    assert np.isfinite(m.normals.numpy()).all()
    assert np.abs(np.linalg.norm(m.normals.numpy(), axis=1) - 1.0).max() < 1e-6
    assert m.watertight  # what is left is the closed tetrahedron
    assert not any("watertight" in str(w.message) for w in rec)


def test_all_degenerate_raises(tmp_path):
    v = [[0, 0, 0], [1, 0, 0], [2, 0, 0]]
    path = write_ply(tmp_path / "flat.ply", v, [[0, 1, 2], [0, 2, 1]])
    with pytest.raises(ConfigError, match=r"flat\.ply.*degenerate"):
        load_mesh(path, Transform())


def test_non_watertight_mesh_loads_with_a_warning(tmp_path):
    ico = trimesh.creation.icosphere(subdivisions=2, radius=1.0)
    faces = np.delete(ico.faces, [0, 17, 101], axis=0)
    path = write_ply(tmp_path / "holes.ply", ico.vertices, faces)
    with pytest.warns(UserWarning, match=r"holes\.ply.*not watertight"):
        m = load_mesh(path, Transform())
    assert not m.watertight
    assert m.num_faces == len(ico.faces) - 3
    # a closed mesh loads silently
    closed = write_ply(tmp_path / "closed.ply", ico.vertices, ico.faces)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert load_mesh(closed, Transform()).watertight


@pytest.mark.parametrize("name,content,fragment", [
    ("garbage.ply", b"this is not a mesh\x00\x01\x02", "cannot be loaded"),
    ("empty.ply", b"", "cannot be loaded"),
    ("points.ply", b"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\n"
                   b"property float y\nproperty float z\nend_header\n0 0 0\n1 0 0\n0 1 0\n",
     "no triangles"),
    ("empty.obj", b"", "no triangles"),
    ("truncated.ply", None, "cannot be loaded"),
    ("mesh.unknownformat", b"v 0 0 0\n", "cannot be loaded"),
])
def test_unreadable_or_empty_mesh_names_the_file(tmp_path, name, content, fragment):
    path = tmp_path / name
    if content is None:  # a binary PLY cut in the middle of its faces
        good = export_ply(trimesh.creation.icosphere(subdivisions=1))
        content = good[: len(good) - 200]
    path.write_bytes(content)
    with pytest.raises(ConfigError) as info:
        load_mesh(str(path), Transform())
    msg = str(info.value)
    assert f"mesh {str(path)!r}" in msg and fragment in msg, msg


def test_missing_mesh_file_raises_config_error(tmp_path):
    path = str(tmp_path / "absent.ply")
    with pytest.raises(ConfigError, match="absent.ply"):
        load_mesh(path, Transform())


def test_nan_vertices_are_rejected(tmp_path):
    v = TET_V.copy()
    v[2, 1] = np.nan
    path = write_ply(tmp_path / "nan.ply", v, TET_F)
    with pytest.raises(ConfigError, match=r"nan\.ply.*NaN"):
        load_mesh(path, Transform())


def test_shipped_meshes_load_closed_with_unit_normals():
    for name in ("spot.ply", "suzanne.ply"):
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            m = load_mesh(str(ROOT / "assets" / "meshes" / name), Transform())
        assert m.watertight and m.num_faces > 1000
        n = m.normals.numpy()
        assert np.abs(np.linalg.norm(n, axis=1) - 1.0).max() < 1e-5
        # the mesh is outward-wound: positive signed volume
        tm = trimesh.Trimesh(m.vertices.numpy(), m.faces.numpy(), process=False)
        assert tm.volume > 0


@pytest.mark.parametrize("name", ["spot.ply", "suzanne.ply"])
def test_across_is_the_face_over_the_edge_opposite_each_corner(name):
    """MeshData.across (the march's walk table): on a closed mesh every corner has a face
    across its opposite edge, which holds both other corners' positions and not its own."""
    m = load_mesh(str(ROOT / "assets" / "meshes" / name), Transform())
    tv = m.vertices[m.faces].numpy()  # (F, 3, 3)
    across = m.across.numpy()
    assert across.shape == (m.num_faces, 3) and (across >= 0).all()
    f = np.arange(m.num_faces)
    for k in range(3):
        other = tv[across[:, k]]  # (F, 3 corners, 3)
        at = [(np.abs(other - tv[:, c][:, None, :]).max(-1) < 1e-6).any(-1) for c in range(3)]
        assert not at[k].any(), k  # the opposite corner is not on the face across
        assert all(at[c].all() for c in range(3) if c != k), k  # the edge is shared
        assert (across[:, k] != f).all()


def test_across_on_an_open_mesh_is_minus_one_at_the_border(tmp_path):
    # two triangles sharing the edge 1-2: corner 0 of face 0 looks across it to face 1
    path = write_ply(tmp_path / "two.ply", [[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]],
                     [[0, 1, 2], [1, 3, 2]])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # not watertight
        m = load_mesh(path, Transform())
    assert m.across.tolist() == [[1, -1, -1], [-1, 0, -1]]


def _neighbors_by_loop(adjacency: np.ndarray, num_faces: int) -> np.ndarray:
    """The reference: trimesh's pairs in order, (a, b) then (b, a), three per face."""
    out = np.full((num_faces, 3), -1, dtype=np.int64)
    fill = np.zeros(num_faces, dtype=np.int64)
    for a, b in adjacency:
        for f, g in ((a, b), (b, a)):
            if fill[f] < 3:
                out[f, fill[f]] = g
                fill[f] += 1
    return out


@pytest.mark.parametrize("name", ["spot.ply", "suzanne.ply", "torus.ply", "vgroove.ply"])
def test_face_neighbors_match_the_pairs_in_order(name):
    from torchrefract.geometry.mesh import face_neighbors

    tm = trimesh.load(str(ASSETS / "meshes" / name), process=False)
    adj = np.asarray(tm.face_adjacency, dtype=np.int64)
    assert np.array_equal(face_neighbors(adj, len(tm.faces)),
                          _neighbors_by_loop(adj, len(tm.faces)))


def test_face_neighbors_keep_three_of_a_non_manifold_edge():
    from torchrefract.geometry.mesh import face_neighbors

    adj = np.array([[0, 1], [0, 2], [0, 3], [0, 4], [1, 2], [4, 0]])
    got = face_neighbors(adj, 6)
    assert np.array_equal(got, _neighbors_by_loop(adj, 6))
    assert got[0].tolist() == [1, 2, 3] and got[5].tolist() == [-1, -1, -1]
    assert (face_neighbors(np.zeros((0, 2), dtype=np.int64), 2) == -1).all()


def test_topology_kept_in_the_cache_folder_is_the_computed_one(tmp_path, monkeypatch):
    """A new process (the in-memory caches cleared) reads the file's topology from the
    cache folder, gets the same mesh, and is warned as the first was; a file with its own
    normals then loads without trimesh."""
    import sys

    import torchrefract.geometry.mesh as mesh_mod

    monkeypatch.setenv("TORCHREFRACT_CACHE", str(tmp_path / "cache"))
    src = ASSETS / "meshes" / "torus.ply"  # with normals in the file
    holes = tmp_path / "holes.ply"  # without, and open
    m = trimesh.load(ASSETS / "meshes" / "bunny.ply", process=False)
    trimesh.Trimesh(m.vertices, m.faces[:-40], process=False).export(holes)
    for path in (src, holes):
        for f in (mesh_mod._topology, mesh_mod._load_mesh_cached):
            f.cache_clear()
        with warnings.catch_warnings(record=True) as first:
            warnings.simplefilter("always")
            a = load_mesh(str(path), Transform(scale=1.3, rotate_deg=(10.0, 20.0, 30.0)))
        assert list((tmp_path / "cache" / "mesh").glob("topology_*.npz"))
        for f in (mesh_mod._topology, mesh_mod._load_mesh_cached):
            f.cache_clear()
        if path == src:  # importing trimesh would now fail
            monkeypatch.setitem(sys.modules, "trimesh", None)
        try:
            with warnings.catch_warnings(record=True) as again:
                warnings.simplefilter("always")
                b = load_mesh(str(path), Transform(scale=1.3, rotate_deg=(10.0, 20.0, 30.0)))
        finally:
            monkeypatch.setitem(sys.modules, "trimesh", trimesh)
        for name in ("vertices", "faces", "normals", "neighbors", "across"):
            assert torch.equal(getattr(a, name), getattr(b, name)), name
        assert a.watertight == b.watertight == (path == src)
        assert [str(w.message) for w in first] == [str(w.message) for w in again]

"""G-buffers (id passes, native and OpenGL, + exact torch attributes) against trimesh ray
casting.

Reference: for every pixel, the camera ray of SCENE_SPEC.md (built by hand here, not with
``torchrefract.geometry.camera``) is cast with ``trimesh`` (``multiple_hits=True``). The front layer
is the nearest hit whose face normal faces the camera, the back layer the nearest hit whose
face normal faces away.

Rasterization snaps vertices to a sub-pixel grid (Mesa llvmpipe: 1/256 px), so a pixel
center closer than that to a triangle edge may be given the neighbouring triangle; the
G-buffer repairs those ids with exact ray tests. Every remaining disagreement must be such
an edge pixel (``EDGE_TOL_PX``). Agreement rates, of the G-buffer and of the raw
rasterizer ids, are asserted and printed (run with ``-s`` to see them).
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh

import torchrefract.geometry.raster as raster
from torchrefract.geometry.camera import project
from torchrefract.geometry.gbuffer import build_gbuffer, carries_points
from torchrefract.geometry.mesh import load_mesh
from torchrefract.kernels import native
from torchrefract.scene.model import Camera, Transform
from torchrefract.settings import RenderSettings, using

ASSETS = Path(__file__).resolve().parents[1] / "assets" / "meshes"
EDGE_TOL_PX = 1.0 / 256.0  # sub-pixel precision of the rasterizer's vertex snapping
W, H = 96, 72

# Per mesh: transform and two off-axis cameras (tilted up vectors, targets off the center).
CASES = {
    "spot": (
        Transform(scale=1.0, rotate_deg=(10.0, -35.0, 5.0), translate=(0.1, 0.0, 0.0)),
        [Camera(eye=(2.0, 1.0, 2.4), target=(0.15, -0.1, 0.05), up=(0.15, 1.0, 0.0),
                yfov_deg=38.0, width=W, height=H),
         Camera(eye=(-2.3, -0.8, -1.6), target=(-0.1, 0.1, 0.0), up=(0.0, 1.0, 0.3),
                yfov_deg=44.0, width=W, height=H)]),
    "suzanne": (
        Transform(scale=0.9, rotate_deg=(-20.0, 30.0, 0.0), translate=(0.0, 0.1, 0.0)),
        [Camera(eye=(-1.5, 0.6, 2.6), target=(0.1, 0.1, 0.0), up=(0.0, 1.0, 0.2),
                yfov_deg=45.0, width=W, height=H),
         Camera(eye=(1.9, -1.2, -2.0), target=(0.05, 0.0, -0.1), up=(-0.2, 1.0, 0.0),
                yfov_deg=40.0, width=W, height=H)]),
    "icosphere": (
        Transform(scale=0.8, rotate_deg=(30.0, 20.0, 10.0), translate=(0.2, -0.1, 0.1)),
        [Camera(eye=(1.2, 0.9, 2.9), target=(0.3, 0.0, 0.0), up=(0.1, 1.0, 0.0),
                yfov_deg=40.0, width=W, height=H),
         Camera(eye=(-2.6, 1.8, -0.7), target=(0.1, -0.2, 0.2), up=(0.0, 1.0, -0.25),
                yfov_deg=35.0, width=W, height=H)]),
}


@pytest.fixture(scope="module")
def mesh_paths(tmp_path_factory):
    d = tmp_path_factory.mktemp("gbuffer_meshes")
    ico = trimesh.creation.icosphere(subdivisions=3, radius=1.0)  # 1280 faces
    ico_path = d / "icosphere.ply"
    ico_path.write_bytes(trimesh.exchange.ply.export_ply(
        trimesh.Trimesh(ico.vertices, ico.faces, process=False)))
    return {"spot": str(ASSETS / "spot.ply"), "suzanne": str(ASSETS / "suzanne.ply"),
            "icosphere": str(ico_path)}


# --------------------------------------------------------------------------------------
# Reference: hand-built rays, trimesh ray casting
# --------------------------------------------------------------------------------------

def frame(cam: Camera):
    eye = np.asarray(cam.eye, np.float64)
    f = np.asarray(cam.target, np.float64) - eye
    f /= np.linalg.norm(f)
    r = np.cross(f, np.asarray(cam.up, np.float64))
    r /= np.linalg.norm(r)
    return eye, r, np.cross(r, f), f


def spec_rays(cam: Camera, n: int = 1) -> np.ndarray:
    """SCENE_SPEC.md rays through the n x n sub-pixel centers: (n H, n W, 3) float64."""
    eye, r, u, f = frame(cam)
    t = math.tan(math.radians(cam.yfov_deg) / 2.0)
    a = cam.width / cam.height
    x = (np.arange(cam.width * n) + 0.5) / n  # continuous pixel coordinates of the centers
    y = (np.arange(cam.height * n) + 0.5) / n
    sx = (2.0 * x / cam.width - 1.0) * t * a
    sy = (1.0 - 2.0 * y / cam.height) * t
    d = f + sx[None, :, None] * r + sy[:, None, None] * u
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


def to_pixels(cam: Camera, n: int, p: np.ndarray) -> np.ndarray:
    """World points (..., 3) -> continuous pixel coordinates (..., 2) of the n-times grid."""
    eye, r, u, f = frame(cam)
    t = math.tan(math.radians(cam.yfov_deg) / 2.0)
    a = cam.width / cam.height
    rel = p - eye
    z = rel @ f
    x = (rel @ r) / (z * t * a)
    y = (rel @ u) / (z * t)
    return np.stack([(x + 1.0) * 0.5 * cam.width * n, (1.0 - y) * 0.5 * cam.height * n], -1)


def reference_layers(verts: np.ndarray, faces: np.ndarray, cam: Camera, dirs: np.ndarray):
    """Nearest front-facing and back-facing hits per ray with trimesh.

    The mesh and the rays are moved rigidly into the camera frame first: trimesh's rtree
    candidate search uses the bounding box of each ray segment, which is thin only for rays
    near an axis (same hits, ~10x faster).
    """
    eye, r, u, f = frame(cam)
    rot = np.stack([r, u, -f])  # world -> camera rows
    tm = trimesh.Trimesh((verts - eye) @ rot.T, faces, process=False)
    d_cam = dirs.reshape(-1, 3) @ rot.T
    tri, ray, loc = tm.ray.intersects_id(np.zeros_like(d_cam), d_cam, multiple_hits=True,
                                         return_locations=True)
    facing = (tm.face_normals[tri] * d_cam[ray]).sum(-1)
    dist = (loc * d_cam[ray]).sum(-1)
    n_rays = d_cam.shape[0]
    out = {}
    for name, sel in (("front", facing < 0), ("back", facing > 0)):
        ids = np.full(n_rays, -1, np.int64)
        best = np.full(n_rays, np.inf)
        pos = np.zeros((n_rays, 3))
        order = np.argsort(-dist[sel], kind="stable")  # farthest first: nearest written last
        rr = ray[sel][order]
        ids[rr] = tri[sel][order]
        best[rr] = dist[sel][order]
        pos[rr] = loc[sel][order] @ rot + eye  # back to world
        out[name] = (ids, best, pos)
    return out


def _seg_dist(p, a, b):
    e = b - a
    t = np.clip(np.dot(p - a, e) / max(np.dot(e, e), 1e-300), 0.0, 1.0)
    return float(np.linalg.norm(a + t * e - p))


def boundary_dist(p, tri2):
    """Distance (px) from a 2D point to the boundary of a 2D triangle."""
    return min(_seg_dist(p, tri2[i], tri2[(i + 1) % 3]) for i in range(3))


def region_dist(p, tri2):
    """Distance (px) from a 2D point to a 2D triangle (0 inside)."""
    a, b, c = tri2
    cr = [np.cross(b - a, p - a), np.cross(c - b, p - b), np.cross(a - c, p - c)]
    if all(x >= 0 for x in cr) or all(x <= 0 for x in cr):
        return 0.0
    return boundary_dist(p, tri2)


def compare_layers(g, b, mesh, cam, n, ref, label):
    """Check one G-buffer view against the reference; return the measured figures."""
    verts = mesh.vertices.numpy().astype(np.float64)
    faces = mesh.faces.numpy()
    off = int(g.meshes.face_offset[b])
    _, radius = mesh.bounding_sphere()
    eye, _, _, fwd = frame(cam)
    dirs = spec_rays(cam, n).reshape(-1, 3)
    w = cam.width * n
    stats = {}
    for name in ("front", "back"):
        layer = getattr(g, name)
        tri_g = layer.tri[b].numpy().reshape(-1)
        local = np.where(tri_g >= 0, tri_g - off, -1)
        ref_ids, ref_dist, ref_pos = ref[name]
        # mask == (id >= 0) and invalid pixels carry zeros
        mask = layer.mask[b].numpy().reshape(-1)
        assert np.array_equal(mask, tri_g >= 0), f"{label} {name}: mask != (tri >= 0)"
        assert (local < len(faces)).all(), f"{label} {name}: id outside this mesh's faces"
        points = carries_points(name == "back")
        assert (layer.position is not None) == points and (layer.bary is not None) == points
        for field in ("position", "dist", "depth", "bary", "normal", "uv"):
            if getattr(layer, field) is None:
                continue
            vals = getattr(layer, field)[b].numpy().reshape(mask.shape[0], -1)
            assert not vals[~mask].any(), f"{label} {name}.{field} nonzero outside the mask"

        either = (local >= 0) | (ref_ids >= 0)
        agree = either & (local == ref_ids)
        rate = agree.sum() / either.sum()
        # Every disagreement is an edge pixel: the rasterized triangle contains the pixel
        # center up to the snapping tolerance, and the reference triangle either has an
        # edge within it or lies behind the rasterized one.
        worst = 0.0
        for p in np.nonzero(either & ~agree)[0]:
            center = np.array([p % w + 0.5, p // w + 0.5])
            ok = True
            if local[p] >= 0:
                tri2 = to_pixels(cam, n, verts[faces[local[p]]])
                dr = region_dist(center, tri2)
                worst = max(worst, dr)
                ok &= dr <= EDGE_TOL_PX
            if ref_ids[p] >= 0:
                tri2 = to_pixels(cam, n, verts[faces[ref_ids[p]]])
                de = boundary_dist(center, tri2)
                behind = local[p] >= 0 and float(layer.dist[b].reshape(-1)[p]) < ref_dist[p]
                if not behind:
                    worst = max(worst, de)
                    ok &= de <= EDGE_TOL_PX
            assert ok, (f"{label} {name}: pixel {center} has id {local[p]} but ray casting "
                        f"sees {ref_ids[p]}, not on a triangle edge")

        dist = layer.dist[b].numpy().reshape(-1).astype(np.float64)
        # the back layer has no positions: its hits as eye + dist * ray
        pos = (layer.position[b].numpy().reshape(-1, 3).astype(np.float64) if points
               else np.where(mask[:, None], eye + dist[:, None] * dirs, 0.0))
        pos_err = np.linalg.norm(pos[agree] - ref_pos[agree], axis=1).max() / radius
        dist_err = np.abs(dist[agree] - ref_dist[agree]).max() / radius
        depth = layer.depth[b].numpy().reshape(-1).astype(np.float64)
        ref_depth = (ref_pos[agree] - eye) @ fwd
        depth_err = np.abs(depth[agree] - ref_depth).max() / radius
        assert pos_err < 1e-4, f"{label} {name}: position error {pos_err:.2e} x radius"
        assert dist_err < 1e-4, f"{label} {name}: dist error {dist_err:.2e} x radius"
        assert depth_err < 1e-4, f"{label} {name}: depth error {depth_err:.2e} x radius"
        # dist is along the unit ray: position = eye + dist * ray
        recon = eye + dist[mask, None] * dirs[mask]
        assert np.abs(recon - pos[mask]).max() < 1e-5 * radius + 1e-6

        # Orientation: each layer's triangle faces the camera (front) or away (back), by
        # its face normal (trimesh's, outward by winding).
        gn = trimesh.triangles.normals(verts[faces[local[mask]]])[0]
        facing = (gn * dirs[mask]).sum(-1)
        assert (facing < 0).all() if name == "front" else (facing > 0).all(), \
            f"{label} {name}: layer holds faces of the wrong orientation"

        # Barycentrics (where the layer has them): sum to 1, reproduce the position, match
        # the reference's.
        tv = verts[faces[np.maximum(local, 0)]]  # (N, 3, 3)
        ref_bary = trimesh.triangles.points_to_barycentric(tv[agree], ref_pos[agree])
        if points:
            bary = layer.bary[b].numpy().reshape(-1, 3).astype(np.float64)
            assert np.abs(bary[mask].sum(-1) - 1.0).max() < 1e-5
            from_bary = (bary[:, :, None] * tv).sum(1)
            assert np.abs(from_bary[mask] - pos[mask]).max() < 1e-5 * radius + 1e-6
            assert np.abs(bary[agree] - ref_bary).max() < 1e-3  # ~ position error / size
            assert bary[agree].min() > -1e-4  # agreeing pixels lie inside their triangle

        # Shading normal: unit, equal to the clamped barycentric interpolation of the
        # mesh's vertex normals.
        nrm = layer.normal[b].numpy().reshape(-1, 3).astype(np.float64)
        assert np.abs(np.linalg.norm(nrm[mask], axis=1) - 1.0).max() < 1e-5
        cn = mesh.normals.numpy().astype(np.float64)[faces[ref_ids[agree]]]  # (N, 3, 3)
        wts = np.clip(ref_bary, 0.0, None)
        wts /= wts.sum(-1, keepdims=True)
        ref_n = (wts[:, :, None] * cn).sum(1)
        ref_n /= np.linalg.norm(ref_n, axis=1, keepdims=True)
        assert np.abs(nrm[agree] - ref_n).max() < 1e-4, f"{label} {name}: shading normal"

        stats[name] = dict(pixels=int(either.sum()), agree=float(rate),
                           disagree=int((either & ~agree).sum()), worst_edge_px=worst,
                           pos_err=float(pos_err))
    return stats


# --------------------------------------------------------------------------------------
# Tests
# --------------------------------------------------------------------------------------

@pytest.mark.parametrize("rasterizer", ["native", "opengl"])
@pytest.mark.parametrize("cam_index", [0, 1])
@pytest.mark.parametrize("name", ["spot", "suzanne", "icosphere"])
def test_gbuffer_matches_ray_casting(mesh_paths, name, cam_index, rasterizer):
    if rasterizer == "native" and not native.available():
        pytest.skip("native kernels unavailable")
    transform, cams = CASES[name]
    cam = cams[cam_index]
    mesh = load_mesh(mesh_paths[name], transform)
    with using(RenderSettings(rasterizer=rasterizer)):
        g = build_gbuffer([mesh], [cam])
    assert g.shape == (1, H, W)
    # rays are the spec's rays
    assert np.abs(g.ray_dir[0].numpy() - spec_rays(cam)).max() < 1e-6
    ref = reference_layers(mesh.vertices.numpy().astype(np.float64), mesh.faces.numpy(),
                           cam, spec_rays(cam))
    stats = compare_layers(g, 0, mesh, cam, 1, ref, f"{name}/cam{cam_index}")
    for layer, s in stats.items():
        # The rasterizer's own ids, before the G-buffer's exact edge repair.
        raw = raster.visibility_pass(mesh, cam, back=(layer == "back")).numpy().reshape(-1)
        ref_ids = ref[layer][0]
        either = (raw >= 0) | (ref_ids >= 0)
        raw_rate = float((either & (raw == ref_ids)).sum() / either.sum())
        print(f"\n{name} cam{cam_index} {layer}: {s['pixels']} px, id agreement "
              f"{100 * s['agree']:.3f}% (raw raster {100 * raw_rate:.3f}%; {s['disagree']} "
              f"edge px left, worst {s['worst_edge_px']:.5f} px from the edge), position "
              f"error {s['pos_err']:.2e} x radius")
        assert s["pixels"] > 300  # the object is really in view
        assert s["agree"] >= 0.999
        assert raw_rate >= 0.98  # the rasterizer alone: off on edge pixels (1e-2 at most)
        assert s["agree"] >= raw_rate  # the edge repair never makes it worse


def test_supersampling_renders_subpixel_centers(mesh_paths):
    transform, cams = CASES["spot"]
    base = cams[0]
    small = dataclasses.replace(base, width=W // 2, height=H // 2, samples_per_pixel=2)
    mesh = load_mesh(mesh_paths["spot"], transform)
    g = build_gbuffer([mesh], [small])
    assert g.shape == (1, H, W) and g.supersample == 2
    assert torch.equal(g.proj[0, 14:16], torch.tensor([float(W), float(H)]))
    # rays through the 2 x 2 sub-pixel centers of the 48 x 36 camera
    rays = spec_rays(small, 2)
    assert rays.shape == (H, W, 3)
    assert np.abs(g.ray_dir[0].numpy() - rays).max() < 1e-6
    # the four sub-pixel rays of pixel (i, j) are symmetric about its center ray
    center = spec_rays(small, 1)
    mean4 = rays.reshape(H // 2, 2, W // 2, 2, 3).mean((1, 3))
    mean4 /= np.linalg.norm(mean4, axis=-1, keepdims=True)
    assert np.abs(mean4 - center).max() < 1e-4
    assert np.abs(rays[::2, ::2] - center).min(-1).max() > 1e-4  # not the center rays
    # hit points project back onto the sub-pixel centers
    xy, _ = project(g.front.position, g.proj)
    m = g.front.mask[0]
    jj, ii = torch.meshgrid(torch.arange(H), torch.arange(W), indexing="ij")
    want = torch.stack([ii + 0.5, jj + 0.5], -1).float()
    assert (xy[0][m] - want[m]).abs().max() < 2e-3
    # same ids as ray casting through the sub-pixel centers
    ref = reference_layers(mesh.vertices.numpy().astype(np.float64), mesh.faces.numpy(),
                           small, rays)
    stats = compare_layers(g, 0, mesh, small, 2, ref, "spot spp2")
    assert min(s["agree"] for s in stats.values()) >= 0.999
    # and the very same G-buffer as a 96 x 72 camera without supersampling
    full = build_gbuffer([mesh], [base])
    for name in ("front", "back"):
        a, b = getattr(g, name), getattr(full, name)
        assert torch.equal(a.tri, b.tri)
        assert torch.allclose(a.dist, b.dist, atol=1e-6)
        if a.position is not None:  # the front layer's (carries_points)
            assert torch.allclose(a.position, b.position, atol=1e-6)


def test_batch_of_two_meshes_indexes_concatenation(mesh_paths):
    t_spot, cams_spot = CASES["spot"]
    t_suz, cams_suz = CASES["suzanne"]
    spot = load_mesh(mesh_paths["spot"], t_spot)
    suz = load_mesh(mesh_paths["suzanne"], t_suz)
    g = build_gbuffer([spot, suz], [cams_spot[0], cams_suz[0]])
    assert g.shape == (2, H, W)
    assert g.meshes.face_offset.tolist() == [0, spot.num_faces]
    assert g.meshes.num_faces.tolist() == [spot.num_faces, suz.num_faces]
    assert g.meshes.tri_vertices.shape == (spot.num_faces + suz.num_faces, 3, 3)
    # edge neighbours are batch indices too: within the same mesh, sharing two corners
    nb = g.meshes.tri_neighbors
    for b, mesh in enumerate((spot, suz)):
        off = int(g.meshes.face_offset[b])
        own = nb[off:off + mesh.num_faces]
        assert ((own == -1) | ((own >= off) & (own < off + mesh.num_faces))).all()
        f_idx, k = torch.nonzero(own >= 0, as_tuple=True)
        a = mesh.faces[f_idx]
        c = mesh.faces[own[f_idx, k] - off]
        shared = (a[:, :, None] == c[:, None, :]).any(-1).sum(-1)
        assert (shared == 2).all()
    singles = [build_gbuffer([spot], [cams_spot[0]]), build_gbuffer([suz], [cams_suz[0]])]
    for b, (mesh, single) in enumerate(zip((spot, suz), singles)):
        off = int(g.meshes.face_offset[b])
        for name in ("front", "back"):
            lb, ls = getattr(g, name), getattr(single, name)
            m = lb.mask[b]
            assert m.sum() > 300
            assert torch.equal(m, ls.mask[0])
            tri = lb.tri[b][m]
            assert (tri >= off).all() and (tri < off + mesh.num_faces).all()
            assert torch.equal(tri - off, ls.tri[0][m])
            # the batch's triangle of each pixel is the mesh's own triangle
            assert torch.equal(g.meshes.tri_vertices[tri], mesh.vertices[mesh.faces[tri - off]])
            assert torch.equal(g.meshes.tri_normals[tri], mesh.normals[mesh.faces[tri - off]])
            assert torch.allclose(lb.dist[b], ls.dist[0], atol=1e-6)
            if lb.position is not None:  # the front layer's (carries_points)
                assert torch.allclose(lb.position[b], ls.position[0], atol=1e-6)
            assert torch.allclose(lb.normal[b], ls.normal[0], atol=1e-6)
        assert torch.equal(g.eye[b], torch.tensor((cams_spot[0], cams_suz[0])[b].eye).float())
    # the second view checked against ray casting directly, through the batch
    ref = reference_layers(suz.vertices.numpy().astype(np.float64), suz.faces.numpy(),
                           cams_suz[0], spec_rays(cams_suz[0]))
    stats = compare_layers(g, 1, suz, cams_suz[0], 1, ref, "batch[1]")
    assert min(s["agree"] for s in stats.values()) >= 0.999


def test_build_gbuffer_rejects_mismatched_lists(mesh_paths):
    transform, cams = CASES["icosphere"]
    mesh = load_mesh(mesh_paths["icosphere"], transform)
    with pytest.raises(ValueError, match="one camera per mesh"):
        build_gbuffer([mesh, mesh], [cams[0]])
    with pytest.raises(ValueError, match="one camera per mesh"):
        build_gbuffer([], [])


def test_egl_context_is_reused_across_calls_and_sizes(mesh_paths):
    transform, cams = CASES["icosphere"]
    mesh = load_mesh(mesh_paths["icosphere"], transform)
    cam = cams[0]
    opengl = RenderSettings(rasterizer="opengl")
    with using(opengl):
        g1 = build_gbuffer([mesh], [cam])
    r1 = raster._renderer
    assert r1 is not None
    assert (r1.viewport_width, r1.viewport_height) == (W, H)
    small = dataclasses.replace(cam, width=40, height=30)
    with using(opengl):
        g2 = build_gbuffer([mesh], [small])
    assert raster._renderer is r1
    assert (r1.viewport_width, r1.viewport_height) == (40, 30)
    assert g2.shape == (1, 30, 40) and g2.front.mask.any()
    with using(opengl):
        g3 = build_gbuffer([mesh], [cam])
    assert raster._renderer is r1
    # resizing back gives the same ids as the first call (no stale framebuffer)
    assert torch.equal(g1.front.tri, g3.front.tri) and torch.equal(g1.back.tri, g3.back.tri)
    assert raster.get_renderer(W, H) is r1


def test_passes_leave_pyrender_unpatched():
    """The visibility pass patches pyrender's glEnable and multisample storage only while it
    runs (single-sample framebuffer, multisampling off) and restores them after."""
    import pyrender.renderer as prr

    before = (prr.glEnable, prr.glRenderbufferStorageMultisample)
    mesh = load_mesh(str(ASSETS / "suzanne.ply"))
    ids = raster.visibility_pass(mesh, Camera(eye=(0.0, 0.0, 3.0), width=16, height=12),
                                 direct=False)
    assert ids.shape == (12, 16) and (ids >= 0).any()
    assert (prr.glEnable, prr.glRenderbufferStorageMultisample) == before


@pytest.mark.parametrize("rasterizer", ["native", "opengl"])
def test_repeated_views_are_built_once_and_equal_separate_builds(mesh_paths, monkeypatch,
                                                                 rasterizer):
    """A batch that repeats (mesh, camera) pairs (a material or environment sweep over one
    view) rasterizes each distinct view once, stores each distinct mesh's faces once, and
    gives every batch item exactly the layers of a G-buffer built for it alone."""
    if rasterizer == "native" and not native.available():
        pytest.skip("native kernels unavailable")
    t_spot, cams_spot = CASES["spot"]
    t_suz, cams_suz = CASES["suzanne"]
    spot = load_mesh(mesh_paths["spot"], t_spot)
    suz = load_mesh(mesh_paths["suzanne"], t_suz)
    meshes = [spot, suz, spot, spot, suz]
    cams = [cams_spot[0], cams_suz[0], cams_spot[1], cams_spot[0], cams_suz[0]]
    calls = []  # (mesh, camera, layer) per view and layer drawn
    real_pass, real_native = raster.visibility_pass, raster.native_layers

    def counting(mesh, cam, n=1, back=False):
        calls.append((id(mesh), cam, back))
        return real_pass(mesh, cam, n, back=back)

    def counting_native(ms, cs, n, offsets, **kw):
        calls.extend((id(m), c, back) for m, c in zip(ms, cs) for back in (False, True))
        return real_native(ms, cs, n, offsets, **kw)

    monkeypatch.setattr(raster, "visibility_pass", counting)
    monkeypatch.setattr(raster, "native_layers", counting_native)
    with using(RenderSettings(rasterizer=rasterizer)):
        g = build_gbuffer(meshes, cams)
    assert len(calls) == 2 * 3  # three distinct views, two layers each
    assert g.meshes.tri_vertices.shape[0] == spot.num_faces + suz.num_faces
    assert g.meshes.face_offset.tolist() == [0, spot.num_faces, 0, 0, spot.num_faces]
    for b, (mesh, cam) in enumerate(zip(meshes, cams)):
        with using(RenderSettings(rasterizer=rasterizer)):
            single = build_gbuffer([mesh], [cam])
        off = int(g.meshes.face_offset[b])
        for name in ("front", "back"):
            lb, ls = getattr(g, name), getattr(single, name)
            assert torch.equal(lb.mask[b], ls.mask[0])
            assert torch.equal(torch.where(lb.tri[b] >= 0, lb.tri[b] - off, -1), ls.tri[0])
            for f in ("position", "normal", "depth", "dist", "uv", "bary"):
                if getattr(ls, f) is None:  # the back layer's position and bary
                    assert getattr(lb, f) is None and not carries_points(name == "back")
                    continue
                assert torch.equal(getattr(lb, f)[b], getattr(ls, f)[0]), (b, name, f)
        assert torch.equal(g.ray_dir[b], single.ray_dir[0])
        assert torch.equal(g.proj[b], single.proj[0])


def test_cached_pass_scenes_give_the_ids_of_fresh_ones(mesh_paths):
    """The meshes kept on the context (raster._GLMesh, and pyrender's raster._PassScene)
    switch layer and camera between passes; interleaving meshes, layers and cameras gives
    the ids of a cleared cache, on both paths."""
    t_spot, cams_spot = CASES["spot"]
    t_ico, cams_ico = CASES["icosphere"]
    spot = load_mesh(mesh_paths["spot"], t_spot)
    ico = load_mesh(mesh_paths["icosphere"], t_ico)
    order = [(spot, cams_spot[0], False), (ico, cams_ico[1], True), (spot, cams_spot[1], True),
             (spot, cams_spot[0], True), (ico, cams_ico[0], False), (spot, cams_spot[0], False)]
    interleaved = [raster.visibility_pass(m, c, 1, back=bk) for m, c, bk in order]
    for (m, c, bk), ids in zip(order, interleaved):
        with raster._lock:
            raster._forget_meshes()
        fresh = raster.visibility_pass(m, c, 1, back=bk)
        assert (fresh >= 0).sum() > 300
        assert torch.equal(ids, fresh)
        assert torch.equal(ids, raster.visibility_pass(m, c, 1, back=bk, direct=False))
    assert torch.equal(interleaved[0], interleaved[5])
    assert not torch.equal(interleaved[3], interleaved[5])  # the back layer differs


def test_pixel_rays_are_cached_but_each_caller_gets_its_own():
    from torchrefract.geometry.camera import pixel_rays
    cam = Camera(eye=(0.3, 0.2, 3.0), width=12, height=8, yfov_deg=33.0)
    a = pixel_rays(cam, 2)
    ref = a.clone()
    a.zero_()  # a caller writing to its rays does not change the next caller's
    b = pixel_rays(cam, 2)
    assert torch.equal(b, ref) and b.shape == (16, 24, 3)
    assert torch.allclose(b.norm(dim=-1), torch.ones(16, 24))
    assert not torch.equal(pixel_rays(dataclasses.replace(cam, yfov_deg=34.0), 2), ref)


@pytest.mark.parametrize("name", ["spot", "suzanne", "icosphere"])
def test_direct_id_pass_gives_pyrender_forward_pass_ids(mesh_paths, name):
    """The direct id pass (gl_PrimitiveID into an integer renderbuffer, the mesh resident)
    gives the ids of pyrender's own forward pass (flat vertex colors) exactly: every view,
    both layers, supersampled too (the suite's 12 scenes: 7.9M pixels, 0 differ)."""
    transform, cams = CASES[name]
    mesh = load_mesh(mesh_paths[name], transform)
    for cam in cams:
        for n in (1, 2):
            for back in (False, True):
                a = raster.visibility_pass(mesh, cam, n, back=back)
                b = raster.visibility_pass(mesh, cam, n, back=back, direct=False)
                assert (a >= 0).sum() > 50
                assert torch.equal(a, b), (name, cam, n, back)


def test_object_index_follows_the_mask_it_reads(mesh_paths):
    """object_index is kept per G-buffer family (``derived``), but always names the set
    bits of the mask in use: a replaced G-buffer's own ``shade``, and a mask changed in
    place, get their own indices."""
    transform, cams = CASES["spot"]
    g = build_gbuffer([load_mesh(mesh_paths["spot"], transform)], [cams[0]])
    flat = g.front.mask.reshape(-1)
    first = g.object_index()
    assert torch.equal(first, flat.nonzero(as_tuple=True)[0]) and first.numel() > 100
    assert g.object_index() is first  # kept
    half = g.front.mask.clone()
    half.view(-1)[first[::2]] = False
    h = dataclasses.replace(g, shade=half)  # shares g.derived
    assert torch.equal(h.object_index(), first[1::2])
    assert torch.equal(g.object_index(), first)
    half.view(-1)[first[1]] = False  # in place: a new version of the same mask
    assert torch.equal(h.object_index(), first[3::2])

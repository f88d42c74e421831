"""The native triangle-id rasterizer (csrc/raster.c) against the OpenGL passes.

The OpenGL passes (``raster.visibility_pass``, llvmpipe) are the reference: both snap
window positions to 1/256 pixel and share the fill rule, so their ids agree but at pixel
centers within rounding of an edge (OpenGL transforms in float32, the native rasterizer in
float64) and at exact depth ties (OpenGL's 24-bit depth buffer). Checked: the ids of suite
scenes, both layers, supersampled; every differing pixel is next to a triangle edge or a
silhouette; the G-buffers built from either are the same but for a handful of such
pixels; cameras close to and inside the mesh (near-plane and guard-band clipping); the
``rasterizer`` setting; batches of views of different meshes. Agreement figures are
printed (``-s``).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import fields
from pathlib import Path

import numpy as np
import pytest
import torch

import torchrefract.geometry.raster as raster
from torchrefract.checks import ConfigError
from torchrefract.geometry.camera import project, projection_params
from torchrefract.geometry.gbuffer import Layer, build_gbuffer, intersect_triangles
from torchrefract.geometry.mesh import MeshData, load_mesh
from torchrefract.kernels import native
from torchrefract.scene.loader import load_scene
from torchrefract.scene.model import Camera
from torchrefract.settings import RenderSettings, using

ROOT = Path(__file__).resolve().parents[1]
SUITE = ROOT / "configs" / "suite"
SCENES = ["sphere_a0", "slab_a02", "bunny_a01", "teapot_a01", "torus_a01", "vgroove_a01",
          "wingnut_a01", "globe_2rough"]
SIZE, N = 64, 2  # 64 x 64 cameras, 2 x 2 supersampling: 128 x 128 ids
EDGE_TOL_PX = 1.0 / 64.0  # a differing center lies this close to an edge (snap: 1/256)

pytestmark = pytest.mark.skipif(not native.available(), reason="native kernels unavailable")


@pytest.fixture(scope="module", autouse=True)
def one_thread():
    """One torch thread (the shared 2-core machine; the band split is tested apart)."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def _view(name: str, eye_scale: float = 1.0) -> tuple[MeshData, Camera]:
    """A suite scene's mesh and camera at SIZE x SIZE, N x N supersampled, the eye moved
    to ``eye_scale`` times its distance from the origin (the suite's targets)."""
    s = load_scene(SUITE / f"{name}.yaml")
    cam = dataclasses.replace(s.camera, eye=tuple(e * eye_scale for e in s.camera.eye),
                              width=SIZE, height=SIZE, samples_per_pixel=N)
    return load_mesh(s.mesh, s.transform), cam


def _gl(mesh: MeshData, cam: Camera, n: int = N) -> tuple[torch.Tensor, torch.Tensor]:
    return (raster.visibility_pass(mesh, cam, n, back=False, direct=True),
            raster.visibility_pass(mesh, cam, n, back=True, direct=True))


def _at_boundary(ids: torch.Tensor) -> torch.Tensor:
    """(H, W) bool: the pixel's 3 x 3 neighbourhood holds another id (or -1): it is next
    to a triangle edge or a silhouette of that id map."""
    p = torch.nn.functional.pad(ids[None, None].double(), (1, 1, 1, 1), mode="replicate")[0, 0]
    h, w = ids.shape
    out = torch.zeros(h, w, dtype=torch.bool)
    for dy in range(3):
        for dx in range(3):
            out |= p[dy:dy + h, dx:dx + w] != ids.double()
    return out


def _edge_distance(mesh: MeshData, cam: Camera, face: int, y: int, x: int) -> float:
    """Screen distance (pixels of the supersampled frame) from the center of (y, x) to the
    nearest edge of ``face`` (a triangle wholly in front of the camera)."""
    params = projection_params(cam)
    params[14:16] *= cam.samples_per_pixel
    xy, z = project(mesh.vertices[mesh.faces[face]][None], params[None])
    assert (z > 0).all()
    xy = xy[0].double().numpy()
    c = np.array([x + 0.5, y + 0.5])
    best = math.inf
    for e in range(3):
        a, b = xy[e], xy[(e + 1) % 3]
        t = np.clip(np.dot(c - a, b - a) / max(np.dot(b - a, b - a), 1e-300), 0.0, 1.0)
        best = min(best, float(np.linalg.norm(c - (a + t * (b - a)))))
    return best


def _check_ids(mesh: MeshData, cam: Camera, label: str, geometric: bool) -> float:
    """Native ids against OpenGL's, both layers: >= 99.5% agree, every differing pixel is
    next to an edge or silhouette of one of the two id maps, and (``geometric``: views
    whose triangles all lie in front of the camera) its center lies within EDGE_TOL_PX of
    an edge of one of the two triangles. Returns the worst agreement."""
    front, back = raster.native_layers([mesh], [cam], cam.samples_per_pixel, [0])
    gl_front, gl_back = _gl(mesh, cam, cam.samples_per_pixel)
    worst = 1.0
    for layer, ours, gl in (("front", front[0], gl_front), ("back", back[0], gl_back)):
        assert ours.shape == gl.shape and ours.dtype == torch.int64
        assert int(ours.min()) >= -1 and int(ours.max()) < mesh.num_faces
        either = (ours >= 0) | (gl >= 0)
        differ = ours != gl
        rate = 1.0 - float(differ.sum()) / max(int(either.sum()), 1)
        print(f"\n{label} {layer}: {int(either.sum())} px, {int(differ.sum())} differ, "
              f"agreement {100 * rate:.3f}%")
        assert rate >= 0.995, (label, layer)
        assert bool((_at_boundary(ours) | _at_boundary(gl))[differ].all()), (label, layer)
        if geometric:
            for y, x in differ.nonzero().tolist():
                d = min(_edge_distance(mesh, cam, int(i), y, x)
                        for i in (ours[y, x], gl[y, x]) if i >= 0)
                assert d < EDGE_TOL_PX, (label, layer, y, x, d)
        worst = min(worst, rate)
    return worst


def _largest(x: torch.Tensor) -> float:
    """The largest element, 0 where there is none."""
    return float(x.max()) if x.numel() else 0.0


def _gbuffers(meshes, cams):
    """(native, opengl) G-buffers of the same views."""
    with using(RenderSettings(rasterizer="native")):
        a = build_gbuffer(meshes, cams)
    with using(RenderSettings(rasterizer="opengl")):
        b = build_gbuffer(meshes, cams)
    return a, b


def _bary(g, lay: Layer) -> torch.Tensor:
    """The layer's barycentrics, or where it does not carry them (the back layer:
    ``carries_points``) those of its pixels' rays on their triangles, as the layer computes
    them (float64, zeros where empty)."""
    if lay.bary is not None:
        return lay.bary
    b, h, w = lay.mask.shape
    tv = g.meshes.tri_vertices[lay.tri.clamp(min=0).long()].double()  # (B, H, W, 3, 3)
    eye = g.eye.double()[:, None, None, :].expand(b, h, w, 3)
    _, bary = intersect_triangles(eye, g.ray_dir.double(), tv)
    return torch.where(lay.mask[..., None], bary, torch.zeros((), dtype=bary.dtype)).float()


def _check_gbuffers(a, b, radius: float, label: str) -> None:
    """Every Layer field of both layers identical on >= 99.9% of pixels; elsewhere two
    valid hits of the same surface (positions, distances within 1e-3 x the mesh radius,
    barycentrics inside to 1e-3) or, where only one layer covers the pixel, a hit within
    1e-2 (barycentric) of its triangle's edge: a silhouette pixel."""
    for name in ("front", "back"):
        la, lb = getattr(a, name), getattr(b, name)
        same = torch.ones_like(la.mask)
        for f in fields(Layer):
            if getattr(la, f.name) is None:  # not made (the back layer's position, bary)
                assert getattr(lb, f.name) is None and name == "back", (label, name, f.name)
                continue
            eq = getattr(la, f.name) == getattr(lb, f.name)
            same &= eq.all(-1) if eq.dim() == 4 else eq
        differ = ~same
        total = same.numel()
        print(f"\n{label} G-buffer {name}: {int(differ.sum())} of {total} px differ")
        assert int(differ.sum()) <= 0.001 * total, (label, name)
        both = differ & la.mask & lb.mask
        tol = 1e-3 * radius
        for f in ("position", "dist", "depth"):
            if getattr(la, f) is not None:
                assert _largest((getattr(la, f) - getattr(lb, f))[both].abs()) <= tol, (label, f)
        bary = {id(la): _bary(a, la), id(lb): _bary(b, lb)}
        for lay in (la, lb):
            assert -_largest(-bary[id(lay)][both]) >= -1e-3
        one = differ & (la.mask != lb.mask)
        for lay in (la, lb):
            sel = one & lay.mask
            assert _largest(bary[id(lay)][sel].min(-1).values) < 1e-2, (label, name)


# --------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", SCENES)
def test_ids_agree_with_the_opengl_passes(name):
    mesh, cam = _view(name)
    _check_ids(mesh, cam, name, geometric=True)
    # whole pixels too (no supersampling)
    _check_ids(mesh, dataclasses.replace(cam, samples_per_pixel=1), f"{name} 1spp", True)


@pytest.mark.parametrize("name", ["sphere_a0", "bunny_a01", "torus_a01", "vgroove_a01"])
def test_gbuffer_equals_the_opengl_gbuffer(name):
    mesh, cam = _view(name)
    a, b = _gbuffers([mesh], [cam])
    _check_gbuffers(a, b, mesh.bounding_sphere()[1], name)


@pytest.mark.parametrize("name,eye_scale", [("sphere_a0", 0.4), ("sphere_a0", 0.0),
                                            ("bunny_a01", 0.3), ("slab_a02", 0.05),
                                            ("wingnut_a01", 0.1), ("vgroove_a01", 0.2)])
def test_close_and_inside_cameras_are_clipped_as_opengl_clips(name, eye_scale):
    """Cameras near the surface or inside the bounding sphere (eye_scale 0: at the center
    of the sphere mesh): triangles crossing the near plane, and triangles whose corners
    project millions of pixels off the frame (the guard band), are clipped; the ids agree
    with OpenGL's and the closed sphere seen from inside has no hole."""
    mesh, cam = _view(name, eye_scale)
    if eye_scale == 0.0:
        cam = dataclasses.replace(cam, eye=(0.0, 0.0, 0.0), target=(0.3, 0.1, -1.0))
    _check_ids(mesh, cam, f"{name} x{eye_scale}", geometric=False)
    front, back = raster.native_layers([mesh], [cam], N, [0])
    if name == "sphere_a0" and eye_scale == 0.0:
        assert bool((back >= 0).all()) and bool((front < 0).all())
    a, b = _gbuffers([mesh], [cam])
    _check_gbuffers(a, b, mesh.bounding_sphere()[1], f"{name} x{eye_scale}")


def _mesh(verts, faces) -> MeshData:
    """A MeshData of ``verts`` and ``faces`` (no neighbours, flat normals unused here)."""
    v = torch.tensor(verts, dtype=torch.float32)
    f = torch.tensor(faces, dtype=torch.int64)
    none = torch.full((len(f), 3), -1, dtype=torch.int64)
    return MeshData(v, f, torch.nn.functional.normalize(v + 1e-3, dim=-1), None, False,
                    none, none)


def test_guard_band_clipping_keeps_the_surface_watertight():
    """A closed cone whose apex lies just in front of the near plane, far to the side:
    its triangles reach millions of pixels off the frame (beyond the 2^20-pixel guard
    band) and are clipped there. The cone still covers the convex hull of its base and
    the apex's direction without a hole, as OpenGL draws it."""
    apex, k = (3000.0, 0.0, 0.0), 24
    ring = [(0.8 * math.cos(2 * math.pi * i / k), 0.8 * math.sin(2 * math.pi * i / k), -5.0)
            for i in range(k)]
    verts = [apex, (0.0, 0.0, -5.0)] + ring
    faces = [[0, 2 + i, 2 + (i + 1) % k] for i in range(k)]  # the mantle
    faces += [[1, 2 + (i + 1) % k, 2 + i] for i in range(k)]  # the base
    mesh = _mesh(verts, faces)
    cam = Camera(eye=(0.0, 0.0, 0.0), target=(0.0, 0.0, -1.0), up=(0.0, 1.0, 0.0),
                 yfov_deg=4.0, width=96, height=64)
    znear = raster._view_matrices(cam, mesh.bounding_sphere())[2]  # the eye is inside
    mesh = _mesh([(apex[0], apex[1], -1.5 * znear)] + verts[1:], faces)  # the apex moved
    _, _, znear, _ = raster._view_matrices(cam, mesh.bounding_sphere())  # just in front
    clip = raster.view_projection(cam, mesh.bounding_sphere()) @ np.array(
        [*mesh.vertices[0].tolist(), 1.0])
    assert clip[3] > znear  # of the near plane, and far beyond the guard band (2^31 units)
    assert abs(clip[0] / clip[3]) * cam.width / 2 > 2 ** 23
    front, back = raster.native_layers([mesh], [cam], 1, [0])
    gl_front, gl_back = _gl(mesh, cam, 1)
    covered = (front[0] >= 0) | (back[0] >= 0)
    assert int(covered.sum()) > 0.1 * covered.numel()
    for row in covered:  # convex: every covered row from its first pixel to its last
        cols = row.nonzero()[:, 0]
        if len(cols):
            assert int(cols[-1] - cols[0] + 1) == len(cols)
    for ours, gl in ((front[0], gl_front), (back[0], gl_back)):
        differ = ours != gl
        assert float(differ.float().mean()) < 0.005
        assert bool((_at_boundary(ours) | _at_boundary(gl))[differ].all())


def test_rasterizer_setting_validates_and_picks_the_passes(monkeypatch):
    with pytest.raises(ConfigError, match="RenderSettings.rasterizer"):
        RenderSettings(rasterizer="vulkan")
    with pytest.raises(ConfigError, match="RenderSettings.rasterizer"):
        RenderSettings(rasterizer="native", native=False)
    assert RenderSettings().rasterizer == "auto"
    monkeypatch.setenv("TORCHREFRACT_RASTERIZER", "opengl")
    assert RenderSettings.from_env().rasterizer == "opengl"
    monkeypatch.setenv("TORCHREFRACT_RASTERIZER", "bogus")
    with pytest.raises(ConfigError, match="RenderSettings.rasterizer"):
        RenderSettings.from_env()
    monkeypatch.delenv("TORCHREFRACT_RASTERIZER")

    mesh, cam = _view("teapot_a01")
    gl_calls, native_calls = [], []
    real_pass, real_ids = raster.visibility_pass, native.raster_ids

    def gl_pass(*args, **kwargs):
        gl_calls.append(args[1])
        return real_pass(*args, **kwargs)

    def raster_ids(*args):
        native_calls.append(args[2].shape[0])
        return real_ids(*args)

    monkeypatch.setattr(raster, "visibility_pass", gl_pass)
    monkeypatch.setattr(native, "raster_ids", raster_ids)
    for choice, gl, nat in (("opengl", 2, 0), ("native", 0, 1), ("auto", 0, 1)):
        gl_calls.clear()
        native_calls.clear()
        with using(RenderSettings(rasterizer=choice)):
            g = build_gbuffer([mesh, mesh], [cam, dataclasses.replace(cam, yfov_deg=35.0)])
        assert (len(gl_calls), len(native_calls)) == (2 * gl, nat), choice
        assert g.front.mask.any() and g.back.mask.any()
    # auto without the native kernels: the OpenGL passes
    gl_calls.clear()
    with using(RenderSettings(native=False)):
        build_gbuffer([mesh], [cam])
    assert len(gl_calls) == 2
    # native asked for where the kernels did not build: an error naming the setting
    monkeypatch.setattr(native, "available", lambda: False)
    with using(RenderSettings(rasterizer="native")):
        with pytest.raises(RuntimeError, match="rasterizer='native'"):
            build_gbuffer([mesh], [cam])


def test_a_batch_of_two_meshes_gives_each_views_ids(monkeypatch):
    """Views of two different meshes in one call (global ids offset per mesh, as the
    MeshBatch concatenates them): each view's ids are those of a call for it alone, with
    1 and 2 threads (row bands), agree with OpenGL's, and the batch's G-buffer equals the
    OpenGL one."""
    bunny, cam_b = _view("bunny_a01")
    torus, cam_t = _view("torus_a01")
    meshes = [bunny, torus, bunny, torus]
    cams = [cam_b, cam_t, dataclasses.replace(cam_b, eye=(1.0, 0.8, 3.0)),
            dataclasses.replace(cam_t, yfov_deg=30.0)]
    offsets = [0, bunny.num_faces, 0, bunny.num_faces]
    front, back = raster.native_layers(meshes, cams, N, offsets)
    assert front.shape == (4, SIZE * N, SIZE * N)
    for threads in (1, 2):
        torch.set_num_threads(threads)
        for b, (m, c, off) in enumerate(zip(meshes, cams, offsets)):
            f1, b1 = raster.native_layers([m], [c], N, [0])
            assert torch.equal(front[b], torch.where(f1[0] >= 0, f1[0] + off, -1))
            assert torch.equal(back[b], torch.where(b1[0] >= 0, b1[0] + off, -1))
    torch.set_num_threads(1)
    for b, (m, c, off) in enumerate(zip(meshes, cams, offsets)):
        gf, gb = _gl(m, c)
        for ours, gl in ((front[b], gf), (back[b], gb)):
            gl = torch.where(gl >= 0, gl + off, -1)
            assert float((ours != gl).float().mean()) < 0.005
    a, g = _gbuffers(meshes, cams)
    assert a.meshes.face_offset.tolist() == offsets
    _check_gbuffers(a, g, max(bunny.bounding_sphere()[1], torus.bounding_sphere()[1]), "batch")


def test_views_split_into_row_bands_give_the_same_ids():
    """One view on 2 and 3 threads is split into row bands, each drawn by its own thread:
    the same ids as one thread."""
    mesh, cam = _view("wingnut_a01", 0.5)
    ref = raster.native_layers([mesh], [cam], N, [0])
    for threads in (2, 3):
        torch.set_num_threads(threads)
        try:
            out = raster.native_layers([mesh], [cam], N, [0])
        finally:
            torch.set_num_threads(1)
        assert torch.equal(out[0], ref[0]) and torch.equal(out[1], ref[1])


def test_the_cli_sets_the_rasterizer():
    from torchrefract.cli import _parser, _settings

    args = _parser().parse_args(["render", "x.yaml", "--out", "o", "--rasterizer", "opengl"])
    assert _settings(args).rasterizer == "opengl"
    args = _parser().parse_args(["sweep", "x.yaml", "--out", "o", "--rasterizer", "native"])
    assert _settings(args).rasterizer == "native"
    with pytest.raises(SystemExit):
        _parser().parse_args(["render", "x.yaml", "--out", "o", "--rasterizer", "gl"])


@pytest.mark.parametrize("eye,up", [((0.0, 0.3, 3.4), (0, 1, 0)), ((2.0, -1.5, 0.7), (0, 0, 1)),
                                     ((-0.3, 4.0, 0.01), (1, 0, 0))])
def test_view_matrix_is_the_inverse_of_the_camera_pose(eye, up):
    """The passes' view matrix (built from the camera frame, not by a 4x4 inverse) takes
    the camera pose to the identity, and P V maps the target to the image center."""
    from torchrefract.geometry.camera import camera_pose  # noqa: PLC0415

    cam = Camera(eye=eye, target=(0.1, -0.2, 0.3), up=up, width=64, height=48)
    proj, view, znear, zfar = raster._view_matrices(cam, (np.zeros(3), 1.0))
    assert np.abs(view @ camera_pose(cam) - np.eye(4)).max() < 1e-14
    clip = raster.view_projection(cam, (np.zeros(3), 1.0)) @ np.array([0.1, -0.2, 0.3, 1.0])
    assert abs(clip[0] / clip[3]) < 1e-12 and abs(clip[1] / clip[3]) < 1e-12
    assert 0.0 < znear < zfar

"""The native kernels (``torchrefract.kernels.native``: csrc/march.c, csrc/gbuffer.c, csrc/cone.c)
compute what the tensor code computes exactly: the same march exits (so the same images and
gradients), the same G-buffer layers and the same cone footprints and spreads, on real
meshes; they fall back to the tensor code with a warning where they cannot be built."""

from __future__ import annotations

import dataclasses
import math
import os
import subprocess
import warnings

import pytest
import torch
from conftest import ASSETS

import torchrefract as tr
from torchrefract.geometry.camera import pixel_rays_rows, views_pixel_rays
from torchrefract.geometry.gbuffer import build_gbuffer
from torchrefract.geometry.mesh import load_mesh
from torchrefract.kernels import native
from torchrefract.kernels.march import camera_planes, march_back, march_inside
from torchrefract.lighting.lights import Lighting
from torchrefract.methods import registry
from torchrefract.optics.materials import MaterialBatch
from torchrefract.optics.smooth import face_forward, reflect, refract
from torchrefract.settings import RenderSettings, using

ENV = str(ASSETS / "envmaps" / "lebombo.exr")

needs_native = pytest.mark.skipif(not native.available(),
                                  reason="the native kernel does not build here")


@pytest.fixture
def tensor_code():
    """Returns a function running ``fn()`` with the native kernel off."""
    def run(fn):
        with using(RenderSettings(native=False)):
            return fn()
    return run


def _entries(mesh: str, size: int, eye=(0.0, 0.4, 3.2), transform=None, views=2):
    """Entry points and refracted directions of every covered pixel of ``views`` views."""
    m = load_mesh(mesh, transform or tr.Transform(rotate_deg=(0.0, -35.0, 0.0)))
    cams = [tr.Camera(eye=(eye[0] + 0.3 * i, eye[1], eye[2]), width=size, height=size)
            for i in range(views)]
    g = build_gbuffer([m] * views, cams)
    idx = g.front.mask.reshape(-1).nonzero()[:, 0]
    d = g.ray_dir.reshape(-1, 3)[idx]
    n = face_forward(g.front.normal.reshape(-1, 3)[idx], d)
    t1, _ = refract(d, n, torch.tensor(1 / 1.5))
    p1 = g.front.position.reshape(-1, 3)[idx]
    batch = idx // (size * size)
    return g, batch, p1, t1, n


def _assert_same(a, b):
    for f in dataclasses.fields(a):
        x, y = getattr(a, f.name), getattr(b, f.name)
        if x is None or y is None:  # a field not made (the back layer's position, bary)
            assert x is None and y is None, f"{type(a).__name__}.{f.name}: one is None"
            continue
        assert torch.equal(x, y), f"{type(a).__name__}.{f.name} differs at {(x != y).sum().item()}"


@needs_native
@pytest.mark.parametrize("mesh, size, steps, refine, eye", [
    ("spot.ply", 64, 24, 8, (0.0, 0.4, 3.2)),       # rousiers' central rays
    ("spot.ply", 64, 4, 3, (0.0, 0.4, 3.2)),        # its bounding rays' settings
    ("suzanne.ply", 48, 64, 10, (0.4, 0.3, 3.0)),   # non-convex: rays lost and found
    ("suzanne.ply", 48, 7, 0, (0.1, 0.0, 1.2)),     # camera close: rays leave the frame
])
@pytest.mark.parametrize("simd", [True, False])
def test_back_exits_are_identical(mesh, size, steps, refine, eye, simd, tensor_code,
                                  monkeypatch):
    """Both searches of the kernel (AVX2 where the CPU has it, and scalar)."""
    g, batch, p1, t1, _ = _entries(str(ASSETS / "meshes" / mesh), size, eye)
    with using(RenderSettings(native_simd=simd)):
        fast = march_back(g, batch, p1, t1, steps=steps, refine=refine)
    slow = tensor_code(lambda: march_back(g, batch, p1, t1, steps=steps, refine=refine))
    assert slow.found.float().mean() > 0.5
    _assert_same(fast, slow)


@needs_native
def test_walk_over_triangles_smaller_than_pixels_is_identical(sphere_ply, tensor_code):
    """81,920 faces seen at 32x32: most exits are walked across several edges."""
    g, batch, p1, t1, _ = _entries(str(sphere_ply), 32, eye=(0.0, 0.0, 3.0),
                                   transform=tr.Transform())
    fast = march_back(g, batch, p1, t1, steps=24, refine=8)
    slow = tensor_code(lambda: march_back(g, batch, p1, t1, steps=24, refine=8))
    assert slow.found.float().mean() > 0.99
    _assert_same(fast, slow)


@needs_native
@pytest.mark.parametrize("simd", [True, False])
def test_inside_exits_through_both_layers_are_identical(simd, tensor_code, monkeypatch):
    """march_inside (8 plane terms, four candidate tries): internal reflections at the
    back surface of suzanne, which leave through either layer."""
    monkeypatch.setenv("TORCHREFRACT_NATIVE_SIMD", "1" if simd else "0")
    g, batch, p1, t1, n = _entries(str(ASSETS / "meshes" / "suzanne.ply"), 48,
                                   eye=(0.4, 0.3, 3.0))
    ex = march_back(g, batch, p1, t1, steps=24, refine=8)
    keep = ex.found.nonzero()[:, 0]
    p, t = ex.position[keep], reflect(t1[keep], ex.normal[keep])
    planes = camera_planes(g, both=True)
    fast = march_inside(g, batch[keep], p, t, steps=32, refine=10, planes=planes)
    slow = tensor_code(lambda: march_inside(g, batch[keep], p, t, steps=32, refine=10,
                                            planes=planes))
    assert (slow.layer == 0).any() and (slow.layer == 1).any()
    _assert_same(fast, slow)


@needs_native
@pytest.mark.parametrize("method, options", [
    ("rousiers", {}),
    ("rousiers", {"cone_rays": "plane"}),  # the footprint and spread kernels, normals read
    ("rousiers", {"internal_bounces": 2}),
    ("specular", {"internal_bounces": 2}),
])
def test_renders_and_gradients_are_identical(method, options, tensor_code):
    """Suzanne, two views: the images and passes are the same bit for bit, and so are the
    IOR and roughness gradients of the mean image but for summation order."""
    suzanne = str(ASSETS / "meshes" / "suzanne.ply")
    scenes = [tr.Scene(mesh=suzanne, envmap=tr.EnvMap(path=ENV, rotate_deg=r),
                       material=tr.Material(ior=1.5, roughness=a),
                       camera=tr.Camera(eye=(0.4, 0.3, 3.0), width=40, height=32),
                       method=method, method_options=options)
              for r, a in ((0.0, 0.1), (40.0, 0.3))]
    g = build_gbuffer([load_mesh(s.mesh, s.transform) for s in scenes],
                      [s.camera for s in scenes])
    lighting = Lighting.from_scenes(scenes)
    meth = registry.get(method)

    def run():
        out = tr.render(scenes)
        ior = torch.tensor([1.45, 1.5], requires_grad=True)
        rough = torch.tensor([0.1, 0.3], requires_grad=True)
        m = MaterialBatch(ior=ior, roughness=rough, absorption=torch.zeros(2, 3),
                          distribution=("beckmann", "beckmann"))
        img = meth.shade(g, lighting, m, meth.parse(options), None).radiance
        grads = torch.autograd.grad(img.double().mean(), (ior, rough))
        return out, grads

    with using(RenderSettings(fused=False)):  # the fused kernels: tests/test_fused.py
        fast, g_fast = run()
    slow, g_slow = tensor_code(run)
    assert slow.coverage.sum() > 300
    assert torch.equal(fast.radiance, slow.radiance)
    for k in ("exit_found", "tir"):
        assert torch.equal(fast.passes[k], slow.passes[k]), k
    # the same values through a differently shaped graph (one hit over all rays against
    # hits over the subsets of each try): equal up to the float32 order of summation
    for a, b in zip(g_fast, g_slow):
        assert (b != 0).all() and torch.allclose(a, b, rtol=1e-5, atol=0), (a, b)


def _cone_inputs(monkeypatch, eye):
    """The arguments rousiers passes to its footprint and spread (``_footprint``,
    ``_ray_spread``) on suzanne, two views, recorded from a real render."""
    from torchrefract.methods.rousiers import cone as rousiers

    seen = {}
    for name in ("_footprint", "_ray_spread"):
        fn = getattr(rousiers, name)
        monkeypatch.setattr(rousiers, name,
                            lambda *a, _fn=fn, _name=name: seen.setdefault(_name, a) and _fn(*a))
    suzanne = str(ASSETS / "meshes" / "suzanne.ply")
    tr.render([tr.Scene(mesh=suzanne, envmap=tr.EnvMap(path=ENV),
                        material=tr.Material(ior=1.5, roughness=a),
                        camera=tr.Camera(eye=eye, width=48, height=40), method="rousiers")
               for a in (0.05, 0.4)], settings=RenderSettings(fused=False))  # the cone's calls
    monkeypatch.undo()
    return rousiers, seen


@needs_native
@pytest.mark.parametrize("eye", [(0.4, 0.3, 3.0), (0.1, 0.0, 1.2)])  # far; close: off-frame
@pytest.mark.parametrize("threads", [1, 2])
def test_cone_footprint_and_spread_are_identical(eye, threads, monkeypatch, tensor_code):
    """The bounding rays' footprint and spread of a real render, some of them lost (the
    central exit and the fallback variance stand in), on one and two threads; with every
    ray lost the fallback comes back as is."""
    rousiers, seen = _cone_inputs(monkeypatch, eye)
    q, ok4 = seen["_footprint"][:2]
    assert (~ok4).any() and ok4.any()
    monkeypatch.setattr(torch, "get_num_threads", lambda: threads)  # what the kernels use
    assert native.footprint(*seen["_footprint"]) is not None  # the kernel runs here
    for name, args in seen.items():
        fast = getattr(rousiers, name)(*args)
        slow = tensor_code(lambda: getattr(rousiers, name)(*args))
        for a, b in zip(fast if isinstance(fast, tuple) else (fast,),
                        slow if isinstance(slow, tuple) else (slow,)):
            assert torch.equal(a, b), f"{name}: {(a != b).sum().item()} values differ"
    p, n_c, dirs, n4, ok, ior, fallback = seen["_ray_spread"]
    lost = native.spread(p, n_c, dirs, n4, torch.zeros_like(ok), ior, fallback)
    assert torch.equal(lost, fallback)


@needs_native
def test_cone_kernels_leave_gradients_to_the_tensor_code(monkeypatch):
    """Where a gradient flows through the bounding rays the tensor code runs (the kernels
    have no backward), and gives one."""
    rousiers, seen = _cone_inputs(monkeypatch, (0.4, 0.3, 3.0))
    p, n_c, dirs, n4, ok, ior, fallback = seen["_ray_spread"]
    ior = ior.clone().requires_grad_(True)
    monkeypatch.setattr(native, "spread", lambda *a: pytest.fail("kernel called"))
    var = rousiers._ray_spread(p, n_c, dirs, n4, ok, ior, fallback)
    (g,) = torch.autograd.grad(var.sum(), ior)
    assert torch.isfinite(g).all() and (g != 0).any()


@needs_native
@pytest.mark.parametrize("mesh, size, eye", [
    ("spot.ply", 64, (0.0, 0.4, 3.2)),
    ("suzanne.ply", 48, (0.4, 0.3, 3.0)),
    ("suzanne.ply", 40, (0.1, 0.0, 1.2)),  # close: the object crosses the frame's edges
    (None, 24, (0.0, 0.0, 3.0)),           # 81,920 faces at 24x24: many edge repairs
])
def test_gbuffer_layers_are_identical(mesh, size, eye, sphere_ply, tensor_code):
    """The exact layers (ids after the edge repair, positions, depths, barycentrics,
    normals, UVs) of two views are the same bit for bit (from the same rasterized ids: the
    OpenGL passes', which the tensor code uses; the native rasterizer's are compared with
    them in tests/test_native_raster.py)."""
    path = str(sphere_ply) if mesh is None else str(ASSETS / "meshes" / mesh)
    m = load_mesh(path, tr.Transform(rotate_deg=(0.0, -35.0, 0.0)))
    cams = [tr.Camera(eye=(eye[0] + 0.3 * i, eye[1], eye[2]), width=size, height=size)
            for i in range(2)]
    with using(RenderSettings(rasterizer="opengl")):
        fast = build_gbuffer([m, m], cams)
    slow = tensor_code(lambda: build_gbuffer([m, m], cams))
    assert slow.front.mask.sum() > 200 and slow.back.mask.sum() > 200
    for layer in ("front", "back"):
        _assert_same(getattr(fast, layer), getattr(slow, layer))


@needs_native
@pytest.mark.parametrize("n", [1, 2, 3])
def test_pixel_rays_are_identical(n, tensor_code):
    """The batch's camera rays (csrc/gbuffer.c) are pixel_rays_rows' bit for bit, for
    views of every kind (wide and narrow fields, odd widths: the lanes' remainder), whole
    or a strip of rows."""
    cams = [tr.Camera(eye=(3.0 * i - 4.0, 1.5 - i, 2.5 + 0.7 * i), target=(0.2 * i, -0.1, 0.0),
                      yfov_deg=12.0 + 19.0 * i, width=37, height=23) for i in range(5)]
    fast = views_pixel_rays(cams, n)
    slow = torch.stack([pixel_rays_rows(c, n, 0, c.height * n) for c in cams])
    assert fast.shape == (5, 23 * n, 37 * n, 3)
    assert torch.equal(fast, slow)
    assert torch.equal(tensor_code(lambda: views_pixel_rays(cams, n)), slow)
    strip = (5 * n, 17 * n + 1)  # a large frame's strip of sub-pixel rows
    assert torch.equal(views_pixel_rays(cams, n, rows=strip), slow[:, strip[0]:strip[1]])
    with pytest.raises(ValueError, match="one width and height"):
        views_pixel_rays([cams[0], dataclasses.replace(cams[1], width=38)], n)


def test_build_failure_falls_back_to_the_tensor_code_with_one_warning(monkeypatch,
                                                                      tmp_path):
    g, batch, p1, t1, _ = _entries(str(ASSETS / "meshes" / "spot.ply"), 32)
    with using(RenderSettings(native=False)):
        slow = march_back(g, batch, p1, t1, steps=24, refine=8)
    monkeypatch.setattr(native, "_LIB", None)
    monkeypatch.setattr(native, "_FAILED", None)
    monkeypatch.setenv("TORCHREFRACT_CACHE", str(tmp_path))  # nothing built there yet
    monkeypatch.setattr(native, "_compiler", lambda: None)
    with pytest.warns(RuntimeWarning, match="native kernels .* are unavailable.*no C "
                                            "compiler"):
        fell_back = march_back(g, batch, p1, t1, steps=24, refine=8)
    _assert_same(fell_back, slow)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # warned once
        assert not native.available()
    assert not list(tmp_path.rglob("*.so"))


def test_a_compile_error_is_reported_with_the_compiler_output(monkeypatch, tmp_path):
    bad = tmp_path / "bad.c"
    bad.write_text("int broken(void) { return undefined_name; }\n")
    monkeypatch.setattr(native, "SOURCES", (bad,))
    with pytest.raises(RuntimeError, match="undefined_name"):
        native.build(tmp_path / "cache")
    assert not list((tmp_path / "cache").rglob("*.so*"))  # no half-written library left


def test_an_error_under_the_machine_flags_is_raised_not_built_around(monkeypatch, tmp_path):
    """A source that fails only with ``-march=native`` (an AVX2 path) raises: a build with
    fewer flags would run without the lane code, and nothing would say so."""
    cc = native._compiler()
    if cc is None or not native._accepts(cc, ("-march=native", "-fopenmp")):
        pytest.skip("no compiler taking -march=native -fopenmp")
    macros = subprocess.run(cc.split() + ["-march=native", "-dM", "-E", "-x", "c", "-"],
                            input="", capture_output=True, text=True).stdout
    if "__AVX2__" not in macros:
        pytest.skip("this CPU has no AVX2")
    src = tmp_path / "lanes.c"
    src.write_text("#ifdef __AVX2__\n#error the lane path is broken\n#endif\n"
                   "int torchrefract_f(void) { return 0; }\n")
    monkeypatch.setattr(native, "SOURCES", (src,))
    with pytest.raises(RuntimeError, match="the lane path is broken"):
        native.build(tmp_path / "cache")
    assert not list((tmp_path / "cache").rglob("*.so*"))


def test_a_probe_that_cannot_run_builds_nothing(monkeypatch, tmp_path):
    """A flag probe that times out (a loaded machine) fails the build: a library made with
    fewer flags would stay in the cache for every later process."""
    cc = tmp_path / "cc-slow"
    cc.write_text("#!/bin/sh\nsleep 5\n")
    cc.chmod(0o755)
    monkeypatch.setenv("CC", str(cc))
    real = subprocess.run

    def hurried(cmd, *a, **k):
        k["timeout"] = min(k.get("timeout") or 1, 1)
        return real(cmd, *a, **k)

    monkeypatch.setattr(native.subprocess, "run", hurried)
    with pytest.raises(RuntimeError, match="did not run"):
        native.build(tmp_path / "cache")
    assert not list((tmp_path / "cache").rglob("*.so*"))


@needs_native
def test_a_compiler_without_openmp_builds_the_pthread_kernels(monkeypatch, tmp_path):
    """``-fopenmp`` is tried first (csrc/common.h: torch's thread pool); a compiler that
    rejects it still builds the kernels, with threads of their own."""
    cc = tmp_path / "cc-no-openmp"
    cc.write_text('#!/bin/sh\nfor a in "$@"; do [ "$a" = -fopenmp ] && exit 1; done\n'
                  'exec cc "$@"\n')
    cc.chmod(0o755)
    monkeypatch.setenv("CC", str(cc))
    path = native.build(tmp_path / "cache")
    assert b"GOMP_parallel" not in path.read_bytes()
    monkeypatch.delenv("CC")
    probe = tmp_path / "probe.c"
    probe.write_text("int f(void) { return 0; }\n")
    if subprocess.run([native._compiler(), "-fopenmp", "-shared", "-fPIC", "-o",
                       str(tmp_path / "probe.so"), str(probe)]).returncode == 0:
        assert b"GOMP_parallel" in native.build(tmp_path / "cache2").read_bytes()


@needs_native
def test_build_is_cached_per_source(tmp_path):
    path = native.build(tmp_path)
    assert path.exists() and path.parent == tmp_path / "native"
    stamp = path.stat().st_mtime_ns
    assert native.build(tmp_path) == path and path.stat().st_mtime_ns == stamp


@needs_native
def test_inputs_it_does_not_take_go_to_the_tensor_code():
    """Only float32 rays with int64 indices and int32 marched ids go native (a float64
    caller, say; int64 ids)."""
    from torchrefract.kernels.march import Marched  # noqa: PLC0415

    z = torch.zeros(1, 3)
    ids = torch.zeros(1024, dtype=torch.int32)
    ok = Marched(back=ids, front=None, table=torch.zeros(1, 4),
                 base=torch.zeros(1, dtype=torch.long), h=32, w=32)

    def run(c0, planes):
        return native.march(c0, z, torch.ones(1), torch.zeros(1), torch.ones(1),
                            torch.ones(1), torch.zeros(1, dtype=torch.long), planes, False, 4,
                            3, z, z, torch.zeros(1, 3, 3), torch.zeros(1, 3, dtype=torch.long))

    assert run(z.double(), ok) is None
    assert run(z, dataclasses.replace(ok, back=ids.long())) is None
    assert run(z, ok) is not None


def test_native_is_on_by_default_and_switchable(monkeypatch):
    monkeypatch.delenv("TORCHREFRACT_NATIVE", raising=False)
    assert native.native_enabled()
    with using(RenderSettings(native=False)):
        assert not native.native_enabled() and not native.available()
    assert native.native_enabled()
    monkeypatch.setenv("TORCHREFRACT_NATIVE", "0")  # the environment's default
    assert not native.native_enabled()


def test_cli_no_native_flag_is_a_setting_of_its_renders(monkeypatch):
    """``--no-native`` goes into the run's RenderSettings (handed to worker processes with
    each batch), not into this process's environment."""
    from torchrefract.cli import _parser, _settings

    monkeypatch.setenv("TORCHREFRACT_NATIVE", "1")
    s = _settings(_parser().parse_args(["render", "x.yaml", "--out", "o", "--no-native",
                                        "--threads", "1"]))
    assert s.native is False and s.threads == 1
    assert os.environ["TORCHREFRACT_NATIVE"] == "1" and native.native_enabled()



@needs_native
def test_triangle_plane_table_matches_the_tensor_code(monkeypatch):
    """march.plane_table's rows by the native kernel (every distinct view of a batch in one
    call) equal the tensor code's view by view (float64, then rounded to float32: equal but
    where float64 rounding meets a float32 tie): two meshes, two cameras, a repeated view
    sharing its rows."""
    from torchrefract.kernels import march  # noqa: PLC0415

    suite = ASSETS.parent / "configs" / "suite"
    scene = tr.load_scene(str(suite / "bunny_a01.yaml"))
    other = tr.load_scene(str(suite / "suzanne_a01.yaml"))
    bunny, monkey = (load_mesh(s.mesh, s.transform) for s in (scene, other))
    cam2 = dataclasses.replace(scene.camera, eye=(0.5, 0.6, 2.7))
    g = build_gbuffer([bunny, monkey, bunny, bunny],
                      [scene.camera, scene.camera, cam2, scene.camera])
    fast, base = march.plane_table(g.meshes, g.eye, g.proj)
    monkeypatch.setattr(native, "tri_planes", lambda *a: None)
    slow, base2 = march.plane_table(g.meshes, g.eye, g.proj)
    nb, nm = bunny.faces.shape[0], monkey.faces.shape[0]
    assert torch.equal(base, base2) and fast.shape == slow.shape == (2 * nb + nm, 4)
    assert base[3] == base[0]  # the repeated view reads the first one's rows
    assert (fast != slow).any(-1).float().mean() < 1e-3
    assert torch.allclose(fast, slow, rtol=0, atol=1e-6)
    assert torch.allclose(fast[:, :3].norm(dim=-1), torch.ones(1))


@needs_native
def test_triangle_plane_rows_do_not_depend_on_their_place_in_the_table():
    """csrc/march.c's plane rows in AVX2 lanes (four at a time) and one by one (a view's
    last rows) are the same bits: the bunny's rows computed from a shifted start, and its
    first three as a view of their own, equal its rows computed in place."""
    suite = ASSETS.parent / "configs" / "suite"
    s = tr.load_scene(str(suite / "bunny_a01.yaml"))
    tv = load_mesh(s.mesh, s.transform).tri_vertices.contiguous()
    t = tv.shape[0]
    q, _ = torch.linalg.qr(torch.randn(3, 3, generator=torch.Generator().manual_seed(5)))
    eye, basis = torch.tensor([[0.3, 0.4, 3.0]]), q.T.reshape(1, 9).float().contiguous()
    a = native.tri_planes(tv, torch.tensor([0]), torch.tensor([t]), eye, basis)
    b = native.tri_planes(tv, torch.tensor([1, 0]), torch.tensor([t - 1, 3]),
                          eye.repeat(2, 1), basis.repeat(2, 1))
    assert a is not None and b is not None and t % 4 == 0  # a: every row in lanes
    assert torch.equal(b[:t - 1], a[1:]) and torch.equal(b[t - 1:], a[:3])


@pytest.mark.skipif(not native.available(), reason="no native build here")
def test_the_built_kernels_keep_their_prefetches():
    """The lookups ask for their texels before they read them (csrc/lighting.h). GCC
    deletes a call to a function holding only prefetches (it finds it const) unless the
    helper is inlined first (``TR_PREFETCH``): every env and SG prefetch of the fused
    kernels was gone so (docs/benchmarks.md, nineteenth sitting). The built library must
    hold them (x86-64, where objdump reads it)."""
    import platform
    import shutil

    objdump = shutil.which("objdump")
    if objdump is None or platform.machine() not in ("x86_64", "AMD64"):
        pytest.skip("needs objdump on x86-64")
    text = subprocess.run([objdump, "-d", "--no-show-raw-insn", native._load()._name],
                          capture_output=True, text=True, check=True).stdout
    holders, fn = {}, None
    for line in text.splitlines():
        if line.endswith(">:"):
            fn = line.split("<", 1)[1].split(">", 1)[0].split(".", 1)[0]
        elif "prefetch" in line:
            holders[fn] = holders.get(fn, 0) + 1
    # specular's block (env taps), the SG taps of rousiers' blocks and lean's EWA
    assert sum(holders.values()) >= 20, holders
    assert len(holders) >= 3, holders


def test_four_refractions_in_lanes_give_the_scalar_bits():
    """csrc/optics.h's refract_x4 (a pixel's four bounding rays at once, in SSE lanes where
    built for it) against its scalar refract, bit for bit: grazing and head-on rays, total
    internal reflection, a zero and a NaN normal; and both against the tensor code."""
    if not native.available():
        pytest.skip("native kernels unavailable")
    g = torch.Generator().manual_seed(7)
    d = torch.nn.functional.normalize(torch.randn(4096, 4, 3, generator=g), dim=-1)
    n = torch.nn.functional.normalize(torch.randn(4096, 4, 3, generator=g), dim=-1)
    n = torch.where((d * n).sum(-1, keepdim=True) > 0, -n, n)  # facing the ray
    n[:8, 0] = -d[:8, 0]  # head-on
    n[8:16, 1] = torch.nn.functional.normalize(torch.cross(d[8:16, 1], n[8:16, 1], dim=-1)
                                               + 1e-4 * n[8:16, 1], dim=-1)  # grazing
    n[16, 2] = 0.0
    n[17, 3] = float("nan")
    eta = torch.rand(4096, generator=g) * 2.0 + 0.4  # both sides of 1: TIR where eta > 1
    lanes, scalar = native.refract_x4(d, n, eta)
    nan = torch.isnan(scalar)
    assert torch.equal(torch.isnan(lanes), nan) and nan[17, 3].all()  # (NaN bits may differ)
    assert torch.equal(lanes.view(torch.int32)[~nan], scalar.view(torch.int32)[~nan])
    ref, _ = refract(d.reshape(-1, 3), n.reshape(-1, 3), eta.repeat_interleave(4))
    ok = torch.isfinite(ref).all(-1)
    assert ok.sum() > 16000
    assert torch.allclose(scalar.reshape(-1, 3)[ok], ref[ok], atol=1e-5)
    with pytest.raises(ValueError, match="refract_x4"):  # not groups of four: never read
        native.refract_x4(d[:, :3], n[:, :3], eta)


def test_spread_cosines_in_lanes_give_the_scalar_bits():
    """csrc/sgtable.h's sg_theta_n and fresnel_n on a spread's three cosines (in lanes
    where built for them) against the scalar sg_theta and fresnel, bit for bit: cosines
    over [0, 1] and around both branch points (0.5, and s = 1/2 at cos = sqrt(3)/2),
    outside it, -0, NaN; eta on both sides of 1 (TIR); and the coordinates against the
    tensor code's (sgfit._coordinates' z)."""
    if not native.available():
        pytest.skip("native kernels unavailable")
    g = torch.Generator().manual_seed(11)
    cs = torch.rand(20000, 3, generator=g)
    around = torch.tensor([0.5, math.sqrt(3) / 2, 0.0, 1.0])
    cs[:4000] = (around[torch.randint(0, 4, (4000, 3), generator=g)]
                 + (torch.rand(4000, 3, generator=g) - 0.5) * 1e-5)
    cs[4000, :] = torch.tensor([-0.3, 1.7, -0.0])
    cs[4001, :] = torch.tensor([float("nan"), 1e-30, 1.0 - 1e-7])
    eta = torch.rand(20000, generator=g) * 2.0 + 0.4
    lanes, scalar = native.theta3(cs, eta)
    nan = torch.isnan(scalar)
    assert torch.equal(torch.isnan(lanes), nan)
    assert torch.equal(lanes.view(torch.int32)[~nan], scalar.view(torch.int32)[~nan])
    assert (scalar[:, 1] == 1.0).sum() > 1000  # TIR lanes seen
    c = cs.clamp(0.0, 1.0)[4002:]
    z = torch.acos(c).clamp(0.0, math.pi / 2) * (4.0 / math.pi) - 1.0
    assert torch.allclose(scalar[4002:, 0], z, atol=1e-6)
    with pytest.raises(ValueError, match="theta3"):
        native.theta3(cs[:, :2], eta)


def test_light_coverage_bessel_matches_torch():
    """csrc/lighting.h's i0e (Cephes' Chebyshev expansions, 24 values in lanes at a time, as
    the light coverage's Gauss-Legendre nodes take it) against torch.special.i0e: the same
    bits where torch's kernel is compiled with FMA (AVX2 and above, as Clenshaw's step is
    fused here), else within an ulp or two; both ranges, their boundary at 8, counts that are
    not multiples of 24, signs, zero, infinity and NaN."""
    if not native.available():
        pytest.skip("native kernels unavailable")
    g = torch.Generator().manual_seed(3)
    x = torch.cat([torch.rand(30001, generator=g, dtype=torch.float64) * 10.0,
                   torch.rand(30001, generator=g, dtype=torch.float64) * 1000.0 - 500.0,
                   torch.exp(torch.rand(30001, generator=g, dtype=torch.float64) * 60 - 30),
                   torch.tensor([0.0, 8.0, math.nextafter(8.0, 9.0), math.nextafter(8.0, 7.0),
                                 -8.0, 1e-300, 1e300, math.inf, -math.inf, math.nan],
                                dtype=torch.float64)])
    ours, ref = native.i0e(x), torch.special.i0e(x)
    assert torch.equal(torch.isnan(ours), torch.isnan(ref)) and torch.isnan(ours[-1])
    ok = ~torch.isnan(ref)
    if torch.backends.cpu.get_cpu_capability() in ("AVX2", "AVX512"):
        assert torch.equal(ours[ok], ref[ok])
    else:
        torch.testing.assert_close(ours[ok], ref[ok], rtol=1e-15, atol=0.0)
    assert native.i0e(x.float()) is None  # float64 only


def test_roughness_maps_in_one_call_match_the_tensor_code():
    """csrc/materials.c's roughness_at (the fused kernels' map lookup, materials.h) against
    the tensor code's (textures.sample_uv through grid_sample): the same bits where torch's
    kernel is compiled with FMA (AVX2 and above), else within an ulp or two; views with and
    without a map (two maps of different sizes), UVs outside [0, 1), on texel centers and
    edges, a NaN; and the fallback where a gradient is wanted."""
    if not native.available():
        pytest.skip("native kernels unavailable")
    from torchrefract.optics.materials import MaterialBatch
    g = torch.Generator().manual_seed(5)
    maps = (torch.rand(37, 53, generator=g), None, torch.rand(8, 3, generator=g))
    m = MaterialBatch(ior=torch.full((3,), 1.5), roughness=torch.tensor([0.1, 0.25, 0.4]),
                      absorption=torch.zeros(3, 3), distribution=("beckmann",) * 3,
                      roughness_maps=maps,
                      roughness_range=torch.tensor([[0.05, 0.6], [0.0, 0.0], [0.3, 0.1]]))
    n = 60000
    batch = torch.randint(0, 3, (n,), generator=g)
    uv = torch.rand(n, 2, generator=g) * 6.0 - 3.0
    uv[:300] = torch.randint(-60, 60, (300, 2), generator=g) / torch.tensor([53.0, 37.0])
    uv[300:600] = (torch.randint(-60, 60, (300, 2), generator=g) + 0.5) / 8.0
    uv[600, 0] = float("nan")
    ours = native.roughness_at(m.roughness, maps, m.roughness_range, batch, uv)
    assert ours is not None and torch.isfinite(ours).all()
    ref = m.roughness.clone().requires_grad_(True)  # the tensor code: a gradient wanted
    want = dataclasses.replace(m, roughness=ref).roughness_at(batch, uv).detach()
    assert torch.equal(ours[batch == 1], torch.full_like(ours[batch == 1], 0.25))
    if torch.backends.cpu.get_cpu_capability() in ("AVX2", "AVX512"):
        assert torch.equal(ours, want)
    else:
        torch.testing.assert_close(ours, want, rtol=1e-6, atol=1e-7)
    assert torch.equal(m.roughness_at(batch, uv), ours)  # the kernel, where it runs


def test_level_coverage_in_one_call_matches_the_tensor_code():
    """csrc/materials.c's level_coverage (a back layer's roughness as hat weights on the
    exit's roughness levels) against cone.level_coverage's tensor code, bit for bit on the
    globe with a roughness map (2 and 4 levels), a view without a map and a range given
    high to low; zero off the back layer."""
    if not native.available():
        pytest.skip("native kernels unavailable")
    from torchrefract.geometry.gbuffer import build_gbuffer
    from torchrefract.geometry.mesh import load_mesh
    from torchrefract.methods.rousiers.cone import level_coverage
    from torchrefract.optics.materials import MaterialBatch
    base = tr.load_scene(str(ASSETS.parent / "configs" / "suite" / "globe_gradient.yaml"))
    cam = dataclasses.replace(base.camera, width=48, height=40, samples_per_pixel=1)
    s = base.replace(camera=cam)
    scenes = [s, s.replace(material=dataclasses.replace(s.material, roughness_map=None,
                                                        roughness=0.2)),
              s.replace(material=dataclasses.replace(s.material, roughness_range=(0.5, 0.1)))]
    g = build_gbuffer([load_mesh(x.mesh, x.transform) for x in scenes],
                      [x.camera for x in scenes])
    m = MaterialBatch.from_scenes(scenes)
    ref_m = dataclasses.replace(m, roughness=m.roughness.clone().requires_grad_(True))
    for n in (2, 4):
        ours = level_coverage(g, m, n)
        ref = level_coverage(g, ref_m, n).detach()  # a gradient wanted: the tensor code
        assert ours.shape == (3, 40, 48, n) and torch.equal(ours, ref)
        assert (ours[~g.back.mask] == 0).all() and (ours.sum(-1)[g.back.mask] > 0.99).all()


def test_light_coverage_in_one_call_matches_the_tensor_code():
    """lights.sg_light_coverage through csrc/lighting.h's light_coverage (the fused kernels'
    integral, in one call for the tensor code's callers) against the tensor code (taken
    where a gradient is wanted): wide and sharp lobes, infinite sharpness, padding lights
    (radius 0) and an origin inside a light; float32 rounding apart, the same values."""
    if not native.available():
        pytest.skip("native kernels unavailable")
    from torchrefract.lighting.lights import sg_light_coverage
    g = torch.Generator().manual_seed(11)
    n, nl = 6000, 3
    o = torch.randn(n, 3, generator=g)
    d = torch.nn.functional.normalize(torch.randn(n, 3, generator=g), dim=-1)
    k = torch.exp(torch.rand(n, generator=g) * 12.0 - 2.0)
    k[:20] = float("inf")
    pos = torch.randn(n, nl, 3, generator=g) * 3.0
    pos[:, 0] = o + 2.0 * d + 0.1 * torch.randn(n, 3, generator=g)  # near the axis
    rad = torch.rand(n, nl, generator=g) * 0.8
    rad[:, 2] = 0.0
    pos[30:40, 1] = o[30:40]  # the origin inside the light
    ours = sg_light_coverage(o, d, k, pos, rad)
    ref = sg_light_coverage(o, d, k.clone().requires_grad_(True), pos, rad).detach()
    assert ours.dtype == torch.float32 and (ours[:, 2] == 0).all()
    assert (ours[30:40, 1] == 1).all() and (ours[:, 0] > 0.5).sum() > 1000
    torch.testing.assert_close(ours, ref, rtol=1e-6, atol=1e-12)
    assert (ours == ref).float().mean() > 0.999


def test_roughness_lookup_refuses_views_out_of_range():
    """A view index outside the batch never reaches the kernel (it would read past the
    arrays): the tensor code runs and raises its own IndexError."""
    from torchrefract.optics.materials import MaterialBatch
    m = MaterialBatch(ior=torch.full((2,), 1.5), roughness=torch.tensor([0.1, 0.2]),
                      absorption=torch.zeros(2, 3), distribution=("beckmann",) * 2,
                      roughness_maps=(torch.rand(4, 4), None),
                      roughness_range=torch.tensor([[0.0, 1.0], [0.0, 0.0]]))
    uv = torch.rand(3, 2)
    for bad in (torch.tensor([0, 1, 2]), torch.tensor([0, -1, 1])):
        assert native.roughness_at(m.roughness, m.roughness_maps, m.roughness_range, bad,
                                   uv) is None
        with pytest.raises(IndexError):
            m.roughness_at(bad, uv)
    assert m.roughness_at(torch.tensor([1, 1, 1]), uv).tolist() == pytest.approx([0.2] * 3)

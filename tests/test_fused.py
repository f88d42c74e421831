"""The fused shading kernels (``torchrefract.shading.fused``: csrc/specular.c for
``specular`` and ``prefiltered``, csrc/rousiers.c, csrc/background.c for every method's
background) give the tensor code's images: on every suite scene and ``tir`` rule, within
1e-4 relative on 99.9% of the object pixels and 0.002 of FLIP, with the same passes; the
background within float rounding; internal bounces within the tensor code's own float32
conditioning. Where they cannot run (a gradient is wanted, ``rousiers``' paper spreads,
``fused=False``) the tensor code runs, unchanged."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import ASSETS

import torchrefract as tr
from torchrefract.kernels import native
from torchrefract.settings import RenderSettings, using

SUITE = sorted((Path(__file__).resolve().parent.parent / "configs" / "suite").glob("*.yaml"))
# every pixel shaded: the kernels against the tensor code pixel by pixel (adaptive
# shading on top: test_fused_matches_the_tensor_code_with_adaptive_shading)
FUSED = RenderSettings(fused=True, adaptive=False)
TENSOR = RenderSettings(fused=False, adaptive=False)

pytestmark = pytest.mark.skipif(not native.available(),
                                reason="the native kernels do not build here")


def _small(path: Path, size: int = 48, spp: int = 1, **changes) -> tr.Scene:
    s = tr.load_scene(path)
    c = s.camera
    return s.replace(camera=tr.Camera(eye=c.eye, target=c.target, up=c.up,
                                      yfov_deg=c.yfov_deg, width=size, height=size,
                                      samples_per_pixel=spp), **changes)


def _compare(a: tr.RenderResult, b: tr.RenderResult) -> dict:
    """Per image: the share of object pixels beyond 1e-4 relative, the largest relative
    difference, the FLIP between the two, the background's largest difference."""
    from torchrefract.truth.metrics import flip_map

    out = []
    for i in range(a.radiance.shape[0]):
        obj = a.coverage[i] > 0
        ra, rb = a.radiance[i], b.radiance[i]
        rel = ((ra - rb).abs() / ra.abs().clamp(min=1e-3)).amax(-1)
        flip = flip_map(rb.numpy(), ra.numpy())
        out.append({"beyond": float((rel[obj] > 1e-4).float().mean()) if obj.any() else 0.0,
                    "max_rel": float(rel[obj].max()) if obj.any() else 0.0,
                    "flip": float(flip[obj.numpy()].mean()) if obj.any() else 0.0,
                    "background": float(rel[~obj].max()) if (~obj).any() else 0.0})
    return out


@pytest.mark.parametrize("method", ["specular", "prefiltered", "rousiers", "rousiers plane"])
@pytest.mark.parametrize("path", SUITE, ids=[p.stem for p in SUITE])
def test_fused_matches_the_tensor_code_on_the_suite(path, method):
    method, *cone = method.split()  # "rousiers plane": ``cone_rays: plane``
    cone = {"cone_rays": cone[0]} if cone else {}
    scenes = [_small(path, 96, method=method, method_options={"tir": tir, **cone})
              for tir in ("conserve", "clamp", "reflect")]
    for s in scenes:
        a, b = tr.render(s, settings=TENSOR), tr.render(s, settings=FUSED)
        for m in _compare(a, b):
            assert m["beyond"] <= 1e-3 and m["max_rel"] < 1e-2, (s.method_options, m)
            assert m["flip"] <= 0.002, (s.method_options, m)
            assert m["background"] <= 1e-4, (s.method_options, m)
        for k in ("exit_found", "tir"):
            assert torch.equal(a.passes[k], b.passes[k]), k
        # lobe_sigma of a sharp lobe comes from |t_k - t_c|^2 of nearly parallel refracted
        # rays (cone.ray_spread): its rounding is amplified (smooth sphere: up to 7e-4
        # relative on 6% of the pixels, while the radiance stays within 7e-5)
        for k, rtol in {"prefiltered": (("blur_sigma", 1e-4),),
                        "rousiers": (("lobe_sigma", 2e-3), ("footprint", 1e-4))
                        }.get(method, ()):
            assert torch.allclose(a.passes[k], b.passes[k], rtol=rtol, atol=1e-6), k


@pytest.mark.parametrize("path", SUITE, ids=[p.stem for p in SUITE])
def test_fused_matches_the_tensor_code_with_adaptive_shading(path):
    """The default settings (adaptive shading): the lattice's decisions read the radiance,
    which the two paths round differently, but a pixel near a threshold is blended
    (adaptive.BLEND_FROM), so the images stay as close as without it."""
    s = _small(path, 96, method="rousiers")
    a = tr.render(s, settings=TENSOR.replace(adaptive=True))
    b = tr.render(s, settings=FUSED.replace(adaptive=True))
    for m in _compare(a, b):
        assert m["beyond"] <= 1e-3 and m["max_rel"] < 1e-2, m
        assert m["flip"] <= 0.002, m
        assert m["background"] <= 1e-4, m


BOUNCES = {"ib2": {"internal_bounces": 2}, "auto": {"internal_bounces": "auto"},
           "rays4": {"internal_bounces": 2, "bounce_rays": 4},
           "plane2": {"internal_bounces": 2, "cone_rays": "plane"},
           "clamp1": {"internal_bounces": 1, "tir": "clamp"},
           "reflect3": {"internal_bounces": 3, "tir": "reflect"}}


def _nudged(s: tr.Scene) -> tr.Scene:
    """The scene with its eye moved by ~3 float32 roundings (3e-7 relative)."""
    c = s.camera
    return s.replace(camera=tr.Camera(eye=tuple(e * (1 + 3e-7) for e in c.eye),
                                      target=c.target, up=c.up, yfov_deg=c.yfov_deg,
                                      width=c.width, height=c.height))


# specular's lobes are rays: no bounce_rays, no cone
BOUNCE_CASES = [(m, v) for m in ("rousiers", "specular") for v in sorted(BOUNCES)
                if m == "rousiers" or v not in ("rays4", "plane2")]


@pytest.mark.parametrize("method, variant", BOUNCE_CASES)
@pytest.mark.parametrize("path", SUITE, ids=[p.stem for p in SUITE])
def test_fused_bounces_match_the_tensor_code(path, variant, method):
    """``rousiers`` and ``specular`` with internal bounces (csrc/bounces.h's follow_block):
    the tensor code's image and bounce passes. A path reflected inside a detailed mesh is chaotic: a
    float32 rounding in its first direction (the kernel's sinf against torch's vectorized
    sin: 1 ulp) moves where the next interface is met, and after a few bounces such a
    pixel differs by more than 1e-4. There the fused image must stay within what the
    tensor code itself does when the eye moves by 3 roundings (measured on the bunny,
    ``auto``, 96 px: fused 6.8% of pixels beyond 1e-4 and FLIP 0.0025, while the nudged
    tensor code gives 22.8% and 0.0059). ``specular``'s sharp lookups carry a rounding of a
    bounce's direction straight into the environment's texels: up to 4e-4 relative on a
    few pixels of smooth shapes too (the sphere's rim)."""
    s = _small(path, 64, method=method, method_options=BOUNCES[variant])
    check_bounces_match(s)


def check_bounces_match(s: tr.Scene) -> None:
    """A scene with internal bounces: the fused image against the tensor code's (the
    bounds above; where paths are chaotic, within the tensor code's own change when the eye
    moves by 3 float32 roundings), the exit passes equal, the bounce passes close."""
    a, b = tr.render(s, settings=TENSOR), tr.render(s, settings=FUSED)
    assert b.timings.get("fused", 0) > 0
    m = _compare(a, b)[0]
    assert m["background"] <= 1e-4, m
    for k in ("exit_found", "tir"):
        assert torch.equal(a.passes[k], b.passes[k]), k
    if m["beyond"] > 1e-3 or m["flip"] > 0.002:  # chaotic paths: the tensor code's own
        own = _compare(a, tr.render(_nudged(s), settings=TENSOR))[0]
        assert m["beyond"] <= own["beyond"] and m["flip"] <= own["flip"] + 1e-4, (m, own)
    else:
        obj = a.coverage[0] > 0
        for k in ("bounces", "bounce_residual"):
            d = (a.passes[k][0, ..., 0] - b.passes[k][0, ..., 0]).abs()[obj]
            assert float((d > 1e-4).float().mean()) <= 1e-3, k


@pytest.mark.parametrize("method", ["specular", "prefiltered", "rousiers"])
@pytest.mark.parametrize("material", [
    {"distribution": "ggx", "roughness": 0.3}, {"ior": 1.0, "roughness": 0.2},
    {"ior": 1.05, "roughness": 0.2}, {"ior": 0.8, "roughness": 0.1},
    {"roughness": 0.0, "absorption": [0.5, 0.2, 0.0]}, {"roughness": 1.0, "ior": 2.4}],
    ids=["ggx", "ior1", "ior1.05", "ior0.8", "smooth-absorbing", "rough-ior2.4"])
def test_fused_matches_the_tensor_code_off_the_suite(method, material):
    """Materials the suite does not hold: GGX (its L2 sharpness), index-matched and nearly
    index-matched glass (the energies' fade), IOR below 1, absorption, the roughest."""
    import dataclasses

    base = _small(SUITE[[p.stem for p in SUITE].index("suzanne_a01")], 64, method=method)
    s = base.replace(material=dataclasses.replace(base.material, **material))
    a, b = tr.render(s, settings=TENSOR), tr.render(s, settings=FUSED)
    for m in _compare(a, b):
        assert m["beyond"] <= 1e-3 and m["max_rel"] < 1e-2 and m["flip"] <= 0.002, m
    assert torch.equal(a.passes["exit_found"], b.passes["exit_found"])


def test_fused_lights_and_a_batch_of_views():
    """Sphere lights behind the slab (seen through its rough lobes: their SG coverage), in
    front of it (hiding part of it) and beside it, maps rotated and scaled per view: the
    fused kernels give the tensor code's images, background included."""
    base = _small(ASSETS.parent / "configs" / "suite" / "slab_light.yaml", size=48)
    lights = (*base.lights,
              tr.SphereLight(position=(0.1, 0.25, 2.4), radius=0.12, radiance=(3.0, 2.0, 1.0)),
              tr.SphereLight(position=(-1.2, 0.0, 0.3), radius=0.4, radiance=(0.5, 2.0, 4.0)))
    scenes = [base.replace(envmap=tr.EnvMap(path=base.envmap.path, rotate_deg=37.0 * i,
                                            scale=1.0 + i), lights=lights,
                           camera=tr.Camera(eye=(0.3 * i, 0.3, 4.0), width=48, height=48))
              for i in range(3)]
    for method in ("specular", "prefiltered", "rousiers"):
        a = tr.render(scenes, method=method, settings=TENSOR)
        b = tr.render(scenes, method=method, settings=FUSED)
        for m in _compare(a, b):
            assert m["background"] <= 1e-4 and m["beyond"] <= 1e-3, (method, m)
            assert m["flip"] <= 0.002, (method, m)
        assert b.timings["fused"] > 0, method  # the kernel ran, lights and all


def test_lights_struct_built_once_per_lighting_and_rebuilt_when_it_changes():
    """The kernels' lights struct is built once per Lighting object (the background and
    each pass of a render share it) and built again where its tensors change in place
    (a new map rotation must reach the kernel)."""
    from torchrefract.lighting.lights import Lighting
    from torchrefract.shading import fused

    base = _small(ASSETS.parent / "configs" / "suite" / "slab_light.yaml", size=16)
    lighting = Lighting.from_scenes([base, base.replace(
        envmap=tr.EnvMap(path=base.envmap.path, rotate_deg=30.0))])
    keep_a, keep_b, keep_c = fused._Keep(), fused._Keep(), fused._Keep()
    a = fused._lights(lighting, keep_a)
    assert fused._lights(lighting, keep_b) is a and len(keep_b) == len(keep_a) > 0
    cos_before = _floats_at(a.rot_cos, 2)
    lighting.rotate_deg.add_(90.0)
    c = fused._lights(lighting, keep_c)
    assert c is not a
    assert _floats_at(c.rot_cos, 2) != cos_before
    other = Lighting.from_scenes([base])
    assert fused._lights(other, fused._Keep()) is not c


def _floats_at(address: int, n: int) -> list[float]:
    """n float32 values at a struct's pointer field."""
    import ctypes

    return list((ctypes.c_float * n).from_address(address))


def test_fused_kernel_runs_where_it_covers_the_scene(monkeypatch):
    """Fused only where it can give the same image: not for ``rousiers`` with the paper's
    spread, not with fused=False (then the tensor code's image, bit for bit)."""
    calls = []
    orig = native._call
    monkeypatch.setattr(native, "_call", lambda name, job: calls.append(name) or orig(name, job))
    sphere = _small(SUITE[[p.stem for p in SUITE].index("sphere_a03")], 32, method="specular")
    globe = _small(SUITE[[p.stem for p in SUITE].index("globe_2rough")], 32)
    for s, kernel in ((sphere, "specular"), (globe.replace(method="specular"), "specular"),
                      (globe.replace(method="prefiltered"), "specular"),
                      (sphere.replace(method="rousiers"), "rousiers"), (globe, "rousiers"),
                      (sphere.replace(method="rousiers", method_options={"cone_rays": "plane"}),
                       "rousiers"),
                      (globe.replace(method_options={"internal_bounces": 2}), "rousiers"),
                      (sphere.replace(method_options={"internal_bounces": 1}), "specular")):
        calls.clear()
        tr.render(s, settings=FUSED)
        assert kernel in calls and "background" in calls, s.method
    for s, kernel in ((globe.replace(method_options={"spread": "paper"}), "rousiers"),):
        calls.clear()
        out = tr.render(s, settings=FUSED)
        assert kernel not in calls
        ref = tr.render(s, settings=TENSOR)
        obj = ref.coverage[0] > 0
        assert torch.equal(out.radiance[0][obj], ref.radiance[0][obj])
    calls.clear()
    tr.render(sphere, settings=TENSOR)
    assert "specular" not in calls and "background" not in calls


@pytest.mark.parametrize("method", ["specular", "prefiltered", "rousiers", "rousiers ib2"])
def test_fused_roughness_maps_in_a_mixed_batch(method):
    """A batch of a mapped view (its range starting at 0: smooth entry points with rough
    exits), a smooth view and a rough uniform one: the per-pixel roughness at the entry and
    at the exit (the map at the exit's UV; ``rousiers``: the levels' coverage over the
    footprint, sec. 5.1, and each bounce's own), as the tensor code takes it."""
    import dataclasses

    opts = {"internal_bounces": 2} if method.endswith("ib2") else {}
    globe = _small(SUITE[[p.stem for p in SUITE].index("globe_2rough")], 48,
                   method=method.split()[0], method_options=opts)
    mapped = globe.replace(material=dataclasses.replace(globe.material,
                                                        roughness_range=(0.0, 0.5)))
    smooth = globe.replace(material=dataclasses.replace(globe.material, roughness_map=None,
                                                        roughness=0.0))
    rough = globe.replace(material=dataclasses.replace(globe.material, roughness_map=None,
                                                       roughness=0.3))
    for batch in ([mapped, smooth, rough], [smooth, globe]):
        a, b = tr.render(batch, settings=TENSOR), tr.render(batch, settings=FUSED)
        for m in _compare(a, b):
            assert m["beyond"] <= 1e-3 and m["flip"] <= 0.002, m
        assert b.timings["fused"] > 0
        for k in ("exit_found", "tir"):
            assert torch.equal(a.passes[k], b.passes[k]), k


def test_gradient_takes_the_tensor_path():
    """A roughness that requires grad: render() takes the differentiable tensor code by
    itself, and the gradient is finite and nonzero."""
    from torchrefract.geometry.gbuffer import build_gbuffer
    from torchrefract.geometry.mesh import load_mesh
    from torchrefract.lighting.lights import Lighting
    from torchrefract.methods.specular import SpecularOptions, render_specular
    from torchrefract.optics.materials import MaterialBatch

    s = _small(SUITE[[p.stem for p in SUITE].index("sphere_a03")], 24, method="specular")
    g = build_gbuffer([load_mesh(s.mesh, s.transform)], [s.camera])
    mats = MaterialBatch.from_scenes([s])
    alpha = mats.roughness.clone().requires_grad_(True)
    mats = type(mats)(**{**mats.__dict__, "roughness": alpha})
    with using(FUSED):
        rad, _ = render_specular(g, Lighting.from_scenes([s]), mats, SpecularOptions())
    rad.sum().backward()
    assert alpha.grad is not None and torch.isfinite(alpha.grad).all()
    assert float(alpha.grad.abs().sum()) > 0


def test_no_object_pixels():
    s = _small(SUITE[0], 24, method="specular")
    s = s.replace(camera=tr.Camera(eye=(0.0, 0.0, 4.0), target=(0.0, 0.0, 8.0), width=24,
                                   height=24))
    a, b = tr.render(s, settings=TENSOR), tr.render(s, settings=FUSED)
    assert float(b.coverage.sum()) == 0
    assert np.allclose(a.radiance.numpy(), b.radiance.numpy(), rtol=1e-4, atol=1e-6)


def test_background_lanes_match_the_tensor_code_at_odd_sizes():
    """csrc/background.c looks up 8 pixels at a time (a view's last few one by one): frames
    whose rows are no multiple of 8, several views and map rotations, with and without a
    sphere light, give the tensor code's background. Its atan2/acos are correctly rounded
    where the C library's may be an ulp off: a lookup moves by ~1e-4 texel at most, so
    the bound is the map's texel contrast times that (docs/decisions.md)."""
    import dataclasses

    for name in ("sphere_a03", "slab_light"):
        s = tr.load_scene(Path(__file__).resolve().parent.parent / "configs" / "suite"
                          / f"{name}.yaml")
        cams = [dataclasses.replace(s.camera, width=37, height=29, samples_per_pixel=1)]
        views = [s.replace(camera=cams[0], envmap=dataclasses.replace(
            s.envmap, rotate_deg=s.envmap.rotate_deg + 23 * i)) for i in range(3)]
        a, b = tr.render(views, settings=TENSOR), tr.render(views, settings=FUSED)
        for i in range(3):
            obj = a.coverage[i] > 0
            ra, rb = a.radiance[i][~obj], b.radiance[i][~obj]
            rel = ((ra - rb).abs() / ra.abs().clamp(min=1e-3)).amax(-1)
            assert rel.numel() and float(rel.max()) < 5e-3, (name, i, float(rel.max()))
            assert float((rel > 1e-4).float().mean()) < 0.05, (name, i)


@pytest.mark.parametrize("method, options", [
    ("rousiers", {"internal_bounces": 2, "bounce_rays": 4}),
    ("rousiers", {"internal_bounces": "auto"}),
    ("specular", {"internal_bounces": 3}),
    ("gsr", {"internal_bounces": 2})])
def test_fused_bounces_the_same_bits_in_lanes_and_scalar(method, options):
    """The fused marches' search in AVX2 lanes gives the scalar search's bits, image and
    every pass, also for the rays a bounce keeps (part blocks: their empty lanes copies
    of the first ray, dropped). Where the CPU has no AVX2 both runs are scalar."""
    s = _small(SUITE[0].parent / "suzanne_a01.yaml", 48, method=method,
               method_options=options)
    with using(RenderSettings(native_simd=True)):
        a = tr.render(s)
    with using(RenderSettings(native_simd=False)):
        b = tr.render(s)
    assert a.timings.get("fused", 0) > 0 and float(a.passes["bounces"].max()) >= 1
    assert torch.equal(a.radiance, b.radiance)
    assert list(a.passes) == list(b.passes)
    for k in a.passes:
        assert torch.equal(a.passes[k], b.passes[k]), k


def test_incident_sg_in_one_call_matches_the_tensor_code():
    """fused.incident_sg (the fused kernels' SG lookups and sphere lights for N lobes, as
    `sh` uses them) against lights.incident_radiance_sg: two views (different map
    rotations, a light), wide to plain lobes; float32 rounding apart, the same radiance.
    Where the tensor code would refuse (a negative sharpness) or a view is out of range,
    it does not run."""
    if not native.available():
        pytest.skip("native kernels unavailable")
    from torchrefract.lighting.lights import Lighting, incident_radiance_sg
    from torchrefract.shading import fused
    base = tr.load_scene(str(ASSETS.parent / "configs" / "suite" / "slab_light.yaml"))
    lighting = Lighting.from_scenes([base, base.replace(envmap=tr.EnvMap(
        path=base.envmap.path, rotate_deg=140.0, scale=0.5))])
    g = torch.Generator().manual_seed(4)
    n = 5000
    batch = torch.randint(0, 2, (n,), generator=g)
    origin = torch.randn(n, 3, generator=g) * 0.3
    direction = torch.nn.functional.normalize(torch.randn(n, 3, generator=g), dim=-1)
    direction[:500] = torch.nn.functional.normalize(
        torch.tensor([0.3, 0.2, -1.5]) - origin[:500], dim=-1)  # at the light
    k = torch.exp(torch.rand(n, generator=g) * 10.0 - 1.0)
    k[::7] = float("inf")
    ours = fused.incident_sg(lighting, batch, origin, direction, k)
    ref = incident_radiance_sg(lighting, batch, origin, direction, k)
    assert ours is not None and torch.isfinite(ours).all()
    rel = ((ours - ref).abs() / ref.abs().clamp(min=1e-3)).amax(-1)
    assert (rel <= 1e-4).float().mean() >= 0.999, float(rel.max())
    assert (ref[:500].amax(-1) > 5.0).sum() > 50  # the light seen
    bad = k.clone()
    bad[3] = -1.0
    assert fused.incident_sg(lighting, batch, origin, direction, bad) is None
    with pytest.raises(ValueError, match="sharpness"):
        incident_radiance_sg(lighting, batch, origin, direction, bad)
    assert fused.incident_sg(lighting, batch + 1, origin, direction, k) is None


def test_lobes_in_one_call_match_the_tensor_code():
    """fused.front_lobes and fused.exit_lobes (the SG table's lobes for N points through the
    fused kernels' lookups, as `sh` uses them) against lobes.front_lobes, sg_lobe and
    spread_energies: random views, IOR 1-2.5 and its inverse (TIR), roughness 0.001-0.7,
    both distributions; float32 rounding apart, the same values."""
    if not native.available():
        pytest.skip("native kernels unavailable")
    from torchrefract.methods.rousiers.lobes import front_lobes, sg_lobe, spread_energies
    from torchrefract.optics.sgfit import load_sg_table
    from torchrefract.shading import fused
    g = torch.Generator().manual_seed(2)
    n = 20000
    view = torch.nn.functional.normalize(torch.randn(n, 3, generator=g), dim=-1)
    n1 = torch.nn.functional.normalize(torch.randn(n, 3, generator=g), dim=-1)
    n1 = torch.where((view * n1).sum(-1, keepdim=True) < 0, -n1, n1)
    cos1 = (view * n1).sum(-1).clamp(0.0, 1.0)
    ior = 1.0 + torch.rand(n, generator=g) * 1.5
    alpha = torch.rand(n, generator=g) * 0.7 + 0.001
    dist = torch.randint(0, 2, (n,), generator=g)
    var = torch.rand(n, generator=g) * 0.05
    table = load_sg_table()

    def close(a, b, name):  # unit axes: absolute; the rest relative
        err = (a - b).abs() if a.dim() == 2 else (a - b).abs() / b.abs().clamp(min=1e-3)
        assert float(err.max()) < (1e-5 if a.dim() == 2 else 1e-4), (name, float(err.max()))

    ours = fused.front_lobes(view, n1, cos1, ior, alpha, dist)
    ref = front_lobes(table, view, n1, cos1, ior, alpha, dist)
    for f in ("e_r", "k_r", "axis_r", "e_t1", "k_t1", "p_t1"):
        close(getattr(ours, f), getattr(ref, f), f)
    for eta in (ior, 1.0 / ior):
        k, e_t, e_r = fused.exit_lobes(cos1, eta, alpha, dist, var)
        close(k, sg_lobe(table, cos1, eta, alpha, dist, "transmit")[1], "k_t")
        for a, b, name in zip((e_t, e_r), spread_energies(table, cos1, var, eta, alpha, dist),
                              ("e_t", "e_r")):
            close(a, b, name)
        only_k = fused.exit_lobes(cos1, eta, alpha, dist)
        assert torch.equal(only_k[0], k) and only_k[1] is None and only_k[2] is None
    # runs of points at one (eta, alpha, distribution), as a view without a roughness map
    # gives them, are read through the axes' slices: the same bits as point by point
    run_ior, run_alpha = ior.view(-1, 500)[:, :1].expand(-1, 500).reshape(-1), \
        alpha.view(-1, 500)[:, :1].expand(-1, 500).reshape(-1)
    run_dist = dist.view(-1, 500)[:, :1].expand(-1, 500).reshape(-1)
    runs = fused.front_lobes(view, n1, cos1, run_ior, run_alpha, run_dist)
    for j in range(0, 1500, 50):  # 50 points a call: below the kernel's run length
        t = slice(j, j + 50)
        one = fused.front_lobes(view[t], n1[t], cos1[t], run_ior[t], run_alpha[t], run_dist[t])
        for f in ("e_r", "k_r", "axis_r", "e_t1", "k_t1", "p_t1"):
            assert torch.equal(getattr(one, f), getattr(runs, f)[t]), f
    k_run, e_t_run, _ = fused.exit_lobes(cos1, 1.0 / run_ior, run_alpha, run_dist, var)
    k_one, e_t_one, _ = fused.exit_lobes(cos1[:50], 1.0 / run_ior[:50], run_alpha[:50],
                                         run_dist[:50], var[:50])
    assert torch.equal(k_run[:50], k_one) and torch.equal(e_t_run[:50], e_t_one)
    assert fused.front_lobes(view, n1, cos1, ior, alpha.requires_grad_(True), dist) is None


@pytest.mark.parametrize("spp", [1, 2])
def test_a_fused_render_dispatches_few_torch_ops(spp):
    """The Python between the kernels stays small: a torch op is costly cache-cold after a
    kernel, so a fused render (one view, adaptive, the lattice and at 2x2 the sparse
    samples) dispatches few of them (the counts, and what a detach per kernel input
    again gives: docs/benchmarks.md, thirtieth sitting). Counted with a
    TorchDispatchMode, the second render (caches warm)."""
    from torch.utils._python_dispatch import TorchDispatchMode  # noqa: PLC0415

    scene = _small(SUITE[[p.stem for p in SUITE].index("sphere_a03")], 64, spp=spp)
    count = [0]

    class Count(TorchDispatchMode):
        def __torch_dispatch__(self, func, types, args=(), kwargs=None):
            count[0] += 1
            return func(*args, **(kwargs or {}))

    tr.render(scene, method="rousiers")
    with Count():
        out = tr.render(scene, method="rousiers")
    assert bool(torch.isfinite(out.radiance).all())
    assert count[0] <= (150 if spp == 1 else 300), count[0]

"""Mitsuba 3 ground truth (torchrefract.truth.mitsuba): conventions, conversion, and the
``specular`` method scored against converged path tracing.

(a) The camera and environment-map conventions of SCENE_SPEC.md are checked pixel by pixel
    against Mitsuba's own sensor and ``envmap`` emitter (no light transport involved).
(b) A smooth glass sphere rendered by ``specular`` is scored (relMSE, FLIP) against Mitsuba at
    max_depth 64 (full truth) and 3 (the light a two-interface method models); the figures
    go to ``outputs/reference_figures.json`` and are printed (``pytest -s``).
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh

import torchrefract as tr
from torchrefract.geometry.camera import pixel_rays
from torchrefract.lighting.envmap import direction_to_uv, load_envmap, lookup, rotate_y
from torchrefract.output.images import linear_to_srgb8, write_exr

pytest.importorskip("mitsuba")
reference = pytest.importorskip("torchrefract.truth.mitsuba")

ROOT = Path(__file__).resolve().parent.parent
ENVS = ROOT / "assets" / "envmaps"
SPOT = str(ROOT / "assets" / "meshes" / "spot.ply")  # any mesh: (a) never renders it

# (eye, target, up): the u seam (u = 0 == 1) lies along map direction (0, 0, -1) (atan2(x, -z)
# = 0 there); atan2's own branch cut (+-pi, i.e. u = 0.5 from both sides) along (0, 0, +1).
CAMERAS = {
    "seam_minus_z": ((0.0, 0.0, 4.0), (0.0, 0.0, 0.0), (0.0, 1.0, 0.0)),
    "plus_z": ((0.0, 0.0, 0.0), (0.0, 0.0, 1.0), (0.0, 1.0, 0.0)),
    "up_pole": ((0.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, -1.0)),
    "down_pole": ((0.0, 0.0, 0.0), (0.0, -1.0, 0.0), (1.0, 0.0, 0.0)),
    "side_plus_x": ((0.0, 0.0, 0.0), (1.0, 0.0, 0.0), (0.0, 1.0, 0.0)),
    "oblique_down": ((1.0, 2.0, 3.0), (-2.0, -5.0, 1.0), (0.0, 1.0, 0.0)),
    "oblique_up": ((0.3, -0.2, 0.1), (1.0, 3.0, -2.0), (0.0, 1.0, 0.0)),
}
ROTATIONS = (0.0, 37.0, -120.0)
ENV_SCALE = 1.7


def _env_scene(env_path, cam, rotate_deg, scale=ENV_SCALE, width=64, height=48, yfov=70.0):
    eye, target, up = cam
    return tr.Scene(mesh=SPOT, envmap=tr.EnvMap(path=str(env_path), rotate_deg=rotate_deg,
                                                scale=scale),
                    camera=tr.Camera(eye=eye, target=target, up=up, yfov_deg=yfov, width=width,
                                     height=height))


def _rel(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.abs(a - b) / np.maximum(np.abs(b), 1e-3)


def _float32_allowance(texels: torch.Tensor, d: torch.Tensor, rotate_deg: float,
                       scale: float, ulps: float = 16.0) -> np.ndarray:
    """How much the lookup moves when the direction moves by a few float32 ulps.

    Mitsuba evaluates ``u = atan2(x, -z)``, ``v = acos(y)`` in float32 on a direction that
    is itself float32 (and not renormalized): a component error of ~1 ulp shifts (u, v) by
    ~ulp / (2 pi sin(theta)) and ~ulp / (pi sin(theta)), which near the poles of a 1024-wide
    HDR map with steep vertical gradients (sun, horizon) changes the radiance by ~1e-3
    relative on a handful of pixels. Measured: the same float32 ray direction looked up by
    torch in float64 and by Mitsuba differs by up to 7e-4 (llvm) / 1.5e-3 (scalar) relative,
    always at sin(theta) < 0.07. This returns, per pixel, the largest change of the float64
    lookup over (u, v) offsets of +-ulps * 2^-24 / (2 pi sin(theta)) (u) and
    / (pi sin(theta)) (v): (H, W, 3). It is tiny away from the poles and high contrast.
    """
    d64 = d.double() / d.double().norm(dim=-1, keepdim=True)  # (H, W, 3)
    tex = texels.double()
    base = lookup(tex, d64, rotate_deg, scale)  # (H, W, 3)
    dm = rotate_y(d64, -rotate_deg)  # map frame
    uv = direction_to_uv(dm)  # (H, W, 2)
    sin_t = torch.sqrt(dm[..., 0] ** 2 + dm[..., 2] ** 2).clamp(min=1e-6)  # (H, W)
    eps = ulps * 2.0 ** -24
    du, dv = eps / (2 * math.pi * sin_t), eps / (math.pi * sin_t)
    worst = torch.zeros_like(base)
    for su in (-1, 0, 1):
        for sv in (-1, 0, 1):
            u = uv[..., 0] + su * du
            v = (uv[..., 1] + sv * dv).clamp(0.0, 1.0)
            th, ph = v * math.pi, u * 2 * math.pi
            dd = torch.stack([torch.sin(ph) * torch.sin(th), torch.cos(th),
                              -torch.cos(ph) * torch.sin(th)], -1)  # map frame, (H, W, 3)
            val = lookup(tex, rotate_y(dd, rotate_deg), rotate_deg, scale)
            worst = torch.maximum(worst, (val - base).abs())
    return worst.numpy()


def _compare_env(scene) -> tuple[float, float]:
    """(plain max relative error, max relative error beyond the float32 allowance)."""
    e = scene.envmap
    texels = load_envmap(e.path)
    d = pixel_rays(scene.camera)  # (H, W, 3)
    ours = lookup(texels, d, e.rotate_deg, e.scale).numpy()
    theirs = reference.eval_envmap_at_pixel_centers(scene)
    assert theirs.shape == ours.shape == (scene.camera.height, scene.camera.width, 3)
    assert np.isfinite(theirs).all()
    plain = _rel(ours, theirs)
    allow = _float32_allowance(texels, d, e.rotate_deg, e.scale)
    beyond = np.maximum(np.abs(ours - theirs) - allow, 0.0) / np.maximum(np.abs(theirs), 1e-3)
    return float(plain.max()), float(beyond.max())


# --------------------------------------------------------------------------------------
# (a) camera + environment conventions, pixel by pixel
# --------------------------------------------------------------------------------------

@pytest.mark.parametrize("env_name", ["studio_small_03.exr", "rooitou_park.exr"])
def test_envmap_matches_mitsuba_on_every_pixel(env_name):
    """Shipped HALF-float maps (512 x 1024), 7 cameras x 3 rotations, scale 1.7.

    Every pixel within 1e-3 relative after allowing for float32 rounding of the direction
    inside Mitsuba (see _float32_allowance; measured plain max: 9.7e-4 with llvm_ad_rgb,
    1.6e-3 with scalar_rgb, at one pixel near the -Y pole of rooitou_park). A convention
    error (half-texel shift, mirrored u, rotation sign, v flip) is 10-1000x larger: see
    test_envmap_comparison_detects_a_half_texel_shift.
    """
    worst_plain, worst = 0.0, 0.0
    for name, cam in CAMERAS.items():
        for rot in ROTATIONS:
            plain, beyond = _compare_env(_env_scene(ENVS / env_name, cam, rot))
            assert beyond <= 1e-3, (f"{env_name} camera {name} rotate_deg {rot}: relative "
                                    f"error {beyond:.2e} beyond float32 rounding")
            worst_plain, worst = max(worst_plain, plain), max(worst, beyond)
    print(f"\n[env {env_name}] max relative error {worst_plain:.2e} "
          f"(beyond float32 allowance: {worst:.2e}), variant {reference.choose_variant()}")
    _record("envmap", env_name, {"max_rel_error": worst_plain,
                                 "max_rel_error_beyond_f32": worst})


@pytest.fixture(scope="module")
def tiny_env(tmp_path_factory) -> Path:
    """8 x 16 random map (values in [0.05, 1]): texels span 22.5 degrees, so the bilinear
    weights across the u seam and next to the poles decide every pixel of a 70-degree view."""
    rng = np.random.default_rng(7)
    img = rng.uniform(0.05, 1.0, size=(8, 16, 3)).astype(np.float32)
    path = tmp_path_factory.mktemp("env") / "tiny.exr"
    write_exr(path, {"R": img[..., 0], "G": img[..., 1], "B": img[..., 2]})
    return path


@pytest.mark.parametrize("rot", ROTATIONS)
def test_tiny_envmap_seam_and_poles(tiny_env, rot):
    """Plain 1e-3 relative on every pixel (no allowance needed: texels are huge)."""
    for name, cam in CAMERAS.items():
        plain, _ = _compare_env(_env_scene(tiny_env, cam, rot, scale=0.6, width=40, height=30,
                                           yfov=90.0))
        assert plain <= 1e-3, f"tiny map, camera {name}, rotate_deg {rot}: {plain:.2e}"


def test_envmap_comparison_detects_a_half_texel_shift(tiny_env):
    """The comparison has teeth: rotating our lookup by half a texel (11.25 deg on the
    16-wide map) must fail it by far."""
    scene = _env_scene(tiny_env, CAMERAS["seam_minus_z"], 0.0, width=40, height=30, yfov=90.0)
    theirs = reference.eval_envmap_at_pixel_centers(scene)
    shifted = lookup(load_envmap(tiny_env), pixel_rays(scene.camera), 360.0 / 16 / 2,
                     ENV_SCALE).numpy()
    assert _rel(shifted, theirs).max() > 0.05


def test_envmap_scalar_variant_subprocess(tiny_env):
    """The scalar fallback (per-pixel loop) gives the same answer (fresh process: the
    variant is chosen once per process)."""
    code = (
        "import sys, numpy as np, torchrefract as tr\n"
        "from torchrefract.truth import mitsuba as reference\n"
        "from torchrefract.lighting.envmap import load_envmap, lookup\n"
        "from torchrefract.geometry.camera import pixel_rays\n"
        "s = tr.Scene(mesh=sys.argv[2], envmap=tr.EnvMap(path=sys.argv[1], rotate_deg=-120,"
        " scale=2.0), camera=tr.Camera(eye=(0, 0, 0), target=(0.2, 0.9, 1), width=20,"
        " height=14, yfov_deg=100))\n"
        "a = reference.eval_envmap_at_pixel_centers(s)\n"
        "b = lookup(load_envmap(sys.argv[1]), pixel_rays(s.camera), -120, 2.0).numpy()\n"
        "print(reference.mitsuba().variant(), float((abs(a - b) / np.maximum(b, 1e-3)).max()))\n"
    )
    env = dict(os.environ, TORCHREFRACT_MI_VARIANT="scalar_rgb")
    out = subprocess.run([sys.executable, "-c", code, str(tiny_env), SPOT], env=env,
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    variant, err = out.stdout.split()[-2:]
    assert variant == "scalar_rgb"
    assert float(err) <= 1e-3


# --------------------------------------------------------------------------------------
# Conversion details (no or tiny renders)
# --------------------------------------------------------------------------------------

def _sphere_ply(tmp_path: Path, subdivisions: int = 3) -> Path:
    p = tmp_path / f"ico{subdivisions}.ply"
    if not p.exists():
        trimesh.creation.icosphere(subdivisions=subdivisions, radius=1.0).export(p)
    return p


def test_dict_follows_spec(tmp_path):
    mi = reference.mitsuba()
    env = ENVS / "rooitou_park.exr"
    scene = tr.Scene(mesh=str(_sphere_ply(tmp_path)), envmap=tr.EnvMap(path=str(env)),
                     transform=tr.Transform(scale=0.7, rotate_deg=(10, 20, 30),
                                            translate=(0.1, -0.2, 0.3)),
                     material=tr.Material(ior=1.33, roughness=0.2, distribution="ggx"),
                     camera=tr.Camera(width=40, height=30, yfov_deg=35))
    d = reference.to_mitsuba_dict(scene, spp=8, seed=3, max_depth=5)
    assert d["integrator"] == {"type": "path", "max_depth": 5, "rr_depth": 6,
                               "hide_emitters": False}
    sensor = d["sensor"]
    assert sensor["type"] == "perspective" and sensor["fov_axis"] == "y"
    assert sensor["fov"] == 35.0
    assert sensor["film"]["rfilter"] == {"type": "box"}
    assert sensor["film"]["pixel_format"] == "rgba"
    assert (sensor["film"]["width"], sensor["film"]["height"]) == (40, 30)
    assert sensor["sampler"] == {"type": "independent", "sample_count": 8, "seed": 3}
    assert d["envmap"]["type"] == "envmap" and d["envmap"]["scale"] == 1.0
    # The glass mesh carries our world-space vertices and normals, untouched.
    mesh = d["glass"]
    from torchrefract.geometry.mesh import load_mesh

    md = load_mesh(scene.mesh, scene.transform)
    params = mi.traverse(mesh)
    np.testing.assert_array_equal(np.array(params["vertex_positions"]).reshape(-1, 3),
                                  md.vertices.numpy())
    np.testing.assert_array_equal(np.array(params["vertex_normals"]).reshape(-1, 3),
                                  md.normals.numpy())
    np.testing.assert_array_equal(np.array(params["faces"]).reshape(-1, 3),
                                  md.faces.numpy())
    assert not mesh.has_vertex_texcoords()  # the icosphere has no UVs
    # UVs, when the file has them, go over with v flipped (Mitsuba's loaders do the same).
    tm = trimesh.creation.icosphere(subdivisions=1)
    uv = np.random.default_rng(1).random((len(tm.vertices), 2))
    tm.visual = trimesh.visual.TextureVisuals(uv=uv)
    obj = tmp_path / "uv.obj"
    tm.export(obj)
    uv_scene = scene.replace(mesh=str(obj))
    mdu = load_mesh(uv_scene.mesh, uv_scene.transform)
    assert mdu.uvs is not None
    tc = np.array(mi.traverse(reference.to_mitsuba_dict(uv_scene)["glass"])["vertex_texcoords"])
    expect = mdu.uvs.numpy().copy()
    expect[:, 1] = 1.0 - expect[:, 1]
    np.testing.assert_allclose(tc.reshape(-1, 2), expect, atol=1e-7)
    bsdf = mesh.bsdf()
    assert "RoughDielectric" in str(bsdf) and "ggx" in str(bsdf).lower()
    smooth = reference.to_mitsuba_dict(scene.replace(material=tr.Material(roughness=0.0)))
    assert "SmoothDielectric" in str(smooth["glass"].bsdf())


def _uv_sphere_ply(tmp_path: Path) -> Path:
    """Icosphere 4 with u = 0.5 and v = (y + 1) / 2 (no seam): image top = +y."""
    p = tmp_path / "uvsphere.ply"
    if not p.exists():
        m = trimesh.creation.icosphere(subdivisions=4)
        uv = np.stack([np.full(len(m.vertices), 0.5), (m.vertices[:, 1] + 1.0) / 2.0], -1)
        m.visual = trimesh.visual.TextureVisuals(uv=uv)
        m.export(p)
    return p


def _map_png(path: Path, img: np.ndarray) -> str:
    from PIL import Image

    Image.fromarray(img.astype(np.uint8)).save(path)
    return str(path)


def test_roughness_map_texture_convention(tmp_path):
    """Mitsuba's alpha texture, looked up where _mitsuba_mesh puts a point's UV (v flipped),
    equals SCENE_SPEC.md's lo + v (hi - lo) with our bilinear, wrapping sample_uv, texel by
    texel on a random 5 x 7 map at UVs well outside [0, 1] (wrapping both ways). Without the
    v flip (or with a half-texel shift) the values differ by ~0.1-0.5."""
    import drjit as dr

    from torchrefract.optics.textures import load_roughness_map, sample_uv

    mi = reference.mitsuba()
    rng = np.random.default_rng(0)
    png = _map_png(tmp_path / "r.png", rng.integers(0, 256, (5, 7)))
    scene = tr.Scene(mesh=str(_uv_sphere_ply(tmp_path)),
                     envmap=tr.EnvMap(path=str(ENVS / "lebombo.exr")),
                     material=tr.Material(roughness=0.0, roughness_map=png,
                                          roughness_range=(0.1, 0.6)))
    bsdf = reference.to_mitsuba_dict(scene)["glass"].bsdf()
    assert "RoughDielectric" in str(bsdf)  # roughness 0 is ignored when a map is given
    tex = mi.load_dict(reference._alpha_map(scene))
    uv = rng.uniform(-1.0, 2.0, (2000, 2)).astype(np.float32)
    ours = 0.1 + 0.5 * sample_uv(load_roughness_map(png), torch.from_numpy(uv)).numpy()

    def theirs(u, v):
        if reference._is_jit(mi):
            si = dr.zeros(mi.SurfaceInteraction3f, len(u))
            si.uv = mi.Point2f(mi.Float(u), mi.Float(v))
            return np.array(tex.eval_1(si))
        out = []
        for a, b in zip(u, v):
            si = mi.SurfaceInteraction3f()
            si.uv = mi.Point2f(float(a), float(b))
            out.append(float(tex.eval_1(si)))
        return np.array(out)

    np.testing.assert_allclose(theirs(uv[:, 0], 1.0 - uv[:, 1]), ours, atol=1e-6)
    assert np.abs(theirs(uv[:, 0], uv[:, 1]) - ours).max() > 0.1  # no flip: detected
    # A mesh without UVs reads the map at UV (0, 0) in our methods: a constant alpha here.
    flat = scene.replace(mesh=str(_sphere_ply(tmp_path)))
    a0 = reference._alpha_map(flat)
    assert isinstance(a0, float)
    assert a0 == pytest.approx(0.1 + 0.5 * float(sample_uv(load_roughness_map(png),
                                                           torch.zeros(2))), abs=1e-6)


def _map_scene(tmp_path: Path, **material) -> tr.Scene:
    return tr.Scene(mesh=str(_uv_sphere_ply(tmp_path)),
                    envmap=tr.EnvMap(path=str(ENVS / "lebombo.exr")),
                    material=tr.Material(ior=1.5, **material),
                    camera=tr.Camera(eye=(0.0, 0.0, 3.5), width=32, height=32, yfov_deg=40))


def test_constant_roughness_map_renders_like_uniform(tmp_path):
    """A map of 255 everywhere (alpha = hi = 0.4) renders as roughness 0.4, same seed: the
    same random numbers meet the same alphas, so the images agree to float rounding."""
    png = _map_png(tmp_path / "c.png", np.full((8, 8), 255))
    mapped = _map_scene(tmp_path, roughness_map=png, roughness_range=(0.05, 0.4))
    uniform = _map_scene(tmp_path, roughness=0.4)
    a, ca = reference.render_reference(mapped, spp=16, seed=5, max_depth=16)
    b, cb = reference.render_reference(uniform, spp=16, seed=5, max_depth=16)
    assert np.isfinite(a).all()
    np.testing.assert_array_equal(ca, cb)
    np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-5)


def test_two_level_roughness_map_halves_match_uniform_renders(tmp_path):
    """Map top half 255 (alpha 0.4, the sphere's +y half), bottom half 0 (alpha 0.05). Away
    from the equator each half of the image is much closer to the uniform render of its own
    alpha (same seed) than to the other one (measured ratios 0.29-0.41 over seeds 0-4; a
    v-flipped convention gives ~2.5-3); the v-flipped map swaps them."""
    img = np.zeros((64, 4))
    img[:32] = 255  # image top = v 1 = +y
    mixed_png = _map_png(tmp_path / "half.png", img)
    flipped_png = _map_png(tmp_path / "half_flipped.png", img[::-1])
    rng = (0.05, 0.4)
    kw = dict(spp=32, seed=2, max_depth=16)
    mixed, cov = reference.render_reference(
        _map_scene(tmp_path, roughness_map=mixed_png, roughness_range=rng), **kw)
    flipped, _ = reference.render_reference(
        _map_scene(tmp_path, roughness_map=flipped_png, roughness_range=rng), **kw)
    rough, _ = reference.render_reference(_map_scene(tmp_path, roughness=0.4), **kw)
    smooth, _ = reference.render_reference(_map_scene(tmp_path, roughness=0.05), **kw)
    obj = cov > 0.99
    top, bottom = obj.copy(), obj.copy()
    top[12:], bottom[:20] = False, False  # rows 0-11 (+y) and 20-31 (-y), equator left out
    d = lambda a, b, m: float(np.abs(a - b)[m].mean())  # noqa: E731
    figures = {"top": (d(mixed, rough, top), d(mixed, smooth, top)),
               "bottom": (d(mixed, smooth, bottom), d(mixed, rough, bottom)),
               "flipped_top": (d(flipped, smooth, top), d(flipped, rough, top))}
    print("\n[roughness map halves: (own level, other level)]", figures)
    for own, other in figures.values():
        assert own < 0.6 * other, figures  # measured 0.29-0.41 over seeds 0-4


def test_missing_mitsuba_raises_install_hint(monkeypatch):
    monkeypatch.setattr(reference, "_mi", None)
    monkeypatch.setitem(sys.modules, "mitsuba", None)  # makes `import mitsuba` fail
    with pytest.raises(ImportError, match=r"pip install 'torchrefract\[reference\]'"):
        reference.mitsuba()


def test_sphere_light_and_absorption(tmp_path, smooth_env_exr):
    """A light seen directly shows exactly its radiance and hides the map; absorption
    switches to volpath and darkens the glass (Beer-Lambert)."""
    env = ENVS / "rooitou_park.exr"
    light = tr.SphereLight(position=(0.0, 0.0, -3.0), radius=0.6, radiance=(5.0, 2.5, 0.5))
    cam = tr.Camera(eye=(0.0, 0.0, 4.0), target=(0.0, 0.0, 0.0), width=32, height=24,
                    yfov_deg=40)
    mesh = str(_sphere_ply(tmp_path))
    # Light straight behind a tiny sphere far off to the side: centre pixels see the light.
    scene = tr.Scene(mesh=mesh, envmap=tr.EnvMap(path=str(env)), lights=(light,),
                     transform=tr.Transform(scale=0.05, translate=(1.5, 1.0, 0.0)),
                     material=tr.Material(roughness=0.0), camera=cam)
    rad, alpha = reference.render_reference(scene, spp=4, max_depth=8)
    assert np.isfinite(rad).all()
    np.testing.assert_allclose(rad[11:13, 15:17], np.broadcast_to([5.0, 2.5, 0.5], (2, 2, 3)),
                               rtol=1e-5)
    assert alpha[11:13, 15:17].max() == 0.0  # coverage counts the glass only
    # Absorption: the same glass sphere, clear vs absorbing (volpath), one channel at 0
    # (which made Mitsuba's volpath return NaN before the sigma_t floor in reference.py).
    # Smooth map without a sun. The unabsorbed channel is noisy in volpath (the free-flight
    # distance is sampled in a random channel; blue's estimate swings with that choice):
    # its mean ratio over 3 seeds at 128 spp ranged 0.92-1.18, hence the 0.3 tolerance.
    base = tr.Scene(mesh=mesh, envmap=tr.EnvMap(path=str(smooth_env_exr)), camera=cam,
                    material=tr.Material(roughness=0.0))
    absorbing = base.replace(material=tr.Material(roughness=0.0, absorption=(2.0, 0.5, 0.0)))
    assert reference.to_mitsuba_dict(absorbing)["integrator"]["type"] == "volpath"
    clear_rad, a1 = reference.render_reference(base, spp=256, seed=3, max_depth=8)
    abs_rad, a2 = reference.render_reference(absorbing, spp=256, seed=3, max_depth=8)
    assert np.isfinite(abs_rad).all()
    m = a1 > 0.99
    assert m.sum() > 100
    np.testing.assert_array_equal(a1, a2)
    ratio = abs_rad[m].mean(0) / clear_rad[m].mean(0)  # (3,)
    # Red (sigma 2 over paths of ~1.5) is nearly gone, green halved, blue untouched.
    assert ratio[0] < 0.2 and 0.2 < ratio[1] < 0.8 and abs(ratio[2] - 1.0) < 0.3, ratio


# --------------------------------------------------------------------------------------
# (b) specular vs converged Mitsuba on a smooth glass sphere
# --------------------------------------------------------------------------------------

FIGURES = ROOT / "outputs" / "reference_figures.json"


def _record(section: str, key: str, value) -> None:
    FIGURES.parent.mkdir(parents=True, exist_ok=True)
    data = json.loads(FIGURES.read_text()) if FIGURES.is_file() else {}
    data.setdefault(section, {})[key] = value
    FIGURES.write_text(json.dumps(data, indent=2, sort_keys=True))


def _relmse(x: np.ndarray, ref: np.ndarray, mask: np.ndarray) -> float:
    """SCENE_SPEC.md relMSE: mean over object pixels and channels of (x-r)^2/(r^2+0.01)."""
    return float(((x - ref) ** 2 / (ref ** 2 + 0.01))[mask].mean())


def _flip(x: np.ndarray, ref: np.ndarray, mask: np.ndarray) -> tuple[float, float]:
    """Mean LDR-FLIP of the sRGB previews: (object pixels, whole image)."""
    import flip_evaluator

    to01 = lambda img: linear_to_srgb8(img).astype(np.float32) / 255.0  # noqa: E731
    err, _, _ = flip_evaluator.evaluate(to01(ref), to01(x), "LDR", applyMagma=False)
    err = np.asarray(err).reshape(ref.shape[:2])
    return float(err[mask].mean()), float(err.mean())


def test_specular_sphere_against_mitsuba(tmp_path):
    """Scores of ``specular`` on a smooth IOR-1.5 sphere (icosphere 5, 64x64, 2x2 ss).

    Figures measured on this machine (llvm_ad_rgb, rooitou_park, 1024 spp truth):
    relMSE vs depth-3 truth 0.0021 (0.0017 at 4096 spp; two independent 1024-spp truths
    differ by 0.0006: the Monte Carlo floor), vs depth-64 truth 0.041, black image 0.39 /
    0.47; FLIP (object pixels) vs depth 3 0.025 (truth-vs-truth floor 0.014), vs depth 64
    0.17 (DESIGN.md's depth-3 floor for this scene is 0.196 at 256x256). At 64 spp the
    truth is not converged (relMSE is heavy-tailed: one sun-lit sample in a dark pixel
    dominates), so the assertions use 1024 spp and 64 spp is only reported.
    Bounds: relMSE vs depth 3 < 0.01 (5x measured; 40x below black) and FLIP < 0.06
    (2.4x measured); vs depth 64 only "much better than black" and "worse than vs depth 3",
    since the missing internal bounces are an expected, measured floor.
    """
    ply = tmp_path / "ico5.ply"
    trimesh.creation.icosphere(subdivisions=5, radius=1.0).export(ply)
    scene = tr.Scene(mesh=str(ply), envmap=tr.EnvMap(path=str(ENVS / "rooitou_park.exr")),
                     material=tr.Material(ior=1.5, roughness=0.0),
                     camera=tr.Camera(eye=(0.0, 0.6, 3.4), target=(0.0, 0.0, 0.0),
                                      yfov_deg=40.0, width=64, height=64,
                                      samples_per_pixel=2),
                     method="specular", method_options={"tir": "clamp"})  # two interfaces
    out = tr.render([scene], method="specular")
    x = out.radiance[0].numpy()  # (64, 64, 3)
    cov = out.coverage[0].numpy()  # (64, 64)
    assert np.isfinite(x).all()
    mask = cov > 0.5
    assert mask.sum() > 1000

    figures, truths = {"variant": reference.mitsuba().variant(),
                       "specular_seconds": out.timings["total"]}, {}
    for depth in (64, 3):
        for spp in (64, 1024):
            t0 = time.perf_counter()
            ref, alpha = reference.render_reference(scene, spp=spp, seed=1, max_depth=depth)
            dt = time.perf_counter() - t0
            assert np.isfinite(ref).all() and np.isfinite(alpha).all()
            truths[depth, spp] = (ref, alpha)
            fo, fw = _flip(x, ref, mask)
            figures[f"depth{depth}_spp{spp}"] = {
                "mitsuba_seconds": dt,
                "relmse_specular": _relmse(x, ref, mask),
                "relmse_black": _relmse(np.zeros_like(x), ref, mask),
                "flip_specular_object": fo, "flip_specular_image": fw,
                "flip_black_object": _flip(np.zeros_like(x), ref, mask)[0],
            }
    print("\n[specular vs Mitsuba, smooth sphere 64x64]")
    print(json.dumps(figures, indent=1))
    _record("specular_sphere", "rooitou_park_64x64", figures)

    d3, d64 = figures["depth3_spp1024"], figures["depth64_spp1024"]
    # Much closer than black, against both truths.
    assert d3["relmse_specular"] < 0.1 * d3["relmse_black"]
    assert d64["relmse_specular"] < 0.25 * d64["relmse_black"]
    assert d3["flip_specular_object"] < 0.3 * d3["flip_black_object"]
    # Closer to the depth-3 truth (the light it models) than to the full truth.
    assert d3["relmse_specular"] < d64["relmse_specular"]
    assert d3["flip_specular_object"] < d64["flip_specular_object"]
    # Generous bounds on the measured figures (see docstring).
    assert d3["relmse_specular"] < 0.01
    assert d3["flip_specular_object"] < 0.06

    # Coverage: Mitsuba's (random 1024 samples per pixel) vs ours (2x2 sub-pixel centers).
    # Away from the silhouette both are exactly 0 or 1; on it, a 2x2 grid misjudges a
    # straight edge's coverage by up to 0.25 (plus Monte Carlo noise, std <= 0.016).
    alpha = truths[3, 1024][1]
    pad = np.pad(alpha, 1, mode="edge")
    win = np.stack([pad[i:i + 64, j:j + 64] for i in range(3) for j in range(3)])  # (9, H, W)
    interior = (win.min(0) == win.max(0)) & ((alpha == 0) | (alpha == 1))
    assert np.array_equal(cov[interior], alpha[interior])
    assert np.abs(cov - alpha).max() < 0.35
    assert abs(cov.sum() - alpha.sum()) < 0.01 * alpha.sum()


def test_method_reference_through_render(tmp_path):
    """``method: reference`` renders with Mitsuba through the normal API and CLI outputs."""
    pytest.importorskip("mitsuba")
    import torchrefract as tr
    from torchrefract.truth.mitsuba import render_reference

    s = tr.Scene(mesh=str(ROOT / "assets" / "meshes" / "sphere.ply"),
                 envmap=tr.EnvMap(path=str(ROOT / "assets" / "envmaps" / "lebombo.exr")),
                 material=tr.Material(roughness=0.2),
                 camera=tr.Camera(width=24, height=20, samples_per_pixel=2),
                 method="reference", method_options={"spp": 16, "seed": 3, "max_depth": 8})
    out = tr.render([s])
    assert out.radiance.shape == (1, 20, 24, 3) and torch.isfinite(out.radiance).all()
    assert "depth_front" in out.passes and out.coverage[0].max() == 1
    # Equals Mitsuba at the sub-pixel grid, box-filtered 2x2.
    sub = s.replace(camera=tr.Camera(width=48, height=40))
    rgb, _ = render_reference(sub, spp=16, seed=3, max_depth=8)
    want = rgb.reshape(20, 2, 24, 2, 3).mean((1, 3))
    assert np.allclose(out.radiance[0].numpy(), want, rtol=1e-5, atol=1e-6)
    with pytest.raises(tr.ConfigError, match="method_options.spp"):
        tr.render([s.replace(method_options={"spp": 0})])

"""Method ``specular`` against an analytic two-interface glass sphere, and its switches."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import torchrefract as tr
from torchrefract.lighting.envmap import load_envmap, lookup


def _sphere_scene(sphere_ply, env_path, **kw):
    cam = dict(eye=(0.3, 0.5, 3.6), target=(0.0, 0.0, 0.0), yfov_deg=38.0, width=96,
               height=80)
    cam.update(kw.pop("camera", {}))
    return tr.Scene(mesh=str(sphere_ply), envmap=tr.EnvMap(path=str(env_path), **kw.pop("env", {})),
                    material=tr.Material(roughness=0.0, **kw.pop("material", {})),
                    camera=tr.Camera(**cam), method="specular", **kw)


def _analytic_sphere(scene, texels, conserve=False):
    """Exact two-interface radiance of a unit sphere at the origin (float64, numpy);
    ``conserve``: the exit's reflection leaves along the refracted ray too (exit weight 1:
    smooth glass loses nothing)."""
    from torchrefract.geometry.camera import pixel_rays

    d = pixel_rays(scene.camera).double().numpy().reshape(-1, 3)
    o = np.asarray(scene.camera.eye, np.float64)
    ior = scene.material.ior

    def refract(i, n, eta):
        c = -(i * n).sum(-1, keepdims=True)
        k = 1 - eta ** 2 * (1 - c ** 2)
        return eta * i + (eta * c - np.sqrt(np.maximum(k, 0))) * n, k[:, 0] < 0

    def fresnel(ci, eta):
        s2 = eta ** 2 * (1 - ci ** 2)
        ct = np.sqrt(np.maximum(1 - s2, 0))
        rs = (eta * ci - ct) / (eta * ci + ct)
        rp = (ci - eta * ct) / (ci + eta * ct)
        return np.where(s2 >= 1, 1.0, 0.5 * (rs ** 2 + rp ** 2))

    b = (o * d).sum(-1)
    disc = b * b - (o @ o - 1.0)
    hit = disc > 0
    t = -b - np.sqrt(np.maximum(disc, 0))
    p1 = o + t[:, None] * d
    n1 = p1
    c1 = -(d * n1).sum(-1)
    f1 = fresnel(c1, 1 / ior)
    r = d - 2 * (d * n1).sum(-1, keepdims=True) * n1
    t1, _ = refract(d, n1, 1 / ior)
    s = -2 * (p1 * t1).sum(-1)
    p2 = p1 + s[:, None] * t1
    t2, tir = refract(t1, -p2, ior)
    assert not tir[hit].any()  # a sphere never traps light at its first exit
    f2 = fresnel(-(t1 * -p2).sum(-1), ior)
    env = torch.from_numpy(texels).double()
    look = lambda v: lookup(env, torch.from_numpy(v), scene.envmap.rotate_deg,  # noqa: E731
                            scene.envmap.scale).numpy()
    w2 = np.ones_like(f2) if conserve else 1 - f2
    lo = f1[:, None] * look(r) + ((1 - f1) * w2)[:, None] * look(t2)
    out = np.where(hit[:, None], lo, look(d))
    h, w = scene.camera.height, scene.camera.width
    return out.reshape(h, w, 3), c1.reshape(h, w), hit.reshape(h, w)


@pytest.mark.parametrize("tir", ["clamp", "conserve"])
def test_sphere_matches_analytic_two_interface(sphere_ply, smooth_env_exr, tir):
    scene = _sphere_scene(sphere_ply, smooth_env_exr, env={"rotate_deg": 25.0},
                          method_options={"tir": tir})
    out = tr.render([scene])
    ref, cos1, hit = _analytic_sphere(scene, load_envmap(smooth_env_exr).numpy(),
                                      conserve=tir == "conserve")
    img = out.radiance[0].double().numpy()
    inner = hit & (cos1 > 0.3)  # away from the silhouette
    assert inner.sum() > 1000
    rel = ((img - ref) ** 2 / (ref ** 2 + 0.01))[inner].mean()
    print(f"analytic sphere relMSE (cos > 0.3): {rel:.3e}")
    assert rel <= 1e-3, rel
    # Background pixels are exact environment lookups.
    outside = ~hit & (out.coverage[0].numpy() == 0)
    assert np.abs(img[outside] - ref[outside]).max() < 1e-4
    assert (out.passes["exit_found"][0, ..., 0].numpy()[inner] == 1).all()


def test_ior_one_is_invisible(sphere_ply):
    env = tr.EnvMap(path=str(__import__("conftest").ASSETS / "envmaps" / "studio_small_03.exr"))
    scene = tr.Scene(mesh=str(sphere_ply), envmap=env, material=tr.Material(ior=1.0,
                     roughness=0.0), camera=tr.Camera(width=64, height=48))
    out = tr.render([scene])
    tex = load_envmap(env.path)
    from torchrefract.geometry.camera import pixel_rays
    bg = lookup(tex, pixel_rays(scene.camera))
    rel = (out.radiance[0] - bg).abs() / bg.abs().clamp(min=1e-3)
    assert out.coverage[0].mean() > 0.1
    assert rel.max() < 1e-3, rel.max()


def test_tir_switch_and_finiteness(smooth_env_exr):
    """A high-IOR non-convex mesh traps light; both TIR modes stay finite and differ."""
    from conftest import ASSETS
    base = tr.Scene(mesh=str(ASSETS / "meshes" / "suzanne.ply"),
                    envmap=tr.EnvMap(path=str(smooth_env_exr)),
                    material=tr.Material(ior=2.4, roughness=0.0),
                    camera=tr.Camera(eye=(0.5, 0.3, 2.2), width=64, height=64))
    clamp = tr.render([base])
    refl = tr.render([base.replace(method_options={"tir": "reflect"})])
    tirmask = clamp.passes["tir"][0, ..., 0] > 0
    assert tirmask.float().mean() > 0.01
    for o in (clamp, refl):
        assert torch.isfinite(o.radiance).all()
        assert o.radiance.max() < 2.0 * load_envmap(smooth_env_exr).max()
    diff = (clamp.radiance[0] - refl.radiance[0]).abs().sum(-1)
    assert diff[tirmask].mean() > 1e-3
    assert diff[clamp.coverage[0] == 0].max() == 0


def test_absorption_darkens_by_beer_lambert(sphere_ply, smooth_env_exr):
    clear = _sphere_scene(sphere_ply, smooth_env_exr)
    tinted = _sphere_scene(sphere_ply, smooth_env_exr, material={"absorption": (0.5, 0.0, 0.0)})
    a, b = tr.render([clear, tinted]).radiance  # one batch, two materials
    # At the sphere's center pixel the path inside is the diameter (2); the transmitted part
    # dominates there, so the red ratio is close to exp(-1) and green/blue are unchanged.
    cov = tr.render([clear]).coverage[0]
    assert torch.allclose(a[..., 1:], b[..., 1:], atol=1e-6)
    assert (b[..., 0] <= a[..., 0] + 1e-6).all()
    assert (b[..., 0][cov == 0] == a[..., 0][cov == 0]).all()


def test_close_camera_rays_leaving_frame_stay_finite(sphere_ply, smooth_env_exr):
    """A camera so close that the sphere overfills the frame: exits leave the image."""
    scene = _sphere_scene(sphere_ply, smooth_env_exr, camera={"eye": (0.0, 0.0, 1.3),
                                                              "yfov_deg": 60.0})
    out = tr.render([scene])
    assert out.coverage[0].min() == 1.0
    assert torch.isfinite(out.radiance).all()
    assert out.radiance.min() >= 0
    assert out.radiance.max() < 2.0 * load_envmap(smooth_env_exr).max()


def test_fallback_without_back_layer_uses_refracted_direction(tmp_path, smooth_env_exr):
    """A single triangle has no back face: every exit falls back to the refracted ray T1."""
    import trimesh

    tri = trimesh.Trimesh([[-1.0, -1.0, 0.0], [1.0, -1.0, 0.0], [0.0, 1.2, 0.0]], [[0, 1, 2]])
    path = tmp_path / "tri.ply"
    tri.export(path)
    scene = tr.Scene(mesh=str(path), envmap=tr.EnvMap(path=str(smooth_env_exr)),
                     material=tr.Material(ior=1.5, roughness=0.0),
                     camera=tr.Camera(eye=(0.4, 0.2, 3.0), width=48, height=48))
    with pytest.warns(UserWarning, match="not watertight"):
        out = tr.render([scene])
    cov = out.coverage[0] == 1
    assert cov.sum() > 100
    assert (out.passes["exit_found"][0, ..., 0][cov] == 0).all()
    # Expected: F1 * env(reflect) + (1 - F1) * env(T1) with the plane normal +Z.
    from torchrefract.geometry.camera import pixel_rays
    from torchrefract.optics.smooth import fresnel_dielectric, reflect, refract

    d = pixel_rays(scene.camera)
    n = torch.tensor([0.0, 0.0, 1.0]).expand_as(d)
    f1 = fresnel_dielectric(-(d * n).sum(-1), 1 / 1.5)[..., None]
    t1, _ = refract(d, n, torch.tensor(1 / 1.5))
    tex = load_envmap(smooth_env_exr)
    want = f1 * lookup(tex, reflect(d, n)) + (1 - f1) * lookup(tex, t1)
    assert torch.allclose(out.radiance[0][cov], want[cov], rtol=1e-4, atol=1e-5)


def test_sphere_lights_seen_directly_and_through_glass(sphere_ply, smooth_env_exr):
    from torchrefract.geometry.camera import pixel_rays

    bright = (50.0, 40.0, 30.0)
    lights = (tr.SphereLight(position=(1.6, 0.0, 0.0), radius=0.25, radiance=bright),  # beside
              tr.SphereLight(position=(0.0, 0.0, -3.0), radius=0.6, radiance=bright))  # behind
    scene = tr.Scene(mesh=str(sphere_ply), envmap=tr.EnvMap(path=str(smooth_env_exr)),
                     material=tr.Material(roughness=0.0), lights=lights,
                     camera=tr.Camera(eye=(0.0, 0.0, 4.0), yfov_deg=50.0, width=64, height=64))
    out = tr.render([scene])
    img, cov = out.radiance[0], out.coverage[0]
    want = torch.tensor(bright)
    # Seen directly: the light beside the sphere covers background pixels with its radiance.
    d = pixel_rays(scene.camera)
    from torchrefract.lighting.lights import hit_lights
    t, _ = hit_lights(torch.tensor([scene.camera.eye]).expand(64 * 64, 3), d.reshape(-1, 3),
                      torch.tensor([l.position for l in lights])[None].expand(64 * 64, 2, 3),
                      torch.tensor([l.radius for l in lights])[None].expand(64 * 64, 2),
                      torch.tensor([l.radiance for l in lights])[None].expand(64 * 64, 2, 3))
    direct = torch.isfinite(t).view(64, 64) & (cov == 0)
    assert direct.sum() > 10
    assert torch.allclose(img[direct], want.expand_as(img[direct]))
    # Seen through the glass: the light behind the sphere (hidden from the eye by it) lights
    # up the center of the sphere, where the env alone is ~1.
    center = img[28:36, 28:36]
    assert (center.mean((0, 1)) > 0.5 * want).all()
    without = tr.render([scene.replace(lights=())]).radiance[0]
    assert without[28:36, 28:36].max() < 3.0


@pytest.mark.parametrize("method", ["specular", "prefiltered", "rousiers"])
def test_conserve_is_the_default_exit_rule(method, sphere_ply, smooth_env_exr):
    """No ``tir`` option means ``conserve`` (the same image bit for bit), which differs from
    the papers' ``clamp`` on rough glass (the exit's reflection leaves instead of being
    lost: brighter)."""
    scene = _sphere_scene(sphere_ply, smooth_env_exr, camera={"width": 24, "height": 20})
    scene = scene.replace(method=method, material=tr.Material(roughness=0.3))
    default = tr.render([scene]).radiance
    conserve = tr.render([scene.replace(method_options={"tir": "conserve"})]).radiance
    clamp = tr.render([scene.replace(method_options={"tir": "clamp"})]).radiance
    assert torch.equal(default, conserve)
    assert conserve.mean() > clamp.mean() + 1e-3

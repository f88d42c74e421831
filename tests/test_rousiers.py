"""Method ``rousiers``: limits, stability, options (truth comparisons: tests/test_truth_rough.py)."""

from __future__ import annotations

import pytest
import torch
from conftest import ASSETS

import torchrefract as tr
from torchrefract.geometry.camera import pixel_rays
from torchrefract.lighting.envmap import load_envmap, lookup
from torchrefract.methods.rousiers import RousiersOptions, bounding_angle
from torchrefract.options import parse_options

ENV = str(ASSETS / "envmaps" / "studio_small_03.exr")


def _scene(mesh, **material):
    return tr.Scene(mesh=str(mesh), envmap=tr.EnvMap(path=ENV, rotate_deg=30.0),
                    material=tr.Material(**material),
                    camera=tr.Camera(eye=(0.2, 0.4, 3.5), width=40, height=32),
                    method="rousiers")


def test_smooth_limit_is_close_to_specular(sphere_ply, smooth_env_exr):
    # A smooth environment: the table's axis interpolation (~3e-4 rad at alpha -> 0) would
    # flip pixels on the edges of the studio map's 1000x-brighter lights.
    s = _scene(sphere_ply, ior=1.5, roughness=0.0).replace(
        envmap=tr.EnvMap(path=str(smooth_env_exr)))
    a = tr.render([s]).radiance[0]
    ref = tr.render([s], method="specular")
    b = ref.radiance[0]
    # Away from the silhouette: on a sphere the exit angle equals the entry angle, and from
    # 53 degrees of incidence (facing < 0.6) on the exit nears the critical angle (41.8
    # degrees inside), where d(theta_out)/d(theta_in) diverges and the table's
    # interpolation in theta (1.9 degree nodes) shows.
    facing = -(ref.passes["normal_front"][0] * pixel_rays(s.camera)).sum(-1)
    inner = (ref.coverage[0] == 1) & (facing > 0.6)
    assert inner.sum() > 200
    rel = ((a - b) ** 2 / (b ** 2 + 0.01))[inner].mean()
    assert rel < 1e-4, rel


def test_ior_one_is_invisible_at_any_roughness(sphere_ply):
    for r in (0.0, 0.05, 0.5, 1.0):
        s = _scene(sphere_ply, ior=1.0, roughness=r)
        out = tr.render([s], settings=tr.RenderSettings(adaptive=False))  # the method's own
        bg = lookup(load_envmap(ENV), pixel_rays(s.camera), 30.0)
        rel = (out.radiance[0] - bg).abs() / bg.abs().clamp(min=1e-3)
        assert out.coverage[0].mean() > 0.1
        assert rel.max() < 1e-3, (r, rel.max())


@pytest.mark.parametrize("roughness", [0.0, 1e-4, 0.5, 1.0])
@pytest.mark.parametrize("ior", [1.0001, 1.33, 2.4, 3.0])
def test_finite_and_bounded(roughness, ior):
    mesh = ASSETS / "meshes" / "suzanne.ply"
    out = tr.render([_scene(mesh, ior=ior, roughness=roughness)])
    assert torch.isfinite(out.radiance).all()
    assert out.radiance.min() >= 0
    assert out.radiance.max() <= load_envmap(ENV).max() * 1.05
    for k, v in out.passes.items():
        assert torch.isfinite(v).all(), k


def test_batch_of_materials_equals_single_renders(sphere_ply):
    scenes = [_scene(sphere_ply, ior=i, roughness=r) for i, r in ((1.5, 0.05), (1.33, 0.4))]
    batch = tr.render(scenes).radiance
    for i, s in enumerate(scenes):
        single = tr.render([s]).radiance[0]
        assert torch.allclose(batch[i], single, atol=1e-5)


def test_options_and_cone_variants(sphere_ply):
    s = _scene(sphere_ply, ior=1.5, roughness=0.2)
    a = tr.render([s]).radiance
    b = tr.render([s.replace(method_options={"cone_rays": "plane"})]).radiance
    c_out = tr.render([s.replace(method_options={"spread": "paper"})])
    c = c_out.radiance
    full = tr.render([s])
    cov = full.coverage[0] == 1
    # On a sphere the plane approximation of the footprint is close to marching it.
    assert ((a - b).abs()[0][cov]).mean() < 0.05 * a[0][cov].mean()
    # Adding the front lobe's spread to the paper's model widens the lobe everywhere.
    pf = tr.render([s.replace(method_options={"spread": "paper+front"})])
    found = (full.passes["exit_found"][0, ..., 0] == 1) & cov
    s_paper = c_out.passes["lobe_sigma"][0, ..., 0][found]
    s_front = pf.passes["lobe_sigma"][0, ..., 0][found]
    assert (s_paper <= s_front + 1e-6).all() and (s_paper < 0.9 * s_front).float().mean() > 0.5
    assert not torch.allclose(a, c)
    with pytest.raises(tr.ConfigError, match="cone_rays"):
        parse_options(RousiersOptions, {"cone_rays": "cone"})
    with pytest.raises(tr.ConfigError, match="spread"):
        parse_options(RousiersOptions, {"spread": "wide"})
    o = parse_options(RousiersOptions, {})
    assert (o.refine_steps, o.cone_refine_steps, o.cone_march_steps) == (8, 3, 4)
    assert parse_options(RousiersOptions, {"cone_refine_steps": 6}).cone_refine_steps == 6
    with pytest.raises(tr.ConfigError, match="cone_refine_steps"):
        parse_options(RousiersOptions, {"cone_refine_steps": -1})


def test_bounding_angle_holds_75_percent_of_the_lobe():
    # For exp(k (cos - 1)) on the sphere the mass within theta is
    # (1 - exp(-k (1 - cos theta))) / (1 - exp(-2k)); eq. 12 bounds 75% for a lobe cos^k,
    # which matches for large k.
    for k in (20.0, 100.0, 1000.0):
        tb = bounding_angle(torch.tensor(k, dtype=torch.float64))
        mass = (1 - torch.exp(-k * (1 - torch.cos(tb)))) / (1 - torch.exp(torch.tensor(-2 * k)))
        assert 0.72 < mass.item() < 0.78


def test_ggx_renders_and_differs_from_beckmann(sphere_ply):
    s = _scene(sphere_ply, ior=1.5, roughness=0.2)
    beck = tr.render([s]).radiance
    ggx = tr.render([s.replace(material=tr.Material(ior=1.5, roughness=0.2,
                                                    distribution="ggx"))]).radiance
    assert torch.isfinite(ggx).all()
    assert (beck - ggx).abs().mean() > 1e-3

"""Relighting a matte with another map, rotation and scale against direct renders
(issue #27, part 2): FLIP <= 0.01 on object pixels."""

from __future__ import annotations

import pytest
import torch

import torchrefract as tr
from torchrefract.truth.metrics import flip_map

from conftest import ASSETS, ROOT

OTHER = str(ASSETS / "envmaps" / "rooitou_park.exr")
TENSOR = tr.RenderSettings(fused=False)


def _scene(name, method, opts, size=48):
    s = tr.load_scene(ROOT / "configs" / "suite" / name)
    cam = tr.Camera(**{**s.camera.__dict__, "width": size, "height": size,
                       "samples_per_pixel": 1})
    return s.replace(camera=cam, method=method, method_options=opts)


def _flip(img, ref, cov):
    fm = flip_map(img[0].numpy(), ref[0].numpy())
    return float(fm[(cov[0] > 0.999).numpy()].mean())


@pytest.mark.parametrize("name,method,opts", [
    ("sphere_a03.yaml", "rousiers", {"internal_bounces": 2}),
    ("torus_a01.yaml", "prefiltered", {}),
    ("suzanne_a01.yaml", "specular", {"internal_bounces": 1}),
    ("slab_light.yaml", "rousiers", {}),
])
def test_other_map_rotation_scale(one_thread, name, method, opts):
    s = _scene(name, method, opts)
    out = tr.render(s.replace(passes={"matte": {}}))
    for env in (tr.EnvMap(path=OTHER, rotate_deg=0.0, scale=1.0),
                tr.EnvMap(path=OTHER, rotate_deg=-75.0, scale=0.5),
                tr.EnvMap(path=s.envmap.path, rotate_deg=s.envmap.rotate_deg + 140.0,
                          scale=2.0)):
        img = tr.relight(out, env.path, rotate_deg=env.rotate_deg, scale=env.scale)
        direct = tr.render(s.replace(envmap=env), settings=TENSOR)
        assert bool(torch.isfinite(img).all())
        assert _flip(img, direct.radiance, out.coverage) <= 0.01
        # nothing folded at 1 spp: the relit image is the render to float32 rounding
        rel = (img - direct.radiance).abs().amax(-1) / direct.radiance.amax(-1).clamp(min=1e-4)
        assert float(rel.max()) <= 1e-4


def test_texels_and_batches(one_thread):
    """Texels in memory (their pyramid built here) and per-view rotations of a batch."""
    s = _scene("sphere_a03.yaml", "rousiers", {}, size=24)
    out = tr.render([s.replace(passes={"matte": {}}),
                     s.replace(passes={"matte": {}}, material=tr.Material(roughness=0.05))])
    tex = torch.ones(16, 32, 3) * torch.tensor([0.2, 0.5, 1.0])
    img = tr.relight(out, tex, rotate_deg=torch.tensor([0.0, 90.0]), scale=2.0)
    # a constant map: the image is 2 * color * (sum of the weights) everywhere
    from torchrefract.matte.matte import from_passes

    m = from_passes(out.passes)
    expect = 2.0 * torch.tensor([0.2, 0.5, 1.0]) * m.weight.sum(-2)
    assert torch.allclose(img, expect, rtol=1e-4, atol=1e-5)
    with pytest.raises(tr.ConfigError, match="rotate_deg"):
        tr.relight(out, tex, rotate_deg=[1.0, 2.0, 3.0])


def test_prepared_equals_lookups(one_thread):
    """The prepared relight (gathers of precomputed texel indices) against the lookups one
    by one: per-view rotations and scales, a pyramid passed in, rotations seen before, a
    matte changed in place (prepared again)."""
    from torchrefract.lighting.sg_pyramid import sg_pyramid_for
    from torchrefract.matte.matte import from_passes
    from torchrefract.matte.relight import prepare, relight_reference

    s = _scene("suzanne_a01.yaml", "rousiers", {"internal_bounces": 1}, size=32)
    out = tr.render([s.replace(passes={"matte": {}}),
                     s.replace(passes={"matte": {}}, material=tr.Material(roughness=0.02))])
    pyr = sg_pyramid_for(OTHER)

    def close(a, b):
        rel = (a - b).abs().amax(-1) / b.amax(-1).clamp(min=1e-6)
        return float(rel.max()) <= 1e-6

    for env in (OTHER, pyr, s.envmap.path):
        for rot, sc in ((torch.tensor([10.0, -200.0]), torch.tensor([1.0, 0.3])),
                        (33.0, 2.0), (torch.tensor([10.0, -200.0]), 1.0)):
            assert close(tr.relight(out, env, rot, sc), relight_reference(out, env, rot, sc))
    m = from_passes(out.passes)
    before = tr.relight(m, OTHER, 5.0)
    assert prepare(m) is prepare(m)  # kept
    m.weight.mul_(2.0)  # in place: prepared again
    assert torch.allclose(tr.relight(m, OTHER, 5.0) - m.lights, 2 * (before - m.lights),
                          rtol=1e-5, atol=1e-6)

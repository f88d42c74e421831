"""The environment matte (torchrefract.matte): every lookup recorded with its weight, so a
relit image with the render's own map equals the render (issue #27, part 1)."""

from __future__ import annotations

import pytest
import torch

import torchrefract as tr
from torchrefract.matte.matte import PLAIN, from_passes
from torchrefract.matte.relight import relight

from conftest import ROOT, SH_SMALL

TENSOR = tr.RenderSettings(fused=False, adaptive=False)  # the matte's own render


def _scene(name="sphere_a03.yaml", size=32, **changes):
    s = tr.load_scene(ROOT / "configs" / "suite" / name)
    cam = tr.Camera(**{**s.camera.__dict__, "width": size, "height": size,
                       "samples_per_pixel": changes.pop("spp", 1)})
    return s.replace(camera=cam, **changes)


def _max_rel(a, b, mask):
    rel = (a - b).abs().amax(-1) / b.amax(-1).clamp(min=1e-6)
    return float(rel[mask].max())


CASES = [
    ("sphere_a03.yaml", "specular", {}),
    ("sphere_a03.yaml", "specular", {"internal_bounces": 2, "tir": "clamp"}),
    ("sphere_a03.yaml", "prefiltered", {"tir": "reflect"}),
    ("sphere_a03.yaml", "rousiers", {}),
    ("sphere_ior24_a01.yaml", "rousiers", {"internal_bounces": "auto", "bounce_rays": 4}),
    ("sphere_ior24_a01.yaml", "rousiers", {"tir": "reflect"}),
    ("globe_2rough.yaml", "rousiers", {"internal_bounces": 1}),  # roughness map
    ("slab_light.yaml", "rousiers", {"internal_bounces": 2}),  # sphere light
    ("slab_light.yaml", "specular", {}),
    ("sphere_a03.yaml", "lean", {}),
    ("sphere_a03.yaml", "gsr", {"internal_bounces": 1}),
    # sh at a table that takes about a second (200 directions per sample)
    ("sphere_a03.yaml", "sh", SH_SMALL),
]


@pytest.mark.parametrize("name,method,opts", CASES)
def test_same_map_relight_equals_render(one_thread, name, method, opts):
    """Same map, rotation and scale: the relit image equals the direct render (tensor code)
    to <= 1e-4 relative on object pixels (measured ~3e-7), with absorption where set."""
    mat = {}
    if "slab" in name:
        mat = {"material": tr.Material(ior=1.5, roughness=0.2, absorption=(0.4, 0.1, 0.0))}
    s = _scene(name, method=method, method_options=opts, **mat)
    out = tr.render(s.replace(passes={"matte": {"lobes": 32}}))  # room for every lookup
    direct = tr.render(s, settings=TENSOR)
    assert torch.equal(out.radiance, direct.radiance)  # recording changes nothing
    m = from_passes(out.passes)
    assert float(m.folded.max()) == 0.0
    img = relight(m, s.envmap.path, s.envmap.rotate_deg, s.envmap.scale)
    obj = out.coverage > 0.999
    assert obj.sum() > 50
    assert _max_rel(img, direct.radiance, obj) <= 1e-4
    assert _max_rel(img, direct.radiance, torch.ones_like(obj)) <= 1e-4  # background too
    for t in out.passes.values():
        assert bool(torch.isfinite(t).all())
    if "light" in name:
        assert float(m.lights.amax()) > 0.1  # the light seen through the slab
    else:
        assert float(m.lights.abs().amax()) == 0.0


def test_default_render_close(one_thread):
    """Against the default (fused kernel) render: float32 rounding of another code path."""
    s = _scene(method="rousiers")
    out = tr.render(s.replace(passes={"matte": {}}))
    img = relight(out, s.envmap.path, s.envmap.rotate_deg, s.envmap.scale)
    fused = tr.render(s, settings=tr.RenderSettings(adaptive=False))  # every pixel shaded
    assert _max_rel(img, fused.radiance, out.coverage > 0.999) <= 1e-3


def test_lobes_and_folding(one_thread):
    """Lobes are sorted by energy, weights are Fresnel-sized (the front reflection of
    smooth glass at normal incidence: ~0.04), and folding keeps the total weight."""
    s = _scene("sphere_a0.yaml", method="specular", method_options={"internal_bounces": 2})
    full = from_passes(tr.render(s.replace(passes={"matte": {"lobes": 8}})).passes)
    one = from_passes(tr.render(s.replace(passes={"matte": {"lobes": 1}})).passes)
    e = full.weight.mean(-1)  # (B, H, W, L)
    assert bool((e[..., :-1] >= e[..., 1:] - 1e-7).all())
    assert torch.allclose(one.weight.sum(-2), full.weight.sum(-2), atol=1e-5)
    center = full.weight[0, 16, 16]
    assert 0.03 < float(center[1].mean()) < 0.05  # second lobe: the front reflection
    assert float(one.folded.max()) > 0.01 and float(full.folded.max()) == 0.0
    # smooth glass in this map, no absorption: the weights of a pixel sum to ~1
    tot = full.weight.sum(-2).mean(-1)[0, 8:24, 8:24]
    assert float((tot - 1).abs().max()) < 0.02
    assert bool(((full.sharpness == PLAIN) | (full.sharpness == 0)).all())


def test_supersampled_merge(one_thread):
    """2x2 sampling with more lookups than lobes: siblings merged (recorded), else exact."""
    s = _scene("sphere_a03.yaml", size=24, spp=2, method="rousiers")
    out = tr.render(s.replace(passes={"matte": {"lobes": 8}}))
    m = from_passes(out.passes)
    img = relight(m, s.envmap.path, s.envmap.rotate_deg, s.envmap.scale)
    assert float(m.merged.max()) == 0.0
    assert _max_rel(img, out.radiance, out.coverage > 0.999) <= 1e-4
    small = from_passes(tr.render(s.replace(passes={"matte": {"lobes": 2}})).passes)
    assert float(small.merged.max()) > 0.5
    img2 = relight(small, s.envmap.path, s.envmap.rotate_deg, s.envmap.scale)
    obj = out.coverage > 0.999
    err = ((img2 - out.radiance).abs().mean(-1) / out.radiance.mean(-1).clamp(min=1e-3))[obj]
    assert float(err.mean()) < 0.05


def test_exr_and_dataset_roundtrip(one_thread, tmp_path):
    """The matte's EXR channels (documented names) decode back into the same lobes."""
    from torchrefract.dataset.loaders import decode_exr
    from torchrefract.output.export import save_render
    from torchrefract.output.images import read_exr

    s = _scene(size=24, method="prefiltered", passes={"matte": {"lobes": 3}}).replace(name="m")
    out = tr.render(s)
    paths = save_render(out, 0, tmp_path)
    ch = read_exr(paths["exr"])
    for c in ("matte.lobe0.direction.X", "matte.lobe2.sharpness", "matte.lobe1.weight.Z",
              "matte.lights.Y", "matte.folded", "matte.merged"):
        assert c in ch
    sample = decode_exr(paths["exr"])  # the loaders' tensors, channels first
    m = from_passes(sample["passes"], layout="chw")
    assert m.weight.shape == (1, 24, 24, 3, 3)
    img = relight(m, s.envmap.path, s.envmap.rotate_deg, s.envmap.scale)
    assert torch.allclose(img[0], out.radiance[0], rtol=1e-5, atol=1e-6)


def test_cli_passes(tmp_path):
    from torchrefract.cli import main
    from torchrefract.output.images import read_exr

    from conftest import small_scene_yaml

    path = small_scene_yaml(tmp_path, method="specular")
    assert main(["render", str(path), "--out", str(tmp_path / "o"), "--quiet",
                 "--passes", "matte,flow"]) == 0
    ch = read_exr(tmp_path / "o" / "small.exr")
    assert "matte.lobe7.weight.X" in ch and "flow.X" in ch and "flow_cov.Z" in ch
    assert main(["render", str(path), "--out", str(tmp_path / "o"), "--quiet",
                 "--passes", "mate"]) == 2


def test_errors():
    s = _scene(size=16)
    with pytest.raises(tr.ConfigError, match="policy 'auto'"):
        tr.render(s.replace(method="auto", passes={"matte": {}}))
    with pytest.raises(tr.ConfigError, match="'reference' has no environment matte"):
        tr.render(s.replace(method="reference", passes={"matte": {}}))
    with pytest.raises(tr.ConfigError, match="env_lookup"):
        tr.render(s.replace(method="lean", method_options={"env_lookup": "mip"},
                            passes={"matte": {}}))
    with pytest.raises(tr.ConfigError, match="unknown pass 'mat'"):
        tr.scene_from_dict({**s.to_dict(), "passes": ["mat"]})
    with pytest.raises(tr.ConfigError, match="passes.matte.lobes"):
        tr.scene_from_dict({**s.to_dict(), "passes": {"matte": {"lobes": 0}}})
    with pytest.raises(tr.ConfigError, match="passes.flow.distance"):
        tr.scene_from_dict({**s.to_dict(), "passes": {"flow": {"distance": -1}}})
    ok = tr.scene_from_dict({**s.to_dict(), "passes": ["matte"]})
    assert ok.passes == {"matte": {"lobes": 8}}
    with pytest.raises(tr.ConfigError, match="same passes"):
        tr.render([s, s.replace(passes={"matte": {}})])
    with pytest.raises(tr.ConfigError, match="no matte passes"):
        relight(tr.render(s), s.envmap.path)

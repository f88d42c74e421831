"""``RenderSettings.device``: where the shading runs (torchrefract/placement.py).

On a machine without CUDA these check the setting's validation, that every tensor of a
render's inputs moves as a whole, and that ``auto`` falls back to the CPU with the same
image. Where torch sees a GPU, the CUDA render is held to the CPU tensor code
(scripts/device_check.py runs the full comparison and the timings).
"""

from __future__ import annotations

import dataclasses

import pytest
import torch

import torchrefract as tr
from torchrefract.checks import ConfigError
from torchrefract.cli import _parser, _settings
from torchrefract.geometry.gbuffer import build_gbuffer
from torchrefract.geometry.mesh import load_mesh
from torchrefract.lighting.lights import Lighting
from torchrefract.methods import registry
from torchrefract.optics.materials import MaterialBatch
from torchrefract.placement import to_device

from conftest import ROOT

SCENE = ROOT / "configs" / "suite" / "sphere_a03.yaml"


def _small(path=SCENE, size=24, method="rousiers"):
    s = tr.load_scene(path)
    return s.replace(camera=dataclasses.replace(s.camera, width=size, height=size,
                                                samples_per_pixel=1), method=method)


@pytest.mark.parametrize("bad", ["gpu", "cuda:x", "", "CUDA", 0])
def test_device_setting_rejects_unknown_values(bad):
    with pytest.raises(ConfigError, match="RenderSettings.device"):
        tr.RenderSettings(device=bad)


@pytest.mark.skipif(torch.cuda.is_available(), reason="a GPU is present")
def test_cuda_without_a_gpu_is_a_clear_error_before_any_work():
    with pytest.raises(ConfigError, match="'cuda' asked for, but torch .* sees 0 CUDA"):
        tr.render(_small(), settings=tr.RenderSettings(device="cuda"))


def test_auto_device_on_this_machine_gives_the_default_image():
    s = _small()
    want = "cuda" if torch.cuda.is_available() else "cpu"
    a = tr.render(s, settings=tr.RenderSettings(device="auto"))
    assert a.radiance.device.type == want
    if want == "cpu":
        b = tr.render(s)
        assert torch.equal(a.radiance, b.radiance)


def test_environment_and_cli_set_the_device(monkeypatch):
    monkeypatch.setenv("TORCHREFRACT_DEVICE", "auto")
    assert tr.RenderSettings.from_env().device == "auto"
    args = _parser().parse_args(["render", str(SCENE), "--out", "x", "--device", "cuda:1"])
    assert _settings(args).device == "cuda:1"


def test_inputs_move_as_a_whole():
    """Every tensor of the G-buffer, lighting and materials reaches the device (meta: no
    data needed), nested dataclasses and tuples included; other values are kept."""
    s = _small()
    g = build_gbuffer([load_mesh(s.mesh, s.transform)], [s.camera])
    lighting, materials = Lighting.from_scenes([s]), MaterialBatch.from_scenes([s])
    meta = torch.device("meta")
    moved = to_device((g, lighting, materials), meta)

    def tensors(x):
        if isinstance(x, torch.Tensor):
            yield x
        elif isinstance(x, (tuple, list)):
            for v in x:
                yield from tensors(v)
        elif dataclasses.is_dataclass(x):
            for f in dataclasses.fields(x):
                yield from tensors(getattr(x, f.name))

    before, after = list(tensors((g, lighting, materials))), list(tensors(moved))
    assert len(before) == len(after) > 20
    assert all(t.device == meta for t in after)
    assert all(a.shape == b.shape and a.dtype == b.dtype for a, b in zip(before, after))
    assert moved[0].supersample == g.supersample and moved[1].paths == lighting.paths
    assert moved[2].distribution == materials.distribution


def test_cpu_only_methods_are_declared():
    assert registry.get("reference").devices == ("cpu",)
    for name in ("specular", "prefiltered", "rousiers", "lean", "gsr"):
        assert "cuda" in registry.get(name).devices, name


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")
@pytest.mark.parametrize("method,opts", [("specular", {}), ("rousiers", {}),
                                         ("rousiers", {"internal_bounces": 2}), ("gsr", {})])
def test_cuda_render_matches_the_cpu_tensor_code(method, opts):
    s = _small(size=48, method=method).replace(method_options=opts)
    a = tr.render(s, settings=tr.RenderSettings(fused=False))
    b = tr.render(s, settings=tr.RenderSettings(device="cuda"))
    assert b.radiance.is_cuda and torch.isfinite(b.radiance).all()
    obj = a.coverage > 0
    rel = (a.radiance[obj] - b.radiance.cpu()[obj]).abs() / a.radiance[obj].abs().clamp(min=1e-3)
    assert float((rel > 1e-4).float().mean()) <= 1e-3

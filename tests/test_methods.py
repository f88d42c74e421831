"""The method interface and registry: methods found by name without importing them, a
third-party method registered (in the process, or by an entry point) and rendered through
the CLI, planned methods, and the one options parser every method uses."""

from __future__ import annotations

import dataclasses
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import SH_SMALL, small_scene_yaml

import torchrefract as tr
from torchrefract.checks import ConfigError
from torchrefract.cli import main
from torchrefract.methods import registry
from torchrefract.methods.base import Planned
from torchrefract.methods.prefiltered import PrefilteredOptions
from torchrefract.methods.rousiers import RousiersOptions
from torchrefract.options import option_keys, options_dict, parse_options
from torchrefract.output.images import read_exr
from torchrefract.settings import using

TESTS = Path(__file__).resolve().parent


def _scene_yaml(tmp_path: Path, stem: str = "plug", **changes) -> Path:
    return small_scene_yaml(tmp_path, stem, **changes)


def test_loading_a_scene_imports_no_method():
    """The scene loader checks names through the registry, which imports a method's module
    only when its options are parsed or it renders."""
    code = ("import sys, torchrefract.scene as s; "
            "bad = [m for m in sys.modules if m.startswith('torchrefract.methods.') "
            "and m not in ('torchrefract.methods.registry',)]; "
            "print(bad); assert not bad")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                       timeout=120)
    assert r.returncode == 0, r.stdout + r.stderr


def test_registry_names_and_errors():
    names = registry.method_names()
    for n in ("specular", "prefiltered", "rousiers", "reference", "lean", "gsr", "sh", "auto"):
        assert n in names
    assert registry.get("rousiers").Options is RousiersOptions
    assert registry.is_policy("auto") and not registry.is_policy("rousiers")
    with pytest.raises(ConfigError, match=r"unknown method 'magic'.*rousiers"):
        registry.get("magic")
    with pytest.raises(ConfigError, match="identifier"):
        tr.register_method("not a name", object())
    with pytest.raises(ConfigError, match="policy"):
        tr.register_method("auto", object())


def test_planned_methods_load_and_raise_on_render(tmp_path):
    """A method of the design that is not built yet (``Planned``; every seed method is
    built now): its scenes load with any options, rendering names its issue."""
    name = "planned_y"
    tr.register_method(name, Planned(name, "issue #0"))
    scene = tr.load_scene(_scene_yaml(tmp_path, method=name, method_options={"k": 4}))
    assert scene.method == name
    with pytest.raises(NotImplementedError, match=rf"'{name}' is not implemented yet.*issue"):
        tr.render(scene)


def test_registered_method_renders_through_the_cli(tmp_path):
    """A method from the test folder, registered in the process: YAML, options, the CLI and
    the Python API all reach it; its image is what it shades."""
    sys.path.insert(0, str(TESTS))
    try:
        tr.register_method("flat", "plugin_method:METHOD")
        path = _scene_yaml(tmp_path, method="flat", method_options={"gray": 0.5})
        with pytest.raises(ConfigError, match=r"method_options\.gray.*<= 1"):
            tr.load_scene(_scene_yaml(tmp_path, "bad", method="flat",
                                      method_options={"gray": 2}))
        assert main(["render", str(path), "--out", str(tmp_path / "o"), "--quiet"]) == 0
        ch = read_exr(tmp_path / "o" / "plug.exr")
        obj = ch["A"] == 1
        assert obj.sum() > 100
        for c in "RGB":
            assert np.all(ch[c][obj] == 0.5)
        assert ch["flat"][obj].min() == 1.0  # the method's own pass is written
        out = tr.render(tr.load_scene(path))
        assert float(out.radiance[0][out.coverage[0] == 1].max()) == 0.5
    finally:
        registry._registered.pop("flat", None)
        registry._loaded.pop("flat", None)
        sys.path.remove(str(TESTS))


def test_registration_and_a_methods_output_are_checked(tmp_path):
    """``register_method`` refuses what cannot be a method, warns where a built-in name is
    taken, names the method when its module cannot be loaded; a method whose ``shade``
    returns the wrong shapes fails naming it (not deep in the box filter)."""
    import warnings

    from plugin_method import Flat
    from torchrefract.methods.base import Shaded

    scene = tr.load_scene(_scene_yaml(tmp_path))
    for bad in (42, "no_colon", "module:"):
        with pytest.raises(ConfigError, match="register_method"):
            tr.register_method("broken", bad)

    class Wide(Flat):
        name = "wide"

        def shade(self, g, lighting, materials, options, state):
            out = super().shade(g, lighting, materials, options, state)
            return Shaded(torch.cat([out.radiance, out.radiance[..., :1]], -1), {})

    try:
        tr.register_method("missing", "no_such_module_here:METHOD")
        with pytest.raises(ConfigError, match=r"method 'missing': cannot load.*ModuleNotFound"):
            tr.render(scene, method="missing")
        tr.register_method("wide", Wide())
        for spp in (1, 2):
            cam = dataclasses.replace(scene.camera, samples_per_pixel=spp)
            with pytest.raises(ConfigError, match=r"method 'wide': shade\(\) returned "
                                                  r"radiance of shape .*, 4\), expected"):
                tr.render(scene.replace(camera=cam), method="wide")
        with warnings.catch_warnings(record=True) as seen:
            warnings.simplefilter("always")
            tr.register_method("specular", Flat())
        assert any("replaces the built-in method" in str(w.message) for w in seen)
    finally:
        for name in ("missing", "wide", "specular"):
            registry._registered.pop(name, None)
            registry._loaded.pop(name, None)


def test_entry_point_method_renders_through_the_cli(tmp_path):
    """The same method declared by an installed distribution's entry point
    (``[torchrefract.methods] flat = plugin_method:METHOD``), in a fresh process."""
    site = tmp_path / "site"
    dist = site / "flatplugin-0.1.dist-info"
    dist.mkdir(parents=True)
    (dist / "METADATA").write_text("Metadata-Version: 2.1\nName: flatplugin\nVersion: 0.1\n")
    (dist / "entry_points.txt").write_text("[torchrefract.methods]\nflat = plugin_method:METHOD\n")
    path = _scene_yaml(tmp_path, method="flat", method_options={"gray": 0.125})
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(site), str(TESTS),
                                                       os.environ.get("PYTHONPATH", "")]))
    r = subprocess.run([sys.executable, "-m", "torchrefract.cli", "render", str(path),
                        "--out", str(tmp_path / "o"), "--quiet"], capture_output=True,
                       text=True, timeout=180, env=env)
    assert r.returncode == 0, r.stdout + r.stderr
    ch = read_exr(tmp_path / "o" / "plug.exr")
    assert np.all(ch["G"][ch["A"] == 1] == 0.125)


def test_one_parser_for_every_method():
    o = parse_options(RousiersOptions, {"internal_bounces": "auto", "tir": "clamp",
                                        "bounce_rays": 4}, "s.yaml", "rousiers")
    assert o.tir == "clamp" and o.bounces.internal_bounces == "auto"
    assert o.bounces.bounce_rays == 4
    assert parse_options(RousiersOptions, options_dict(o)) == o  # round trip
    for bad, frag in (({"bounce_rays": 3}, r"bounce_rays: expected 1 or 4, got 3"),
                      ({"bounce_rays": True}, "bounce_rays"),
                      ({"internal_bounces": "many"}, r"integer >= 0 or 'auto'"),
                      ({"march_steps": 1.5}, r"march_steps: expected an integer"),
                      ({"spread": "wide"}, r"spread: expected one of"),
                      ({"roughness_levels": 1}, r">= 2")):
        with pytest.raises(ConfigError, match=r"s\.yaml: method_options\." + frag.split(":")[0]
                           if ":" in frag else frag):
            parse_options(RousiersOptions, bad, "s.yaml", "rousiers")
    # prefiltered follows no internal reflections: those keys are unknown to it
    prefiltered = registry.get("prefiltered")
    assert prefiltered.parse({"tir": "clamp"}) == PrefilteredOptions(tir="clamp")
    with pytest.raises(ConfigError, match="unknown key 'internal_bounces' for method "
                                          "'prefiltered'"):
        prefiltered.parse({"internal_bounces": 1})
    with pytest.raises(ConfigError, match="unknown key 'bounce_rays' for method 'specular'"):
        registry.get("specular").parse({"bounce_rays": 4})


def test_every_option_has_a_checked_default():
    """Each field is declared once, with its default and its check: the parsed empty mapping
    is the dataclass's default, and every key is documented by the dataclass."""
    for name in ("specular", "prefiltered", "rousiers", "reference", "auto"):
        m = registry.get(name)
        assert m.parse({}) == m.Options()
        for f in dataclasses.fields(m.Options):
            assert "option" in f.metadata or "nested" in f.metadata, (name, f.name)
        assert len(set(option_keys(m.Options))) == len(option_keys(m.Options))


def _zero_off_object_cases():
    bounce = {"internal_bounces": 2}
    return [("specular", {}), ("specular", bounce), ("prefiltered", {}),
            ("rousiers", {}), ("rousiers", bounce), ("lean", bounce), ("gsr", {}),
            ("sh", SH_SMALL)]


@pytest.mark.parametrize("method,options", _zero_off_object_cases())
def test_method_passes_are_zero_off_the_object(method, options, tmp_path):
    """``Shaded.passes`` is 0 at every (sub-)pixel that is not the object's, on the fused
    and the tensor path, with and without adaptive shading: ``result.finish_pass`` hands a
    one-sample pass out without masking it. The view sees the background around the cow
    (and through no hole), so the test could fail on any pass that leaks."""
    if method == "sh":
        pytest.importorskip("embreex")
    scene = tr.load_scene(small_scene_yaml(tmp_path, "passes"))
    scene = scene.replace(method=method, method_options=options)
    seen = 0
    for settings in (tr.RenderSettings(), tr.RenderSettings(fused=False),
                     tr.RenderSettings(adaptive=False)):
        with using(settings):
            out = tr.render([scene])
        mask = out.coverage[0] == 0  # no object sub-pixel (one sample: the pixel)
        assert bool(mask.any()) and bool((~mask).any())
        for name, v in out.passes.items():
            if name in ("roughness", "ior", "thickness") or name.startswith(("depth_", "normal_")):
                continue  # the geometry passes, masked by the G-buffer's own layers
            seen += 1
            assert (v[0][mask] == 0).all(), (name, settings)
    assert seen >= 3 * 2, method

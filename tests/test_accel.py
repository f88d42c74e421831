"""The compiled march (``torchrefract.kernels.compiled``, torch.compile) gives the eager images exactly,
and falls back to eager with a warning where compiling fails."""

from __future__ import annotations

import os

import pytest
import torch
from conftest import ASSETS

import torchrefract as tr
from torchrefract.kernels import compiled as accel
from torchrefract.settings import using

SUZANNE = str(ASSETS / "meshes" / "suzanne.ply")
ENV = str(ASSETS / "envmaps" / "lebombo.exr")


COMPILED = tr.RenderSettings(compile=True, native=False)
"""Compiling on, the native march off (where it is on it replaces the compiled search)."""


@pytest.fixture
def compiled():
    """Compiling on for one test (its settings end with it whatever happens)."""
    with using(COMPILED):
        yield


def _scenes(**options):
    # suzanne (non-convex: exits in both layers, rays lost at the silhouette), two views
    return [tr.Scene(mesh=SUZANNE, envmap=tr.EnvMap(path=ENV, rotate_deg=r),
                     material=tr.Material(ior=1.5, roughness=a),
                     camera=tr.Camera(eye=(0.4, 0.3, 3.0), width=40, height=32),
                     method_options=options)
            for r, a in ((0.0, 0.1), (40.0, 0.3))]


@pytest.mark.slow
@pytest.mark.parametrize("method, options", [
    ("rousiers", {}),  # marched axis and cone rays (back layer: 4 plane terms)
    ("specular", {"internal_bounces": 2}),  # march_inside (both layers: 8 plane terms)
])
def test_compiled_march_gives_the_eager_image(method, options, compiled):
    """Compiled, the coarse search runs every ray at every sample instead of compacting;
    the brackets, and so the exits and the image, must be the same bit for bit. (The first
    compiled call of a process costs tens of seconds on a cold inductor cache.)"""
    scenes = [s.replace(method=method) for s in _scenes(**options)]
    fast = tr.render(scenes)
    slow = tr.render(scenes, settings=COMPILED.replace(compile=False))
    assert slow.coverage.sum() > 300  # the object is in view
    assert torch.equal(fast.radiance, slow.radiance)
    for k in ("exit_found", "tir"):
        assert torch.equal(fast.passes[k], slow.passes[k]), k


def test_compile_failure_falls_back_to_eager_with_a_warning(monkeypatch, compiled):
    def broken_compile(fn, **_kwargs):
        def run(*_a, **_k):
            raise RuntimeError("InvalidCxxCompiler: no working C++ compiler found")
        return run

    monkeypatch.setattr(accel.torch, "compile", broken_compile)
    twice = accel.kernel(lambda x: 2 * x)
    x = torch.arange(3.0)
    with pytest.warns(RuntimeWarning, match="torch.compile of <lambda> failed.*InvalidCxx"):
        assert torch.equal(twice(x), 2 * x)
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")  # warned once: later calls stay eager quietly
        assert torch.equal(twice(x), 2 * x)


def test_compile_is_off_by_default_and_a_setting(monkeypatch):
    monkeypatch.delenv("TORCHREFRACT_COMPILE", raising=False)
    assert not accel.compile_enabled()
    with using(tr.RenderSettings(compile=True)):
        assert accel.compile_enabled()
    assert not accel.compile_enabled()
    monkeypatch.setenv("TORCHREFRACT_COMPILE", "1")  # the environment's default
    assert accel.compile_enabled()


def test_cli_compile_flag_is_a_setting_of_its_renders(monkeypatch):
    """``--compile`` goes into the run's RenderSettings (handed to worker processes with
    each batch), not into this process's environment."""
    from torchrefract.cli import _parser, _settings

    monkeypatch.setenv("TORCHREFRACT_COMPILE", "0")
    s = _settings(_parser().parse_args(["sweep", "x.yaml", "--out", "o", "--compile"]))
    assert s.compile and os.environ["TORCHREFRACT_COMPILE"] == "0"
    assert not accel.compile_enabled()

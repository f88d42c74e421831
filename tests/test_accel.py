"""The compiled march (``torchrefract.kernels.compiled``, torch.compile) gives the eager images exactly,
and falls back to eager with a warning where compiling fails."""

from __future__ import annotations

import os

import pytest
import torch
from conftest import ASSETS, render_invalid_scene

import torchrefract as tr
from torchrefract.kernels import compiled as accel

SUZANNE = str(ASSETS / "meshes" / "suzanne.ply")
ENV = str(ASSETS / "envmaps" / "lebombo.exr")


@pytest.fixture
def compiled():
    """Compiling on for one test, and off again after it whatever happens; the native
    march off meanwhile (where it is on it replaces the compiled search)."""
    accel.set_compile(True)
    tr.set_native(False)
    yield
    accel.set_compile(False)
    tr.set_native(True)


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
    accel.set_compile(False)
    slow = tr.render(scenes)
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


def test_compile_is_off_by_default_and_switchable():
    assert not accel.compile_enabled() or os.environ.get("TORCHREFRACT_COMPILE") == "1"
    tr.set_compile(True)
    assert accel.compile_enabled()
    tr.set_compile(False)
    assert not accel.compile_enabled()


def test_cli_compile_flag_sets_it_for_this_and_worker_processes(monkeypatch, tmp_path):
    """``--compile`` turns compiling on here and in the environment that worker processes
    inherit (a scene that fails validation stops the run before anything is compiled)."""
    monkeypatch.setenv("TORCHREFRACT_COMPILE", "0")
    try:
        assert render_invalid_scene(tmp_path, "--compile") == 1
        assert accel.compile_enabled()
        assert os.environ["TORCHREFRACT_COMPILE"] == "1"
    finally:
        accel.set_compile(False)

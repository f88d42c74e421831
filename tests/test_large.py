"""Frames too large for one G-buffer (torchrefract.large, issue #27): rendered in strips of
rows over the frame's marched layers, with the pixels of the whole render, bit for bit;
views the strips do not cover, or that do not fit even in strips of one pixel row, fail
before any work, naming their size and the budget."""

from __future__ import annotations

import dataclasses
import importlib

import pytest
import torch
from conftest import ROOT, SH_SMALL

import torchrefract as tr
from torchrefract import large, tiles
from torchrefract.kernels import native
from torchrefract.methods import registry
from torchrefract.settings import RenderSettings

render_mod = importlib.import_module("torchrefract.render")  # the module, not tr.render
SUITE = ROOT / "configs" / "suite"
needs_native = pytest.mark.skipif(not native.available(), reason="native kernels unavailable")


def _scene(name: str, size: tuple[int, int], spp: int, method: str | None = None,
           options: dict | None = None) -> tr.Scene:
    s = tr.load_scene(str(SUITE / f"{name}.yaml"))
    c = s.camera
    return s.replace(camera=tr.Camera(eye=c.eye, target=c.target, up=c.up,
                                      yfov_deg=c.yfov_deg, width=size[0], height=size[1],
                                      samples_per_pixel=spp),
                     method=method or s.method, method_options=options or {})


def _assert_same(a, b) -> None:
    assert torch.equal(a.radiance, b.radiance)
    assert torch.equal(a.coverage, b.coverage)
    assert sorted(a.passes) == sorted(b.passes)
    for k in a.passes:
        assert torch.equal(a.passes[k], b.passes[k]), k


@pytest.fixture
def strips(monkeypatch):
    """The strips each view is rendered in, as (first, last) sub-pixel rows; strips sized
    for 1 KiB per sub-pixel (several strips under a budget of whole megabytes)."""
    monkeypatch.setattr(large, "STRIP_BYTES", 1024)
    seen: list[tuple[int, int]] = []
    cut = large._strip_layers

    def spy(mesh, cam, n, batch, eye, fwd, r0, r1, front, back):
        if front and back:  # the shading's strips (not the ids' pass)
            seen.append((r0, r1))
        return cut(mesh, cam, n, batch, eye, fwd, r0, r1, front, back)

    monkeypatch.setattr(large, "_strip_layers", spy)
    return seen


@needs_native
@pytest.mark.parametrize("name,method,options,spp", [
    ("sphere_a03", "rousiers", {}, 2),
    ("bunny_a01", "rousiers", {}, 1),
    ("suzanne_a01", "specular", {}, 2),
    ("torus_a01", "prefiltered", {}, 1),
    ("suzanne_a01", "rousiers", {"internal_bounces": 2}, 1),
    ("wingnut_a01", "specular", {"internal_bounces": 2}, 2),
    ("teapot_a01", "sh", SH_SMALL, 2),
    ("globe_2rough", "sh", SH_SMALL, 1),  # a roughness map, read at the front hit
])
def test_strips_give_the_whole_render(strips, name, method, options, spp):
    """Under a budget below the view's G-buffer (tiles.fits_whole False) the render runs
    in strips (several here) and equals the unbounded render bit for bit: radiance,
    coverage and every pass, with the marches crossing strips (rays reach the back layer
    anywhere on the silhouette) and, with internal bounces, the front layer's ids too.
    Strips shade every pixel, adaptive shading on or off: the whole render's without it."""
    scene = _scene(name, (56, 48), spp, method, options)
    whole = tr.render(scene, settings=RenderSettings(adaptive=False))
    budget_mb = 65
    assert not tiles.fits_whole(scene.camera, budget_mb << 20)
    stripped = tr.render(scene, settings=RenderSettings(memory_budget_mb=budget_mb))
    assert len(strips) >= 3 and all((r1 - r0) % spp == 0 for r0, r1 in strips[:-1])
    assert strips[0][0] == 0 and strips[-1][1] == 48 * spp
    _assert_same(whole, stripped)


@needs_native
def test_strips_of_one_pixel_row_and_a_batch():
    """Strips of one pixel row each (the edge repair's neighbours from the strips around)
    and a batch of two views (each in its own strips): the whole render's pixels."""
    a = _scene("teapot_a01", (40, 32), 2)
    b = a.replace(material=dataclasses.replace(a.material, ior=1.3))
    whole = tr.render([a, b], settings=RenderSettings(adaptive=False))
    entry = registry.get("rousiers")
    out = large.render([a, b], entry, entry.parse({}, "t"), 1 << 30, rows=2)
    _assert_same(whole, out)
    with pytest.raises(tr.ConfigError, match="multiple of samples_per_pixel 2"):
        large.render([a], entry, entry.parse({}, "t"), 1 << 30, rows=3)


def test_a_view_the_strips_do_not_cover_fails_up_front(monkeypatch):
    """Outside the strips' scope (here the tensor code, ``fused=False``; a roughness map;
    ``lean``) a view larger than one G-buffer fails before any work, naming its size, the
    budget and why."""
    def no_work(*a, **k):
        raise AssertionError("work started")

    monkeypatch.setattr(render_mod, "load_mesh", no_work)
    monkeypatch.setattr(large, "load_mesh", no_work)
    scene = _scene("sphere_a03", (4096, 4096), 4)
    with pytest.raises(tr.ConfigError, match=(
            r"one 4096x4096 view at samples_per_pixel 4 \(268,435,456 sub-pixels\) needs "
            r"about .* GiB as one G-buffer, over the memory budget of 3\.5 GiB .* not here: "
            r"the fused kernels are off")):
        tr.render(scene, settings=RenderSettings(memory_budget_mb=3584, fused=False))
    with pytest.raises(tr.ConfigError, match=r"not here: method 'lean'"):
        tr.render(scene.replace(method="lean"),
                  settings=RenderSettings(memory_budget_mb=3584))
    globe = _scene("globe_2rough", (4096, 4096), 4)
    with pytest.raises(tr.ConfigError, match=r"not here: a roughness map"):
        tr.render(globe, settings=RenderSettings(memory_budget_mb=3584))


def test_each_method_says_when_it_renders_in_strips():
    """The strips ask the method (``Method.strips``, ``Method.marches_front``) rather than
    its name: the built-in ones that have strips are listed in the error, a method without
    them is refused by name, and a method's own reason reaches the user."""
    assert large.strip_methods() == ["specular", "prefiltered", "rousiers", "sh"]
    scene = _scene("sphere_a03", (64, 64), 1)
    lean = registry.get("lean")
    assert large.why_not([scene], lean, lean.parse({}, "t")).startswith(
        "method 'lean' (strips: specular, prefiltered, rousiers, sh only)")
    rous = registry.get("rousiers")
    assert large.why_not([scene], rous, rous.parse({}, "t")) is None
    assert not rous.marches_front(rous.parse({}, "t"))
    assert rous.marches_front(rous.parse({"internal_bounces": 2}, "t"))
    assert "spread: rays" in large.why_not([scene], rous, rous.parse({"spread": "paper"}, "t"))
    assert not registry.get("sh").marches_front(registry.get("sh").parse({}, "t"))


@needs_native
def test_a_view_that_does_not_fit_even_in_strips_fails_up_front(monkeypatch):
    """The issue's 4096x4096 view at 4x4 samples fits 3.5 GiB in strips; under 1 GiB its
    ids and output alone do not: the render fails before any work, naming the size and
    the budget."""
    def no_work(*a, **k):
        raise AssertionError("work started")

    monkeypatch.setattr(large, "load_mesh", no_work)
    scene = _scene("sphere_a03", (4096, 4096), 4)
    entry = registry.get("rousiers")
    opts = entry.parse({}, "t")
    assert large.check([scene], entry, opts, 3584 << 20) >= 4 * 16  # 16+ pixel rows
    with pytest.raises(tr.ConfigError, match=(
            r"one 4096x4096 view at samples_per_pixel 4 \(268,435,456 sub-pixels\) needs "
            r"about 2\.\d GiB even in strips of one pixel row .* over the memory budget of "
            r"1\.0 GiB")):
        tr.render(scene, settings=RenderSettings(memory_budget_mb=1024))


@needs_native
def test_a_batch_in_strips_counts_every_views_output(monkeypatch):
    """The views of a batch are rendered in strips one after another, but the result holds
    all their outputs: a budget that fits one 2048x2048 view at 4x4 samples in strips does
    not fit a batch of four, which fails up front saying so."""
    monkeypatch.setattr(large, "load_mesh", lambda *a, **k: pytest.fail("work started"))
    one = _scene("sphere_a03", (2048, 2048), 4)
    entry = registry.get("specular")
    opts = entry.parse({}, "t")
    budget = 1024 << 20
    assert large.check([one], entry, opts, budget) >= 4
    with pytest.raises(tr.ConfigError, match=(
            r"2048x2048 view at samples_per_pixel 4 \(67,108,864 sub-pixels\) in a batch of "
            r"4 \(their outputs held together; one alone: fits\) needs about .* over the "
            r"memory budget of 1\.0 GiB .* or in smaller batches")):
        large.check([one] * 4, entry, opts, budget)

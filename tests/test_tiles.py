"""Rendering in bounded memory (torchrefract.tiles, issue #27): a view too large for one
pass under the memory budget is shaded in tiles whose pixels are the untiled render's, bit
for bit; a view that cannot fit even in tiles fails before any work, naming its size and
the budget; sweeps and RenderStream batches keep to the same budget."""

from __future__ import annotations

import dataclasses
import importlib
import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import ROOT
from PIL import Image
from sweep_fixtures import small_sweep, write_config

import torchrefract as tr
from torchrefract import tiles
from torchrefract.dataset.loaders import RenderStream
from torchrefract.kernels import native
from torchrefract.settings import RenderSettings

render_mod = importlib.import_module("torchrefract.render")  # the module, not tr.render
# Tiles give the whole render's bits with the native kernels; the tensor code (no C
# compiler, TORCHREFRACT_NATIVE=0) rounds a tile's sums apart by ~3e-5.
bit_equal_tiles = pytest.mark.skipif(
    not native.available(),
    reason="tiles equal the whole render bit for bit only with the native kernels")
SUITE = ROOT / "configs" / "suite"
SMALL_TILE = 256
"""MIN_TILE in these tests: small frames still split into several tiles."""


@pytest.fixture
def counted(monkeypatch):
    """Small tiles allowed; the sizes of the tiled passes' pieces, as they are cut."""
    monkeypatch.setattr(tiles, "MIN_TILE", SMALL_TILE)
    seen: list[list[int]] = []
    split = tiles.split

    def spy(idx, size):
        parts = split(idx, size)
        seen.append([p.numel() for p in parts])
        assert max(seen[-1]) <= size and sum(seen[-1]) == idx.numel()
        return parts

    monkeypatch.setattr(tiles, "split", spy)
    return seen


def _scene(name: str, size: tuple[int, int], spp: int = 1, method: str | None = None,
           options: dict | None = None, **material) -> tr.Scene:
    s = tr.load_scene(str(SUITE / f"{name}.yaml"))
    c = s.camera
    s = s.replace(camera=tr.Camera(eye=c.eye, target=c.target, up=c.up, yfov_deg=c.yfov_deg,
                                   width=size[0], height=size[1], samples_per_pixel=spp),
                  method=method or s.method, method_options=options or {})
    return s.replace(material=dataclasses.replace(s.material, **material)) if material else s


def _tight_budget_mb(scene: tr.Scene) -> int:
    """A budget (MB) that leaves room for 1-2 MB of shading over the view's frame: tiles of
    512-1024 object sub-pixels."""
    c = scene.camera
    frame = c.width * c.height * c.samples_per_pixel ** 2
    return math.ceil(tiles.pass_bytes(frame, 0) / 2**20) + 1


def _assert_same(a: tr.RenderResult, b: tr.RenderResult) -> None:
    assert torch.equal(a.radiance, b.radiance), (a.radiance - b.radiance).abs().max()
    assert torch.equal(a.coverage, b.coverage)
    assert a.passes.keys() == b.passes.keys()
    for k in a.passes:
        assert torch.equal(a.passes[k], b.passes[k]), k
    assert a.scenes == b.scenes
    assert bool(torch.isfinite(b.radiance).all())


FULL = {"adaptive": False}  # every sub-pixel shaded: one tiled pass
CASES = [
    ("sphere_a03", "specular", {}, 1, FULL),
    ("sphere_a03", "prefiltered", {}, 1, FULL),
    ("sphere_a03", "rousiers", {}, 1, FULL),
    ("sphere_a03", "rousiers", {"internal_bounces": 2}, 1, FULL),
    ("sphere_a03", "specular", {"internal_bounces": 2}, 2, FULL),
    ("globe_2rough", "rousiers", {"internal_bounces": 2}, 1, FULL),
    ("globe_2rough", "rousiers", {}, 2, FULL),
    ("sphere_a03", "rousiers", {"internal_bounces": 2}, 1, {"fused": False, **FULL}),
    ("globe_2rough", "specular", {}, 1, {"fused": False, **FULL}),
    # the n x n plan (cone_rays: plane is not sparse: tests/test_subsamples.py tiles that)
    ("sphere_a03", "rousiers", {"cone_rays": "plane"}, 2, {"adaptive": True}),
    ("sphere_a03", "rousiers", {"internal_bounces": 2}, 1, {"adaptive": True}),
    ("sphere_a03", "rousiers", {}, 1, {"adaptive": True}),
    ("slab_light", "rousiers", {}, 1, FULL),
]


@pytest.mark.parametrize("name, method, options, spp, settings", CASES)
def test_tiles_give_the_untiled_pixels(counted, name, method, options, spp, settings):
    """Several tiles under a tight budget: radiance, coverage and every pass (the
    geometry's, the material's and the method's) equal the one-pass render exactly, with
    supersampling (box filter over sub-pixels of different tiles), internal bounces (marches
    through both layers), roughness maps (coverage mips), the fused kernels and the tensor
    code, adaptive sampling (supersampling, and the lattice's passes at one sample) and a
    sphere light."""
    # (adaptive at one sample: the lattice's first pass shades a small share of the
    # sphere, three levels' lattice at stride 8: a larger frame to tile)
    size = (64, 56) if spp > 1 and not settings.get("adaptive") else (128, 112)
    if spp == 1 and settings.get("adaptive"):
        size = (192, 168)
    scene = _scene(name, size, spp, method, options)
    whole = tr.render(scene, settings=RenderSettings(**settings))
    assert counted == []  # the default budget: one pass
    tiled = tr.render(scene, settings=RenderSettings(memory_budget_mb=_tight_budget_mb(scene),
                                                     **settings))
    if settings.get("adaptive"):  # the lattice's first pass shades a quarter or so:
        assert counted and len(counted[0]) >= 2, counted  # fewer tiles
    else:
        assert len(counted) == 1 and len(counted[0]) >= 3, counted
    _assert_same(whole, tiled)


def test_a_batch_in_chunks_of_tiled_views(counted):
    """Two views under a budget for one view's frame: a chunk per view, each in tiles; the
    batch equals its one-pass render."""
    base = _scene("sphere_a03", (96, 96), 1, "rousiers", {"internal_bounces": 1})
    turned = base.replace(envmap=dataclasses.replace(base.envmap, rotate_deg=150.0))
    whole = tr.render([base, turned], settings=RenderSettings(**FULL))
    budget_mb = _tight_budget_mb(base)
    assert [len(c) for c in render_mod._chunks([base, turned], budget_mb << 20)] == [1, 1]
    tiled = tr.render([base, turned], settings=RenderSettings(memory_budget_mb=budget_mb,
                                                              **FULL))
    assert len(counted) == 2 and all(len(c) >= 3 for c in counted), counted
    _assert_same(whole, tiled)


@bit_equal_tiles
def test_tiles_keep_the_passes_rough_switch(counted, tmp_path):
    """A roughness map whose range starts at 0 and that is smooth over a whole band of the
    image: the methods switch the rough interfaces on for a pass where any shaded
    sub-pixel is rough, so every tile also shades one rough sub-pixel (else the smooth
    band's tile would get the smooth interfaces: up to 0.15 apart on this scene)."""
    img = np.full((64, 128), 255, np.uint8)
    img[:32] = 0  # the upper half of the texture: alpha 0
    png = tmp_path / "half.png"
    Image.fromarray(img).save(png)
    for method in ("specular", "rousiers"):
        scene = _scene("globe_2rough", (96, 96), 1, method, roughness_map=str(png),
                       roughness_range=(0.0, 0.5))
        whole = tr.render(scene)
        tiled = tr.render(scene, settings=RenderSettings(
            memory_budget_mb=_tight_budget_mb(scene)))
        _assert_same(whole, tiled)
    assert all(len(c) >= 3 for c in counted), counted


def test_a_view_that_cannot_fit_even_in_tiles_fails_up_front(monkeypatch):
    """The issue's 4096x4096 view at 4x4 samples per pixel under a 3.5 GiB budget, with
    the tensor code (``fused=False``): its G-buffer alone (read whole by every tile) is over
    the budget and the strips of torchrefract.large need the fused kernels, so the render
    fails before loading anything, naming the size and the budget (tests/test_large.py:
    the fused kernels render it in strips)."""
    scene = _scene("sphere_a03", (4096, 4096), 4)

    def no_work(*a, **k):
        raise AssertionError("work started")

    monkeypatch.setattr(render_mod, "load_mesh", no_work)
    monkeypatch.setattr(render_mod, "build_gbuffer", no_work)
    need = tiles.size_text(tiles.pass_bytes(4096 * 4096 * 16, tiles.MIN_TILE), up=True)
    with pytest.raises(tr.ConfigError, match=(
            rf"one 4096x4096 view at samples_per_pixel 4 \(268,435,456 sub-pixels\) needs "
            rf"about {need} as one G-buffer, over the memory budget of 3\.5 GiB "
            rf"\(RenderSettings\.memory_budget_mb")):
        tr.render(scene, settings=RenderSettings(memory_budget_mb=3584, fused=False))


@bit_equal_tiles
def test_render_stream_batches_keep_to_the_budget(counted, tmp_path, monkeypatch):
    """A RenderStream (and so a sweep: both render through render()) under a budget that
    fits one 32x32 view per pass: every pass's estimate is within the budget, and the
    samples equal those of the unbounded stream."""
    cfg = write_config(tmp_path / "s.yaml", small_sweep())
    budget_mb = math.ceil(tiles.pass_bytes(32 * 32, 32 * 32) / 2**20)  # one view, not two
    passes: list[int] = []
    one_pass = render_mod._render_pass

    def spy(scenes, entry, options, budget, regions=None):
        c = scenes[0].camera
        frame = len(scenes) * c.width * c.height * c.samples_per_pixel ** 2
        out = one_pass(scenes, entry, options, budget, regions)
        shaded = min(int(out.coverage.sum() * c.samples_per_pixel ** 2),
                     tiles.tile_size(frame, budget))
        passes.append(tiles.pass_bytes(frame, shaded))
        assert budget == budget_mb << 20
        return out

    free = list(RenderStream(cfg, batch_size=4))
    monkeypatch.setattr(render_mod, "_render_pass", spy)
    bounded = list(RenderStream(cfg, batch_size=4,
                                settings=RenderSettings(memory_budget_mb=budget_mb)))
    assert len(passes) == 8 and max(passes) <= budget_mb << 20  # one view per pass
    assert [x["sample_id"] for x in free] == [x["sample_id"] for x in bounded]
    for a, b in zip(free, bounded):
        assert torch.equal(a["radiance"], b["radiance"])
        for k in a["passes"]:
            assert torch.equal(a["passes"][k], b["passes"][k]), k


def test_a_sweep_records_a_view_that_cannot_fit_as_failed(tmp_path):
    """A sweep whose views do not fit the budget even in tiles: each sample is recorded as
    failed with the reason (size and budget), and the run goes on."""
    from torchrefract.dataset.run import run_sweep

    d = small_sweep()
    d["base"]["camera"].update(width=2048, height=2048, samples_per_pixel=4)
    cfg = write_config(tmp_path / "big.yaml", d)
    out = tmp_path / "out"
    summary = run_sweep(cfg, out, batch_size=4, quiet=True,
                        settings=RenderSettings(memory_budget_mb=512))
    assert summary.ok == 0 and summary.failed == 8
    lines = [json.loads(x) for x in (out / "manifest.jsonl").read_text().splitlines()]
    reasons = {r.get("reason", r.get("error", "")) for r in lines if r["status"] == "failed"}
    assert len(reasons) == 1
    (reason,) = reasons
    assert "2048x2048 view at samples_per_pixel 4" in reason and "512 MB" in reason


def test_bad_budget_is_named():
    with pytest.raises(tr.ConfigError, match="memory_budget_mb: expected an integer >= 1"):
        RenderSettings(memory_budget_mb=0)
    with pytest.raises(tr.ConfigError, match="memory_budget_mb"):
        RenderSettings(memory_budget_mb=1.5)


@pytest.mark.skipif(not Path("/proc/meminfo").exists(), reason="Linux /proc only")
def test_memory_budget_reads_meminfo_once_per_max_age(monkeypatch):
    """Renders in quick succession share one reading of MemAvailable; an older one is read
    again (80% of it is the budget)."""
    import builtins  # noqa: PLC0415
    import time  # noqa: PLC0415

    reads, real_open, now = [], builtins.open, [1000.0]

    def counting(path, *args, **kwargs):
        if path == "/proc/meminfo":
            reads.append(path)
        return real_open(path, *args, **kwargs)

    monkeypatch.setattr(tiles._available, "last", None)
    monkeypatch.setattr(builtins, "open", counting)
    monkeypatch.setattr(time, "monotonic", lambda: now[0])
    first = tiles.memory_budget()
    now[0] += 0.5 * tiles.MEMINFO_MAX_AGE_S
    assert tiles.memory_budget() == first and len(reads) == 1
    now[0] += tiles.MEMINFO_MAX_AGE_S
    tiles.memory_budget()
    assert len(reads) == 2
    assert 0 < first <= 0.8 * tiles._available.last[1] + 1

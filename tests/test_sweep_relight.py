"""A sweep's relight mode (issue #27, part 2): samples that differ only in the environment
map render their view once with the matte and are relit from it; the files match direct
renders, the manifest marks them, a run resumes, and the files do not depend on the batch
plan."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from sweep_fixtures import PARK, STUDIO, base_scene, write_config

import torchrefract as tr
from torchrefract.checks import ConfigError
from torchrefract.dataset.run import run_sweep
from torchrefract.dataset.sweep import load_sweep
from torchrefract.output.images import read_exr
from torchrefract.truth.metrics import flip_map


def _config(relight: bool) -> dict:
    """2 maps x 2 rotations of one view at 32x32 (4 samples, one relight group)."""
    base = dict(base_scene(32), method="rousiers", method_options={"internal_bounces": 1},
                material={"ior": 1.5, "roughness": 0.15})
    cfg = {"name": "relit", "base": base, "sampling": {"mode": "grid", "seed": 1},
           "sweep": {"envmap": {"path": [STUDIO, PARK], "rotate_deg": [0.0, 130.0]}}}
    if relight:
        cfg["relight"] = True
    return cfg


def _manifest(out: Path) -> dict[str, dict]:
    rows = [json.loads(ln) for ln in (out / "manifest.jsonl").read_text().splitlines()]
    return {r["sample_id"]: r for r in rows}


def _rgb(ch: dict) -> np.ndarray:
    return np.stack([ch["R"], ch["G"], ch["B"]], -1)


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    root = tmp_path_factory.mktemp("relight")
    direct = root / "direct"
    relit = root / "relit"
    # the direct sweep shading every pixel, as the relit one's mattes do
    s = run_sweep(write_config(root / "direct.yaml", _config(False)), direct, quiet=True,
                  settings=tr.RenderSettings(adaptive=False))
    assert (s.ok, s.failed) == (4, 0)
    s = run_sweep(write_config(root / "relit.yaml", _config(True)), relit, quiet=True)
    assert (s.ok, s.failed) == (4, 0)
    assert json.loads((relit / "sweep.json").read_text())["adaptive"] is False
    return root, direct, relit


def test_relit_match_direct_and_are_marked(runs, one_thread):
    _, direct, relit = runs
    man = _manifest(relit)
    assert sorted(man) == ["000000", "000001", "000002", "000003"]
    # one relight group: sample 0 rendered (with the matte), the others relit from it
    assert "relit_from" not in man["000000"]
    assert [man[i].get("relit_from") for i in ("000001", "000002", "000003")] == ["000000"] * 3
    assert "relit_from" not in _manifest(direct)["000001"]
    for sid, rec in man.items():
        a, b = read_exr(relit / f"{sid}.exr"), read_exr(direct / f"{sid}.exr")
        assert sorted(a) == sorted(b)  # the same channels: no matte pass left in
        assert rec["channels"] == _manifest(direct)[sid]["channels"]
        obj = b["A"] > 0.999
        assert obj.sum() > 50
        fm = flip_map(_rgb(a), _rgb(b))
        assert float(fm[obj].mean()) <= 0.01
        # the default (fused) direct render against the tensor code's: float32 rounding
        rel = np.abs(_rgb(a) - _rgb(b)).max(-1) / np.maximum(_rgb(b).max(-1), 1e-4)
        assert float(rel.max()) <= 2e-3
        for name in a:  # coverage and passes are the view's: the same
            if name not in "RGB":
                np.testing.assert_allclose(a[name], b[name], rtol=1e-4, atol=1e-5)
        assert (relit / f"{sid}.png").is_file()


def test_resume_and_batch_plan(runs, tmp_path, one_thread):
    """Stopped after one sample and resumed, with another batch size: the same bytes (the
    source is the group's first sample of the sweep, rendered again where needed)."""
    root, _, relit = runs
    cfg = root / "relit.yaml"
    out = tmp_path / "resumed"
    s = run_sweep(cfg, out, quiet=True, limit=2, batch_size=1)
    assert s.ok == 2
    s = run_sweep(cfg, out, quiet=True, batch_size=1)
    assert (s.skipped, s.ok, s.failed) == (2, 2, 0)
    for sid in ("000000", "000001", "000002", "000003"):
        for ext in ("exr", "png"):
            assert (out / f"{sid}.{ext}").read_bytes() == (relit / f"{sid}.{ext}").read_bytes()
    assert _manifest(out)["000003"]["relit_from"] == "000000"


def test_config_key(tmp_path):
    assert load_sweep(write_config(tmp_path / "a.yaml", _config(True))).relight is True
    assert load_sweep(write_config(tmp_path / "b.yaml", _config(False))).relight is False
    bad = dict(_config(False), relight="yes")
    with pytest.raises(ConfigError, match="relight"):
        load_sweep(write_config(tmp_path / "c.yaml", bad))

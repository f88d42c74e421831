"""scripts/pareto.py: the speed-against-accuracy sweep, as a smoke run of every code path
(``--quick``, one suite scene at 24x24, truth at 16 spp in a temporary cache) with its CSV
rows, figures and metadata checked; the Pareto front and the option-rejection path alone."""

from __future__ import annotations

import csv
import importlib.util
import json
import math
import platform
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parent.parent
SCRIPT = ROOT / "scripts" / "pareto.py"


def _module():
    spec = importlib.util.spec_from_file_location("pareto_script", SCRIPT)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_pareto_front():
    p = _module()
    ms = np.array([10.0, 20.0, 5.0, 40.0, 30.0, 20.0])
    err = np.array([0.5, 0.3, 0.6, 0.1, 0.35, 0.4])
    # 5 ms / 0.6, 10 / 0.5, 20 / 0.3, 40 / 0.1; (30, 0.35) and (20, 0.4) are beaten.
    assert p.pareto_front(ms, err).tolist() == [2, 0, 1, 3]


def test_rejected_options_raise_config_error():
    import torchrefract as tr
    from torchrefract.checks import ConfigError

    p = _module()
    scene = p.sized(tr.load_scene(ROOT / "configs" / "suite" / "sphere_a03.yaml"), 16)
    with pytest.raises(ConfigError, match="no_such_option"):
        p.time_variant(scene, "rousiers", {"no_such_option": 1}, 1, 1)


def test_quick_run_writes_rows_and_figures(tmp_path):
    pytest.importorskip("mitsuba")
    pytest.importorskip("pyoidn")
    pytest.importorskip("matplotlib")
    out, truth = tmp_path / "pareto", tmp_path / "truth"
    r = subprocess.run([sys.executable, str(SCRIPT), "--quick", "--scenes", "sphere_a03",
                        "--size", "24", "--threads", "1", "--out", str(out),
                        "--truth-dir", str(truth)],
                       capture_output=True, text=True, cwd=ROOT, timeout=600)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    p = _module()
    with open(out / "results.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert tuple(rows[0]) == p.COLUMNS
    meta = json.loads((out / "meta.json").read_text())
    assert meta["heap_reuse"] is (platform.libc_ver()[0] == "glibc")  # on by default
    skipped = {s["variant"] for s in meta["skipped"]}
    variants = [r["variant"] for r in rows]
    expected = ["truth seed 1", "max_depth 3", "max_depth 4", "max_depth 5",
                *[v[0] for v in p.QUICK_VARIANTS if v[0] not in skipped]]
    assert variants == expected
    assert {"specular", "rousiers", "mitsuba 4spp oidn"} <= set(variants)
    for row in rows:
        assert row["scene"] == "sphere_a03" and row["width"] == row["height"] == "24"
        for k in p.METRICS:
            assert math.isfinite(float(row[k])) or k.startswith("psnr"), (row["variant"], k)
        assert 0.0 <= float(row["flip_object"]) <= 1.0
        assert int(row["threads"]) == 1 and row["machine"]
        timed = row["method"] not in ("truth", "floor")
        assert (float(row["ms_per_frame"]) > 0) if timed else row["ms_per_frame"] == ""
        json.loads(row["options"])
    by = {r["variant"]: r for r in rows}
    assert by["rousiers b2"]["batch"] == "2"
    assert by["rousiers b2"]["flip_object"] == by["rousiers"]["flip_object"]  # same frame 0
    # Denoising helps relMSE even against a 16-spp truth.
    assert float(by["mitsuba 1spp oidn"]["relmse_object"]) < float(
        by["mitsuba 1spp"]["relmse_object"])
    for name in ("pareto.png", "gallery.png"):
        assert (out / name).stat().st_size > 10_000
    assert len(list(truth.glob("sphere_a03_24x24_*.exr"))) == 5  # 2 seeds + 3 floors

    # --append: a second run adds its rows (a 1x1 variant: one sample per pixel) and keeps
    # the first run's; the auto table skips rows at another pixel sampling than the scene's.
    r = subprocess.run([sys.executable, str(SCRIPT), "--append", "--variants", "specular 1x1",
                        "--scenes", "sphere_a03", "--size", "24", "--threads", "1",
                        "--repeats", "1", "--truth-spp", "16", "--out", str(out),
                        "--truth-dir", str(truth)],
                       capture_output=True, text=True, cwd=ROOT, timeout=600)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    with open(out / "results.csv", newline="") as f:
        rows2 = list(csv.DictReader(f))
    assert [r["variant"] for r in rows2] == variants + ["specular 1x1"]
    one = rows2[-1]
    assert one["samples_per_pixel"] == "1" and json.loads(one["options"]) == {}
    assert one["flip_object"] != by["specular"]["flip_object"]  # another pixel sampling
    assert len(json.loads((out / "meta.json").read_text())["appended"]) == 1
    spec = importlib.util.spec_from_file_location(
        "build_auto_table", ROOT / "scripts" / "build_auto_table.py")
    bat = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bat)
    table = bat.build(out / "results.csv")
    names = {v["variant"] for s in table["scenes"] for v in s["variants"]}
    assert "specular" in names and "specular 1x1" not in names
    assert not {"auto"} & {v["method"] for s in table["scenes"] for v in s["variants"]}

    # --report redraws from the csv; --mean-panel adds the aggregate panel alone
    r = subprocess.run([sys.executable, str(SCRIPT), "--report", "--mean-panel", "held out",
                        "--out", str(out)], capture_output=True, text=True, cwd=ROOT,
                       timeout=600)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    assert (out / "mean_panel.png").stat().st_size > 10_000

"""scripts/bench.py: one row per fresh process, stage columns and peak memory in the JSON."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_bench_rows_report_stages_and_their_own_peak_memory(tmp_path):
    proc = subprocess.run(
        [sys.executable, str(ROOT / "scripts" / "bench.py"), "--methods", "specular",
         "rousiers:cone_rays=plane", "--sizes", "32", "--batches", "1", "2", "--repeats", "1",
         "--threads", "1", "--out", str(tmp_path)], capture_output=True, text=True,
        timeout=600)
    assert proc.returncode == 0, proc.stderr[-2000:]
    meta = json.loads((tmp_path / "bench.json").read_text())
    rows = meta["results"]
    assert [(r["method"], r["options"], r["batch"]) for r in rows] == [
        ("specular", {}, 1), ("specular", {}, 2), ("rousiers", {"cone_rays": "plane"}, 1),
        ("rousiers", {"cone_rays": "plane"}, 2)]
    for r in rows:
        st = r["ms_per_frame_stage"]
        assert st["march"] > 0 and st["mips"] == 0
        assert abs(st["shading"] - st["march"] - st["mips"] - st["shading_rest"]) < 1e-6
        assert 0 < st["gbuffer"] < r["ms_per_frame"]
        # a fresh process per row: its peak is above its own start, not the run's peak so far
        assert r["peak_rss_mb"] > r["baseline_rss_mb"] > 50
    assert meta["threads"] == 1

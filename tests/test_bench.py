"""scripts/bench.py: one row per fresh process, stage columns and peak memory in the JSON;
the Mitsuba rows and their ratios."""

from __future__ import annotations

import json
import math
import platform
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def test_bench_rows_report_stages_and_their_own_peak_memory(tmp_path):
    proc = subprocess.run(
        [sys.executable, str(ROOT / "scripts" / "bench.py"), "--methods", "specular",
         "rousiers:spread=paper", "--sizes", "32", "--batches", "1", "2", "--repeats", "1",
         "--threads", "1", "--views", "distinct", "shared", "--no-mitsuba", "--out",
         str(tmp_path)], capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-2000:]
    meta = json.loads((tmp_path / "bench.json").read_text())
    rows = meta["results"]
    paper = {"spread": "paper"}
    assert [(r["method"], r["options"], r["views"], r["batch"]) for r in rows] == [
        ("specular", {}, "distinct", 1), ("specular", {}, "distinct", 2),
        ("specular", {}, "shared", 2), ("rousiers", paper, "distinct", 1),
        ("rousiers", paper, "distinct", 2), ("rousiers", paper, "shared", 2)]
    on = platform.libc_ver()[0] == "glibc"  # on by default where the allocator is glibc's
    assert meta["heap_reuse"] is on and all(r["heap_reuse"] is on for r in rows)
    for r in rows:
        st = r["ms_per_frame_stage"]
        # a fused kernel marches inside its own stage; the tensor code's march is its own
        assert (st["fused"] > 0) != (st["march"] > 0)
        # rousiers' paper spread: the tensor code, with its NDF mips (eq. 11)
        assert (st["fused"] > 0) == (r["method"] == "specular") == (st["mips"] == 0)
        assert abs(st["shading"] - st["march"] - st["mips"] - st["fused"]
                   - st["shading_rest"]) < 1e-6
        assert 0 < st["gbuffer"] < r["ms_per_frame"]
        # a fresh process per row: its peak is above its own start, not the run's peak so far
        assert r["peak_rss_mb"] > r["baseline_rss_mb"] > 50
        assert isinstance(r["native"], bool)
    assert meta["threads"] == 1
    # --no-mitsuba: no Mitsuba rows, the comparison's Mitsuba cells empty
    assert meta["mitsuba"] == {"skipped": "--no-mitsuba", "rows": []}
    assert len(meta["vs_mitsuba"]) == len(rows)
    assert all(c["mitsuba_1spp_ms_per_frame"] is None and c["mitsuba_4spp_oidn_ratio"] is None
               for c in meta["vs_mitsuba"])


def test_bench_mitsuba_rows_time_the_same_scenes_and_give_ratios(tmp_path):
    """Mitsuba at 1 spp and at 4 spp + OIDN, in the bench's own process, on the run's scenes:
    positive finite times per frame, and ratios Mitsuba / ours that match them."""
    pytest.importorskip("mitsuba")
    pytest.importorskip("pyoidn")
    proc = subprocess.run(
        [sys.executable, str(ROOT / "scripts" / "bench.py"), "--methods", "specular",
         "--sizes", "32", "--batches", "2", "--repeats", "1", "--threads", "1",
         "--mitsuba", "--out", str(tmp_path)], capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "mi 4spp+oidn" in proc.stdout  # the second table
    meta = json.loads((tmp_path / "bench.json").read_text())
    (ours,) = meta["results"]  # the old keys are kept
    mits = meta["mitsuba"]
    assert mits["variant"].endswith("_rgb")  # the bridge's pick, recorded
    assert mits["threads"] == 1 and mits["oidn_threads"] == "1"  # --threads: theirs too
    assert [(m["spp"], m["denoise"], m["size"], m["views"], m["batch"]) for m in mits["rows"]] \
        == [(1, False, 32, "distinct", 2), (4, True, 32, "distinct", 2)]
    for m in mits["rows"]:
        assert m["variant"] == mits["variant"]
        for k in ("ms_per_frame", "render_ms_per_frame", "build_ms_per_frame"):
            assert math.isfinite(m[k]) and m[k] > 0, (k, m)
        assert math.isclose(m["ms_per_frame"], m["render_ms_per_frame"]
                            + m["denoise_ms_per_frame"], rel_tol=0.5)  # medians of sums
        assert (m["denoise_ms_per_frame"] > 0) is m["denoise"]
    (c,) = meta["vs_mitsuba"]
    assert (c["method"], c["size"], c["views"], c["batch"]) == ("specular", 32, "distinct", 2)
    assert c["ms_per_frame"] == ours["ms_per_frame"] > 0
    for key, m in zip(("mitsuba_1spp", "mitsuba_4spp_oidn"), mits["rows"]):
        assert c[f"{key}_ms_per_frame"] == m["ms_per_frame"]
        assert math.isfinite(c[f"{key}_ratio"]) and c[f"{key}_ratio"] > 0
        assert math.isclose(c[f"{key}_ratio"], m["ms_per_frame"] / ours["ms_per_frame"],
                            rel_tol=1e-12)


def test_bench_interleaved_rounds_time_every_row_the_same_number_of_times(tmp_path):
    """--interleave: our rows and Mitsuba's in one process, one render each per round; every
    row has the run's repeats, and the ratios are Mitsuba's over ours."""
    pytest.importorskip("mitsuba")
    proc = subprocess.run(
        [sys.executable, str(ROOT / "scripts" / "bench.py"), "--methods", "specular",
         "rousiers", "--sizes", "32", "--batches", "2", "--repeats", "2", "--threads", "1",
         "--interleave", "--out", str(tmp_path)], capture_output=True, text=True,
        timeout=600)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert proc.stderr.count("round ") == 2
    meta = json.loads((tmp_path / "bench.json").read_text())
    assert meta["interleaved"]
    assert [r["method"] for r in meta["results"]] == ["specular", "rousiers"]
    assert all(r["repeats"] == 2 and r["ms_per_frame"] > 0 for r in meta["results"])
    rows = meta["mitsuba"]["rows"]
    assert rows and all(m["repeats"] == 2 and m["ms_per_frame"] > 0 for m in rows)
    for c, ours in zip(meta["vs_mitsuba"], meta["results"]):
        assert math.isclose(c["mitsuba_1spp_ratio"],
                            rows[0]["ms_per_frame"] / ours["ms_per_frame"], rel_tol=1e-12)


def test_bench_distinct_views_orbit_the_target():
    """``--views distinct`` turns each batch item's camera around the target about its up
    vector: same distance and height, the requested angle apart."""
    import importlib.util
    import math

    import torchrefract as tr
    spec = importlib.util.spec_from_file_location("bench", ROOT / "scripts" / "bench.py")
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    cam = tr.Camera(eye=(0.5, 1.0, 4.0), target=(0.5, 0.2, 0.0), up=(0.0, 1.0, 0.0))
    turned = bench.orbit(cam, 30.0)
    a = [e - t for e, t in zip(cam.eye, cam.target)]
    b = [e - t for e, t in zip(turned.eye, turned.target)]
    assert math.isclose(b[1], a[1], abs_tol=1e-12)  # about the up axis
    assert math.isclose(math.hypot(b[0], b[2]), math.hypot(a[0], a[2]), rel_tol=1e-12)
    ang = math.degrees(math.atan2(b[0], b[2]) - math.atan2(a[0], a[2]))
    assert math.isclose(abs(ang), 30.0, rel_tol=1e-9)
    assert all(math.isclose(x, y, abs_tol=1e-12) for x, y in zip(bench.orbit(cam, 0.0).eye,
                                                                  cam.eye))


def test_bench_spp_rows_render_the_supersampled_grid(tmp_path):
    """``spp=N`` in a row's options is the camera's N x N grid, not a method option: the
    row's scenes have it, the JSON records it, the method's options do not; a bad value is
    refused naming the row."""
    import importlib.util

    import torchrefract as tr
    spec = importlib.util.spec_from_file_location("bench", ROOT / "scripts" / "bench.py")
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    base = tr.load_scene(str(ROOT / "configs" / "demo.yaml"))
    row = bench.OursRow(base, "rousiers:spp=2,march_steps=12+adaptive", 16, 2)
    assert row.spp == 2 and row.options == {"march_steps": 12} and row.adaptive
    assert all(s.camera.samples_per_pixel == 2 and s.method_options == {"march_steps": 12}
               for s in row.scenes)
    row.warm()
    row.once()
    r = row.result()
    assert r["spp"] == 2 and r["options"] == {"march_steps": 12} and r["ms_per_frame"] > 0
    plain = bench.OursRow(base, "rousiers", 16, 1)
    assert plain.spp == 1 and plain.scenes[0].camera.samples_per_pixel == 1
    with pytest.raises(ValueError, match="rousiers:spp=x"):
        bench.OursRow(base, "rousiers:spp=x", 16, 1)


def test_kernel_times_splits_a_frame_between_the_kernels_and_the_rest(tmp_path):
    """scripts/kernel_times.py: each native kernel's ms a frame (the G-buffer's and the
    method's among them), their sum and the time outside them within the frame's."""
    from torchrefract.kernels import native  # noqa: PLC0415

    if not native.available():
        pytest.skip("native kernels unavailable")
    out = tmp_path / "k.json"
    proc = subprocess.run(
        [sys.executable, str(ROOT / "scripts" / "kernel_times.py"),
         str(ROOT / "configs" / "demo.yaml"), "--method", "specular+adaptive", "--size", "32",
         "--batch", "2", "--repeats", "3", "--threads", "1", "--json", str(out)],
        capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-2000:]
    res = json.loads(out.read_text())
    k = res["kernels"]
    assert {"raster", "layer", "background"} <= set(k) and ({"specular", "lattice_shade"} & set(k))
    assert all(v >= 0 for v in k.values()) and list(k.values()) == sorted(k.values())[::-1]
    assert 0 < res["native"] <= res["total"] and res["other"] > 0
    assert "native kernels" in proc.stdout and "layer" in proc.stdout


def test_direction_fill_study_fills_nothing_at_a_negative_tolerance():
    """scripts/direction_fill.py: filling no pixel by directions shades every waiting one
    (the full render, FLIP 0); the radiance rule and "either" at that tolerance agree; a
    tolerance that fills shades fewer pixels than all, with a finite error."""
    sys.path.insert(0, str(ROOT / "scripts"))
    from direction_fill import study  # noqa: PLC0415

    rows = study(ROOT / "configs" / "suite" / "sphere_a03.yaml", 48,
                 [("radiance", 0.0), ("direction", -1.0), ("either", -1.0),
                  ("direction", 0.1)])
    rad, none, either, some = rows
    assert none["shaded"] == 1.0 and none["flip"] == 0.0
    assert 0 < rad["shaded"] < 1 and rad["flip"] > 0
    assert either["shaded"] == rad["shaded"] and either["flip"] == rad["flip"]
    assert 0 < some["shaded"] < 1 and 0 < some["flip"] < 0.1


def test_interleaved_rounds_turn_the_order_of_the_rows():
    """--interleave's rounds: every row once a round, and a different one of our rows right
    after Mitsuba's OIDN pass each round (turning the whole list kept our first row there
    every round)."""
    sys.path.insert(0, str(ROOT / "scripts"))
    from bench import round_order  # noqa: PLC0415

    ours = ["specular", "rousiers", "2 bounces", "specular 2x2", "rousiers 2x2", "sh"]
    theirs = ["mitsuba 1 spp", "mitsuba 4 spp + oidn"]
    rounds = [round_order(ours, theirs, k) for k in range(5)]
    assert all(sorted(r) == sorted(ours + theirs) for r in rounds)
    # as they run: the warm-ups (ours, then Mitsuba's), then round after round
    seq = ours + theirs + [row for r in rounds for row in r]
    after_oidn = [seq[i + 1] for i, row in enumerate(seq[:-1]) if row.endswith("oidn")]
    assert len(after_oidn) == 5 and len(set(after_oidn)) == 5  # a different row each round
    assert round_order([], theirs, 3) == theirs and round_order(ours, [], 2)[0] == "2 bounces"

"""scripts/validation_report.py (issue #26's figures) on a made-up chart: the means per
half, the best fixed variant and auto's three checks; and the chart's switches for the
validation set (no floors, cached truth only)."""

from __future__ import annotations

import csv
import importlib.util
import json
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent


def _script(name: str):
    spec = importlib.util.spec_from_file_location(name, ROOT / "scripts" / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    sys.path.insert(0, str(ROOT / "scripts"))
    spec.loader.exec_module(mod)
    return mod


def _chart(path: Path, rows: list[tuple[str, str, float, float]]) -> None:
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, ["scene", "method", "variant", "ms_per_frame", "flip_object"])
        w.writeheader()
        for scene, variant, flip, ms in rows:
            w.writerow({"scene": scene, "method": variant.split()[0], "variant": variant,
                        "ms_per_frame": ms, "flip_object": flip})
        w.writerow({"scene": "a", "method": "truth", "variant": "truth seed 1",
                    "ms_per_frame": "", "flip_object": 0.01})


def test_report_means_best_variant_and_auto_checks(tmp_path):
    rep = _script("validation_report")
    rows = []
    for scene, (r, r2, au) in {"a": (0.30, 0.20, 0.20), "b": (0.40, 0.30, 0.45),
                               "c": (0.50, 0.10, 0.11), "d": (0.20, 0.25, 0.21)}.items():
        rows += [(scene, "rousiers", r, 10.0), (scene, "rousiers ib2", r2, 20.0),
                 (scene, "auto", au, 15.0), (scene, "auto scene blend", 0.0, 15.0)]
    _chart(tmp_path / "results.csv", rows)
    splits = tmp_path / "splits.json"
    splits.write_text(json.dumps({"fit": ["a", "b"], "heldout": ["c", "d", "e"]}))
    out = tmp_path / "report.json"
    assert rep.main([str(tmp_path / "results.csv"), "--splits", str(splits),
                     "--json", str(out)]) == 0
    got = json.loads(out.read_text())
    fit, held = got["fit"], got["heldout"]
    assert fit["scenes"] == 2 and held["scenes"] == 2  # "e" has no rows
    assert fit["best_fixed"] == held["best_fixed"] == "rousiers ib2"
    assert abs(fit["means"]["auto"][0] - 0.325) < 1e-9
    # fit: auto's mean 0.075 above ib2's, scene b 0.15 above it and 0.05 above rousiers'
    assert fit["auto"]["worst_scene"] == "b" and abs(fit["auto"]["worst_gap"] - 0.15) < 1e-9
    assert fit["auto"]["worse_than_rousiers"] == ["b"]
    assert fit["auto"]["meets"] == {"mean": False, "every_scene": False, "rousiers": False}
    # held out: within 0.005 of ib2 (0.16 against 0.175), cheaper, never far off
    assert held["auto"]["meets"] == {"mean": True, "every_scene": True, "rousiers": True}


def test_chart_skips_scenes_without_cached_truth(tmp_path, capsys):
    pareto = _script("pareto")
    scene = ROOT / "configs" / "suite" / "sphere_a03.yaml"
    # nothing rendered (no truth there, none made): nothing measured
    assert pareto.main(["--scenes", str(scene), "--truth-dir", str(tmp_path / "none"),
                        "--no-floors", "--cached-truth-only", "--variants", "rousiers",
                        "--out", str(tmp_path / "chart"), "--size", "16"]) == 1
    assert "sphere_a03: no cached truth" in capsys.readouterr().out
    assert not (tmp_path / "none").exists() or not list((tmp_path / "none").iterdir())


def test_auto_rows_from_another_run_replace_the_charts(tmp_path):
    """``--auto``: auto's rows come from a second run (a new table), the fixed variants' from
    the first; a variant of the second run other than auto is ignored."""
    rep = _script("validation_report")
    old, new = [], []
    for scene in "abcd":
        old += [(scene, "rousiers", 0.30, 10.0), (scene, "rousiers ib2", 0.20, 20.0),
                (scene, "auto", 0.50, 15.0)]
        new += [(scene, "auto", 0.20, 18.0), (scene, "rousiers ib2", 0.90, 99.0)]
    _chart(tmp_path / "old.csv", old)
    _chart(tmp_path / "new.csv", new)
    splits = tmp_path / "splits.json"
    splits.write_text(json.dumps({"fit": ["a", "b"], "heldout": ["c", "d"]}))
    out = tmp_path / "report.json"
    assert rep.main([str(tmp_path / "old.csv"), "--auto", str(tmp_path / "new.csv"),
                     "--splits", str(splits), "--json", str(out)]) == 0
    held = json.loads(out.read_text())["heldout"]
    assert held["means"]["auto"] == [0.20, 18.0]
    assert held["means"]["rousiers ib2"] == [0.20, 20.0]  # the first run's, not 0.90
    assert held["auto"]["meets"] == {"mean": True, "every_scene": True, "rousiers": True}
    _chart(tmp_path / "none.csv", [("a", "rousiers", 0.3, 10.0)])
    with pytest.raises(SystemExit, match="no timed auto rows"):
        rep.main([str(tmp_path / "old.csv"), "--auto", str(tmp_path / "none.csv"),
                  "--splits", str(splits)])

"""Condense the speed/accuracy chart's measurements into the table method ``auto`` reads.

    .venv/bin/python scripts/build_auto_table.py [outputs/pareto/results.csv]
        [--out torchrefract/tables/auto_v1.json] [--metric flip_object] [--evaluate]
    .venv/bin/python scripts/build_auto_table.py --split fit \
        [outputs/validation_chart/results.csv] [--out torchrefract/tables/auto_v2.json]

Without ``--split``: the chart's suite scenes (``configs/suite/<scene>.yaml``). With
``--split fit`` (or ``heldout``): only the validation set's scenes of that half
(``configs/validation/splits.json``, scene files in ``configs/validation/``); every other row
of the CSV is left out, so the held-out half stays unseen. The shipped table
(``torchrefract.auto.DEFAULT_TABLE``) is the ``fit`` half's.

For every such scene in the CSV: its features (``torchrefract.auto.features`` of its scene
file) and, for each of our method variants measured at batch 1
(``specular``, ``prefiltered``, ``rousiers``, ``lean``, ``gsr``, with their options; not
Mitsuba, not ``auto`` itself, not ``sh``, whose precomputation the chart does not time), the
time per frame and the error. The table is small JSON and shipped with the package; rebuild it after a new ``scripts/pareto.py`` run on the target machine.
"""

from __future__ import annotations

import argparse
import csv
import json
import statistics
import tempfile
import sys
import time
from pathlib import Path

# the package next to this script, not another checkout's editable install (the table is
# written next to the auto.py it is built for)
sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import torchrefract as tr  # noqa: E402
from torchrefract.auto import DEFAULT_TABLE, features  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
OURS = ("specular", "prefiltered", "rousiers", "lean", "gsr")
SUITE = ROOT / "configs" / "suite"
VALIDATION = ROOT / "configs" / "validation"
SUITE_TABLE = DEFAULT_TABLE.parent / "auto_v1.json"


def split_scenes(split: str | None, splits: Path = VALIDATION / "splits.json"
                 ) -> tuple[Path, set[str] | None]:
    """(folder of the scene files, the scene names a table may hold: None for all of them)."""
    if split is None:
        return SUITE, None
    halves = json.loads(Path(splits).read_text())
    if split not in ("fit", "heldout") or split not in halves:
        raise SystemExit(f"build_auto_table: no split {split!r} in {splits}")
    return Path(splits).parent, set(halves[split])


def build(csv_path: Path, metric: str = "flip_object", split: str | None = None,
          splits: Path = VALIDATION / "splits.json") -> dict:
    """The table from a chart's CSV: the suite's scenes, or one half of the validation set."""
    configs, allowed = split_scenes(split, splits)
    with open(csv_path, newline="") as f:
        rows = list(csv.DictReader(f))
    scenes: dict[str, dict] = {}
    spp: dict[str, int] = {}  # each scene's own n x n pixel sampling
    for r in rows:
        if r["method"] not in OURS or int(r["batch"] or 0) != 1 or not r["ms_per_frame"]:
            continue
        name = r["scene"]
        if allowed is not None and name not in allowed:
            continue
        if name not in scenes:
            cfg = configs / f"{name}.yaml"
            if not cfg.exists():
                print(f"skip {name}: {cfg} not found")
                continue
            scene = tr.load_scene(cfg)
            scenes[name] = {"name": name, "features": features(scene), "variants": []}
            spp[name] = scene.camera.samples_per_pixel
        # auto keeps the user's pixel sampling: rows measured at another n x n grid (the
        # chart's "1x1" variants) are not choices it can make
        if int(r["samples_per_pixel"] or 0) != spp[name]:
            continue
        # compiled and adaptive rows are render settings (RenderSettings.compile,
        # .adaptive), not options
        if {"compile", "adaptive"} & set(json.loads(r["options"] or "{}")):
            continue
        scenes[name]["variants"].append({
            "method": r["method"], "options": json.loads(r["options"] or "{}"),
            "variant": r["variant"], "ms": float(r["ms_per_frame"]), "flip": float(r[metric])})
    machine = next((r["machine"] for r in rows if r.get("machine")), "")
    threads = next((r["threads"] for r in rows if r.get("threads")), "")
    return {"version": 1, "metric": metric, "source": str(csv_path), "machine": machine,
            "threads": threads, "built": time.strftime("%Y-%m-%d"),
            "configs": str(configs.relative_to(ROOT)) if configs.is_relative_to(ROOT)
            else str(configs), "split": split,
            "scenes": sorted(scenes.values(), key=lambda s: s["name"])}


def leave_one_out(table: dict, tolerance: float | None = None) -> list[dict]:
    """For every scene of the table, what ``auto`` picks from a table without that scene,
    and how the pick measured there against the most accurate and the fastest variant."""
    from torchrefract.auto import AutoOptions, choose, load_table  # noqa: PLC0415

    if tolerance is None:
        tolerance = AutoOptions().auto_tolerance
    configs = ROOT / table.get("configs", "configs/suite")
    tmpdir = tempfile.mkdtemp(prefix="auto_loo_")
    out = []
    for i, row in enumerate(table["scenes"]):
        rest = {**table, "scenes": table["scenes"][:i] + table["scenes"][i + 1:]}
        tmp = Path(tmpdir) / f"auto_loo_{row['name']}.json"
        tmp.write_text(json.dumps(rest))
        load_table.cache_clear()
        scene = tr.load_scene(configs / f"{row['name']}.yaml")
        c = choose(scene, AutoOptions(auto_tolerance=tolerance, auto_table=str(tmp)))
        tmp.unlink()
        load_table.cache_clear()
        meas = {(v["method"], json.dumps(v["options"], sort_keys=True)): v
                for v in row["variants"]}
        got = [(meas.get((m, json.dumps(o, sort_keys=True))), w) for m, o, w in c.blend]
        # a blend renders each of its variants: their times add up; its error is taken as
        # the weighted mean of theirs (FLIP of a weighted sum of two images close to each
        # other; the chart measures the real one)
        measured = all(g is not None for g, _ in got)
        pick = " + ".join(f"{g['variant'] if g else m}" + (f" {w:.2f}" if len(got) > 1 else "")
                          for (g, w), (m, _, _) in zip(got, c.blend))
        best = min(row["variants"], key=lambda v: v["flip"])
        fastest = min(row["variants"], key=lambda v: v["ms"])
        out.append({"scene": row["name"], "pick": pick,
                    "pick_ms": sum(g["ms"] for g, _ in got) if measured else None,
                    "pick_flip": sum(w * g["flip"] for g, w in got) if measured else None,
                    "best": best["variant"], "best_ms": best["ms"], "best_flip": best["flip"],
                    "fastest": fastest["variant"], "fastest_ms": fastest["ms"],
                    "fastest_flip": fastest["flip"], "neighbours": list(c.neighbours)})
    Path(tmpdir).rmdir()
    return out


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("csv", nargs="?", default=None,
                    help="the chart's results.csv (default: outputs/pareto/results.csv, with "
                         "--split outputs/validation_chart/results.csv)")
    ap.add_argument("--out", default=None,
                    help=f"default: {SUITE_TABLE.name}, with --split {DEFAULT_TABLE.name}")
    ap.add_argument("--metric", default="flip_object")
    ap.add_argument("--split", choices=("fit", "heldout"), default=None,
                    help="build from this half of the validation set only (its scenes in "
                         "configs/validation/splits.json); default: the suite's scenes")
    ap.add_argument("--splits", default=str(VALIDATION / "splits.json"))
    ap.add_argument("--evaluate", action="store_true",
                    help="also print a leave-one-out check: per scene, auto's pick from the "
                         "other scenes' measurements against that scene's best and fastest")
    args = ap.parse_args(argv)
    if args.csv is None:
        args.csv = str(ROOT / "outputs" / ("validation_chart" if args.split else "pareto")
                       / "results.csv")
    if args.out is None:
        args.out = str(DEFAULT_TABLE if args.split else SUITE_TABLE)
    table = build(Path(args.csv), args.metric, args.split, Path(args.splits))
    if args.evaluate:
        print(f"{'scene':<16}{'auto picks (leave-one-out)':<52}{'ms':>6}{'FLIP':>7}   "
              f"{'most accurate':<24}{'ms':>6}{'FLIP':>7}   {'fastest':<20}{'ms':>6}{'FLIP':>7}")
        loo = leave_one_out(table)
        for e in loo:
            pm = "" if e["pick_ms"] is None else f"{e['pick_ms']:.0f}"
            pf = "" if e["pick_flip"] is None else f"{e['pick_flip']:.3f}"
            print(f"{e['scene']:<16}{e['pick']:<52}{pm:>6}{pf:>7}   {e['best']:<24}"
                  f"{e['best_ms']:>6.0f}{e['best_flip']:>7.3f}   {e['fastest']:<20}"
                  f"{e['fastest_ms']:>6.0f}{e['fastest_flip']:>7.3f}")
        done = [e for e in loo if e["pick_flip"] is not None]
        if done:  # against every variant measured on all the table's scenes, on the same
            per = {}  # scenes
            for row in table["scenes"]:
                for v in row["variants"]:
                    per.setdefault(v["variant"], {})[row["name"]] = (v["flip"], v["ms"])
            names = {e["scene"] for e in done}
            print(f"leave-one-out over {len(done)} scenes: auto "
                  f"{statistics.mean(e['pick_flip'] for e in done):.3f} FLIP, "
                  f"{statistics.mean(e['pick_ms'] for e in done):.0f} ms")
            for v, got in sorted(per.items(), key=lambda kv: statistics.mean(
                    f for f, _ in kv[1].values())):
                if names <= got.keys():
                    print(f"  {v:<32}{statistics.mean(got[n][0] for n in names):.3f} FLIP, "
                          f"{statistics.mean(got[n][1] for n in names):.0f} ms")
    Path(args.out).write_text(json.dumps(table, indent=1) + "\n")
    print(f"saved {args.out}: {len(table['scenes'])} scenes, "
          f"{sum(len(s['variants']) for s in table['scenes'])} measurements")


if __name__ == "__main__":
    main()

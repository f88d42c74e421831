"""Condense the speed/accuracy chart's measurements into the table method ``auto`` reads.

    .venv/bin/python scripts/build_auto_table.py [outputs/pareto/results.csv]
        [--out torchrefract/tables/auto_v1.json] [--metric flip_object]

For every suite scene in the CSV: its features (``torchrefract.auto.features`` of
``configs/suite/<scene>.yaml``) and, for each of our method variants measured at batch 1
(``specular``, ``prefiltered``, ``rousiers``, ``lean``, ``gsr``, with their options; not
Mitsuba, not ``auto`` itself, not ``sh``, whose precomputation the chart does not time), the time per frame and the error. The table is small JSON and shipped with the
package; rebuild it after a new ``scripts/pareto.py`` run on the target machine.
"""

from __future__ import annotations

import argparse
import csv
import json
import time
from pathlib import Path

import torchrefract as tr
from torchrefract.auto import DEFAULT_TABLE, features

ROOT = Path(__file__).resolve().parent.parent
OURS = ("specular", "prefiltered", "rousiers", "lean", "gsr")


def build(csv_path: Path, metric: str = "flip_object") -> dict:
    with open(csv_path, newline="") as f:
        rows = list(csv.DictReader(f))
    scenes: dict[str, dict] = {}
    spp: dict[str, int] = {}  # each scene's own n x n pixel sampling
    for r in rows:
        if r["method"] not in OURS or int(r["batch"] or 0) != 1 or not r["ms_per_frame"]:
            continue
        name = r["scene"]
        if name not in scenes:
            cfg = ROOT / "configs" / "suite" / f"{name}.yaml"
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
        # compiled rows are a render setting (RenderSettings.compile), not an option
        if "compile" in json.loads(r["options"] or "{}"):
            continue
        scenes[name]["variants"].append({
            "method": r["method"], "options": json.loads(r["options"] or "{}"),
            "variant": r["variant"], "ms": float(r["ms_per_frame"]), "flip": float(r[metric])})
    machine = next((r["machine"] for r in rows if r.get("machine")), "")
    threads = next((r["threads"] for r in rows if r.get("threads")), "")
    return {"version": 1, "metric": metric, "source": str(csv_path), "machine": machine,
            "threads": threads, "built": time.strftime("%Y-%m-%d"),
            "scenes": sorted(scenes.values(), key=lambda s: s["name"])}


def leave_one_out(table: dict, tolerance: float = 0.05) -> list[dict]:
    """For every scene of the table, what ``auto`` picks from a table without that scene,
    and how the pick measured there against the most accurate and the fastest variant."""
    from torchrefract.auto import AutoOptions, choose, load_table  # noqa: PLC0415

    out = []
    for i, row in enumerate(table["scenes"]):
        rest = {**table, "scenes": table["scenes"][:i] + table["scenes"][i + 1:]}
        tmp = ROOT / "outputs" / "pareto" / f".auto_loo_{row['name']}.json"
        tmp.parent.mkdir(parents=True, exist_ok=True)
        tmp.write_text(json.dumps(rest))
        load_table.cache_clear()
        scene = tr.load_scene(ROOT / "configs" / "suite" / f"{row['name']}.yaml")
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
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("csv", nargs="?", default=str(ROOT / "outputs" / "pareto" / "results.csv"))
    ap.add_argument("--out", default=str(DEFAULT_TABLE))
    ap.add_argument("--metric", default="flip_object")
    ap.add_argument("--evaluate", action="store_true",
                    help="also print a leave-one-out check: per scene, auto's pick from the "
                         "other scenes' measurements against that scene's best and fastest")
    args = ap.parse_args()
    table = build(Path(args.csv), args.metric)
    if args.evaluate:
        print(f"{'scene':<16}{'auto picks (leave-one-out)':<52}{'ms':>6}{'FLIP':>7}   "
              f"{'most accurate':<24}{'ms':>6}{'FLIP':>7}   {'fastest':<20}{'ms':>6}{'FLIP':>7}")
        for e in leave_one_out(table):
            pm = "" if e["pick_ms"] is None else f"{e['pick_ms']:.0f}"
            pf = "" if e["pick_flip"] is None else f"{e['pick_flip']:.3f}"
            print(f"{e['scene']:<16}{e['pick']:<52}{pm:>6}{pf:>7}   {e['best']:<24}"
                  f"{e['best_ms']:>6.0f}{e['best_flip']:>7.3f}   {e['fastest']:<20}"
                  f"{e['fastest_ms']:>6.0f}{e['fastest_flip']:>7.3f}")
    Path(args.out).write_text(json.dumps(table, indent=1) + "\n")
    print(f"saved {args.out}: {len(table['scenes'])} scenes, "
          f"{sum(len(s['variants']) for s in table['scenes'])} measurements")


if __name__ == "__main__":
    main()

"""Condense the speed/accuracy chart's measurements into the table method ``auto`` reads.

    .venv/bin/python scripts/build_auto_table.py [outputs/pareto/results.csv]
        [--out torchrefract/tables/auto_v1.json] [--metric flip_object]

For every suite scene in the CSV: its features (``torchrefract.methods.auto.features`` of
``configs/suite/<scene>.yaml``) and, for each of our method variants measured at batch 1
(``specular``, ``prefiltered``, ``rousiers``, with their options; not Mitsuba, not ``auto``
itself), the time per frame and the error. The table is small JSON and shipped with the
package; rebuild it after a new ``scripts/pareto.py`` run on the target machine.
"""

from __future__ import annotations

import argparse
import csv
import json
import time
from pathlib import Path

import torchrefract as tr
from torchrefract.methods.auto import DEFAULT_TABLE, features

ROOT = Path(__file__).resolve().parent.parent
OURS = ("specular", "prefiltered", "rousiers")


def build(csv_path: Path, metric: str = "flip_object") -> dict:
    with open(csv_path, newline="") as f:
        rows = list(csv.DictReader(f))
    scenes: dict[str, dict] = {}
    for r in rows:
        if r["method"] not in OURS or int(r["batch"] or 0) != 1 or not r["ms_per_frame"]:
            continue
        name = r["scene"]
        if name not in scenes:
            cfg = ROOT / "configs" / "suite" / f"{name}.yaml"
            if not cfg.exists():
                print(f"skip {name}: {cfg} not found")
                continue
            scenes[name] = {"name": name, "features": features(tr.load_scene(cfg)),
                            "variants": []}
        scenes[name]["variants"].append({
            "method": r["method"], "options": json.loads(r["options"] or "{}"),
            "variant": r["variant"], "ms": float(r["ms_per_frame"]), "flip": float(r[metric])})
    machine = next((r["machine"] for r in rows if r.get("machine")), "")
    threads = next((r["threads"] for r in rows if r.get("threads")), "")
    return {"version": 1, "metric": metric, "source": str(csv_path), "machine": machine,
            "threads": threads, "built": time.strftime("%Y-%m-%d"),
            "scenes": sorted(scenes.values(), key=lambda s: s["name"])}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("csv", nargs="?", default=str(ROOT / "outputs" / "pareto" / "results.csv"))
    ap.add_argument("--out", default=str(DEFAULT_TABLE))
    ap.add_argument("--metric", default="flip_object")
    args = ap.parse_args()
    table = build(Path(args.csv), args.metric)
    Path(args.out).write_text(json.dumps(table, indent=1) + "\n")
    print(f"saved {args.out}: {len(table['scenes'])} scenes, "
          f"{sum(len(s['variants']) for s in table['scenes'])} measurements")


if __name__ == "__main__":
    main()

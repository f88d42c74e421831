"""rousiers against prefiltered where the object is thick: FLIP and relMSE by thickness.

Issue #3 asks that ``rousiers`` be clearly better than ``prefiltered`` "on thick regions".
For every suite scene this renders both methods (their defaults, plus any variants given)
at the truth's size, and scores them against converged Mitsuba 3 (``max_depth`` 64, the
cached truth of scripts/accuracy.py / scripts/pareto.py) on object pixels split by the
G-buffer's ``thickness`` pass (distance between the front and back layers along the view
ray), relative to the scene's thickest object pixel:

- ``thin``: thickness < ``--split`` (default 0.5) of the maximum;
- ``thick``: thickness >= ``--split`` of the maximum (the region the issue names);
- ``all``: every object pixel (coverage > 0.5).

FLIP is the LDR-FLIP map of the whole image (so its spatial filter sees the same
neighbourhood as the chart's), averaged over each region. The truth's own noise (seed 0
against seed 1) is given per region: a difference below it is not a measurement. Prints a
table and writes outputs/thick_regions/results.json and summary.md.

    .venv/bin/python scripts/thick_regions.py [--scenes sphere_a03 bunny_a01] [--size 128]
        [--spp 1024] [--split 0.5] [--variants "rousiers:cone_rays=plane"]
        [--against full|d3] [--base-options tir=clamp]

The README's tables come from two runs: against full truth with
``--variants rousiers:internal_bounces=2 rousiers:internal_bounces=auto`` (the defaults and
rousiers with internal bounces), and ``--against d3 --base-options tir=clamp`` (both
methods as two-interface models, against the two-interface floor: the comparison of the
lobes alone, without the exit rule's light). summary.md ends with every variant's delta
against prefiltered and on how many scenes it is clearly better (by more than the truth's
noise).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch

import torchrefract as tr
from torchrefract.truth.metrics import flip_map, relmse

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(Path(__file__).resolve().parent))
from accuracy import truth as cached_truth  # noqa: E402  (the one truth renderer and cache)
from bench import parse_method_spec  # noqa: E402  (the one method[:k=v,...] syntax)

REGIONS = ("all", "thin", "thick")


def parse_variant(spec: str) -> tuple[str, str, dict]:
    """``method[:k=v,...]`` -> (label, method, options)."""
    return (spec, *parse_method_spec(spec))


def region_masks(coverage: np.ndarray, thickness: np.ndarray, split: float
                 ) -> dict[str, np.ndarray]:
    """Object pixels (coverage > 0.5) split at ``split`` times the largest thickness."""
    obj = coverage > 0.5
    t_max = float(thickness[obj].max()) if obj.any() else 0.0
    thick = obj & (thickness >= split * t_max)
    return {"all": obj, "thin": obj & ~thick, "thick": thick}


def scores(img: np.ndarray, ref: np.ndarray, masks: dict[str, np.ndarray]) -> dict:
    fm = flip_map(img, ref)
    return {r: {"flip": float(fm[m].mean()) if m.any() else float("nan"),
                "relmse": relmse(img, ref, m) if m.any() else float("nan"),
                "pixels": int(m.sum())} for r, m in masks.items()}


def clearly_better(rows: list[dict], pre: str, others: list[str]) -> list[str]:
    """A markdown table: each variant's thick-region FLIP minus prefiltered's per scene, and
    on how many scenes it is clearly better (lower by more than the truth's own noise
    there, seed 0 against seed 1) or clearly worse."""
    head = "| scene | truth noise (thick) | prefiltered thick | " + " | ".join(
        f"{o} thick (delta)" for o in others) + " |"
    lines = ["Thick-region FLIP of every variant (delta = variant - prefiltered; clearly "
             "better: delta < -noise).", "", head, "|---" * (3 + len(others)) + "|"]
    better = {o: 0 for o in others}
    worse = {o: 0 for o in others}
    for row in rows:
        noise = row["noise"]["thick"]["flip"]
        p = row["variants"][pre]["thick"]["flip"]
        cells = []
        for o in others:
            v = row["variants"][o]["thick"]["flip"]
            better[o] += v - p < -noise
            worse[o] += v - p > noise
            cells.append(f"{v:.3f} ({v - p:+.3f})")
        lines.append(f"| {row['scene']} | {noise:.3f} | {p:.3f} | " + " | ".join(cells) + " |")
    lines.append("| clearly better / worse | | | " + " | ".join(
        f"{better[o]} / {worse[o]} of {len(rows)}" for o in others) + " |")
    return lines


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", nargs="*", default=None,
                    help="suite scene names (default: every configs/suite/*.yaml)")
    ap.add_argument("--size", type=int, default=128)
    ap.add_argument("--spp", type=int, default=1024, help="truth spp (cached in outputs/truth)")
    ap.add_argument("--split", type=float, default=0.5,
                    help="thick = thickness >= split x the scene's largest thickness")
    ap.add_argument("--variants", nargs="*", default=[],
                    help="extra method[:k=v,...] renders next to the two defaults")
    ap.add_argument("--against", choices=["full", "d3"], default="full",
                    help="truth: full (max_depth 64) or the two-interface floor (max_depth 3, "
                         "what both methods model with tir: clamp)")
    ap.add_argument("--base-options", default="",
                    help="k=v,... applied to both default variants (e.g. tir=clamp)")
    ap.add_argument("--threads", type=int, default=None)
    ap.add_argument("--out", default=None,
                    help="default outputs/thick_regions/<against> (full or d3)")
    args = ap.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    names = args.scenes or sorted(p.stem for p in (ROOT / "configs" / "suite").glob("*.yaml"))
    base = f":{args.base_options}" if args.base_options else ""
    variants = [parse_variant(v) for v in [f"prefiltered{base}", f"rousiers{base}",
                                           *args.variants]]
    depth = 64 if args.against == "full" else 3
    cache = ROOT / "outputs" / "truth"
    rows = []
    print(f"torch threads {torch.get_num_threads()}, size {args.size}, truth spp {args.spp} "
          f"max_depth {depth}, "
          f"thick = thickness >= {args.split} x max")
    print(f"{'scene':<18}{'variant':<30}" + "".join(f"{'FLIP ' + r:>12}" for r in REGIONS)
          + f"{'relMSE thick':>14}")
    for name in names:
        scene = tr.load_scene(ROOT / "configs" / "suite" / f"{name}.yaml")
        c = scene.camera
        scene = scene.replace(camera=tr.Camera(
            eye=c.eye, target=c.target, up=c.up, yfov_deg=c.yfov_deg, width=args.size,
            height=args.size, samples_per_pixel=c.samples_per_pixel))
        full, alpha, _ = cached_truth(scene, args.spp, depth, 0, cache)
        if depth == 64:
            full2, _, _ = cached_truth(scene, args.spp, 64, 1, cache)
        else:  # the cache holds one seed of the floor: its noise is that of full truth's
            full2 = cached_truth(scene, args.spp, 64, 1, cache)[0] \
                - cached_truth(scene, args.spp, 64, 0, cache)[0] + full
        row = {"scene": name, "variants": {}}
        for label, method, options in variants:
            out = tr.render([scene.replace(method_options=options)], method=method)
            if "masks" not in row:
                masks = region_masks(alpha, out.passes["thickness"][0, ..., 0].numpy(),
                                     args.split)
                row["masks"] = {r: int(m.sum()) for r, m in masks.items()}
                row["noise"] = scores(full2, full, masks)
                print(f"{name:<18}{'truth noise':<30}"
                      + "".join(f"{row['noise'][r]['flip']:>12.3f}" for r in REGIONS)
                      + f"{row['noise']['thick']['relmse']:>14.4f}")
            s = scores(out.radiance[0].numpy(), full, masks)
            row["variants"][label] = s
            print(f"{name:<18}{label[:29]:<30}" + "".join(f"{s[r]['flip']:>12.3f}"
                                                        for r in REGIONS)
                  + f"{s['thick']['relmse']:>14.4f}")
        rows.append(row)
    out_dir = Path(args.out or ROOT / "outputs" / "thick_regions" / args.against)
    out_dir.mkdir(parents=True, exist_ok=True)
    meta = {"torchrefract": tr.__version__, "threads": torch.get_num_threads(),
            "against": args.against, "base_options": args.base_options, "size": args.size, "truth_spp": args.spp, "split": args.split, "results": rows}
    (out_dir / "results.json").write_text(json.dumps(meta, indent=2) + "\n")
    pre, rou = variants[0][0], variants[1][0]
    lines = [f"FLIP on object pixels against {'full truth' if depth == 64 else 'the floor (max_depth 3)'}"
             f" ({args.size}x{args.size}, truth "
             f"{args.spp} spp); thick = thickness >= {args.split} x the scene's largest. "
             "Delta = rousiers - prefiltered (negative: rousiers better).", "",
             "| scene | thick px | truth noise (thick) | prefiltered thick | rousiers thick | "
             "delta thick | delta thin | delta all |", "|---|---|---|---|---|---|---|---|"]
    for row in rows:
        p, r = row["variants"][pre], row["variants"][rou]
        d = {k: r[k]["flip"] - p[k]["flip"] for k in REGIONS}
        lines.append(f"| {row['scene']} | {row['masks']['thick']} | "
                     f"{row['noise']['thick']['flip']:.3f} | {p['thick']['flip']:.3f} | "
                     f"{r['thick']['flip']:.3f} | {d['thick']:+.3f} | {d['thin']:+.3f} | "
                     f"{d['all']:+.3f} |")
    lines += ["", *clearly_better(rows, pre, [v[0] for v in variants[1:]])]
    (out_dir / "summary.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines[3:]))
    print(f"saved {out_dir / 'results.json'} and summary.md")


if __name__ == "__main__":
    main()

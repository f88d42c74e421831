"""Adaptive shading (``RenderSettings(adaptive=True)``; ``--spp 2``: sparse supersampling
or the n x n plan, as the method takes) against the full render, on the validation set's scenes (out of sample: the threshold was fit on the
``fit`` half) or the chart's suite, scored against the cached Mitsuba truth.

    .venv/bin/python scripts/adaptive_accuracy.py [--split heldout|fit|suite]
        [--size 128] [--spp 1] [--variants rousiers "rousiers ib2"] [--rtol R]
        [--refine-rtol R] [--out outputs/adaptive]

Per scene and variant: FLIP on object pixels of the full and the adaptive render against
the truth (their difference: what adaptive shading costs in accuracy), FLIP of the
adaptive render against the full one, and the share of object pixels shaded (those equal
to the full render's bit for bit: the shaded pixels are). Prints the per-variant means and
worst scenes and saves ``adaptive.json``. Scenes without cached truth are skipped (make it
with ``scripts/validation_set.py truth`` or ``scripts/accuracy.py``).
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(Path(__file__).resolve().parent))

import torchrefract as tr  # noqa: E402
from pareto import VARIANTS, load_truth, sized, truth_cached  # noqa: E402
from torchrefract.geometry import adaptive  # noqa: E402
from torchrefract.truth.metrics import compare, flip_map  # noqa: E402


def scenes(split: str) -> list[tuple[Path, int]]:
    """(YAML, truth spp) of the split's scenes."""
    if split == "suite":
        return [(p, 1024) for p in sorted((ROOT / "configs" / "suite").glob("*.yaml"))]
    names = json.loads((ROOT / "configs" / "validation" / "splits.json").read_text())[split]
    return [(ROOT / "configs" / "validation" / f"{n}.yaml", 2048) for n in names]


def report(rows: list[dict], variants: list[str]) -> None:
    """Per variant: the means and the worst scene."""
    for name in variants:
        rs = [r for r in rows if r["variant"] == name]
        if not rs:
            continue
        d = [r["flip_adaptive"] - r["flip_full"] for r in rs]
        worst = max(rs, key=lambda r: r["flip_adaptive"] - r["flip_full"])
        print(f"{name}: {len(rs)} scenes, FLIP vs truth {statistics.mean(r['flip_full'] for r in rs):.4f}"
              f" -> {statistics.mean(r['flip_adaptive'] for r in rs):.4f} (mean change "
              f"{statistics.mean(d):+.4f}, worst {max(d):+.4f} {worst['scene']}), vs full "
              f"{statistics.mean(r['flip_vs_full'] for r in rs):.4f} (max "
              f"{max(r['flip_vs_full'] for r in rs):.4f}), shaded "
              f"{statistics.mean(r['shaded'] for r in rs):.2f} of the object pixels, time "
              f"{statistics.median(r['ms_adaptive'] / r['ms_full'] for r in rs):.2f} of the full "
              "render's (median)")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--split", default="heldout", choices=("heldout", "fit", "suite"))
    ap.add_argument("--size", type=int, default=128)
    ap.add_argument("--spp", type=int, default=1,
                    help="samples per pixel side (2: the supersampled plan against uniform 2x2)")
    ap.add_argument("--variants", nargs="+", default=["rousiers", "rousiers ib2"])
    ap.add_argument("--truth", type=Path, default=ROOT / "outputs" / "truth")
    ap.add_argument("--out", type=Path, default=ROOT / "outputs" / "adaptive")
    ap.add_argument("--rtol", type=float, default=None,
                    help="the fill's radiance tolerance (default: adaptive.LATTICE_RTOL)")
    ap.add_argument("--refine-rtol", type=float, default=None,
                    help="with --spp 2: the refinement's radiance spread (default: "
                         "adaptive.REFINE_RTOL; inf: none)")
    args = ap.parse_args(argv)
    if args.rtol is not None:
        adaptive.LATTICE_RTOL = args.rtol
    if args.refine_rtol is not None:
        adaptive.REFINE_RTOL = args.refine_rtol
    table = {v[0]: v for v in VARIANTS}
    unknown = [v for v in args.variants if v not in table]
    if unknown:
        raise SystemExit(f"adaptive_accuracy: unknown variants {unknown} (pareto.VARIANTS)")
    full_s, ad_s = tr.RenderSettings(adaptive=False), tr.RenderSettings(adaptive=True)
    rows = []
    todo = scenes(args.split)
    for k, (path, spp) in enumerate(todo, 1):
        base = tr.load_scene(path)
        s1 = sized(base, args.size)
        if not truth_cached(s1, spp, args.truth):
            print(f"[{k}/{len(todo)}] {path.stem}: no cached truth, skipped", flush=True)
            continue
        truth = load_truth(s1, spp, args.truth, floors=False)
        cov = truth["alpha"]
        for name in args.variants:
            _, method, opts = table[name][:3]
            s = sized(base, args.size, args.spp).replace(method=method, method_options=opts)
            t0 = time.perf_counter()
            full = tr.render(s, settings=full_s).radiance[0]
            t1 = time.perf_counter()
            ad = tr.render(s, settings=ad_s).radiance[0]
            t2 = time.perf_counter()
            obj = torch.from_numpy(cov > 0.5)
            row = {"scene": path.stem, "variant": name,
                   "flip_full": compare(full.numpy(), truth["full"], cov)["flip_object"],
                   "flip_adaptive": compare(ad.numpy(), truth["full"], cov)["flip_object"],
                   "flip_vs_full": float(flip_map(ad.numpy(), full.numpy())[obj.numpy()].mean()),
                   "shaded": float((ad == full).all(-1)[obj].float().mean()),
                   "ms_full": 1000 * (t1 - t0), "ms_adaptive": 1000 * (t2 - t1)}
            rows.append(row)
            print(f"[{k}/{len(todo)}] {path.stem} {name}: truth {row['flip_full']:.4f} -> "
                  f"{row['flip_adaptive']:.4f}, vs full {row['flip_vs_full']:.4f}, shaded "
                  f"{row['shaded']:.2f}", flush=True)
    args.out.mkdir(parents=True, exist_ok=True)
    tag = ("" if args.rtol is None else f"_rtol{args.rtol:g}") + (
        "" if args.spp == 1 else f"_spp{args.spp}") + (
        "" if args.refine_rtol is None else f"_refine{args.refine_rtol:g}")
    (args.out / f"adaptive_{args.split}{tag}.json").write_text(json.dumps(rows, indent=1))
    report(rows, args.variants)
    print(f"saved {args.out / f'adaptive_{args.split}{tag}.json'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""Adaptive shading at one sample per pixel (``RenderSettings(adaptive=True)``) against the
full render, on the validation set's scenes (out of sample: the threshold was fit on the
``fit`` half) or the chart's suite, scored against the cached Mitsuba truth.

    .venv/bin/python scripts/adaptive_accuracy.py [--split heldout|fit|suite]
        [--size 128] [--spp 1] [--variants rousiers "rousiers ib2"] [--rtol R]
        [--out outputs/adaptive]

Per scene and variant: FLIP on object pixels of the full and the adaptive render against
the truth (their difference: what adaptive shading costs in accuracy), FLIP of the
adaptive render against the full one, and the share of object pixels shaded (those equal
to the full render's bit for bit: the shaded pixels are). Prints the per-variant means and
worst scenes and saves ``adaptive.json``. Scenes without cached truth are skipped (make it
with ``scripts/validation_set.py truth`` or ``scripts/accuracy.py``).

``--sparse`` (with ``--spp 2``) also scores a supersampling design not built yet: the
one-sample adaptive render, with the 2x2 adaptive render's pixels only where the
one-sample passes change within the 3x3 neighbourhood (:func:`edge_pixels`, the plan's
tolerances between pixel centers), and the one-sample render alone; and records the share
of object pixels such a design would supersample (docs/benchmarks.md, fifteenth sitting).
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import torch
import torch.nn.functional as F

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


def edge_pixels(r: tr.RenderResult) -> torch.Tensor:
    """(H, W) bool: the pixels of a one-sample render ``r`` (its first view) whose 3x3
    neighbourhood changes coverage or back coverage, a front or back normal by more than
    adaptive.NORMAL_TOL (1 - cos), the back depth by more than adaptive.DEPTH_TOL relative,
    or that are smoother than adaptive.SMOOTH_ALPHA: where sub-pixels can differ, judged
    from pixel centers (adaptive.plan judges from the sub-pixels themselves)."""
    p = r.passes
    fm = (r.coverage[0] > 0).float()
    nf, nb, db = p["normal_front"][0], p["normal_back"][0], p["depth_back"][0, ..., 0]
    bm = (nb.abs().sum(-1) > 0).float()
    h, w = fm.shape

    def most(x: torch.Tensor) -> torch.Tensor:
        return F.max_pool2d(x[None, None], 3, 1, 1)[0, 0]

    def padded(x: torch.Tensor) -> torch.Tensor:
        return F.pad(x.movedim(-1, 0)[None], (1, 1, 1, 1), mode="replicate")[0].movedim(0, -1)

    edge = (most(fm) != -most(-fm)) | (most(bm) != -most(-bm))
    nfp, nbp, dbp = padded(nf), padded(nb), padded(db[..., None])[..., 0]
    back = bm > 0
    for dy in range(3):
        for dx in range(3):
            at = (slice(dy, dy + h), slice(dx, dx + w))
            edge |= (1 - (nfp[at] * nf).sum(-1)) > adaptive.NORMAL_TOL
            edge |= back & ((1 - (nbp[at] * nb).sum(-1)) > adaptive.NORMAL_TOL)
            edge |= back & ((dbp[at] - db).abs() > adaptive.DEPTH_TOL * db.abs())
    edge |= (fm > 0) & (p["roughness"][0, ..., 0] < adaptive.SMOOTH_ALPHA)
    return edge & (most(fm) > 0)


def sparse_scores(s: tr.Scene, supersampled: torch.Tensor, truth: dict) -> dict:
    """``--sparse``'s figures for scene ``s`` (2x2) whose adaptive render is
    ``supersampled`` (H, W, 3): FLIP against the truth of the one-sample render and of the
    design's image, and the share of object pixels it supersamples."""
    one = tr.render(sized(s, None, 1))
    edge = edge_pixels(one)
    image = torch.where(edge[..., None], supersampled, one.radiance[0])
    cov = truth["alpha"]
    obj = torch.from_numpy(cov > 0.5)
    return {"flip_one": compare(one.radiance[0].numpy(), truth["full"], cov)["flip_object"],
            "flip_sparse": compare(image.numpy(), truth["full"], cov)["flip_object"],
            "edge_share": float((edge & obj).sum()) / max(int(obj.sum()), 1)}


def report(rows: list[dict], variants: list[str], sparse: bool) -> None:
    """Per variant: the means, the worst scene and (``sparse``) the design's figures."""
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
        if sparse:
            for key in ("flip_sparse", "flip_one"):
                d = [r[key] - r["flip_full"] for r in rs]
                print(f"  {key[5:]}: mean change {statistics.mean(d):+.4f}, worst {max(d):+.4f},"
                      f" {sum(x > 0.005 for x in d)} scenes beyond +0.005")
            print(f"  edge share: median {statistics.median(r['edge_share'] for r in rs):.2f}")


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
    ap.add_argument("--sparse", action="store_true",
                    help="with --spp 2: also the one-sample render with 2x2 at edge pixels")
    args = ap.parse_args(argv)
    if args.sparse and args.spp != 2:
        raise SystemExit("adaptive_accuracy: --sparse needs --spp 2")
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
            if args.sparse:
                row.update(sparse_scores(s, ad, truth))
            rows.append(row)
            print(f"[{k}/{len(todo)}] {path.stem} {name}: truth {row['flip_full']:.4f} -> "
                  f"{row['flip_adaptive']:.4f}, vs full {row['flip_vs_full']:.4f}, shaded "
                  f"{row['shaded']:.2f}", flush=True)
    args.out.mkdir(parents=True, exist_ok=True)
    tag = ("" if args.rtol is None else f"_rtol{args.rtol:g}") + (
        "" if args.spp == 1 else f"_spp{args.spp}") + ("_sparse" if args.sparse else "") + (
        "" if args.refine_rtol is None else f"_refine{args.refine_rtol:g}")
    (args.out / f"adaptive_{args.split}{tag}.json").write_text(json.dumps(rows, indent=1))
    report(rows, args.variants, args.sparse)
    print(f"saved {args.out / f'adaptive_{args.split}{tag}.json'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""Fit ``auto``'s first-pass ramp (``torchrefract.auto.DIVERGENCE``) on the validation set's
fit half, and show what it does on a half.

    .venv/bin/python scripts/fit_auto_pass.py [outputs/validation_chart/results.csv]
        [--split fit] [--show heldout] [--json out.json]

Per scene of ``--split``: the first pass's divergence (``torchrefract.auto_pass``) between
the table's cheap and accurate variants (``auto.pass_variants``) and the pass's time; from
the chart's CSV each variant's FLIP (object pixels, against the truth) and ms per frame.
For every ramp (lo, hi) on a grid (hi - lo >= ``MIN_WIDTH``, for continuity) it scores the
policy as ``auto`` would run it: a scene's image is the cheap variant below lo, the accurate
one above hi, both in between (its FLIP taken as the weighted mean of theirs, its time
their sum), plus the pass's time. The ramp kept: the least mean time among those with no
scene more than ``WORST`` FLIP behind the accurate variant (issue #26's bound) and the mean
FLIP and time no worse than its (ties: the lower mean FLIP), and hi at least ``MIN_HI``:
the continuity suite's suzanne has divergence ~0.02 at alpha 0.05-0.3, where four bounce
rays alone step 0.23 (99th-percentile pixel, bound 0.15); a ramp ending at 0.02 gives them
all the weight there (0.225), one ending at 0.03 about half (0.13). ``--show`` prints the
kept ramp's figures on another half (never used for the choice).
"""

from __future__ import annotations

import argparse
import csv
import json
import statistics
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import numpy as np  # noqa: E402

import torchrefract as tr  # noqa: E402
from torchrefract import auto, auto_pass  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
VALIDATION = ROOT / "configs" / "validation"
WORST, MIN_WIDTH, MIN_HI = 0.03, 0.005, 0.03
GRID = np.round(np.arange(0.005, 0.0601, 0.0025), 4)


def chart(path: Path) -> dict[str, dict[tuple[str, str], tuple[float, float]]]:
    """scene -> (method, options as sorted JSON) -> (FLIP on object pixels, ms per frame) of
    the chart's timed batch-1 rows."""
    out: dict[str, dict] = {}
    with open(path, newline="") as f:
        for r in csv.DictReader(f):
            if r["ms_per_frame"] and int(r["batch"] or 0) == 1:
                key = (r["method"], json.dumps(json.loads(r["options"] or "{}"), sort_keys=True))
                out.setdefault(r["scene"], {})[key] = (float(r["flip_object"]),
                                                       float(r["ms_per_frame"]))
    return out


def evidence(names: list[str], cheap: tuple, accurate: tuple) -> dict[str, tuple[float, float]]:
    """scene -> (first-pass divergence, pass ms: the fastest of two runs after a warm-up)."""
    out = {}
    for n in names:
        scene = tr.load_scene(VALIDATION / f"{n}.yaml")
        auto_pass.divergences([scene], cheap, accurate)  # warm-up: mesh, map, kernels
        runs = [auto_pass.divergences([scene], cheap, accurate) for _ in range(2)]
        out[n] = (runs[0][0][0], 1000.0 * min(r[1] for r in runs))
        print(f"{n:<32} divergence {out[n][0]:.4f}  pass {out[n][1]:.0f} ms", flush=True)
    return out


def score(lo: float, hi: float, names, ev, meas, keys) -> dict:
    """The policy with ramp (lo, hi) on ``names``: mean FLIP and ms, and per scene the gap to
    the accurate variant."""
    cheap, accurate = keys
    flips, ms, gaps = [], [], {}
    for n in names:
        d, pass_ms = ev[n]
        w = 1.0 if d <= lo else 0.0 if d >= hi else (hi - d) / (hi - lo)
        (fc, tc), (fa, ta) = meas[n][cheap], meas[n][accurate]
        flips.append(w * fc + (1 - w) * fa)
        ms.append((tc if w > 0 else 0.0) + (ta if w < 1 else 0.0) + pass_ms)
        gaps[n] = flips[-1] - fa
    acc_f = statistics.mean(meas[n][accurate][0] for n in names)
    acc_t = statistics.mean(meas[n][accurate][1] for n in names)
    return {"lo": float(lo), "hi": float(hi), "flip": statistics.mean(flips),
            "ms": statistics.mean(ms),
            "accurate_flip": acc_f, "accurate_ms": acc_t, "worst": max(gaps.values()),
            "worst_scene": max(gaps, key=gaps.get),
            "cheap_scenes": int(sum(ev[n][0] < hi for n in names))}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("csv", nargs="?",
                    default=str(ROOT / "outputs" / "validation_chart_pass" / "results.csv"),
                    help="a chart run over the validation set with the table's cheap and "
                         "accurate variants (only the --split half's rows are read)")
    ap.add_argument("--split", default="fit", choices=("fit", "heldout"))
    ap.add_argument("--show", default=None, choices=("fit", "heldout"),
                    help="also print the kept ramp's figures on this half")
    ap.add_argument("--json", default=None)
    args = ap.parse_args(argv)
    halves = json.loads((VALIDATION / "splits.json").read_text())
    t = auto._arrays(auto.load_table(str(auto.DEFAULT_TABLE)))
    cols = auto.pass_variants(t, auto.AutoOptions().auto_tolerance)
    keys = tuple(t.keys[c] for c in cols)
    decoded = [(m, json.loads(o)) for m, o in keys]
    print(f"cheap {keys[0]}, accurate {keys[1]}")
    meas = chart(Path(args.csv))
    names = [n for n in halves[args.split] if all(k in meas.get(n, {}) for k in keys)]
    ev = evidence(names, *decoded)
    rows = [score(lo, hi, names, ev, meas, keys) for lo in GRID for hi in GRID
            if hi - lo >= MIN_WIDTH - 1e-9 and hi >= MIN_HI - 1e-9]
    ok = [r for r in rows if r["worst"] <= WORST and r["flip"] <= r["accurate_flip"]
          and r["ms"] <= r["accurate_ms"]]
    if not ok:
        print("no ramp meets the fit's conditions")
        return 1
    best = min(ok, key=lambda r: (round(r["ms"], 6), r["flip"]))
    print(f"{args.split}: {len(ok)} of {len(rows)} ramps qualify; kept ({best['lo']}, "
          f"{best['hi']}): FLIP {best['flip']:.4f} at {best['ms']:.0f} ms against the accurate "
          f"variant's {best['accurate_flip']:.4f} at {best['accurate_ms']:.0f}; worst "
          f"{best['worst']:+.3f} ({best['worst_scene']}); cheap on {best['cheap_scenes']} "
          f"scenes")
    report = {"split": args.split, "kept": best, "evidence": ev}
    if args.show:
        other = [n for n in halves[args.show] if all(k in meas.get(n, {}) for k in keys)]
        ev2 = evidence(other, *decoded)
        s = score(best["lo"], best["hi"], other, ev2, meas, keys)
        print(f"{args.show} (shown, not fitted): FLIP {s['flip']:.4f} at {s['ms']:.0f} ms "
              f"against {s['accurate_flip']:.4f} at {s['accurate_ms']:.0f}; worst "
              f"{s['worst']:+.3f} ({s['worst_scene']})")
        report["shown"] = {"split": args.show, **s, "evidence": ev2}
    if args.json:
        Path(args.json).write_text(json.dumps(report, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

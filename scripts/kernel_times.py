"""Where a frame goes: each native kernel's wall time per frame, and the time outside them
(Python, torch ops), for one of bench.py's rows (issue #28; docs/benchmarks.md, "Where a
one-sample frame goes").

    .venv/bin/python scripts/kernel_times.py SCENE.yaml [--method rousiers+adaptive]
        [--size 256] [--batch 8] [--repeats 15] [--threads 2] [--json OUT.json]

The row renders as ``scripts/bench.py``'s do (``OursRow``: ``--batch`` views turned 3
degrees apart, new cameras every batch, heap reuse on; a method spec as bench.py's,
e.g. ``specular:spp=2+adaptive``), after two warm-up batches. Every call of a native
kernel (``torchrefract.kernels.native``) is timed as it returns; per kernel the median
over the timed batches of its summed time in a batch, per frame. A kernel's time is the
wall time of its call on all its threads; the rest is the batch's time outside them.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from collections import defaultdict
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(Path(__file__).resolve().parent))

import torchrefract as tr  # noqa: E402
from bench import OursRow  # noqa: E402
from torchrefract.kernels import native  # noqa: E402


def kernel_times(scene: tr.Scene, method: str, size: int, batch: int, repeats: int) -> dict:
    """Per native kernel the median ms a frame over ``repeats`` timed batches (``kernels``,
    largest first), the batch's median ms a frame (``total``), the kernels' summed median
    (``native``) and the rest (``other``)."""
    row = OursRow(scene, method, size, batch, "distinct",
                  tr.RenderSettings(heap_reuse=True))
    acc: dict[str, float] = defaultdict(float)
    call = native._call

    def timed(name, job):
        t = time.perf_counter()
        try:
            return call(name, job)
        finally:
            acc[name] += time.perf_counter() - t

    per: dict[str, list[float]] = defaultdict(list)
    totals, natives = [], []
    native._call = timed  # this process only, restored below
    try:
        row.warm()
        row.warm()
        for _ in range(repeats):
            acc.clear()
            t = time.perf_counter()
            row.once()
            totals.append(time.perf_counter() - t)
            natives.append(sum(acc.values()))
            for k, v in acc.items():
                per[k].append(v)
    finally:
        native._call = call
    ms = 1000.0 / batch
    kernels = {k: ms * statistics.median(v + [0.0] * (repeats - len(v)))
               for k, v in per.items()}
    total, nat = ms * statistics.median(totals), ms * statistics.median(natives)
    return {"method": method, "size": size, "batch": batch, "repeats": repeats,
            "threads": torch.get_num_threads(), "total": total, "native": nat,
            "other": ms * statistics.median(t - n for t, n in zip(totals, natives)),
            "kernels": dict(sorted(kernels.items(), key=lambda kv: -kv[1]))}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scene")
    ap.add_argument("--method", default="rousiers+adaptive")
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--repeats", type=int, default=15)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--json", default=None, help="also write the figures here")
    args = ap.parse_args(argv)
    if min(args.size, args.batch, args.repeats, args.threads) < 1:
        ap.error("--size, --batch, --repeats and --threads must be at least 1")
    if not native.available():
        print(f"kernel_times: the native kernels are unavailable ({native.failure()})",
              file=sys.stderr)
        return 1
    torch.set_num_threads(args.threads)
    res = kernel_times(tr.load_scene(args.scene), args.method, args.size, args.batch,
                       args.repeats)
    print(f"{args.method} on {Path(args.scene).name}, {args.size}x{args.size}, batch "
          f"{args.batch}, {res['threads']} threads, median of {args.repeats} batches, "
          "ms a frame")
    print(f"  total {res['total']:.3f}   native kernels {res['native']:.3f}   outside "
          f"them {res['other']:.3f}")
    for k, v in res["kernels"].items():
        print(f"  {k:<16}{v:8.3f}")
    if args.json:
        Path(args.json).write_text(json.dumps(res, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""FLIP on object pixels of method variants against the suite's cached truth, one table.

A quick accuracy comparison (no timing discipline: ``scripts/pareto.py`` times and charts).
Truth comes from ``scripts/accuracy.py``'s cache (rendered once if missing: 1024 spp, max
depth 64). Variants are ``method[:key=value...]``; every scene is rendered at --size with
one sample per pixel.

    .venv/bin/python scripts/flip_table.py rousiers:internal_bounces=2 lean:internal_bounces=2 \
        [--scenes sphere_a03 globe_2rough] [--size 128] [--out table.md]
        [--suite configs/suite_sh] [--relmse]

``--suite``: another folder of scene files (``configs/suite_sh``: method ``sh``'s scenes,
kept out of ``configs/suite``, whose scenes every suite-wide table must cover);
``--relmse``: relMSE on object pixels beside each FLIP.
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import sys
from pathlib import Path

import torch

import torchrefract as tr
from torchrefract.truth.metrics import compare

sys.path.insert(0, str(Path(__file__).resolve().parent))
from accuracy import truth  # noqa: E402  (the one truth renderer and cache)

ROOT = Path(__file__).resolve().parent.parent


def variant(spec: str) -> tuple[str, dict]:
    """``method:key=value:...`` -> (method, options); integers become ints."""
    method, *pairs = spec.split(":")
    opts = {}
    for p in pairs:
        k, _, v = p.partition("=")
        opts[k] = int(v) if v.lstrip("-").isdigit() else v
    return method, opts


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("variants", nargs="+")
    ap.add_argument("--scenes", nargs="*", default=None, help="suite names (default: all)")
    ap.add_argument("--size", type=int, default=128)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--truth-dir", default=str(ROOT / "outputs" / "truth"))
    ap.add_argument("--out", default=None, help="also write the markdown table here")
    ap.add_argument("--suite", default=str(ROOT / "configs" / "suite"),
                    help="folder of scene files")
    ap.add_argument("--relmse", action="store_true", help="relMSE beside each FLIP")
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    suite = Path(args.suite)
    names = args.scenes or sorted(p.stem for p in suite.glob("*.yaml"))
    specs = [variant(v) for v in args.variants]
    lines = [f"| scene{' (FLIP / relMSE)' if args.relmse else ''} | "
             + " | ".join(args.variants) + " |",
             "|---" * (len(specs) + 1) + "|"]
    cols: list[list[float]] = [[] for _ in specs]
    for name in names:
        s = tr.load_scene(suite / f"{name}.yaml")
        s = s.replace(camera=dataclasses.replace(s.camera, width=args.size, height=args.size,
                                                 samples_per_pixel=1))
        ref, alpha, _ = truth(s, 1024, 64, 0, Path(args.truth_dir))
        row = []
        for i, (method, opts) in enumerate(specs):
            img = tr.render([s.replace(method=method, method_options=opts)]).radiance[0]
            m = compare(img.numpy(), ref, alpha)
            f = m["flip_object"]
            cols[i].append(f)
            row.append(f"{f:.3f}" + (f" / {m['relmse_object']:.3f}" if args.relmse else ""))
        lines.append(f"| {name} | " + " | ".join(row) + " |")
        print(lines[-1], flush=True)
    lines.append("| mean | " + " | ".join(f"{statistics.mean(c):.4f}" for c in cols) + " |")
    print(lines[-1])
    if args.out:
        Path(args.out).write_text("\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

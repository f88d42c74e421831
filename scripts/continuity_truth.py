"""Does the truth itself keep the continuity suite's per-pixel bound?

tests/test_continuity.py bounds the per-pixel steps of a roughness sweep (at most 1% of
object pixels may change by more than ``P99_BOUND`` of the image mean per step of 0.025 in
alpha). This script renders the same sweep (the same mesh, camera, 32x32 pixels and smooth
environment) with Mitsuba 3 and measures the truth's own 99th-percentile pixel step, so a
variant over the bound is known to be flickering, not merely following a steep truth.

Our renderer samples each pixel at its centre (``samples_per_pixel: 1``); Mitsuba integrates
the pixel's area, which smooths sub-pixel detail. So each truth pixel here is the centre
sub-pixel of a ``--factor`` x ``--factor`` grid (a render at factor times the size, every
factor-th sub-pixel kept): a box of 1/factor of a pixel around the centre. Two seeds give
the truth's own noise (the 99th percentile of their difference, relative to the mean), which
the step includes.

    .venv/bin/python scripts/continuity_truth.py [--mesh suzanne] [--spp 512] [--factor 9]
        [--alphas 0 0.025 0.05 0.075 0.1 0.15 0.175] [--out outputs/continuity_truth.json]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

import torchrefract as tr
from torchrefract.output.images import write_exr
from torchrefract.truth.mitsuba import render_reference

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "tests"))
from conftest import smooth_env_texels  # noqa: E402  (the suite's own environment)
from test_continuity import CAMS, MESHES, P99_BOUND, SIZE  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--mesh", choices=sorted(MESHES), default="suzanne")
    ap.add_argument("--spp", type=int, default=512)
    ap.add_argument("--factor", type=int, default=9, help="odd sub-pixel grid per pixel")
    ap.add_argument("--alphas", type=float, nargs="+",
                    default=[0.0, 0.025, 0.05, 0.075, 0.1, 0.15, 0.175])
    ap.add_argument("--out", default=str(ROOT / "outputs" / "continuity_truth.json"))
    args = ap.parse_args()
    if args.factor % 2 == 0:
        ap.error("--factor must be odd (the centre sub-pixel is the pixel's centre)")
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    env = out.parent / "continuity_smooth_env.exr"
    img = smooth_env_texels()
    write_exr(env, {"R": img[..., 0], "G": img[..., 1], "B": img[..., 2]})
    f, c = args.factor, args.factor // 2
    cam = tr.Camera(eye=CAMS[args.mesh], width=SIZE * f, height=SIZE * f)
    frames = []  # per alpha: (2, SIZE, SIZE) luminance of the two seeds, and coverage
    t0 = time.perf_counter()
    for a in args.alphas:
        scene = tr.Scene(mesh=MESHES[args.mesh], envmap=tr.EnvMap(path=str(env)),
                         material=tr.Material(ior=1.5, roughness=a), camera=cam)
        lum, cov = [], []
        for seed in (1, 2):
            rgb, alpha = render_reference(scene, spp=args.spp, seed=seed, max_depth=64)
            lum.append(rgb.mean(-1)[c::f, c::f])
            cov.append(alpha[c::f, c::f])
        frames.append((np.stack(lum), np.stack(cov)))
        print(f"alpha {a:.4g}: {time.perf_counter() - t0:.0f} s", flush=True)
    obj = np.logical_and.reduce([(cv > 0.999).all(0) for _, cv in frames])
    means = [lum.mean(0) for lum, _ in frames]
    scale = float(np.mean([m[obj].mean() for m in means]))
    steps = []
    for i in range(len(args.alphas) - 1):
        d = np.abs(means[i + 1] - means[i])[obj] / scale
        noise = np.abs(frames[i][0][0] - frames[i][0][1])[obj] / scale
        steps.append({"from": args.alphas[i], "to": args.alphas[i + 1],
                      "p99": float(np.quantile(d, 0.99)), "mean": float(d.mean()),
                      "noise_p99": float(np.quantile(noise, 0.99))})
        s = steps[-1]
        print(f"{s['from']:.4g} -> {s['to']:.4g}: 99th-pct pixel step {s['p99']:.3f} "
              f"(bound {P99_BOUND}; seed-to-seed noise {s['noise_p99']:.3f}), "
              f"mean step {s['mean']:.4f}")
    out.write_text(json.dumps({"mesh": args.mesh, "spp": args.spp, "factor": f,
                               "object_pixels": int(obj.sum()), "bound": P99_BOUND,
                               "steps": steps}, indent=2) + "\n")
    print(f"saved {out}")


if __name__ == "__main__":
    main()

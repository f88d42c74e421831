"""Accuracy of each method against converged Mitsuba 3 truth, with the two-interface floor.

For every scene: full truth (``max_depth`` 64) and the two-interface floor (converged
Mitsuba at ``max_depth`` 3: front reflection + two refractions, what every two-interface
method models at best), both at ``--spp`` samples and cached in outputs/truth/; then each
method's render. Prints relMSE and FLIP on object pixels against full truth (and the floor's
own), the truth's noise (two seeds), and wall time per frame; saves JSON and a side-by-side
PNG per scene under outputs/accuracy/.

    .venv/bin/python scripts/accuracy.py [configs/suite/*.yaml] [--spp 1024]
        [--methods specular prefiltered rousiers] [--size 256]
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import numpy as np
import torch

import torchrefract as tr
from torchrefract.output.images import read_exr, write_exr, write_png
from torchrefract.truth.metrics import compare

ROOT = Path(__file__).resolve().parent.parent
DEFAULT_SCENES = ["sphere_a005", "sphere_a03", "slab_a02", "bunny_a01"]


def truth(scene: tr.Scene, spp: int, max_depth: int, seed: int, cache: Path
          ) -> tuple[np.ndarray, np.ndarray, float]:
    """Mitsuba render (cached by scene name, size, spp, depth, seed)."""
    from torchrefract.truth.mitsuba import render_reference  # noqa: PLC0415

    c = scene.camera
    path = cache / f"{scene.name}_{c.width}x{c.height}_d{max_depth}_spp{spp}_s{seed}.exr"
    if path.exists():
        ch = read_exr(path)
        return np.stack([ch["R"], ch["G"], ch["B"]], -1), ch["A"], float("nan")
    t0 = time.perf_counter()
    rgb, alpha = render_reference(scene, spp=spp, seed=seed, max_depth=max_depth)
    dt = time.perf_counter() - t0
    # Written under a temporary name and renamed: a reader (another script sharing the
    # cache) never sees a half-written file, and an interrupted run leaves no bad entry.
    cache.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.stem}.{os.getpid()}.tmp.exr")
    write_exr(tmp, {"R": rgb[..., 0], "G": rgb[..., 1], "B": rgb[..., 2], "A": alpha})
    os.replace(tmp, path)
    return rgb, alpha, dt


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scenes", nargs="*",
                    default=[str(ROOT / "configs" / "suite" / f"{n}.yaml")
                             for n in DEFAULT_SCENES])
    ap.add_argument("--spp", type=int, default=1024)
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--methods", nargs="+", default=["specular", "prefiltered", "rousiers"])
    ap.add_argument("--repeats", type=int, default=3, help="timing repeats (median)")
    ap.add_argument("--mitsuba-spp", type=int, nargs="*", default=[1, 4, 16, 64],
                    help="Mitsuba (raw) renders to put on the same time/error axes")
    ap.add_argument("--out", default=str(ROOT / "outputs" / "accuracy"))
    args = ap.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    cache = ROOT / "outputs" / "truth"
    results = []
    print(f"torch threads {torch.get_num_threads()}, truth spp {args.spp}")
    print(f"{'scene':<14}{'method':<13}{'relMSE':>9}{'FLIP':>8}{'ms':>9}")
    for path in args.scenes:
        scene = tr.load_scene(path)
        c = scene.camera
        scene = scene.replace(camera=tr.Camera(eye=c.eye, target=c.target, up=c.up,
                                               yfov_deg=c.yfov_deg, width=args.size,
                                               height=args.size,
                                               samples_per_pixel=c.samples_per_pixel))
        full, alpha, t_full = truth(scene, args.spp, 64, 0, cache)
        full2, _, _ = truth(scene, args.spp, 64, 1, cache)
        floor, _, t_floor = truth(scene, args.spp, 3, 0, cache)
        row = {"scene": scene.name, "size": args.size, "truth_spp": args.spp,
               "noise": compare(full2, full, alpha), "floor": compare(floor, full, alpha),
               "methods": {}}
        print(f"{scene.name:<14}{'noise':<13}{row['noise']['relmse_object']:>9.4f}"
              f"{row['noise']['flip_object']:>8.3f}")
        print(f"{scene.name:<14}{'floor(d3)':<13}{row['floor']['relmse_object']:>9.4f}"
              f"{row['floor']['flip_object']:>8.3f}")
        panels = [full, floor]
        for m in args.methods:
            tr.render([scene], method=m)  # warm-up (caches)
            times = []
            for _ in range(args.repeats):
                t0 = time.perf_counter()
                o = tr.render([scene], method=m)
                times.append(time.perf_counter() - t0)
            img = o.radiance[0].numpy()
            met = compare(img, full, alpha)
            met["ms_per_frame"] = 1000 * float(np.median(times))
            met["vs_floor"] = compare(img, floor, alpha)
            row["methods"][m] = met
            panels.append(img)
            print(f"{scene.name:<14}{m:<13}{met['relmse_object']:>9.4f}"
                  f"{met['flip_object']:>8.3f}{met['ms_per_frame']:>9.0f}")
        from torchrefract.truth.mitsuba import render_reference  # noqa: PLC0415

        render_reference(scene, spp=1, seed=7)  # warm-up (JIT compilation)
        row["mitsuba"] = {}
        for spp in args.mitsuba_spp:
            t0 = time.perf_counter()
            img, _ = render_reference(scene, spp=spp, seed=11)
            dt = time.perf_counter() - t0
            met = compare(img, full, alpha)
            met["ms_per_frame"] = 1000 * dt
            row["mitsuba"][spp] = met
            print(f"{scene.name:<14}{'mitsuba ' + str(spp):<13}{met['relmse_object']:>9.4f}"
                  f"{met['flip_object']:>8.3f}{met['ms_per_frame']:>9.0f}")
        results.append(row)
        write_png(out / f"{scene.name}.png", np.concatenate(panels, 1))
    meta = {"torchrefract": tr.__version__, "threads": torch.get_num_threads(),
            "columns_png": ["truth", "floor_d3", *args.methods], "results": results}
    (out / "accuracy.json").write_text(json.dumps(meta, indent=2) + "\n")
    print(f"saved {out / 'accuracy.json'}")


if __name__ == "__main__":
    main()

"""Golden images for refactors: render every suite scene with every method variant of the
chart (and the options the chart does not sweep) and save, or compare against a saved run.

A redesign of the structure must not change the images (issue #23): save before, compare
after. Each image is compared bit for bit; where an operation order had to change, the
largest relative difference on object pixels is printed against ``--rtol``.

    python scripts/golden.py save DIR [--size 64]
    python scripts/golden.py compare DIR [--size 64] [--rtol 1e-5]

Renders at ``--size`` (default 64) with each scene's own supersampling; a batch of 2
(the environment turned by 10 degrees) checks that a batch gives each scene's own image.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
SUITE = ROOT / "configs" / "suite"

# (name, method, method_options, batch)
VARIANTS: list[tuple[str, str, dict, int]] = [
    ("specular", "specular", {}, 1),
    ("specular b2", "specular", {}, 2),
    ("prefiltered", "prefiltered", {}, 1),
    ("rousiers", "rousiers", {}, 1),
    ("rousiers b2", "rousiers", {}, 2),
    ("rousiers plane", "rousiers", {"cone_rays": "plane"}, 1),
    ("rousiers steps 12/4/6", "rousiers",
     {"march_steps": 12, "cone_march_steps": 4, "refine_steps": 6}, 1),
    ("rousiers spread paper", "rousiers", {"spread": "paper"}, 1),
    ("rousiers spread paper+front", "rousiers", {"spread": "paper+front"}, 1),
    ("specular ib1", "specular", {"internal_bounces": 1}, 1),
    ("specular ib2", "specular", {"internal_bounces": 2}, 1),
    ("rousiers ib1", "rousiers", {"internal_bounces": 1}, 1),
    ("rousiers ib2", "rousiers", {"internal_bounces": 2}, 1),
    ("specular ib auto", "specular", {"internal_bounces": "auto"}, 1),
    ("rousiers ib auto", "rousiers", {"internal_bounces": "auto"}, 1),
    ("rousiers ib2 rays4", "rousiers", {"internal_bounces": 2, "bounce_rays": 4}, 1),
    ("specular tir clamp", "specular", {"tir": "clamp"}, 1),
    ("specular tir reflect", "specular", {"tir": "reflect"}, 1),
    ("prefiltered tir clamp", "prefiltered", {"tir": "clamp"}, 1),
    ("rousiers tir clamp", "rousiers", {"tir": "clamp"}, 1),
    ("rousiers tir reflect", "rousiers", {"tir": "reflect"}, 1),
    ("specular ib2 tir clamp", "specular", {"internal_bounces": 2, "tir": "clamp"}, 1),
    ("rousiers ib2 tir clamp", "rousiers", {"internal_bounces": 2, "tir": "clamp"}, 1),
    ("rousiers ib2 tir reflect", "rousiers", {"internal_bounces": 2, "tir": "reflect"}, 1),
    ("auto", "auto", {}, 1),
    ("rousiers 1x1", "rousiers", {"samples_per_pixel": 1}, 1),
]


def _scenes(tr, path: Path, method: str, options: dict, batch: int, size: int):
    s = tr.load_scene(path)
    opts = dict(options)
    spp = opts.pop("samples_per_pixel", s.camera.samples_per_pixel)
    s = s.replace(method=method, method_options=opts,
                  camera=dataclasses.replace(s.camera, width=size, height=size,
                                             samples_per_pixel=spp))
    e = s.envmap
    return [s.replace(envmap=dataclasses.replace(e, rotate_deg=e.rotate_deg + 10.0 * i))
            for i in range(batch)]


def render_all(size: int, only: list[str] | None):
    import torchrefract as tr

    out = {}
    for path in sorted(SUITE.glob("*.yaml")):
        for name, method, options, batch in VARIANTS:
            if only and name not in only:
                continue
            key = f"{path.stem}|{name}"
            t0 = time.perf_counter()
            res = tr.render(_scenes(tr, path, method, options, batch, size))
            out[key + "|radiance"] = res.radiance.numpy()
            out[key + "|coverage"] = res.coverage.numpy()
            for k, v in sorted(res.passes.items()):
                out[f"{key}|pass:{k}"] = v.numpy()
            print(f"{key}: {time.perf_counter() - t0:.2f} s", flush=True)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("mode", choices=("save", "compare"))
    ap.add_argument("dir", type=Path)
    ap.add_argument("--size", type=int, default=64)
    ap.add_argument("--rtol", type=float, default=1e-5)
    ap.add_argument("--only", nargs="*", default=None, help="variant names")
    args = ap.parse_args(argv)
    images = render_all(args.size, args.only)
    f = args.dir / f"golden_{args.size}.npz"
    if args.mode == "save":
        args.dir.mkdir(parents=True, exist_ok=True)
        np.savez_compressed(f, **images)
        print(f"saved {len(images)} arrays to {f}")
        return 0
    ref = np.load(f)
    bad = identical = close = 0
    for k, v in images.items():
        if k not in ref:
            print(f"NEW  {k}")
            continue
        r = ref[k]
        if r.shape == v.shape and np.array_equal(r, v):
            identical += 1
            continue
        if r.shape != v.shape:
            print(f"DIFF {k}: shape {r.shape} vs {v.shape}")
            bad += 1
            continue
        rel = float(np.max(np.abs(v - r) / np.maximum(np.abs(r), 1e-3)))
        ok = rel <= args.rtol
        close += ok
        bad += not ok
        print(f"{'CLOSE' if ok else 'DIFF '} {k}: max rel {rel:.3g}")
    missing = [k for k in ref.files if k not in images and
               (not args.only or k.split("|")[1] in args.only)]
    for k in missing:
        print(f"MISSING {k}")
    print(f"{identical} identical, {close} within rtol {args.rtol}, {bad} different, "
          f"{len(missing)} missing")
    return 1 if bad or missing else 0


if __name__ == "__main__":
    sys.exit(main())

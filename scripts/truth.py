"""Converged Mitsuba truth for the whole suite, cached, with its noise and the floors.

For every scene (default: every ``configs/suite/*.yaml``), at ``--size`` (256) and ``--spp``
(1024, as ``scripts/accuracy.py``): full truth (``max_depth`` 64) at seeds 0 and 1, and the
floors (converged Mitsuba at ``max_depth`` 3, 4 and 5: what a method modelling 2, 3 and 4
interfaces can do at best) at seed 0. Renders go through ``accuracy.truth`` (the one truth
renderer and cache, ``outputs/truth/<scene>_<W>x<H>_d<depth>_spp<spp>_s<seed>.exr``); what is
cached is not rendered again. Then the truth's own noise (seed 1 against seed 0) and each
floor against full truth (relMSE, FLIP, ...: ``torchrefract.truth.metrics.compare``) are written
to ``outputs/truth/noise.json`` (merged with what is there, one entry per scene and size).

    nice -n 10 .venv/bin/python scripts/truth.py [configs/suite/x.yaml ...] [--spp 1024]
        [--size 256] [--threads 1] [--cache outputs/truth]

From Python (e.g. scripts/pareto.py)::

    from truth import ensure_truth
    t = ensure_truth(scene, spp=1024)   # {"full", "full2", "alpha", "floors": {3: ..}, ..}
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

import torchrefract as tr
from torchrefract.checks import ConfigError  # noqa: E402
from torchrefract.truth.metrics import compare

sys.path.insert(0, str(Path(__file__).resolve().parent))
from accuracy import truth  # noqa: E402  (the one truth renderer and cache)

ROOT = Path(__file__).resolve().parent.parent
SUITE = ROOT / "configs" / "suite"
CACHE = ROOT / "outputs" / "truth"
FULL_DEPTH = 64
SEEDS = (0, 1)
FLOOR_DEPTHS = (3, 4, 5)
SPP = 1024
SIZE = 256
METRIC_KEYS = ("relmse_object", "flip_object", "flip", "hdrflip_object", "psnr_object")


def suite_paths() -> list[Path]:
    return sorted(SUITE.glob("*.yaml"))


def sized(scene: tr.Scene, size: int | None) -> tr.Scene:
    """The scene at ``size`` x ``size`` (None: its own size); supersampling is irrelevant
    to Mitsuba (it samples each pixel's square at random)."""
    if not size:
        return scene
    return scene.replace(camera=dataclasses.replace(scene.camera, width=size, height=size))


def ensure_truth(scene: tr.Scene, spp: int = SPP, cache: Path = CACHE,
                 floor_depths: tuple[int, ...] = FLOOR_DEPTHS) -> dict:
    """Full truth at two seeds and the floors of one scene, rendered where not cached.

    Args:
        scene: the scene at the size the truth is wanted.
        spp: Mitsuba samples per pixel.
        cache: the truth cache directory.
        floor_depths: the ``max_depth`` values of the floors.

    Returns:
        ``full`` (H, W, 3) seed 0, ``full2`` seed 1, ``alpha`` (H, W) coverage,
        ``floors`` {depth: (H, W, 3)} at seed 0, ``seconds`` {file key: render time} of what
        this call rendered.
    """
    seconds = {}

    def get(depth: int, seed: int):
        rgb, alpha, dt = truth(scene, spp, depth, seed, cache)
        if not np.isnan(dt):
            seconds[f"d{depth}_s{seed}"] = round(dt, 2)
            print(f"  rendered {scene.name} d{depth} s{seed}: {dt:.1f} s", flush=True)
        return rgb, alpha

    full, alpha = get(FULL_DEPTH, SEEDS[0])
    full2, _ = get(FULL_DEPTH, SEEDS[1])
    floors = {d: get(d, SEEDS[0])[0] for d in floor_depths}
    return {"full": full, "full2": full2, "alpha": alpha, "floors": floors,
            "seconds": seconds}


def truth_metrics(t: dict) -> dict:
    """Noise (seed 1 vs seed 0) and each floor vs full truth (seed 0)."""
    pick = lambda m: {k: float(m[k]) for k in METRIC_KEYS}  # noqa: E731
    return {"noise": pick(compare(t["full2"], t["full"], t["alpha"])),
            "floors": {str(d): pick(compare(img, t["full"], t["alpha"]))
                       for d, img in t["floors"].items()},
            "coverage": float((t["alpha"] > 0.5).mean())}


def record(scene: tr.Scene, spp: int, metrics: dict, seconds: dict, cache: Path) -> None:
    """Merge one scene's entry into ``cache/noise.json`` (atomically replaced)."""
    path = cache / "noise.json"
    data = json.loads(path.read_text()) if path.is_file() else {}
    c = scene.camera
    key = f"{scene.name}_{c.width}x{c.height}_spp{spp}"
    old = data.get(key, {})
    data[key] = {"scene": scene.name, "size": [c.width, c.height], "spp": spp,
                 "full_depth": FULL_DEPTH, "seeds": list(SEEDS),
                 "render_seconds": {**old.get("render_seconds", {}), **seconds}, **metrics}
    tmp = path.with_name(f".noise.{os.getpid()}.tmp.json")
    tmp.write_text(json.dumps(data, indent=1, sort_keys=True) + "\n")
    os.replace(tmp, path)


def ensure_suite(paths: list[Path] | None = None, spp: int = SPP, size: int | None = SIZE,
                 cache: Path = CACHE) -> dict[str, dict]:
    """:func:`ensure_truth` and :func:`record` for every scene; returns the metrics by name."""
    out = {}
    for p in paths or suite_paths():
        scene = sized(tr.load_scene(p), size)
        t0 = time.perf_counter()
        t = ensure_truth(scene, spp, cache)
        m = truth_metrics(t)
        record(scene, spp, m, t["seconds"], cache)
        out[scene.name] = m
        fl = "  ".join(f"d{d} {m['floors'][str(d)]['flip_object']:.3f}"
                       for d in FLOOR_DEPTHS)
        print(f"{scene.name:<18} noise relMSE {m['noise']['relmse_object']:.4f} "
              f"FLIP {m['noise']['flip_object']:.3f} | floors FLIP {fl} "
              f"({time.perf_counter() - t0:.0f} s)", flush=True)
    return out


def _positive(value: str) -> int:
    """argparse type of --spp: a whole number >= 1."""
    if not value.isdigit() or int(value) < 1:
        raise argparse.ArgumentTypeError(f"expected a whole number >= 1, got {value!r}")
    return int(value)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scenes", nargs="*", help="scene files (default: configs/suite/*.yaml)")
    ap.add_argument("--spp", type=_positive, default=SPP)
    ap.add_argument("--size", type=int, default=SIZE, help="0: each scene's own size")
    ap.add_argument("--threads", type=int, default=0, help="torch threads (0: default)")
    ap.add_argument("--cache", default=str(CACHE), help="truth cache directory")
    args = ap.parse_args()
    if args.threads:
        import torch  # noqa: PLC0415

        torch.set_num_threads(args.threads)
    cache = Path(args.cache)
    ensure_suite([Path(p) for p in args.scenes] or None, args.spp, args.size or None, cache)
    print(f"saved {cache / 'noise.json'}")


if __name__ == "__main__":
    try:
        main()
    except ConfigError as exc:  # bad arguments or scenes: one line, exit 2
        print(f"truth: {exc}", file=sys.stderr)
        sys.exit(2)

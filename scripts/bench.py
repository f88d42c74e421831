"""Benchmark: milliseconds per frame by method, resolution and batch size, per stage.

Prints a table and saves JSON (default outputs/bench/bench.json). Quote medians, measured
with the machine quiet; the thread count is recorded. Stages (``RenderResult.timings``):
G-buffer (the pyrender passes and exact intersections) and the method's shading, which
includes the back layer's mip pyramids (``mips``) and the ray marches (``march``); ``rest``
is the shading outside those two (lobes, table and environment lookups, bounces). Each row
runs in a fresh process (``--in-process``: all in this one, faster, but then the memory
column is the peak so far), so its peak resident memory is its own: ``peakMB``, with the
process's memory before the row's first render (torch, pyrender, the scene) in the JSON
as ``baseline_rss_mb``.

    .venv/bin/python scripts/bench.py [--methods specular rousiers rousiers:cone_rays=plane]
        [--sizes 256 512] [--batches 1 8] [--repeats 5] [--threads N] [--compile]
        [--no-native] [--no-heap-reuse] [--in-process] [--views shared distinct]
        [--out outputs/bench]

Heap reuse (``RenderSettings(heap_reuse=True)``) is on, as in the ``torchrefract`` command:
freed tensor memory is reused instead of faulted in again (``--no-heap-reuse``: glibc's
default).

The batch items differ by their environment map's rotation (10 degrees apart). ``--views``:
``distinct`` (default) also turns each item's camera 3 degrees further around the object,
so every item has its own G-buffer; ``shared`` keeps one camera for the whole batch (a
sweep of materials or maps over one view), whose G-buffer is then built once per batch.

A method may carry options after a colon: ``rousiers:cone_rays=plane,march_steps=24``.
"""

from __future__ import annotations

import argparse
import dataclasses
import itertools
import json
import math
import platform
import re
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path

import torch

import torchrefract as tr
from torchrefract import heap
from torchrefract.kernels import native

ROOT = Path(__file__).resolve().parent.parent


def rss_mb(field: str = "VmHWM") -> float:
    """Resident memory of this process in MB: its peak (``VmHWM``) or current (``VmRSS``)
    from /proc; the peak from getrusage where /proc is missing."""
    try:
        with open("/proc/self/status") as f:
            return int(re.search(rf"{field}:\s+(\d+)", f.read()).group(1)) / 1024
    except (OSError, AttributeError):
        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def parse_method_spec(spec: str) -> tuple[str, dict]:
    """``method[:k=v,...]`` (e.g. ``rousiers:cone_rays=plane,march_steps=24``) -> (method,
    options); integer values become ints."""
    method, _, rest = spec.partition(":")
    options: dict = {}
    for kv in filter(None, rest.split(",")):
        k, v = kv.split("=")
        options[k] = int(v) if v.lstrip("-").isdigit() else v
    return method, options


def orbit(cam: tr.Camera, deg: float) -> tr.Camera:
    """``cam`` turned by ``deg`` degrees around its target, about its up vector."""
    eye, target, up = (torch.tensor(v, dtype=torch.float64) for v in (cam.eye, cam.target,
                                                                    cam.up))
    k = up / up.norm()
    r = eye - target
    a = math.radians(deg)
    r = (r * math.cos(a) + torch.cross(k, r, dim=0) * math.sin(a)
         + k * torch.dot(k, r) * (1.0 - math.cos(a)))
    return dataclasses.replace(cam, eye=tuple((target + r).tolist()))


def bench_one(base: tr.Scene, method: str, size: int, batch: int, repeats: int,
              views: str = "distinct", settings: tr.RenderSettings | None = None) -> dict:
    method, options = parse_method_spec(method)
    base = base.replace(method_options=options)
    cam = base.camera
    scene = base.replace(camera=tr.Camera(eye=cam.eye, target=cam.target, up=cam.up,
                                          yfov_deg=cam.yfov_deg, width=size, height=size,
                                          samples_per_pixel=1))
    # Vary each batch item so the batch is not one image repeated: the map's rotation, and
    # (``distinct``) the camera.
    scenes = [scene.replace(envmap=tr.EnvMap(path=scene.envmap.path, scale=scene.envmap.scale,
                                             rotate_deg=scene.envmap.rotate_deg + 10 * i),
                            camera=orbit(scene.camera, 3.0 * i) if views == "distinct"
                            else scene.camera)
              for i in range(batch)]
    baseline = rss_mb("VmRSS")
    t0 = time.perf_counter()
    tr.render(scenes, method=method, settings=settings)  # warm-up (context, caches, compiling)
    warmup = time.perf_counter() - t0
    totals, stages = [], {}
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = tr.render(scenes, method=method, settings=settings)
        totals.append(time.perf_counter() - t0)
        for k, v in out.timings.items():
            stages.setdefault(k, []).append(v)
    for i in range(repeats):  # the method's own time outside its marches and mips
        stages.setdefault("shading_rest", []).append(
            stages["shading"][i] - stages.get("march", [0.0] * repeats)[i]
            - stages.get("mips", [0.0] * repeats)[i])
    return {
        "method": method, "options": options, "size": size, "batch": batch, "views": views,
        "repeats": repeats,
        "ms_per_frame": 1000 * statistics.median(totals) / batch,
        "ms_per_frame_stage": {k: 1000 * statistics.median(v) / batch
                               for k, v in stages.items()},
        "peak_rss_mb": rss_mb("VmHWM"), "baseline_rss_mb": baseline,
        "warmup_s": warmup, "compiled": bool(settings and settings.compile),
        "native": native.available() if settings is None or settings.native else False,
        "heap_reuse": heap.heap_reuse(), "threads": torch.get_num_threads(),
    }


def run_row(args: argparse.Namespace, method: str, size: int, batch: int, views: str) -> dict:
    """One row in a fresh Python process (its own peak memory)."""
    cmd = [sys.executable, str(Path(__file__).resolve()), "--row", method, str(size),
           str(batch), "--repeats", str(args.repeats), "--scene", args.scene,
           "--views", views]
    if args.threads:
        cmd += ["--threads", str(args.threads)]
    if args.compile:
        cmd.append("--compile")
    if args.no_native:
        cmd.append("--no-native")
    if args.no_heap_reuse:
        cmd.append("--no-heap-reuse")
    proc = subprocess.run(cmd, capture_output=True, text=True)
    for line in proc.stdout.splitlines():
        if line.startswith("ROW "):
            return json.loads(line[4:])
    raise RuntimeError(f"bench row {method} {size} {batch} failed (exit {proc.returncode}):\n"
                       f"{proc.stderr[-2000:]}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default=str(ROOT / "configs" / "demo.yaml"))
    ap.add_argument("--methods", nargs="+", default=["specular"])
    ap.add_argument("--sizes", nargs="+", type=int, default=[256, 512])
    ap.add_argument("--batches", nargs="+", type=int, default=[1, 8])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--threads", type=int, default=None)
    ap.add_argument("--compile", action="store_true",
                    help="torch.compile the march (RenderSettings.compile); the first "
                         "render of each row (warm-up, not timed) includes the compiling")
    ap.add_argument("--no-native", action="store_true",
                    help="march with the tensor code instead of the native kernel "
                         "(RenderSettings(native=False); the same images)")
    ap.add_argument("--no-heap-reuse", action="store_true",
                    help="leave glibc's allocator as it is: plain RenderSettings() defaults, "
                         "as a Python process calling torchrefract.render() gets (default "
                         "here: heap reuse, as in the torchrefract command)")
    ap.add_argument("--views", nargs="+", choices=("distinct", "shared"), default=["distinct"],
                    help="batch items each with its own camera (distinct) or all with one "
                         "(shared: its G-buffer is built once)")
    ap.add_argument("--out", default=str(ROOT / "outputs" / "bench"))
    ap.add_argument("--in-process", action="store_true",
                    help="run every row in this process (memory: the peak so far)")
    ap.add_argument("--row", nargs=3, metavar=("METHOD", "SIZE", "BATCH"),
                    help=argparse.SUPPRESS)  # one row, printed as JSON (the child process)
    args = ap.parse_args()
    settings = tr.RenderSettings(threads=args.threads, compile=args.compile,
                                 native=not args.no_native,
                                 heap_reuse=not args.no_heap_reuse)
    heap_reuse = settings.heap_reuse and heap.set_heap_reuse(True)
    if args.threads:
        torch.set_num_threads(args.threads)  # the printed count (renders set their own)
    base = tr.load_scene(args.scene)
    if args.row:
        r = bench_one(base, args.row[0], int(args.row[1]), int(args.row[2]), args.repeats,
                      args.views[0], settings)
        print("ROW " + json.dumps(r))
        return
    rows = []
    print(f"torch {torch.__version__}, threads {torch.get_num_threads()}, {platform.machine()}"
          f"{', compiled march' if args.compile else ''}"
          f"{', tensor-code march' if args.no_native else ''}"
          f"{', heap reuse' if heap_reuse else ''}")
    print(f"{'method':<28}{'views':>9}{'size':>6}{'batch':>6}{'ms/frame':>10}{'gbuffer':>9}"
          f"{'shading':>9}{'(mips':>7}{'march':>7}{'rest)':>7}{'peakMB':>8}")
    for method, views, size, batch in itertools.product(args.methods, args.views, args.sizes,
                                                        args.batches):
        if batch == 1 and views == "shared" and "distinct" in args.views:
            continue  # one item: the same row
        r = (bench_one(base, method, size, batch, args.repeats, views, settings)
             if args.in_process
             else run_row(args, method, size, batch, views))
        rows.append(r)
        st = r["ms_per_frame_stage"]
        print(f"{method[:28]:<28}{views:>9}{size:>6}{batch:>6}{r['ms_per_frame']:>10.1f}"
              f"{st['gbuffer']:>9.1f}{st['shading']:>9.1f}{st['mips']:>7.1f}"
              f"{st['march']:>7.1f}{st['shading_rest']:>7.1f}{r['peak_rss_mb']:>8.0f}")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    meta = {"torchrefract": tr.__version__, "torch": torch.__version__,
            "threads": torch.get_num_threads(), "machine": platform.platform(),
            "compiled": args.compile, "native": not args.no_native,
            "heap_reuse": heap_reuse,
            "scene": args.scene, "results": rows}
    (out / "bench.json").write_text(json.dumps(meta, indent=2) + "\n")
    print(f"saved {out / 'bench.json'}")


if __name__ == "__main__":
    main()

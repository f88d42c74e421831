"""Benchmark: milliseconds per frame by method, resolution and batch size, per stage.

Prints a table and saves JSON (default outputs/bench/bench.json). Quote medians, measured
with the machine quiet; the thread count is recorded. Stages (``RenderResult.timings``):
G-buffer (the pyrender passes and exact intersections) and the method's shading, which
includes the back layer's mip pyramids (``mips``), the ray marches (``march``) and a fused
shading kernel (``fused``, its marches included); ``rest``
is the shading outside those two (lobes, table and environment lookups, bounces). Each row
runs in a fresh process (``--in-process``: all in this one, faster, but then the memory
column is the peak so far), so its peak resident memory is its own: ``peakMB``, with the
process's memory before the row's first render (torch, pyrender, the scene) in the JSON
as ``baseline_rss_mb``.

    .venv/bin/python scripts/bench.py [--methods specular rousiers rousiers:cone_rays=plane]
        [--sizes 256 512] [--batches 1 8] [--repeats 5] [--threads N] [--compile]
        [--no-native] [--no-fused] [--no-heap-reuse] [--in-process] [--views shared distinct]
        [--mitsuba | --no-mitsuba] [--out outputs/bench]

Heap reuse (``RenderSettings(heap_reuse=True)``) is on, as in the ``torchrefract`` command:
freed tensor memory is reused instead of faulted in again (``--no-heap-reuse``: glibc's
default).

The batch items differ by their environment map's rotation (10 degrees apart). ``--views``:
``distinct`` (default) also turns each item's camera 3 degrees further around the object,
so every item has its own G-buffer; ``shared`` keeps one camera for the whole batch (a
sweep of materials or maps over one view), whose G-buffer is then built once per batch.

A method may carry options after a colon: ``rousiers:cone_rays=plane,march_steps=24``.

Mitsuba rows (``--mitsuba``, the default where Mitsuba 3 imports; ``--no-mitsuba`` to leave
them out): after our rows, in this (the parent) process, for each size and ``--views`` of the
run, Mitsuba 3 renders the scenes of the run's largest batch (:func:`bench_scenes`: the same
cameras and map rotations) through the package's bridge (``torchrefract.truth.mitsuba``, the
variant it picks: ``llvm_ad_rgb`` where libLLVM 19 is installed, else ``scalar_rgb``) at
:data:`MITSUBA_ROWS`: 1 sample per pixel, and 4 with Intel Open Image Denoise
(``torchrefract.methods.reference.denoise_oidn``, the ``reference`` method's). One untimed
warm-up pass over the scenes (LLVM kernels, OIDN's device), then the median of ``--repeats``
passes, per frame: the render read back to host memory, plus the denoising in the OIDN row.
Each pass builds every scene's Mitsuba scene anew; that build (conversion, ``load_dict``:
the environment map read and its sampling tables built) is timed apart
(``build_ms_per_frame``) and not in ``ms_per_frame``, as our rows' loads are cached. No
coverage pass. A second table gives, per row, our ms per frame, Mitsuba's and the ratio
(Mitsuba / ours: above 1, ours is faster). ``--threads`` also sets drjit's thread count for
Mitsuba's renders (not its scene builds: see :func:`bench_mitsuba`) and OIDN's
(``OIDN_NUM_THREADS``, unless set already).
"""

from __future__ import annotations

import argparse
import dataclasses
import itertools
import json
import math
import os
import platform
import re
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import torch

import torchrefract as tr
from torchrefract import heap
from torchrefract.kernels import native

ROOT = Path(__file__).resolve().parent.parent

MITSUBA_ROWS: tuple[tuple[int, bool], ...] = ((1, False), (4, True))
"""The Mitsuba rows: (samples per pixel, OIDN denoising)."""
MITSUBA_SEED = 0
MITSUBA_MAX_DEPTH = 64  # the truth's (SCENE_SPEC.md), as the ``reference`` method's default


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


def bench_scenes(base: tr.Scene, size: int, batch: int, views: str = "distinct"
                 ) -> list[tr.Scene]:
    """The ``batch`` scenes of a row: ``base`` at ``size`` x ``size``, one sample per pixel,
    each item's map turned 10 degrees further and (``distinct``) its camera 3 degrees
    further around the target (the Mitsuba rows render these same scenes)."""
    cam = base.camera
    scene = base.replace(camera=tr.Camera(eye=cam.eye, target=cam.target, up=cam.up,
                                          yfov_deg=cam.yfov_deg, width=size, height=size,
                                          samples_per_pixel=1))
    # Vary each batch item so the batch is not one image repeated: the map's rotation, and
    # (``distinct``) the camera.
    return [scene.replace(envmap=tr.EnvMap(path=scene.envmap.path, scale=scene.envmap.scale,
                                           rotate_deg=scene.envmap.rotate_deg + 10 * i),
                          camera=orbit(scene.camera, 3.0 * i) if views == "distinct"
                          else scene.camera)
            for i in range(batch)]


def bench_one(base: tr.Scene, method: str, size: int, batch: int, repeats: int,
              views: str = "distinct", settings: tr.RenderSettings | None = None) -> dict:
    method, options = parse_method_spec(method)
    scenes = bench_scenes(base.replace(method_options=options), size, batch, views)
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
    for i in range(repeats):  # the method's own time outside its marches, mips and kernel
        stages.setdefault("shading_rest", []).append(
            stages["shading"][i] - sum(stages.get(k, [0.0] * repeats)[i]
                                       for k in ("march", "mips", "fused")))
    return {
        "method": method, "options": options, "size": size, "batch": batch, "views": views,
        "repeats": repeats,
        "ms_per_frame": 1000 * statistics.median(totals) / batch,
        "ms_per_frame_stage": {k: 1000 * statistics.median(v) / batch
                               for k, v in stages.items()},
        "peak_rss_mb": rss_mb("VmHWM"), "baseline_rss_mb": baseline,
        "warmup_s": warmup, "compiled": bool(settings and settings.compile),
        "native": native.available() if settings is None or settings.native else False,
        "fused": bool((settings is None or settings.fused) and native.available()),
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
    if args.no_fused:
        cmd.append("--no-fused")
    if args.no_heap_reuse:
        cmd.append("--no-heap-reuse")
    proc = subprocess.run(cmd, capture_output=True, text=True)
    for line in proc.stdout.splitlines():
        if line.startswith("ROW "):
            return json.loads(line[4:])
    raise RuntimeError(f"bench row {method} {size} {batch} failed (exit {proc.returncode}):\n"
                       f"{proc.stderr[-2000:]}")


def load_mitsuba():
    """(the mitsuba module with the bridge's variant set, "") or (None, why not)."""
    try:
        from torchrefract.truth.mitsuba import mitsuba  # noqa: PLC0415 (optional dependency)
        return mitsuba(), ""
    except ImportError as exc:
        return None, str(exc)


def bench_mitsuba(base: tr.Scene, size: int, batch: int, repeats: int,
                  views: str = "distinct", spp: int = 1, denoise: bool = False,
                  threads: int | None = None) -> dict:
    """Mitsuba 3 per frame on the scenes of :func:`bench_scenes` (module docstring), here.

    Each pass builds every scene's Mitsuba scene (``to_mitsuba_dict``, ``load_dict``), renders
    them at ``spp`` (``mi.render``, read back into a NumPy array) and with ``denoise`` runs
    :func:`~torchrefract.methods.reference.denoise_oidn` on each image; the first pass is
    the untimed warm-up. ``ms_per_frame``: the median over ``repeats`` of render (+ denoise)
    per frame; each stage's median apart too, the build's (``build_ms_per_frame``) not in
    ``ms_per_frame``.
    ``threads``: drjit's thread count for the renders; the builds keep drjit's default (with
    one drjit thread, loading the ``envmap`` never returns: Mitsuba 3.9.1, drjit 1.5.0).

    Raises:
        ImportError: Mitsuba (or, with ``denoise``, pyoidn) is not installed.
    """
    from torchrefract.methods.reference import denoise_oidn  # noqa: PLC0415
    from torchrefract.truth.mitsuba import mitsuba, to_mitsuba_dict  # noqa: PLC0415

    mi = mitsuba()
    import drjit as dr  # noqa: PLC0415 (mitsuba's own dependency)

    default_threads = dr.thread_count()
    scenes = bench_scenes(base, size, batch, views)

    def one_pass() -> tuple[float, float, float]:
        t0 = time.perf_counter()
        built = [mi.load_dict(to_mitsuba_dict(s, spp=spp, seed=MITSUBA_SEED,
                                              max_depth=MITSUBA_MAX_DEPTH)) for s in scenes]
        t1 = time.perf_counter()
        if threads:
            dr.set_thread_count(threads)
        try:
            t1b = time.perf_counter()
            images = [np.array(mi.render(m), dtype=np.float32)[..., :3] for m in built]
            t2 = time.perf_counter()
            if denoise:
                for img in images:
                    denoise_oidn(torch.from_numpy(np.ascontiguousarray(img)))
            t3 = time.perf_counter()
        finally:
            if threads:
                dr.set_thread_count(default_threads)
        return t1 - t0, t2 - t1b, t3 - t2 if denoise else 0.0

    t0 = time.perf_counter()
    one_pass()  # warm-up: LLVM kernels, the map's first read, OIDN's device and weights
    warmup = time.perf_counter() - t0
    passes = [one_pass() for _ in range(repeats)]

    def per_frame(values) -> float:
        return 1000 * statistics.median(values) / batch

    return {
        "spp": spp, "denoise": denoise, "size": size, "views": views, "batch": batch,
        "repeats": repeats, "seed": MITSUBA_SEED, "max_depth": MITSUBA_MAX_DEPTH,
        "ms_per_frame": per_frame([r + d for _, r, d in passes]),
        "render_ms_per_frame": per_frame([r for _, r, _ in passes]),
        "denoise_ms_per_frame": per_frame([d for _, _, d in passes]),
        "build_ms_per_frame": per_frame([b for b, _, _ in passes]),
        "warmup_s": warmup, "variant": mi.variant(), "threads": threads or default_threads,
        "build_threads": default_threads,
    }


def mitsuba_rows(args: argparse.Namespace, base: tr.Scene) -> dict:
    """The Mitsuba rows of the run (module docstring) and how they were made; ``skipped``
    says why there are none."""
    mi, why = load_mitsuba()
    if mi is None:
        print(f"Mitsuba rows skipped: {why}")
        return {"skipped": why, "rows": []}
    import drjit as dr  # noqa: PLC0415

    if args.threads:  # OIDN's CPU device reads it when it is made (first denoising)
        os.environ.setdefault("OIDN_NUM_THREADS", str(args.threads))
    threads = args.threads or dr.thread_count()
    meta: dict = {"variant": mi.variant(), "version": mi.__version__,
                  "threads": threads, "build_threads": dr.thread_count(),
                  "oidn_threads": os.environ.get("OIDN_NUM_THREADS", "OIDN's default (all "
                                                 "cores)"),
                  "seed": MITSUBA_SEED,
                  "max_depth": MITSUBA_MAX_DEPTH,
                  "timed": "render (+ OIDN) per frame, median of the repeats after one "
                           "untimed warm-up pass; scene build apart (build_ms_per_frame), "
                           "no coverage pass",
                  "rows": [], "skipped_rows": []}
    batch = max(args.batches)
    print(f"Mitsuba {mi.__version__} {mi.variant()}, {threads} threads, the scenes of "
          f"batch {batch}, scene build not timed in ms/frame")
    print(f"{'mitsuba':<28}{'views':>9}{'size':>6}{'frames':>7}{'ms/frame':>10}{'render':>9}"
          f"{'oidn':>8}{'(build)':>9}")
    for views, size, (spp, denoise) in itertools.product(args.views, args.sizes,
                                                         MITSUBA_ROWS):
        name = f"{spp} spp{' + OIDN' if denoise else ''}"
        try:
            r = bench_mitsuba(base, size, batch, args.repeats, views, spp, denoise,
                              args.threads)
        except ImportError as exc:  # pyoidn missing: the denoised row only
            print(f"Mitsuba {name} skipped: {exc}")
            meta["skipped_rows"].append({"spp": spp, "denoise": denoise, "reason": str(exc)})
            continue
        meta["rows"].append(r)
        print(f"{name:<28}{views:>9}{size:>6}{batch:>7}{r['ms_per_frame']:>10.1f}"
              f"{r['render_ms_per_frame']:>9.1f}{r['denoise_ms_per_frame']:>8.1f}"
              f"{r['build_ms_per_frame']:>9.1f}")
    return meta


def compare_rows(rows: list[dict], mitsuba: list[dict]) -> list[dict]:
    """Per bench row: our ms per frame, each Mitsuba row's of the same size and views, and
    their ratio (Mitsuba / ours: above 1, ours is faster)."""
    out = []
    for r in rows:
        c = {k: r[k] for k in ("method", "options", "views", "size", "batch")}
        c["ms_per_frame"] = r["ms_per_frame"]
        for spp, denoise in MITSUBA_ROWS:
            key = f"mitsuba_{spp}spp{'_oidn' if denoise else ''}"
            m = next((m for m in mitsuba if (m["size"], m["views"], m["spp"], m["denoise"])
                      == (r["size"], r["views"], spp, denoise)), None)
            c[f"{key}_ms_per_frame"] = None if m is None else m["ms_per_frame"]
            c[f"{key}_ratio"] = None if m is None else m["ms_per_frame"] / r["ms_per_frame"]
        out.append(c)
    return out


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
    ap.add_argument("--no-fused", action="store_true",
                    help="each method's tensor code instead of its fused shading kernel "
                         "(RenderSettings(fused=False); the same images within float32 "
                         "rounding)")
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
    ap.add_argument("--mitsuba", action=argparse.BooleanOptionalAction, default=None,
                    help="after our rows, time Mitsuba 3 at 1 spp and at 4 spp + OIDN on "
                         "the same scenes, in this process, and print the ratios (default: "
                         "on where Mitsuba imports; --mitsuba: an error where it does not)")
    ap.add_argument("--row", nargs=3, metavar=("METHOD", "SIZE", "BATCH"),
                    help=argparse.SUPPRESS)  # one row, printed as JSON (the child process)
    args = ap.parse_args()
    settings = tr.RenderSettings(threads=args.threads, compile=args.compile,
                                 native=not args.no_native, fused=not args.no_fused,
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
          f"{', tensor-code shading' if args.no_fused else ''}"
          f"{', heap reuse' if heap_reuse else ''}")
    print(f"{'method':<28}{'views':>9}{'size':>6}{'batch':>6}{'ms/frame':>10}{'gbuffer':>9}"
          f"{'shading':>9}{'(mips':>7}{'march':>7}{'fused':>7}{'rest)':>7}{'peakMB':>8}")
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
              f"{st['march']:>7.1f}{st['fused']:>7.1f}{st['shading_rest']:>7.1f}"
              f"{r['peak_rss_mb']:>8.0f}")
    mitsuba = {"skipped": "--no-mitsuba", "rows": []}
    if args.mitsuba is not False:
        mitsuba = mitsuba_rows(args, base)
    versus = compare_rows(rows, mitsuba["rows"])
    if mitsuba["rows"]:
        print("ms per frame, ours against Mitsuba's (ratio: Mitsuba / ours, above 1: ours "
              "faster)")
        print(f"{'method':<28}{'views':>9}{'size':>6}{'batch':>6}{'ours':>8}{'mi 1spp':>9}"
              f"{'ratio':>7}{'mi 4spp+oidn':>14}{'ratio':>7}")

        def cell(v, width: int, fmt: str) -> str:
            return f"{'-':>{width}}" if v is None else f"{v:>{width}{fmt}}"

        for c in versus:
            name = c["method"] + (":" + ",".join(f"{k}={v}" for k, v in c["options"].items())
                                  if c["options"] else "")
            print(f"{name[:28]:<28}{c['views']:>9}{c['size']:>6}{c['batch']:>6}"
                  f"{c['ms_per_frame']:>8.1f}{cell(c['mitsuba_1spp_ms_per_frame'], 9, '.1f')}"
                  f"{cell(c['mitsuba_1spp_ratio'], 7, '.2f')}"
                  f"{cell(c['mitsuba_4spp_oidn_ms_per_frame'], 14, '.1f')}"
                  f"{cell(c['mitsuba_4spp_oidn_ratio'], 7, '.2f')}")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    meta = {"torchrefract": tr.__version__, "torch": torch.__version__,
            "threads": torch.get_num_threads(), "machine": platform.platform(),
            "compiled": args.compile, "native": not args.no_native, "fused": not args.no_fused,
            "heap_reuse": heap_reuse,
            "scene": args.scene, "results": rows,
            "mitsuba": mitsuba, "vs_mitsuba": versus}
    (out / "bench.json").write_text(json.dumps(meta, indent=2) + "\n")
    print(f"saved {out / 'bench.json'}")
    if args.mitsuba and not mitsuba["rows"]:
        sys.exit(f"bench: --mitsuba: no Mitsuba row measured ({mitsuba.get('skipped')})")


if __name__ == "__main__":
    main()

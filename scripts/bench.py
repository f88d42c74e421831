"""Benchmark: milliseconds per frame by method, resolution and batch size, per stage.

Prints a table and saves JSON (default outputs/bench/bench.json). Quote medians, measured
with the machine quiet; the thread count is recorded. Stages (``RenderResult.timings``):
G-buffer (the id passes and exact intersections) and the method's shading, which
includes the back layer's mip pyramids (``mips``), the ray marches (``march``) and a fused
shading kernel (``fused``, its marches included); ``rest``
is the shading outside those two (lobes, table and environment lookups, bounces). Each row
runs in a fresh process (``--in-process``: all in this one, faster, but then the memory
column is the peak so far), so its peak resident memory is its own: ``peakMB``, with the
process's memory before the row's first render (torch, pyrender, the scene) in the JSON
as ``baseline_rss_mb``. ``--interleave`` runs every row in this process in rounds, one
render of each row per round, our rows turned by one each round and Mitsuba's after them
(:func:`round_order`): on a machine whose load drifts (other jobs, another session's)
every row sees the same drift, so the ratios between rows hold where back-to-back rows
can differ by 2x.

    .venv/bin/python scripts/bench.py [--methods specular rousiers rousiers:cone_rays=plane]
        [--sizes 256 512] [--batches 1 8] [--repeats 5] [--threads N] [--compile]
        [--no-native] [--no-fused] [--no-heap-reuse] [--in-process | --interleave]
        [--views shared distinct]
        [--mitsuba | --no-mitsuba] [--out outputs/bench]

Heap reuse (``RenderSettings(heap_reuse=True)``) is on, as in the ``torchrefract`` command:
freed tensor memory is reused instead of faulted in again (``--no-heap-reuse``: glibc's
default).

The batch items differ by their environment map's rotation (10 degrees apart). ``--views``:
``distinct`` (default) also turns each item's camera 3 degrees further around the object,
so every item has its own G-buffer; ``shared`` keeps one camera for the whole batch (a
sweep of materials or maps over one view), whose G-buffer is then built once per batch.
Every timed batch turns all its cameras a hundredth of a degree further than the last, so
nothing kept per camera (rays, frames) carries over from one timed batch to the next, as
in a dataset whose every batch has new views.

A method may carry options after a colon: ``rousiers:cone_rays=plane,march_steps=24``; a
trailing ``+adaptive`` renders that row with ``RenderSettings(adaptive=True)`` (adaptive
sampling, the library's default: at one sample per pixel, the 2x2 lattice and the pixels
between it only where not smooth); a row without it shades every pixel
(``adaptive=False``), as the bench's rows always have. ``spp=N`` among the options is not
the method's: the row's images have N x N samples per pixel (the camera's grid; default 1,
as Mitsuba's rows stay at theirs), e.g. ``rousiers:spp=2+adaptive`` against
``rousiers+adaptive`` for what supersampling costs.

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
from torchrefract.checks import ConfigError  # noqa: E402
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


ADAPTIVE_SUFFIX = "+adaptive"
"""A row spec ending in it renders with ``RenderSettings(adaptive=True)``."""


def parse_method_spec(spec: str) -> tuple[str, dict]:
    """``method[:k=v,...][+adaptive]`` (e.g. ``rousiers:cone_rays=plane,march_steps=24``)
    -> (method, options); integer values become ints."""
    method, _, rest = spec.removesuffix(ADAPTIVE_SUFFIX).partition(":")
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


def bench_scenes(base: tr.Scene, size: int, batch: int, views: str = "distinct",
                 spp: int = 1) -> list[tr.Scene]:
    """The ``batch`` scenes of a row: ``base`` at ``size`` x ``size``, ``spp`` x ``spp``
    samples per pixel, each item's map turned 10 degrees further and (``distinct``) its
    camera 3 degrees further around the target (the Mitsuba rows render these same scenes,
    at their own spp)."""
    cam = base.camera
    scene = base.replace(camera=tr.Camera(eye=cam.eye, target=cam.target, up=cam.up,
                                          yfov_deg=cam.yfov_deg, width=size, height=size,
                                          samples_per_pixel=spp))
    # Vary each batch item so the batch is not one image repeated: the map's rotation, and
    # (``distinct``) the camera.
    return [scene.replace(envmap=tr.EnvMap(path=scene.envmap.path, scale=scene.envmap.scale,
                                           rotate_deg=scene.envmap.rotate_deg + 10 * i),
                          camera=orbit(scene.camera, 3.0 * i) if views == "distinct"
                          else scene.camera)
            for i in range(batch)]


class OursRow:
    """One of our rows: its scenes and settings, a warm-up render and timed renders."""

    def __init__(self, base: tr.Scene, method: str, size: int, batch: int,
                 views: str = "distinct", settings: tr.RenderSettings | None = None):
        self.spec, self.size, self.batch, self.views = method, size, batch, views
        self.method, self.options = parse_method_spec(method)
        self.spp = self.options.pop("spp", 1)  # the camera's, not a method option
        if not isinstance(self.spp, int) or not 1 <= self.spp <= 16:
            raise ValueError(f"bench row {method!r}: spp={self.spp} is not a whole number of "
                             f"samples per pixel side from 1 to 16")
        self.scenes = bench_scenes(base.replace(method_options=self.options), size, batch,
                                   views, self.spp)
        self.adaptive = method.endswith(ADAPTIVE_SUFFIX)
        settings = dataclasses.replace(settings or tr.RenderSettings(), adaptive=self.adaptive)
        self.settings = settings
        self.baseline = rss_mb("VmRSS")
        self.warmup = 0.0
        self.totals: list[float] = []
        self.stages: dict[str, list[float]] = {}

    def warm(self) -> None:
        t0 = time.perf_counter()
        tr.render(self.scenes, method=self.method, settings=self.settings)  # caches, compiling
        self.warmup = time.perf_counter() - t0

    def once(self) -> None:
        # Each timed batch sees new cameras (turned by a hundredth of a degree more each
        # time), as a dataset's batches do: nothing kept per camera from the last batch.
        turn = 0.01 * (len(self.totals) + 1)
        scenes = [s.replace(camera=orbit(s.camera, turn)) for s in self.scenes]
        t0 = time.perf_counter()
        out = tr.render(scenes, method=self.method, settings=self.settings)
        self.totals.append(time.perf_counter() - t0)
        for k, v in out.timings.items():
            self.stages.setdefault(k, []).append(v)

    def result(self) -> dict:
        n, stages = len(self.totals), dict(self.stages)
        for i in range(n):  # the method's own time outside its marches, mips and kernel
            stages.setdefault("shading_rest", []).append(
                stages["shading"][i] - sum(stages.get(k, [0.0] * n)[i]
                                           for k in ("march", "mips", "fused")))
        s = self.settings
        return {
            "method": self.method, "options": self.options, "adaptive": self.adaptive,
            "spp": self.spp, "size": self.size,
            "batch": self.batch, "views": self.views, "repeats": n,
            "ms_per_frame": 1000 * statistics.median(self.totals) / self.batch,
            "ms_per_frame_stage": {k: 1000 * statistics.median(v) / self.batch
                                   for k, v in stages.items()},
            "peak_rss_mb": rss_mb("VmHWM"), "baseline_rss_mb": self.baseline,
            "warmup_s": self.warmup, "compiled": bool(s and s.compile),
            "native": native.available() if s is None or s.native else False,
            "fused": bool((s is None or s.fused) and native.available()),
            "heap_reuse": heap.heap_reuse(), "threads": torch.get_num_threads(),
        }


def bench_one(base: tr.Scene, method: str, size: int, batch: int, repeats: int,
              views: str = "distinct", settings: tr.RenderSettings | None = None) -> dict:
    row = OursRow(base, method, size, batch, views, settings)
    row.warm()
    for _ in range(repeats):
        row.once()
    return row.result()


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
    row = MitsubaRow(base, size, batch, views, spp, denoise, threads)
    row.warm()
    for _ in range(repeats):
        row.once()
    return row.result()


class MitsubaRow:
    """One Mitsuba row (:func:`bench_mitsuba`): a warm-up pass and timed passes."""

    def __init__(self, base: tr.Scene, size: int, batch: int, views: str = "distinct",
                 spp: int = 1, denoise: bool = False, threads: int | None = None):
        from torchrefract.truth.mitsuba import mitsuba  # noqa: PLC0415

        self.mi = mitsuba()
        import drjit as dr  # noqa: PLC0415 (mitsuba's own dependency)

        self.dr, self.default_threads = dr, dr.thread_count()
        self.size, self.batch, self.views = size, batch, views
        self.spp, self.denoise, self.threads = spp, denoise, threads
        self.scenes = bench_scenes(base, size, batch, views)
        self.warmup = 0.0
        self.passes: list[tuple[float, float, float]] = []

    def _pass(self) -> tuple[float, float, float]:
        from torchrefract.methods.reference import denoise_oidn  # noqa: PLC0415
        from torchrefract.truth.mitsuba import to_mitsuba_dict  # noqa: PLC0415

        mi, dr = self.mi, self.dr
        t0 = time.perf_counter()
        built = [mi.load_dict(to_mitsuba_dict(s, spp=self.spp, seed=MITSUBA_SEED,
                                              max_depth=MITSUBA_MAX_DEPTH))
                 for s in self.scenes]
        t1 = time.perf_counter()
        if self.threads:
            dr.set_thread_count(self.threads)
        try:
            t1b = time.perf_counter()
            images = [np.array(mi.render(m), dtype=np.float32)[..., :3] for m in built]
            t2 = time.perf_counter()
            if self.denoise:
                for img in images:
                    denoise_oidn(torch.from_numpy(np.ascontiguousarray(img)))
            t3 = time.perf_counter()
        finally:
            if self.threads:
                dr.set_thread_count(self.default_threads)
        return t1 - t0, t2 - t1b, t3 - t2 if self.denoise else 0.0

    def warm(self) -> None:
        t0 = time.perf_counter()
        self._pass()  # LLVM kernels, the map's first read, OIDN's device and weights
        self.warmup = time.perf_counter() - t0

    def once(self) -> None:
        self.passes.append(self._pass())

    def result(self) -> dict:
        def per_frame(values) -> float:
            return 1000 * statistics.median(values) / self.batch

        p = self.passes
        return {
            "spp": self.spp, "denoise": self.denoise, "size": self.size, "views": self.views,
            "batch": self.batch, "repeats": len(p), "seed": MITSUBA_SEED,
            "max_depth": MITSUBA_MAX_DEPTH,
            "ms_per_frame": per_frame([r + d for _, r, d in p]),
            "render_ms_per_frame": per_frame([r for _, r, _ in p]),
            "denoise_ms_per_frame": per_frame([d for _, _, d in p]),
            "build_ms_per_frame": per_frame([b for b, _, _ in p]),
            "warmup_s": self.warmup, "variant": self.mi.variant(),
            "threads": self.threads or self.default_threads,
            "build_threads": self.default_threads,
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
    print_mitsuba(meta, f"the scenes of batch {batch}, scene build not timed in ms/frame")
    return meta


def round_order(ours: list, theirs: list, k: int) -> list:
    """Round ``k``'s order of the interleaved rows: our rows turned by k, then Mitsuba's, so
    that a different one of ours runs right after Mitsuba's last pass each round (a short
    row timed right after Mitsuba's 4-spp + OIDN pass runs slower: docs/benchmarks.md,
    twenty-fifth and twenty-sixth sittings); each row runs once a round. (Turning the whole
    list kept every row's neighbours: our first row followed the OIDN pass every round.)"""
    s = k % len(ours) if ours else 0
    return ours[s:] + ours[:s] + list(theirs)


def interleaved(args: argparse.Namespace, base: tr.Scene, combos: list[tuple],
                settings: tr.RenderSettings) -> tuple[list[dict], dict]:
    """``--interleave``: our rows (``combos``) and Mitsuba's (the scenes of the largest
    batch, as :func:`mitsuba_rows`), each warmed up once, then timed in ``--repeats``
    rounds of one render (pass) per row. Returns our rows and the Mitsuba meta."""
    ours = [OursRow(base, m, size, batch, views, settings) for m, views, size, batch in combos]
    theirs: list[MitsubaRow] = []
    meta: dict = {"skipped": "--no-mitsuba", "rows": []}
    if args.mitsuba is not False:
        mi, why = load_mitsuba()
        if mi is None:
            meta = {"skipped": why, "rows": []}
        else:
            import drjit as dr  # noqa: PLC0415

            if args.threads:
                os.environ.setdefault("OIDN_NUM_THREADS", str(args.threads))
            for views, size, (spp, dn) in itertools.product(args.views, args.sizes,
                                                             MITSUBA_ROWS):
                theirs.append(MitsubaRow(base, size, max(args.batches), views, spp, dn,
                                         args.threads))
            meta = {"variant": mi.variant(), "version": mi.__version__,
                    "threads": args.threads or dr.thread_count(),
                    "build_threads": dr.thread_count(), "seed": MITSUBA_SEED,
                    "max_depth": MITSUBA_MAX_DEPTH,
                    "timed": "interleaved with our rows: one pass per round, render (+ OIDN) "
                             "per frame, median of the rounds after one untimed warm-up",
                    "rows": [], "skipped_rows": []}
    runnable = []
    for row in ours + theirs:
        try:
            row.warm()
            runnable.append(row)
        except ImportError as exc:  # pyoidn missing: the denoised Mitsuba row only
            meta["skipped_rows"].append({"spp": row.spp, "denoise": row.denoise,
                                         "reason": str(exc)})
    for k in range(args.repeats):
        for row in round_order([r for r in runnable if r in ours],
                               [r for r in runnable if r in theirs], k):
            row.once()
        print(f"round {k + 1}/{args.repeats} done", file=sys.stderr, flush=True)
    meta["rows"] = [r.result() for r in theirs if r in runnable]
    return [r.result() for r in ours], meta


def print_mitsuba(meta: dict, note: str) -> None:
    """The Mitsuba rows' table."""
    print(f"Mitsuba {meta['version']} {meta['variant']}, {meta['threads']} threads, {note}")
    print(f"{'mitsuba':<28}{'views':>9}{'size':>6}{'frames':>7}{'ms/frame':>10}{'render':>9}"
          f"{'oidn':>8}{'(build)':>9}")
    for r in meta["rows"]:
        name = f"{r['spp']} spp{' + OIDN' if r['denoise'] else ''}"
        print(f"{name:<28}{r['views']:>9}{r['size']:>6}{r['batch']:>7}"
              f"{r['ms_per_frame']:>10.1f}{r['render_ms_per_frame']:>9.1f}"
              f"{r['denoise_ms_per_frame']:>8.1f}{r['build_ms_per_frame']:>9.1f}")


def print_versus(versus: list[dict]) -> None:
    """The table of :func:`compare_rows`: ours against Mitsuba's, per row."""
    print("ms per frame, ours against Mitsuba's (ratio: Mitsuba / ours, above 1: ours "
          "faster)")
    print(f"{'method':<28}{'views':>9}{'size':>6}{'batch':>6}{'ours':>8}{'mi 1spp':>9}"
          f"{'ratio':>7}{'mi 4spp+oidn':>14}{'ratio':>7}")

    def cell(v, width: int, fmt: str) -> str:
        return f"{'-':>{width}}" if v is None else f"{v:>{width}{fmt}}"

    for c in versus:
        opts = {**c["options"], **({"spp": c["spp"]} if c.get("spp", 1) != 1 else {})}
        name = c["method"] + (":" + ",".join(f"{k}={v}" for k, v in opts.items())
                              if opts else "") + (ADAPTIVE_SUFFIX if c.get("adaptive") else "")
        print(f"{name[:28]:<28}{c['views']:>9}{c['size']:>6}{c['batch']:>6}"
              f"{c['ms_per_frame']:>8.1f}{cell(c['mitsuba_1spp_ms_per_frame'], 9, '.1f')}"
              f"{cell(c['mitsuba_1spp_ratio'], 7, '.2f')}"
              f"{cell(c['mitsuba_4spp_oidn_ms_per_frame'], 14, '.1f')}"
              f"{cell(c['mitsuba_4spp_oidn_ratio'], 7, '.2f')}")


def compare_rows(rows: list[dict], mitsuba: list[dict]) -> list[dict]:
    """Per bench row: our ms per frame, each Mitsuba row's of the same size and views, and
    their ratio (Mitsuba / ours: above 1, ours is faster)."""
    out = []
    for r in rows:
        c = {k: r.get(k) for k in ("method", "options", "adaptive", "spp", "views", "size",
                                   "batch")}
        c["ms_per_frame"] = r["ms_per_frame"]
        for spp, denoise in MITSUBA_ROWS:
            key = f"mitsuba_{spp}spp{'_oidn' if denoise else ''}"
            m = next((m for m in mitsuba if (m["size"], m["views"], m["spp"], m["denoise"])
                      == (r["size"], r["views"], spp, denoise)), None)
            c[f"{key}_ms_per_frame"] = None if m is None else m["ms_per_frame"]
            c[f"{key}_ratio"] = None if m is None else m["ms_per_frame"] / r["ms_per_frame"]
        out.append(c)
    return out


def _positive(value: str, flag: str) -> int:
    """argparse type: a whole number >= 1."""
    if not value.isdigit() or int(value) < 1:
        raise argparse.ArgumentTypeError(f"{flag}: expected a whole number >= 1, got {value!r}")
    return int(value)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default=str(ROOT / "configs" / "demo.yaml"))
    ap.add_argument("--methods", nargs="+", default=["specular"])
    ap.add_argument("--sizes", nargs="+", type=int, default=[256, 512])
    ap.add_argument("--batches", nargs="+", type=int, default=[1, 8])
    ap.add_argument("--repeats", type=lambda v: _positive(v, "--repeats"), default=5)
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
    ap.add_argument("--interleave", action="store_true",
                    help="every row in this process, timed in rounds (each row once per "
                         "round, Mitsuba's too): a machine whose load drifts shifts every "
                         "row alike, so the ratios hold (memory: the peak so far)")
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
    combos = [(method, views, size, batch) for method, views, size, batch in
              itertools.product(args.methods, args.views, args.sizes, args.batches)
              if not (batch == 1 and views == "shared" and "distinct" in args.views)]
    mitsuba = {"skipped": "--no-mitsuba", "rows": []}
    if args.interleave:
        rows, mitsuba = interleaved(args, base, combos, settings)
    for i, (method, views, size, batch) in enumerate(combos):
        if args.interleave:
            r = rows[i]
        else:
            r = (bench_one(base, method, size, batch, args.repeats, views, settings)
                 if args.in_process
                 else run_row(args, method, size, batch, views))
            rows.append(r)
        st = r["ms_per_frame_stage"]
        print(f"{method[:28]:<28}{views:>9}{size:>6}{batch:>6}{r['ms_per_frame']:>10.1f}"
              f"{st['gbuffer']:>9.1f}{st['shading']:>9.1f}{st['mips']:>7.1f}"
              f"{st['march']:>7.1f}{st['fused']:>7.1f}{st['shading_rest']:>7.1f}"
              f"{r['peak_rss_mb']:>8.0f}")
    if args.mitsuba is not False and not args.interleave:
        mitsuba = mitsuba_rows(args, base)
    elif mitsuba["rows"]:
        print_mitsuba(mitsuba, "interleaved with our rows, scene build not timed in ms/frame")
    versus = compare_rows(rows, mitsuba["rows"])
    if mitsuba["rows"]:
        print_versus(versus)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    meta = {"torchrefract": tr.__version__, "torch": torch.__version__,
            "threads": torch.get_num_threads(), "machine": platform.platform(),
            "compiled": args.compile, "native": not args.no_native, "fused": not args.no_fused,
            "heap_reuse": heap_reuse, "interleaved": args.interleave,
            "scene": args.scene, "results": rows,
            "mitsuba": mitsuba, "vs_mitsuba": versus}
    (out / "bench.json").write_text(json.dumps(meta, indent=2) + "\n")
    print(f"saved {out / 'bench.json'}")
    if args.mitsuba and not mitsuba["rows"]:
        sys.exit(f"bench: --mitsuba: no Mitsuba row measured ({mitsuba.get('skipped')})")


if __name__ == "__main__":
    try:
        main()
    except ConfigError as exc:  # bad arguments or scenes: one line, exit 2
        print(f"bench: {exc}", file=sys.stderr)
        sys.exit(2)

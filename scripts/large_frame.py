"""Large frames in bounded memory (issue #27): peak resident memory and time of one view
rendered under a memory budget, each run in a fresh process.

    .venv/bin/python scripts/large_frame.py [--scene configs/suite/sphere_a03.yaml]
        [--method rousiers] [--options '{"internal_bounces": 2}'] [--size 4096] [--spp 4]
        [--budget-mb 3584] [--compare] [--no-fused] [--threads N] [--out outputs/large_frame]
    .venv/bin/python scripts/large_frame.py --calibrate [--scene ...] [--calib-size 1024]
        [--calib-spp 1] [--calib-tile 16384] [--calib-only specular rousiers:ib2 ...]

Default: the scene at ``--size`` x ``--size`` and ``--spp`` x ``--spp`` samples per pixel
under ``--budget-mb`` (3.5 GiB, so that the process, about 0.5 GiB before its first render,
stays within 4 GiB). A view whose G-buffer does not fit the budget is rendered in strips
over its marched layers' ids (:mod:`torchrefract.large`; the run records how many strips
of how many sub-pixel rows); where it does not fit even so (or the strips do not cover it:
``--no-fused``), the render fails up front (the run records the error and how long it
took), and the script then renders the largest square view at the same ``--spp`` (a
multiple of 64 pixels) that the memory model accepts under the budget. ``--compare``
also renders that view in one untiled pass (the budget: 80% of the machine's available
memory) and reports the largest pixel difference (e.g. ``--size 1024 --budget-mb 1024
--compare``: strips against one G-buffer). Each run's peak is the kernel's (``VmHWM``,
reset after a small warm-up render), also given above the process's resident memory
before the render.

``--calibrate``: the memory model's two figures per method, for one view of
``--calib-size`` pixels square at ``--calib-spp`` (``--calib-only rousiers:ib2 ...``: some
of them), fused kernels and tensor code: from an untiled run (peak S V + T N, V sub-pixels,
N of them on the object) and one in tiles of ``--calib-tile`` object sub-pixels
(S V + T t), the shading's bytes T per object sub-pixel and the frame's S per sub-pixel.

Results: ``OUT/large_frame.json`` (or ``OUT/calibrate.json``) and ``OUT/<run>.png``
previews (sRGB, downscaled to 512 pixels). docs/benchmarks.md, "Large frames", has the
figures of a run.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import re
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
CALIBRATE = (("specular", {}), ("prefiltered", {}), ("rousiers", {}),
             ("rousiers", {"internal_bounces": 2}), ("specular", {"internal_bounces": 2}))
"""The calibration's methods on the ``--scene``; plus ``rousiers`` with internal bounces on
the roughness-map globe (configs/suite/globe_2rough.yaml)."""


def _status(field: str) -> float:
    """``VmHWM`` (peak) or ``VmRSS`` of this process in MB."""
    with open("/proc/self/status") as f:
        return int(re.search(rf"{field}:\s+(\d+)", f.read()).group(1)) / 1024


def child(spec: dict) -> dict:
    """One render in this (fresh) process; its figures."""
    import importlib  # noqa: PLC0415

    import numpy as np  # noqa: PLC0415
    import torch  # noqa: PLC0415

    import torchrefract as tr  # noqa: PLC0415

    tiles = importlib.import_module("torchrefract.tiles")
    large = importlib.import_module("torchrefract.large")
    if spec.get("threads"):
        torch.set_num_threads(spec["threads"])
    count = {"tiles": 1, "strips": 0, "strip_rows": 0}
    split = tiles.split
    cut = large._strip_layers

    def strip(mesh, cam, n, batch, eye, fwd, r0, r1, front, back):
        if front and back:  # the shading's strips (not the ids' pass)
            count["strips"] += 1
            count["strip_rows"] = max(count["strip_rows"], r1 - r0)
        return cut(mesh, cam, n, batch, eye, fwd, r0, r1, front, back)

    large._strip_layers = strip

    def counted(idx, size):
        parts = split(idx, size)
        count["tiles"] = len(parts)
        return parts

    tiles.split = counted
    if spec.get("tile"):  # calibration: tiles of this many object sub-pixels
        tiles.tile_size = lambda frame, budget: spec["tile"]
    scene = tr.load_scene(spec["scene"])
    cam = scene.camera
    scene = scene.replace(method=spec["method"], method_options=spec["options"])
    settings = tr.RenderSettings(fused=spec["fused"], memory_budget_mb=spec["budget_mb"])
    small = tr.Camera(eye=cam.eye, target=cam.target, up=cam.up, yfov_deg=cam.yfov_deg,
                      width=32, height=32)
    tr.render(scene.replace(camera=small), settings=settings)  # context, tables, pyramids
    count["strips"] = 0
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")  # the peak (VmHWM) restarts from here
    except OSError:
        pass
    base = _status("VmRSS")
    view = tr.Camera(eye=cam.eye, target=cam.target, up=cam.up, yfov_deg=cam.yfov_deg,
                     width=spec["size"], height=spec["size"],
                     samples_per_pixel=spec["spp"])
    t0 = time.perf_counter()
    row = {**spec, "threads": torch.get_num_threads(), "baseline_rss_mb": round(base)}
    try:
        out = tr.render(scene.replace(camera=view), settings=settings)
    except tr.ConfigError as exc:
        return {**row, "ok": False, "error": str(exc),
                "seconds": round(time.perf_counter() - t0, 4),
                "peak_rss_mb": round(_status("VmHWM"))}
    seconds = time.perf_counter() - t0
    peak = _status("VmHWM")
    n = spec["size"] ** 2 * spec["spp"] ** 2
    shaded = int(round(float(out.coverage.double().sum()) * spec["spp"] ** 2))
    row.update(ok=True, seconds=round(seconds, 2), peak_rss_mb=round(peak),
               above_baseline_mb=round(peak - base),
               bytes_per_subpixel=round((peak - base) * 2**20 / n),
               subpixels=n, object_subpixels=shaded, tiles=count["tiles"],
               strips=count["strips"], strip_rows=count["strip_rows"],
               timings={k: round(v, 2) for k, v in out.timings.items()})
    if spec.get("save"):
        rgb = out.radiance[0].clamp(min=0).numpy()
        np.save(spec["save"] + ".npy", rgb)
        img = torch.from_numpy(rgb).permute(2, 0, 1)[None]
        step = max(1, spec["size"] // 512)
        img = torch.nn.functional.avg_pool2d(img, step)[0].permute(1, 2, 0).numpy()
        srgb = np.where(img <= 0.0031308, 12.92 * img, 1.055 * np.power(img, 1 / 2.4) - 0.055)
        from PIL import Image  # noqa: PLC0415

        Image.fromarray((np.clip(srgb, 0, 1) * 255 + 0.5).astype(np.uint8)).save(
            spec["save"] + ".png")
    return row


def run(spec: dict) -> dict:
    """:func:`child` in a fresh process."""
    proc = subprocess.run([sys.executable, __file__, "--child", json.dumps(spec)],
                          capture_output=True, text=True, cwd=ROOT)
    if proc.returncode != 0:
        return {**spec, "ok": False, "error": f"exit {proc.returncode}: "
                f"{proc.stderr.strip().splitlines()[-1] if proc.stderr.strip() else ''}"}
    return json.loads(proc.stdout.strip().splitlines()[-1])


def largest_fitting(spp: int, budget_mb: int, start: int) -> int:
    """The largest multiple of 64 pixels square, at most ``start``, whose view at ``spp``
    the memory model accepts under ``budget_mb`` as one G-buffer (its shading in tiles;
    what the tensor code can render)."""
    from torchrefract import tiles  # noqa: PLC0415

    for size in range(start - start % 64, 63, -64):
        if tiles.fits_whole(_camera(size, spp), budget_mb << 20):
            return size
    return 0


def _camera(size: int, spp: int):
    import torchrefract as tr  # noqa: PLC0415

    return tr.Camera(width=size, height=size, samples_per_pixel=spp)


def _print(row: dict) -> None:
    if row["ok"]:
        print(f"{row['method']} {row['options']} {row['size']}^2 spp {row['spp']} "
              f"budget {row['budget_mb']} MB fused {row['fused']}: {row['seconds']} s, "
              f"peak {row['peak_rss_mb']} MB ({row['above_baseline_mb']} above the "
              f"{row['baseline_rss_mb']} MB before; {row['bytes_per_subpixel']} B/sub-pixel), "
              f"{row['tiles']} tile(s), {row['strips']} strip(s) of up to "
              f"{row['strip_rows']} sub-pixel rows, {row['object_subpixels']:,} object "
              f"sub-pixels",
              flush=True)
    else:
        print(f"{row['method']} {row['size']}^2 spp {row['spp']} budget {row['budget_mb']} "
              f"MB: failed after {row.get('seconds', '?')} s: {row['error']}", flush=True)


def calibrate(args) -> list[dict]:
    rows = []
    globe = str(ROOT / "configs" / "suite" / "globe_2rough.yaml")
    cases = [(args.scene, m, o) for m, o in CALIBRATE]
    cases.append((globe, "rousiers", {"internal_bounces": 2}))
    if args.calib_only is not None:
        def name(scene, m, o):
            return (m + (":ib2" if o else "")
                    + (":globe" if scene == globe else ""))
        cases = [c for c in cases if name(*c) in args.calib_only]
    for scene, method, options in cases:
        for fused in (True, False):
            base = dict(scene=scene, method=method, options=options, size=args.calib_size,
                        spp=args.calib_spp, fused=fused, budget_mb=1 << 20, threads=args.threads)
            whole = run(base)
            tiled = run({**base, "tile": args.calib_tile})
            if not (whole["ok"] and tiled["ok"]):
                print("failed:", whole.get("error"), tiled.get("error"))
                continue
            # untiled = S V + T N, tiled = S V + T t: the shading's T, then the frame's S
            shade = ((whole["above_baseline_mb"] - tiled["above_baseline_mb"]) * 2**20
                     / max(1, whole["object_subpixels"] - args.calib_tile))
            frame = (tiled["above_baseline_mb"] * 2**20 - shade * args.calib_tile) \
                / tiled["subpixels"]
            row = dict(scene=Path(scene).stem, method=method, options=options, fused=fused,
                       frame_bytes_per_subpixel=round(frame),
                       shade_bytes_per_object_subpixel=round(shade),
                       untiled_peak_above_mb=whole["above_baseline_mb"],
                       tiled_peak_above_mb=tiled["above_baseline_mb"],
                       untiled_s=whole["seconds"], tiled_s=tiled["seconds"],
                       tiles=tiled["tiles"], coverage=round(
                           whole["object_subpixels"] / whole["subpixels"], 3))
            print(json.dumps(row), flush=True)
            rows.append(row)
    return rows


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--child", help=argparse.SUPPRESS)
    p.add_argument("--scene", default=str(ROOT / "configs" / "suite" / "sphere_a03.yaml"))
    p.add_argument("--method", default=None, help="default: the scene's")
    p.add_argument("--options", default=None, help="method_options as JSON")
    p.add_argument("--size", type=int, default=4096)
    p.add_argument("--spp", type=int, default=4)
    p.add_argument("--budget-mb", type=int, default=3584)
    p.add_argument("--compare", action="store_true")
    p.add_argument("--no-fused", action="store_true")
    p.add_argument("--threads", type=int, default=None)
    p.add_argument("--calibrate", action="store_true")
    p.add_argument("--calib-size", type=int, default=1024)
    p.add_argument("--calib-tile", type=int, default=16384)
    p.add_argument("--calib-spp", type=int, default=1)
    p.add_argument("--calib-only", nargs="*", default=None,
                   help="calibrate these methods only (method or method:ib2)")
    p.add_argument("--out", default=str(ROOT / "outputs" / "large_frame"))
    args = p.parse_args(argv)
    if args.child:
        print(json.dumps(child(json.loads(args.child))))
        return 0
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    info = {"date": time.strftime("%Y-%m-%d"), "machine": platform.platform(),
            "cpus": os.cpu_count()}
    if args.calibrate:
        rows = calibrate(args)
        (out / "calibrate.json").write_text(json.dumps({**info, "rows": rows}, indent=1))
        return 0
    import torchrefract as tr  # noqa: PLC0415

    scene = tr.load_scene(args.scene)
    spec = dict(scene=args.scene, method=args.method or scene.method,
                options=json.loads(args.options) if args.options else scene.method_options,
                size=args.size, spp=args.spp, fused=not args.no_fused,
                budget_mb=args.budget_mb, threads=args.threads)
    rows = [run({**spec, "save": str(out / f"tiled_{args.size}_spp{args.spp}")})]
    _print(rows[-1])
    if not rows[-1]["ok"]:
        size = largest_fitting(args.spp, args.budget_mb, args.size)
        if size:
            rows.append(run({**spec, "size": size,
                             "save": str(out / f"tiled_{size}_spp{args.spp}")}))
            _print(rows[-1])
    if args.compare and rows[-1]["ok"]:
        size = rows[-1]["size"]
        rows.append(run({**spec, "size": size, "budget_mb": None,
                         "save": str(out / f"untiled_{size}_spp{args.spp}")}))
        _print(rows[-1])
        if rows[-1]["ok"]:
            import numpy as np  # noqa: PLC0415

            a = np.load(out / f"tiled_{size}_spp{args.spp}.npy")
            b = np.load(out / f"untiled_{size}_spp{args.spp}.npy")
            diff = float(np.abs(a - b).max())
            rows[-1]["max_abs_diff_to_tiled"] = diff
            print(f"largest difference tiled - untiled: {diff}")
    for r in rows:  # the arrays were for the comparison only
        Path(str(r.get("save", "")) + ".npy").unlink(missing_ok=True)
    (out / "large_frame.json").write_text(json.dumps({**info, "rows": rows}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())

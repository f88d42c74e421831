"""Check and time the CUDA path (``RenderSettings(device="cuda")``) where a GPU is lent.

Part 1, agreement: every method variant on every suite scene (small images) rendered with
the tensor code on the CPU and on the GPU; per case the largest relative difference on
object pixels, the share beyond 1e-4, and the error (trace tail) where one is raised.
Part 2, speed: 256x256, batch 8 distinct views (bench.py's ``distinct``: each view 3
degrees further round, map rotated 10 degrees), ms per frame, median of the repeats: the
GPU, and on the CPU the fused kernels at 2 threads and at all the machine's cores.

    python scripts/device_check.py [--size 64] [--repeats 5] [--out outputs/device]

Writes ``device_check.json`` in ``--out``. Needs torch with CUDA; the CPU rows run anyway.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import platform
import statistics
import sys
import time
import traceback
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import torchrefract as tr  # noqa: E402

VARIANTS = [("specular", {}), ("specular", {"internal_bounces": 2}), ("prefiltered", {}),
            ("rousiers", {}), ("rousiers", {"internal_bounces": 2}),
            ("rousiers", {"internal_bounces": "auto", "bounce_rays": 4}),
            ("rousiers", {"cone_rays": "plane"}), ("rousiers", {"tir": "reflect"}),
            ("lean", {}), ("gsr", {}), ("auto", {})]


def _views(scene, size: int, n: int):
    """n views of ``scene`` at size x size, each 3 degrees further round the target."""
    c = scene.camera
    eye = [a - b for a, b in zip(c.eye, c.target)]
    out = []
    for i in range(n):
        a = math.radians(3.0 * i)
        x, z = eye[0] * math.cos(a) + eye[2] * math.sin(a), -eye[0] * math.sin(a) + eye[2] * math.cos(a)
        cam = dataclasses.replace(c, eye=[x + c.target[0], eye[1] + c.target[1], z + c.target[2]],
                                  width=size, height=size, samples_per_pixel=1)
        env = dataclasses.replace(scene.envmap, rotate_deg=scene.envmap.rotate_deg + 10.0 * i)
        out.append(scene.replace(camera=cam, envmap=env))
    return out


def agreement(size: int, pattern: str = "*") -> list[dict]:
    rows = []
    cpu = tr.RenderSettings(fused=False)
    gpu = tr.RenderSettings(device="cuda")
    for path in sorted((ROOT / "configs" / "suite").glob(pattern + ".yaml")):
        scenes = _views(tr.load_scene(path), size, 2)
        for method, opts in VARIANTS:
            sc = [s.replace(method=method, method_options=opts) for s in scenes]
            row = {"scene": path.stem, "method": method, "options": opts}
            try:
                a = tr.render(sc, settings=cpu)
                t0 = time.perf_counter()
                b = tr.render(sc, settings=gpu)
                row["gpu_s"] = time.perf_counter() - t0
                row["on_gpu"] = b.radiance.is_cuda
                obj = a.coverage > 0
                ra, rb = a.radiance[obj], b.radiance.cpu()[obj]
                rel = (ra - rb).abs() / ra.abs().clamp(min=1e-3)
                row["max_rel"] = float(rel.max()) if rel.numel() else 0.0
                row["beyond_1e-4"] = float((rel > 1e-4).float().mean()) if rel.numel() else 0.0
                row["finite"] = bool(torch.isfinite(b.radiance).all())
            except Exception as exc:  # noqa: BLE001 - recorded, the check goes on
                row["error"] = f"{type(exc).__name__}: {exc}"[:400]
                row["trace"] = "".join(traceback.format_exc().splitlines(True)[-14:])
            rows.append(row)
            print(json.dumps({k: v for k, v in row.items() if k != "trace"}), flush=True)
            if "trace" in row:
                print(row["trace"], flush=True)
    rows.append(_matte_case(size))
    return rows


def _matte_case(size: int) -> dict:
    """The matte on the GPU: relit with its own map, it gives the GPU's direct image."""
    s = _views(tr.load_scene(ROOT / "configs" / "suite" / "sphere_a03.yaml"), size, 2)
    s = [x.replace(passes={"matte": {}}) for x in s]
    row = {"scene": "sphere_a03", "method": "rousiers", "options": {"passes": "matte"}}
    try:
        b = tr.render(s, settings=tr.RenderSettings(device="cuda"))
        img = tr.relight(b, s[0].envmap.path, rotate_deg=s[0].envmap.rotate_deg)
        obj = b.coverage[:1] > 0
        rel = ((img[:1] - b.radiance[:1]).abs() / b.radiance[:1].abs().clamp(min=1e-3))[obj]
        row.update(on_gpu=b.radiance.is_cuda, relight_max_rel=float(rel.max()))
    except Exception as exc:  # noqa: BLE001
        row["error"] = f"{type(exc).__name__}: {exc}"[:400]
        row["trace"] = "".join(traceback.format_exc().splitlines(True)[-14:])
    print(json.dumps({k: v for k, v in row.items() if k != "trace"}), flush=True)
    if "trace" in row:
        print(row["trace"], flush=True)
    return row


def speed(repeats: int) -> list[dict]:
    scene = tr.load_scene(ROOT / "configs" / "suite" / "sphere_a03.yaml")
    scenes = _views(scene, 256, 8)
    rows = []
    cores = os.cpu_count() or 1
    cases = [("cuda", tr.RenderSettings(device="cuda")),
             ("cpu 2 threads fused", tr.RenderSettings(threads=2, heap_reuse=True)),
             (f"cpu {cores} threads fused", tr.RenderSettings(threads=cores, heap_reuse=True)),
             ("cpu 2 threads tensor", tr.RenderSettings(threads=2, fused=False))]
    for method, opts in [("specular", {}), ("prefiltered", {}), ("rousiers", {}),
                         ("rousiers", {"internal_bounces": 2}), ("lean", {}), ("gsr", {})]:
        sc = [s.replace(method=method, method_options=opts) for s in scenes]
        extra = [("cuda, compiled march", tr.RenderSettings(device="cuda", compile=True))] \
            if method == "rousiers" and not opts else []
        for name, st in cases + extra:
            row = {"method": method, "options": opts, "where": name}
            try:
                tr.render(sc, settings=st)  # warm-up: kernels, tables, pyramids
                times, stages = [], []
                for _ in range(repeats):
                    t0 = time.perf_counter()
                    out = tr.render(sc, settings=st)
                    if out.radiance.is_cuda:
                        torch.cuda.synchronize()
                    times.append((time.perf_counter() - t0) / len(sc) * 1e3)
                    stages.append(out.timings)
                row["ms_per_frame"] = statistics.median(times)
                for k in ("gbuffer", "shading"):
                    row[k + "_ms"] = statistics.median(t[k] for t in stages) / len(sc) * 1e3
            except Exception as exc:  # noqa: BLE001
                row["error"] = f"{type(exc).__name__}: {exc}"[:300]
            rows.append(row)
            print(json.dumps(row), flush=True)
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=64)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--scenes", default="*", help="suite scenes (glob) of part 1")
    ap.add_argument("--skip-agreement", action="store_true")
    ap.add_argument("--skip-speed", action="store_true")
    ap.add_argument("--out", default=str(ROOT / "outputs" / "device"))
    args = ap.parse_args()
    info = {"torch": torch.__version__, "cuda": torch.cuda.is_available(),
            "gpu": torch.cuda.get_device_name(0) if torch.cuda.is_available() else None,
            "cpu": platform.processor(), "cores": os.cpu_count(),
            "date": time.strftime("%Y-%m-%d %H:%M", time.gmtime())}
    print(json.dumps(info), flush=True)
    res = {"info": info}
    if not args.skip_agreement:
        res["agreement"] = agreement(args.size, args.scenes)
    if not args.skip_speed:
        res["speed"] = speed(args.repeats)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "device_check.json").write_text(json.dumps(res, indent=1))
    print("saved", out / "device_check.json")


if __name__ == "__main__":
    main()

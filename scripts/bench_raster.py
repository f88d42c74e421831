"""Benchmark: the G-buffer's triangle ids, the OpenGL passes against the native rasterizer.

Per scene (``bench.bench_scenes``: ``--views`` distinct cameras 3 degrees apart around the
object, one sample per pixel, at ``--size``): milliseconds per view of

- ``opengl``: the two OpenGL passes of every view (``raster.visibility_pass``, front and
  back; llvmpipe, which threads on its own);
- ``native``: ``raster.native_layers``, both layers of all the views in one call (its
  planes and matrices included), on 1 and on 2 threads (torch's count);
- ``kernel``: the same call's C kernel alone (``native.raster_ids``, inputs prepared);

then, with ``--render``, ``torchrefract.render(scenes, method=...)`` in ms per frame, its
``gbuffer`` stage apart, with ``RenderSettings(rasterizer="native")`` and ``"opengl"``
(default threads). Medians of ``--repeats`` runs after one warm-up; quote them with the
machine quiet (the thread counts are printed).

    .venv/bin/python scripts/bench_raster.py [configs/demo.yaml ...] [--size 256]
        [--views 8] [--repeats 15] [--render specular]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

import torchrefract as tr  # noqa: E402
from bench import bench_scenes  # noqa: E402
from torchrefract.geometry import raster  # noqa: E402
from torchrefract.geometry.mesh import load_mesh  # noqa: E402
from torchrefract.kernels import native  # noqa: E402
from torchrefract.scene.loader import load_scene  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent


def median_ms(fn, repeats: int) -> float:
    """Median wall time of ``fn()`` in ms over ``repeats`` runs, after one warm-up."""
    fn()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return 1000.0 * statistics.median(times)


def ids_row(path: Path, size: int, views: int, repeats: int) -> dict:
    """ms per view of the OpenGL passes, the native rasterizer and its kernel alone."""
    scenes = bench_scenes(load_scene(path), size, views)
    meshes = [load_mesh(s.mesh, s.transform) for s in scenes]
    cams = [s.camera for s in scenes]
    offsets = [0] * views
    row = {"scene": path.name, "faces": meshes[0].num_faces, "size": size, "views": views}

    m = meshes[0]
    sphere = m.bounding_sphere()
    table = torch.tensor([[0, m.vertices.shape[0], 0, m.num_faces, 0]] * views)
    mvp = torch.from_numpy(np.stack([raster.view_projection(c, sphere) for c in cams]))
    threads = torch.get_num_threads()
    for t in (1, 2):
        torch.set_num_threads(t)
        row[f"native_{t}t"] = median_ms(
            lambda: raster.native_layers(meshes, cams, 1, offsets), repeats) / views
        row[f"kernel_{t}t"] = median_ms(
            lambda: native.raster_ids(m.vertices, m.faces, table, mvp, size, size),
            repeats) / views
        row[f"kernel_1view_{t}t"] = median_ms(
            lambda: native.raster_ids(m.vertices, m.faces, table[:1], mvp[:1], size, size),
            repeats)
    torch.set_num_threads(threads)

    def gl():  # last: llvmpipe's threads may still spin right after its passes
        for m, c in zip(meshes, cams):
            raster.visibility_pass(m, c, 1, back=False)
            raster.visibility_pass(m, c, 1, back=True)

    row["opengl"] = median_ms(gl, repeats) / views
    return row


def render_row(path: Path, size: int, views: int, repeats: int, method: str) -> dict:
    """ms per frame of ``tr.render`` (and its gbuffer stage) per rasterizer, the two
    interleaved render by render (the machine's drift hits both alike)."""
    scenes = bench_scenes(load_scene(path), size, views)
    row = {"scene": path.name, "method": method, "threads": torch.get_num_threads()}
    choices = {c: tr.RenderSettings(rasterizer=c) for c in ("native", "opengl")}
    totals: dict[str, list[float]] = {c: [] for c in choices}
    gbuf: dict[str, list[float]] = {c: [] for c in choices}
    for settings in choices.values():
        tr.render(scenes, method=method, settings=settings)  # warm-up
    for _ in range(repeats):
        for c, settings in choices.items():
            t0 = time.perf_counter()
            out = tr.render(scenes, method=method, settings=settings)
            totals[c].append(time.perf_counter() - t0)
            gbuf[c].append(out.timings["gbuffer"])
    for c in choices:
        row[c] = 1000.0 * statistics.median(totals[c]) / views
        row[f"{c}_gbuffer"] = 1000.0 * statistics.median(gbuf[c]) / views
    return row


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("configs", nargs="*", type=Path, default=[
        ROOT / "configs" / "demo.yaml", ROOT / "configs" / "suite_sh" / "armadillo_a01.yaml",
        ROOT / "configs" / "suite_sh" / "shell_bead_a01.yaml"])
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--views", type=int, default=8)
    ap.add_argument("--repeats", type=int, default=15)
    ap.add_argument("--render", default=None, help="also time tr.render with this method")
    args = ap.parse_args(argv)
    if not native.available():
        sys.exit("the native kernels are unavailable here")
    print(f"torch threads {torch.get_num_threads()}; ms per view (both layers)")
    for path in args.configs:
        r = ids_row(path, args.size, args.views, args.repeats)
        print(f"{r['scene']:24s} {r['faces']:6d} faces {r['size']}^2 x{r['views']}: "
              f"opengl {r['opengl']:.3f} | native 1t {r['native_1t']:.3f} "
              f"2t {r['native_2t']:.3f} | kernel 1t {r['kernel_1t']:.3f} "
              f"2t {r['kernel_2t']:.3f} | one view alone 1t {r['kernel_1view_1t']:.3f} "
              f"2t {r['kernel_1view_2t']:.3f}", flush=True)
    if args.render:
        for path in args.configs:
            r = render_row(path, args.size, args.views, args.repeats, args.render)
            print(f"render {r['method']} {r['scene']} ({r['threads']} threads), ms per frame: "
                  f"native {r['native']:.2f} (gbuffer {r['native_gbuffer']:.2f}) | opengl "
                  f"{r['opengl']:.2f} (gbuffer {r['opengl_gbuffer']:.2f})", flush=True)


if __name__ == "__main__":
    main()

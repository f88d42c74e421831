"""Relighting against full renders (issue #27): time per relit image and its error.

For a few suite scenes at 256x256 (1 sample per pixel): render once with ``passes: [matte]``
(the tensor code, lookups recorded; the scenes' own map, ``lebombo`` at 60 degrees), then
for each map and rotation of ``MAPS`` relight and render directly (default settings: fused
kernels; and the tensor code), in one run, with the same torch thread count. Times are
medians of ``--repeats``. Relight times:

- ``ms_relight``: a relight of a prepared matte with the map's textures and the rotation
  seen before (what a sweep pays for every map after the first at a rotation);
- ``ms_relight_new_rotation``: the rotation's caches dropped first (each lobe's u and its
  texel indices computed again, by csrc/relight.c where the native kernels run (the
  summary's ``native``): what the first map at a rotation pays). ``exact_u``: the
  row's rotation is the rendered one, where u is the renderer's op for op (the C library's
  atan2f per lobe); at every other rotation it is each lobe's azimuth at rotation 0,
  shifted (``Prepared.u``; docs/matte.md, "Speed");
- once per matte ``ms_prepare`` (lobes, levels, rows), once per map ``ms_texture`` (its
  channels-last copy), both outside the per-image times.

Prints and writes ``outputs/relight_bench/relight_bench[_<threads>t].json`` and a figure
``outputs/relight_bench/relit_vs_direct.png`` (per map: relit, direct, FLIP error).

Usage: .venv/bin/python scripts/relight_bench.py [--size 256] [--repeats 5] [--threads 1]
       [--out outputs/relight_bench]
"""

from __future__ import annotations

import argparse
import json
import time
from datetime import date
from pathlib import Path

import numpy as np
import torch

import torchrefract as tr
import torchrefract.matte.relight as relight_mod
from torchrefract.heap import set_heap_reuse
from torchrefract.kernels import native
from torchrefract.lighting.sg_pyramid import sg_pyramid_for
from torchrefract.matte.matte import from_passes
from torchrefract.output.images import linear_to_srgb8
from torchrefract.truth.metrics import flip_map

ROOT = Path(__file__).resolve().parent.parent
# the scenes' own map at its rotation (the rendered one: exact u), then new rotations
MAPS = [("lebombo", 60.0), ("lebombo", 150.0), ("rooitou_park", 0.0),
        ("studio_small_03", 135.0)]
SCENES = [("sphere_a03.yaml", "rousiers", {"internal_bounces": 2}),
          ("suzanne_a01.yaml", "rousiers", {}),
          ("torus_a01.yaml", "prefiltered", {})]


def median(fn, repeats: int, before=None) -> tuple[float, object]:
    """Median wall time of ``fn`` over ``repeats`` calls (``before`` run untimed before
    each) and its last result."""
    out, ts = None, []
    for _ in range(repeats):
        if before is not None:
            before()
        t0 = time.perf_counter()
        out = fn()
        ts.append(time.perf_counter() - t0)
    return float(np.median(ts)), out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--threads", type=int, default=1,
                    help="torch threads for both (default 1: on this shared 2-core machine "
                         "two threads were 5-30x slower for the lookups when the other core "
                         "was busy)")
    ap.add_argument("--out", type=Path, default=ROOT / "outputs" / "relight_bench")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    # as the torchrefract command and the other scripts: freed tensor memory reused
    # (torchrefract/heap.py), for the renders and the relights alike
    one = tr.RenderSettings(threads=args.threads, heap_reuse=True)
    set_heap_reuse(True)
    out_dir = args.out
    out_dir.mkdir(parents=True, exist_ok=True)
    rows, figure, drawn = [], [], set()
    for name, method, opts in SCENES:
        s = tr.load_scene(ROOT / "configs" / "suite" / name)
        s = s.replace(method=method, method_options=opts, camera=tr.Camera(
            **{**s.camera.__dict__, "width": args.size, "height": args.size,
               "samples_per_pixel": 1}))
        tr.render(s, settings=one)  # warm caches (pyramids, tables, kernels)
        t_matte, res = median(lambda: tr.render(s.replace(passes={"matte": {}}),
                                                settings=one), 2)
        obj = (res.coverage[0] > 0.999).numpy()
        rendered = s.envmap.rotate_deg  # where the relight takes the renderer's u
        t_prepare, prep = median(lambda: relight_mod.Prepared(from_passes(res.passes),
                                                              rendered), 1)
        for mp, rot in MAPS:
            env = tr.EnvMap(path=str(ROOT / "assets" / "envmaps" / f"{mp}.exr"),
                            rotate_deg=rot, scale=1.0)
            pyr = sg_pyramid_for(env.path)  # built or read from the disk cache, kept
            t_texture, _ = median(lambda: relight_mod._texels_last(pyr, pyr.levels[0]), 1,
                                  relight_mod._LAST.clear)
            tr.relight(prep, env.path, rot)  # the layout's taps
            t_new_rot, _ = median(lambda: tr.relight(prep, env.path, rotate_deg=rot),
                                  args.repeats, prep.forget_rotations)
            t_relight, img = median(lambda: tr.relight(prep, env.path, rotate_deg=rot),
                                    args.repeats)
            t_full, direct = median(lambda: tr.render(s.replace(envmap=env), settings=one),
                                    args.repeats)
            t_tensor, direct_t = median(lambda: tr.render(
                s.replace(envmap=env), settings=one.replace(fused=False)), 1)
            ref = relight_mod.relight_reference(res, env.path, rot)
            rel_ref = ((img - ref).abs().amax(-1) / ref.amax(-1).clamp(min=1e-6))[0]
            fm = flip_map(img[0].numpy(), direct.radiance[0].numpy())
            fm_t = flip_map(img[0].numpy(), direct_t.radiance[0].numpy())
            rel = ((img - direct_t.radiance).abs().amax(-1)
                   / direct_t.radiance.amax(-1).clamp(min=1e-6))[0].numpy()
            row = {"scene": name, "method": method, "options": opts, "map": mp,
                   "rotate_deg": rot, "exact_u": rot == rendered,
                   "ms_relight": 1e3 * t_relight,
                   "ms_relight_new_rotation": 1e3 * t_new_rot,
                   "ms_prepare": 1e3 * t_prepare, "ms_texture": 1e3 * t_texture,
                   "ms_render_default": 1e3 * t_full, "ms_render_tensor": 1e3 * t_tensor,
                   "ms_render_matte": 1e3 * t_matte,
                   "speedup_vs_default": t_full / t_relight,
                   "speedup_new_rotation_vs_default": t_full / t_new_rot,
                   "max_rel_vs_reference_relight": float(rel_ref.max()),
                   "flip_object_vs_default": float(fm[obj].mean()),
                   "flip_object_vs_tensor": float(fm_t[obj].mean()),
                   "max_rel_object_vs_tensor": float(rel[obj].max())}
            rows.append(row)
            print(f"{name:18s} {method:11s} {mp:16s} {rot:5.0f} relight "
                  f"{row['ms_relight']:6.2f} ms "
                  f"(new rotation {row['ms_relight_new_rotation']:6.2f}) | render "
                  f"{row['ms_render_default']:7.1f} ms (x{row['speedup_vs_default']:.1f}, "
                  f"x{row['speedup_new_rotation_vs_default']:.1f})"
                  f" | tensor {row['ms_render_tensor']:7.1f} | matte render "
                  f"{row['ms_render_matte']:7.1f} | FLIP {row['flip_object_vs_default']:.4f}"
                  f" / {row['flip_object_vs_tensor']:.4f} | maxrel "
                  f"{row['max_rel_object_vs_tensor']:.1e}", flush=True)
            if name == SCENES[0][0] and mp not in drawn:  # one view per map
                drawn.add(mp)
                figure.append(np.concatenate([
                    linear_to_srgb8(img[0].numpy()), linear_to_srgb8(direct.radiance[0].numpy()),
                    (np.clip(fm * 4, 0, 1)[..., None].repeat(3, -1) * 255).astype(np.uint8)], 1))
    from PIL import Image  # noqa: PLC0415

    Image.fromarray(np.concatenate(figure, 0)).save(out_dir / "relit_vs_direct.png")
    sp = [r["speedup_vs_default"] for r in rows]
    sp_new = [r["speedup_new_rotation_vs_default"] for r in rows if not r["exact_u"]]
    sp_exact = [r["speedup_new_rotation_vs_default"] for r in rows if r["exact_u"]]
    summary = {"date": date.today().isoformat(), "threads": torch.get_num_threads(),
               "native": native.available(),
               "size": args.size, "rows": rows,
               "speedup_min": min(sp), "speedup_median": float(np.median(sp)),
               "speedup_new_rotation_min": min(sp_new),
               "speedup_new_rotation_median": float(np.median(sp_new)),
               "speedup_rendered_rotation_first_min": min(sp_exact),
               "flip_max_vs_default": max(r["flip_object_vs_default"] for r in rows),
               "max_rel_vs_tensor": max(r["max_rel_object_vs_tensor"] for r in rows),
               "max_rel_vs_reference_relight": max(r["max_rel_vs_reference_relight"]
                                                   for r in rows if r["exact_u"]),
               "max_rel_vs_reference_relight_shifted": max(
                   r["max_rel_vs_reference_relight"] for r in rows if not r["exact_u"])}
    name = "relight_bench.json" if args.threads == 1 else f"relight_bench_{args.threads}t.json"
    (out_dir / name).write_text(json.dumps(summary, indent=2) + "\n")
    print(f"speed-up relight vs default render: min x{summary['speedup_min']:.1f}, median "
          f"x{summary['speedup_median']:.1f} (new rotation: min "
          f"x{summary['speedup_new_rotation_min']:.1f}, median "
          f"x{summary['speedup_new_rotation_median']:.1f}; first relight at the rendered "
          f"rotation: min x{summary['speedup_rendered_rotation_first_min']:.1f}); max rel vs "
          f"the lookup-by-lookup relight {summary['max_rel_vs_reference_relight']:.1e} "
          f"(rendered rotation), {summary['max_rel_vs_reference_relight_shifted']:.1e} "
          f"(shifted); "
          f"FLIP max {summary['flip_max_vs_default']:.4f}; "
          f"threads {summary['threads']}; figure: {out_dir / 'relit_vs_direct.png'}")


if __name__ == "__main__":
    main()

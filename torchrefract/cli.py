"""Command line: ``torchrefract render SCENE.yaml [...] --out DIR`` and
``torchrefract sweep CONFIG --out DIR`` (datasets: docs/datasets.md).

Scenes are grouped by resolution, method and options and rendered in batches; a progress
bar shows frames per second unless ``--quiet``. A scene that cannot be rendered (bad file,
broken asset) is reported with its reason and the others still render; the exit status is
then 1. Invalid command-line use exits with 2.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import time
from collections import defaultdict
from pathlib import Path

from torchrefract.checks import ConfigError


def _add_render(sub) -> None:
    """The ``render`` command's arguments."""
    r = sub.add_parser("render", help="render scene YAML files (SCENE_SPEC.md form)")
    r.add_argument("scenes", nargs="+", help="scene YAML files")
    r.add_argument("--out", required=True, help="output folder (created if missing)")
    r.add_argument("--method", default=None,
                   help="override the scenes' method (default: each scene's own)")
    r.add_argument("--batch-size", type=int, default=8,
                   help="scenes rendered together in one tensor pass (default 8)")
    r.add_argument("--threads", type=int, default=None, help="torch CPU threads")
    r.add_argument("--compile", action="store_true",
                   help="torch.compile the ray march (same images; pays off on long runs: "
                        "seconds of start-up, README 'Compiled march')")
    r.add_argument("--no-native", action="store_true",
                   help="the tensor code instead of the C kernels for the march and the "
                        "G-buffer (same images, slower; README 'Native kernels')")
    r.add_argument("--no-fused", action="store_true",
                   help="each method's tensor code instead of its fused shading kernel "
                        "(the same images within float32 rounding; slower)")
    r.add_argument("--adaptive", action=argparse.BooleanOptionalAction, default=None,
                   help="shade only the (sub-)pixels the image needs (the default): with "
                        "samples_per_pixel > 1 every sub-pixel only where the G-buffer "
                        "changes inside the pixel; with 1, a 2x2 lattice, the pixels between "
                        "interpolated where smooth; --no-adaptive shades every (sub-)pixel "
                        "(RenderSettings.adaptive)")
    r.add_argument("--passes", default=None,
                   help="extra passes for every scene, comma-separated: matte (the lobes "
                        "the method read the environment with, relightable), flow "
                        "(refractive flow); replaces the scenes' own 'passes' (docs/matte.md)")
    r.add_argument("--device", default=None,
                   help="cpu, cuda, cuda:N or auto: where the shading runs "
                        "(RenderSettings.device; default cpu, or $TORCHREFRACT_DEVICE)")
    r.add_argument("--rasterizer", default=None, choices=("auto", "native", "opengl"),
                   help="what draws the G-buffer's triangle ids: the native rasterizer or "
                        "pyrender's OpenGL passes (RenderSettings.rasterizer; default auto)")
    r.add_argument("--quiet", action="store_true", help="no progress bar or summary")


def _add_compare(sub) -> None:
    """The ``compare`` command's arguments."""
    c = sub.add_parser("compare", help="error metrics of an EXR against a reference EXR")
    c.add_argument("test", help="the image to score (EXR with R, G, B)")
    c.add_argument("reference", help="the reference (EXR; its A channel selects object "
                                     "pixels, else the test's, else all)")
    c.add_argument("--error-map", default=None, help="write the FLIP error map (PNG)")
    c.add_argument("--exposure", type=float, default=0.0, help="preview exposure (stops)")
    c.add_argument("--json", default=None, help="also write the metrics as JSON")


def _add_sweep(sub) -> None:
    """The ``sweep`` command's arguments."""
    w = sub.add_parser("sweep", help="render a sweep config into a dataset (docs/datasets.md)")
    w.add_argument("config", help="sweep YAML file (configs/sweep_*.yaml)")
    w.add_argument("--out", required=True,
                   help="output folder; running again resumes what is missing")
    w.add_argument("--format", choices=("folder", "webdataset"), default="folder",
                   help="files per sample (default) or WebDataset tar shards")
    w.add_argument("--shard-size", type=int, default=1000,
                   help="samples per shard with --format webdataset (default 1000)")
    w.add_argument("--workers", type=int, default=0,
                   help="local: rendering processes (0: this process, default); ray: CPUs "
                        "of the local cluster started when no --ray-address is given")
    w.add_argument("--executor", choices=("local", "ray"), default="local",
                   help="local processes (default) or Ray tasks")
    w.add_argument("--ray-address", default=None,
                   help="Ray cluster address for ray.init (default: start a local cluster)")
    w.add_argument("--batch-size", type=int, default=8,
                   help="samples of one resolution rendered together (default 8)")
    w.add_argument("--threads", type=int, default=None,
                   help="torch CPU threads per rendering process")
    w.add_argument("--compile", action="store_true",
                   help="torch.compile the ray march in every rendering process (same "
                        "images; seconds of start-up per process)")
    w.add_argument("--no-native", action="store_true",
                   help="the tensor code instead of the C kernels in every rendering "
                        "process (same images, slower)")
    w.add_argument("--no-fused", action="store_true",
                   help="each method's tensor code instead of its fused shading kernel in "
                        "every rendering process")
    w.add_argument("--adaptive", action=argparse.BooleanOptionalAction, default=None,
                   help="adaptive sampling in every rendering process (the default; "
                        "--no-adaptive: every (sub-)pixel shaded; RenderSettings.adaptive)")
    w.add_argument("--device", default=None,
                   help="cpu, cuda, cuda:N or auto: where every rendering process shades "
                        "(RenderSettings.device)")
    w.add_argument("--rasterizer", default=None, choices=("auto", "native", "opengl"),
                   help="what draws the G-buffer's triangle ids in every rendering process "
                        "(RenderSettings.rasterizer)")
    w.add_argument("--verify", action="store_true",
                   help="on resume, check existing files' sha256 (default: their sizes)")
    w.add_argument("--quiet", action="store_true", help="no progress bar or summary")


def _add_exr_compression(p) -> None:
    """The ``--exr-compression`` option of ``render`` and ``sweep``."""
    from torchrefract.output.images import EXR_COMPRESSIONS  # noqa: PLC0415

    p.add_argument("--exr-compression", choices=tuple(EXR_COMPRESSIONS), default="zip",
                   help="the EXR files' lossless compression: zip (default; every EXR reader "
                        "takes it), rle (faster to write, larger), zstd (smaller, faster to "
                        "read; OpenEXR 3.4 and later only), zips, piz, none")


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="torchrefract",
                                description="Render rough glass objects with PyTorch.")
    sub = p.add_subparsers(dest="command", required=True)
    _add_render(sub)
    _add_compare(sub)
    _add_sweep(sub)
    for name in ("render", "sweep"):
        _add_exr_compression(sub.choices[name])
    return p


def _sweep_cmd(args: argparse.Namespace) -> int:
    from torchrefract.dataset.run import DiskFullError, run_sweep  # noqa: PLC0415

    try:
        s = run_sweep(args.config, args.out, fmt=args.format, shard_size=args.shard_size,
                      workers=args.workers, executor=args.executor,
                      ray_address=args.ray_address, batch_size=args.batch_size,
                      quiet=args.quiet, verify=args.verify, settings=args.settings,
                      exr_compression=args.exr_compression)
    except ConfigError as exc:
        print(f"torchrefract: {exc}", file=sys.stderr)
        return 2
    except DiskFullError as exc:
        print(f"torchrefract: {exc}", file=sys.stderr)
        return 3
    except OSError as exc:  # the output folder cannot be made or written (a file, read-only)
        print(f"torchrefract: --out {args.out}: {exc.strerror or exc}", file=sys.stderr)
        return 2
    if s.failed:
        print(f"torchrefract: {s.failed} sample(s) FAILED (reasons in {args.out}/manifest.jsonl)"
              f": {', '.join(s.failed_ids[:10])}" + (" ..." if s.failed > 10 else ""),
              file=sys.stderr)
    if not args.quiet:
        print(f"{s.ok} rendered, {s.failed} failed, {s.skipped} already complete, into "
              f"{args.out}/ in {s.wall_s:.2f} s ({s.samples_per_s:.2f} samples/s; own "
              f"overhead {100 * s.overhead_fraction:.1f}% of the wall time)")
    return 1 if s.failed else 0


def _render_cmd(args: argparse.Namespace) -> int:
    import torch  # noqa: PLC0415
    from tqdm import tqdm  # noqa: PLC0415

    from torchrefract.scene import load_scene  # noqa: PLC0415

    if args.batch_size < 1:
        print("torchrefract: --batch-size must be >= 1", file=sys.stderr)
        return 2
    failed: list[tuple[str, str]] = []
    scenes = []
    extra = None
    if args.passes is not None:
        from torchrefract.matte.passes import parse_passes  # noqa: PLC0415

        try:
            extra = parse_passes([p.strip() for p in args.passes.split(",") if p.strip()],
                                 None, "--passes")
        except ConfigError as exc:
            print(f"torchrefract: {exc}", file=sys.stderr)
            return 2
    for path in args.scenes:
        try:
            s = load_scene(path)
            s = s if args.method is None else s.replace(method=args.method)
            scenes.append(s if extra is None else s.replace(passes=extra))
        except Exception as exc:  # noqa: BLE001 (recorded as failed; the others still load)
            failed.append((path, _reason(exc)))
    names = [s.name for s in scenes]
    dup = {n for n in names if names.count(n) > 1}
    if dup:
        print(f"torchrefract: several scene files share the output name(s) {sorted(dup)}; "
              "rename them so no output overwrites another", file=sys.stderr)
        return 2
    groups = defaultdict(list)
    for s in scenes:
        c = s.camera
        key = (c.width, c.height, c.samples_per_pixel, s.method, repr(s.method_options),
               repr(s.passes))
        groups[key].append(s)
    out = Path(args.out)
    start = time.perf_counter()
    done = 0
    bar = tqdm(total=len(scenes), unit="frame", disable=args.quiet, dynamic_ncols=True)
    for group in groups.values():
        for k in range(0, len(group), args.batch_size):
            batch = group[k:k + args.batch_size]
            ok = _render_and_save(batch, args.settings, out, failed, args.exr_compression)
            done += ok
            bar.update(len(batch))
    bar.close()
    for name, reason in failed:
        print(f"torchrefract: FAILED {name}: {reason}", file=sys.stderr)
    if not args.quiet:
        dt = time.perf_counter() - start
        threads = args.settings.threads or torch.get_num_threads()
        print(f"rendered {done} frame(s) into {out}/ in {dt:.2f} s ({threads} threads)"
              + (f", {len(failed)} failed" if failed else ""))
    return 1 if failed else 0


def _reason(exc: BaseException) -> str:
    """A failure's line: the message of an input error, the type too for anything else."""
    if isinstance(exc, (ConfigError, NotImplementedError)):
        return str(exc)
    return f"{type(exc).__name__}: {exc}"


def _render_and_save(batch: list, settings, out: Path, failed: list[tuple[str, str]],
                     exr_compression: str = "zip") -> int:
    """Render one batch and write its frames; a batch that fails is tried scene by scene,
    so one broken scene fails alone (recorded in ``failed``). Returns the frames written."""
    from torchrefract.output.export import in_threads, save_render  # noqa: PLC0415
    from torchrefract.render import render  # noqa: PLC0415

    try:
        result = render(batch, settings=settings)
    except Exception as exc:  # noqa: BLE001 (recorded; the other batches go on)
        if len(batch) > 1:
            return sum(_render_and_save([s], settings, out, failed, exr_compression)
                       for s in batch)
        failed.append((batch[0].name, _reason(exc)))
        return 0

    def save(i: int) -> str | None:  # the reason it failed, or None
        try:
            save_render(result, i, out, exr_compression)
            return None
        except Exception as exc:  # noqa: BLE001 (an unwritable output: this frame alone)
            return _reason(exc)

    # side by side: a batch's encoding took longer than its render, one frame at a time
    reasons = in_threads(save, range(len(batch)), "torchrefract-save")
    failed += [(s.name, r) for s, r in zip(batch, reasons) if r is not None]
    return reasons.count(None)


def _compare_cmd(args: argparse.Namespace) -> int:
    import json  # noqa: PLC0415

    import numpy as np  # noqa: PLC0415
    from PIL import Image  # noqa: PLC0415

    from torchrefract.output.images import read_exr  # noqa: PLC0415
    from torchrefract.truth.metrics import compare, flip_magma  # noqa: PLC0415

    try:
        test, ref = read_exr(args.test), read_exr(args.reference)
    except ConfigError as exc:
        print(f"torchrefract: {exc}", file=sys.stderr)
        return 2
    for name, ch in ((args.test, test), (args.reference, ref)):
        if not all(c in ch for c in "RGB"):
            print(f"torchrefract: {name}: no R, G, B channels (found {sorted(ch)})",
                  file=sys.stderr)
            return 2
    x = np.stack([test[c] for c in "RGB"], -1)
    r = np.stack([ref[c] for c in "RGB"], -1)
    if x.shape != r.shape:
        print(f"torchrefract: image sizes differ: {x.shape[:2]} vs {r.shape[:2]}",
              file=sys.stderr)
        return 2
    for name, img in ((args.test, x), (args.reference, r)):
        bad = int((~np.isfinite(img)).any(-1).sum())
        if bad:
            print(f"torchrefract: {name}: {bad} pixels with NaN or infinite values",
                  file=sys.stderr)
            return 2
    if not math.isfinite(args.exposure):
        print(f"torchrefract: --exposure: expected a finite number, got {args.exposure}",
              file=sys.stderr)
        return 2
    # the object's pixels: the reference's alpha, else the test's, else all (an alpha
    # that covers nothing says nothing about where the object is)
    cov = next((a for a in (ref.get("A"), test.get("A")) if a is not None and (a > 0.5).any()),
               np.ones(r.shape[:2], np.float32))
    metrics = compare(x, r, cov, args.exposure)
    for k, v in metrics.items():
        print(f"{k:<14} {v:.6g}")
    for path in (args.error_map, args.json):
        if path:
            Path(path).parent.mkdir(parents=True, exist_ok=True)
    if args.error_map:
        Image.fromarray(flip_magma(x, r, args.exposure)).save(args.error_map)
        print(f"error map: {args.error_map}")
    if args.json:  # strict JSON: an infinite PSNR (identical images) as null
        clean = {k: (v if math.isfinite(v) else None) for k, v in metrics.items()}
        Path(args.json).write_text(json.dumps(clean, indent=2, allow_nan=False) + "\n")
    return 0


def _settings(args: argparse.Namespace):
    """The run's RenderSettings: the environment's defaults, the flags, and heap reuse
    (the command owns its process; ``TORCHREFRACT_HEAP_REUSE=0`` keeps it off)."""
    from torchrefract.settings import RenderSettings  # noqa: PLC0415

    s = RenderSettings.from_env()
    changes = {"heap_reuse": os.environ.get("TORCHREFRACT_HEAP_REUSE", "").strip() != "0"}
    if getattr(args, "threads", None):
        changes["threads"] = args.threads
    if getattr(args, "compile", False):
        changes["compile"] = True
    if getattr(args, "no_native", False):
        changes["native"] = False
    if getattr(args, "no_fused", False):
        changes["fused"] = False
    if getattr(args, "adaptive", None) is not None:
        changes["adaptive"] = args.adaptive
    if getattr(args, "device", None):
        changes["device"] = args.device
    if getattr(args, "rasterizer", None):
        changes["rasterizer"] = args.rasterizer
    return s.replace(**changes)


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    try:  # bad flags (--threads -1, --device bogus, a device torch cannot see) up front
        args.settings = _settings(args)
        if args.command in ("render", "sweep") and getattr(args, "executor", None) != "ray":
            args.settings.torch_device()  # (Ray's workers may see devices this host lacks)
    except ConfigError as exc:
        print(f"torchrefract: {exc}", file=sys.stderr)
        return 2
    if args.settings.heap_reuse:  # now, before any thread has made its own malloc arena
        from torchrefract.heap import set_heap_reuse  # noqa: PLC0415

        set_heap_reuse(True)
    commands = {"render": _render_cmd, "compare": _compare_cmd, "sweep": _sweep_cmd}
    try:
        return commands[args.command](args)
    except KeyboardInterrupt:  # (a sweep's finished samples are kept: run it again to resume)
        print(f"torchrefract: {args.command} interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())

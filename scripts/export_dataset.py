"""Export a dataset from a sweep config: the runner of ``torchrefract sweep``, as a script.

Renders every sample of a sweep (``configs/sweep_*.yaml``, see docs/datasets.md) into a
folder of EXR + PNG files or into WebDataset tar shards, with one manifest line per sample.
Running the same command again resumes: complete samples are skipped, the rest (and any
failed ones) rendered. Extras over the CLI: ``--dry-run`` prints the plan without rendering,
``--limit`` renders only part of what is left, ``--summary-json`` saves the run's timings.

Examples::

    # the demo: 12 samples at 64x64 into outputs/datasets/sweep_demo/
    .venv/bin/python scripts/export_dataset.py configs/sweep_demo.yaml

    # what would be rendered, without rendering
    .venv/bin/python scripts/export_dataset.py configs/sweep_demo.yaml --dry-run

    # shards of 500 samples, 2 local worker processes
    .venv/bin/python scripts/export_dataset.py configs/sweep_demo.yaml \\
        --out outputs/datasets/demo_wds --format webdataset --shard-size 500 --workers 2

    # on a Ray cluster (or a local one when --ray-address is left out)
    .venv/bin/python scripts/export_dataset.py my_sweep.yaml --executor ray \\
        --ray-address ray://head:10001

Exit status: 0 when every sample is complete, 1 when some failed (their reasons are in the
manifest and printed), 2 for an invalid config or arguments.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections import Counter
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def _args(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("config", help="sweep YAML file")
    p.add_argument("--out", default=None,
                   help="output folder (default outputs/datasets/<sweep name>)")
    p.add_argument("--format", choices=("folder", "webdataset"), default="folder")
    p.add_argument("--shard-size", type=int, default=1000, help="samples per shard")
    p.add_argument("--workers", type=int, default=0,
                   help="local rendering processes (0: this process); Ray: local cluster CPUs")
    p.add_argument("--executor", choices=("local", "ray"), default="local")
    p.add_argument("--ray-address", default=None, help="Ray cluster address (ray.init)")
    p.add_argument("--batch-size", type=int, default=8)
    p.add_argument("--threads", type=int, default=None, help="torch threads per process")
    p.add_argument("--limit", type=int, default=None,
                   help="render at most this many of the remaining samples, then stop")
    p.add_argument("--verify", action="store_true",
                   help="on resume, check existing files by sha256 (default: by size)")
    p.add_argument("--dry-run", action="store_true",
                   help="print the plan (counts, batches, first samples) and exit")
    p.add_argument("--summary-json", default=None, help="write the run's summary here")
    p.add_argument("--quiet", action="store_true")
    return p.parse_args(argv)


def _dry_run(cfg, show: int = 5) -> None:
    from torchrefract.dataset.run import _plan_batches  # noqa: PLC0415

    samples = list(cfg.samples())
    batches = _plan_batches(samples, 8)
    shapes = Counter((s.scene.camera.width, s.scene.camera.height, s.scene.method)
                     for s in samples)
    print(f"{cfg.name}: {len(samples)} samples ({cfg.sampling.mode} sampling, seed "
          f"{cfg.sampling.seed}), config hash {cfg.config_hash[:16]}")
    print(f"  {len(batches)} batches of up to 8; resolutions/methods: "
          + ", ".join(f"{w}x{h} {m}: {n}" for (w, h, m), n in sorted(shapes.items())))
    print("  swept axes: " + ", ".join(n for n, _ in cfg.axes()))
    for s in samples[:show]:
        params = {k: v for k, v in s.params.items() if k != "index"}
        print(f"  {s.sample_id}: {json.dumps(params)}")
    if len(samples) > show:
        print(f"  ... {len(samples) - show} more")


def main(argv: list[str] | None = None) -> int:
    args = _args(argv)
    sys.path.insert(0, str(ROOT))  # run from a checkout without installing
    from torchrefract.checks import ConfigError  # noqa: PLC0415
    from torchrefract.dataset.run import run_sweep  # noqa: PLC0415
    from torchrefract.dataset.sweep import load_sweep  # noqa: PLC0415
    from torchrefract.settings import RenderSettings  # noqa: PLC0415

    # heap reuse, as `torchrefract sweep` (torchrefract.heap); TORCHREFRACT_HEAP_REUSE=0: off
    settings = RenderSettings.from_env(heap_reuse=True)

    try:
        cfg = load_sweep(args.config)
        if args.dry_run:
            _dry_run(cfg)
            return 0
        out = Path(args.out) if args.out else ROOT / "outputs" / "datasets" / cfg.name
        s = run_sweep(cfg, out, settings=settings, fmt=args.format, shard_size=args.shard_size,
                      workers=args.workers, executor=args.executor,
                      ray_address=args.ray_address, batch_size=args.batch_size,
                      threads=args.threads, quiet=args.quiet, verify=args.verify,
                      limit=args.limit)
    except ConfigError as exc:
        print(f"export_dataset: {exc}", file=sys.stderr)
        return 2
    if args.summary_json:
        Path(args.summary_json).write_text(json.dumps(s.to_dict(), indent=2) + "\n")
    if s.failed:
        lines = [json.loads(ln) for ln in (out / "manifest.jsonl").read_text().splitlines()]
        for e in lines:
            if e.get("status") == "failed":
                print(f"export_dataset: FAILED {e['sample_id']}: {e['reason']}", file=sys.stderr)
    if not args.quiet:
        print(f"{out}: {s.ok} rendered, {s.failed} failed, {s.skipped} already complete; "
              f"{s.wall_s:.2f} s wall, {s.samples_per_s:.2f} samples/s; render "
              f"{s.render_s:.2f} s, encode {s.encode_s:.2f} s, write {s.write_s:.2f} s, "
              f"manifest {s.manifest_s:.2f} s, plan {s.plan_s:.2f} s; overhead "
              f"{100 * s.overhead_fraction:.1f}% of the wall time")
    return 1 if s.failed else 0


if __name__ == "__main__":
    sys.exit(main())

"""Method ``sh``: the precomputation's time and cache size on one mesh (issue #25's target:
a 100k-triangle mesh in <= 2 minutes at the paper's 2048 directions on the 2-core machine).

Runs :func:`torchrefract.methods.sh.cache.get_table` on the mesh, object space, into a
fresh cache folder (so it is computed, never read), and prints the samples, paths, rays,
seconds, the process's CPU seconds (user + system: less sensitive than the wall time to
other jobs on a shared machine; over the cores, the wall time on a quiet one), chunks
traced at once (``workers``), torch threads, file size, table memory and load average.
Per-frame time against ``rousiers``: ``scripts/bench.py --methods sh rousiers --sizes 256
--batches 8 --threads 1``.

    .venv/bin/python scripts/sh_bench.py ../shared/assets/meshes/lucy.ply [--rings 32]
        [--samples 32768] [--threads 1] [--workers N] [--ior 1.5] [--tracer torch]
        [--save table.npz]
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import tempfile
from pathlib import Path

import torch

from torchrefract.geometry.mesh import load_mesh
from torchrefract.methods.sh import cache, precompute
from torchrefract.methods.sh.precompute import Settings


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("mesh")
    ap.add_argument("--rings", type=int, default=32)
    ap.add_argument("--samples", type=int, default=32768)
    ap.add_argument("--bounces", type=int, default=16)
    ap.add_argument("--ior", type=float, default=1.5)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--workers", type=int, default=None)
    ap.add_argument("--tracer", default="auto", choices=("auto", "embree", "mitsuba", "torch"),
                    help="torch: the paths in torch on Embree (the reference before the C "
                         "path kernel); auto/embree: the C kernel where it builds")
    ap.add_argument("--save", default=None,
                    help="keep the table's file here (to compare two runs)")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    mesh = load_mesh(args.mesh)
    settings = Settings(ior=args.ior, rings=args.rings, samples=args.samples,
                        max_events=args.bounces)
    if args.workers is not None:  # the bench's choice instead of precompute_workers()
        default = precompute.precompute
        cache.precompute = lambda *a, **k: default(*a, **k, workers=args.workers)
    def cpu() -> float:
        ru = resource.getrusage(resource.RUSAGE_SELF)
        return ru.ru_utime + ru.ru_stime

    with tempfile.TemporaryDirectory() as tmp:
        cpu0 = cpu()
        table, source = cache.get_table(mesh, settings, Path(tmp), tracer=args.tracer,
                                        name=Path(args.mesh).name)
        path = cache.cache_path(Path(tmp), cache.mesh_hash(mesh), settings)
        cpu_seconds = cpu() - cpu0
        size = path.stat().st_size
        if args.save:
            shutil.copyfile(path, args.save)
    out = {"mesh": args.mesh, "faces": mesh.num_faces, **table.stats,
           "cache_mb": size / 2 ** 20, "memory_mb": table.nbytes / 2 ** 20,
           "torch_threads": torch.get_num_threads(), "source": source,
           "cpu_seconds": cpu_seconds, "loadavg": os.getloadavg()}
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()

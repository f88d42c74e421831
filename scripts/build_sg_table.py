"""Build the spherical Gaussian BTDF/BRDF table shipped as torchrefract/tables/sg_table_v1.npz.

Fits both lobes (transmit, reflect) for every (theta_o, eta, alpha) node and both NDFs
(see torchrefract/sgfit.py), writes a compressed float32 .npz and prints the time taken.

    .venv/bin/python scripts/build_sg_table.py [--out torchrefract/tables/sg_table_v1.npz]
                                               [--threads 1] [--device cpu]

The default spec is the one `torchrefract.optics.sgfit.load_sg_table()` expects; the file stores
its spec and key, so a table built with other settings is never mistaken for it.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import torch

from torchrefract.optics import sg_fit, sg_table


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=sg_table.SHIPPED_TABLE)
    ap.add_argument("--threads", type=int, default=None,
                    help="torch intra-op threads (default: torch's choice)")
    ap.add_argument("--device", default="cpu", help="cpu or cuda (float64 either way)")
    ap.add_argument("--quiet", action="store_true")
    args = ap.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    spec = sg_table.SGTableSpec()
    print(f"SG table spec {spec} (key {spec.key()}), {torch.get_num_threads()} threads, "
          f"device {args.device}", flush=True)
    t0 = time.perf_counter()
    table = sg_fit.build_sg_table(spec, device=args.device, verbose=not args.quiet)
    seconds = time.perf_counter() - t0
    path = sg_table.save_sg_table(table, args.out)
    size = path.stat().st_size
    print(f"built in {seconds:.1f} s; wrote {path} ({size / 1e6:.2f} MB, data "
          f"{tuple(table.data.shape)} float32)")


if __name__ == "__main__":
    main()

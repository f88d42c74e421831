"""A figure like Genevaux et al.'s fig. 12: one scene rendered by ``sh`` at SH orders 2, 4,
6 and 8 beside converged truth, FLIP on object pixels under each (issue #25).

The mapping is precomputed once (the cache keeps all bands up to 8); ``order`` truncates it
at shading time, so the four images differ only in the bands they keep.

    .venv/bin/python scripts/sh_orders.py [--scene configs/suite/teapot_a01.yaml]
        [--size 128] [--orders 2 4 6 8] [--out docs/sh_orders.jpg]

Writes the strip (PNG previews, exposure of the scene) and ``outputs/sh_orders/orders.json``
(FLIP and relMSE per order).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw

import torchrefract as tr
from torchrefract.output.images import linear_to_srgb8
from torchrefract.truth.metrics import compare

sys.path.insert(0, str(Path(__file__).resolve().parent))
from accuracy import truth  # noqa: E402  (the one truth renderer and cache)

ROOT = Path(__file__).resolve().parent.parent


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default=str(ROOT / "configs" / "suite" / "teapot_a01.yaml"))
    ap.add_argument("--size", type=int, default=128)
    ap.add_argument("--orders", type=int, nargs="+", default=[2, 4, 6, 8])
    ap.add_argument("--truth-dir", default=str(ROOT / "outputs" / "truth"))
    ap.add_argument("--out", default=str(ROOT / "docs" / "sh_orders.jpg"))
    args = ap.parse_args(argv)
    s = tr.load_scene(args.scene)
    s = s.replace(camera=dataclasses.replace(s.camera, width=args.size, height=args.size,
                                             samples_per_pixel=1), method="sh")
    ref, alpha, _ = truth(s, 1024, 64, 0, Path(args.truth_dir))
    tiles, rows = [], []
    for order in args.orders:
        img = tr.render(s.replace(method_options={"order": order})).radiance[0].numpy()
        m = compare(img, ref, alpha)
        rows.append({"order": order, "flip_object": m["flip_object"],
                     "relmse_object": m.get("relmse_object")})
        tiles.append((f"order {order}: FLIP {m['flip_object']:.3f}", img))
        print(json.dumps(rows[-1]), flush=True)
    tiles.append(("truth (1024 spp)", ref))
    w, h = args.size, args.size
    strip = Image.new("RGB", (w * len(tiles), h + 16), "white")
    draw = ImageDraw.Draw(strip)
    for i, (label, img) in enumerate(tiles):
        strip.paste(Image.fromarray(linear_to_srgb8(np.asarray(img), s.exposure)), (i * w, 16))
        draw.text((i * w + 3, 2), label, fill="black")
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    strip.save(out, quality=90)
    js = ROOT / "outputs" / "sh_orders" / "orders.json"
    js.parent.mkdir(parents=True, exist_ok=True)
    js.write_text(json.dumps({"scene": s.name, "size": args.size, "orders": rows}, indent=1))
    print("saved", out, js)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

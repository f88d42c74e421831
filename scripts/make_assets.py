"""Generate the procedural meshes shipped in assets/meshes (deterministic; run to rebuild).

- sphere.ply: icosphere, subdivision 5 (20,480 triangles), radius 1, smooth normals
  computed by trimesh at load time (no normals stored).
- slab.ply: a thin box 1.6 x 1.6 x 0.16 (x, y, z) centered at the origin, flat-shaded: each
  face has its own vertices and stored face normals, so shading normals are exact.

    .venv/bin/python scripts/make_assets.py
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import trimesh
from trimesh.exchange.ply import export_ply

OUT = Path(__file__).resolve().parent.parent / "assets" / "meshes"


def flat_box(extents) -> trimesh.Trimesh:
    box = trimesh.creation.box(extents=extents)
    tri = box.vertices[box.faces]  # (F, 3, 3) unshared corners
    normals = np.repeat(box.face_normals, 3, axis=0)
    return trimesh.Trimesh(tri.reshape(-1, 3), np.arange(len(tri) * 3).reshape(-1, 3),
                           vertex_normals=normals, process=False)


def main() -> None:
    OUT.mkdir(parents=True, exist_ok=True)
    sphere = trimesh.creation.icosphere(subdivisions=5, radius=1.0)
    (OUT / "sphere.ply").write_bytes(export_ply(sphere))
    slab = flat_box((1.6, 1.6, 0.16))
    (OUT / "slab.ply").write_bytes(export_ply(slab, vertex_normal=True))
    print(f"wrote {OUT / 'sphere.ply'} ({len(sphere.faces)} triangles), "
          f"{OUT / 'slab.ply'} ({len(slab.faces)} triangles)")


if __name__ == "__main__":
    main()

"""Generate the meshes of the ``sh`` scenes (configs/suite_sh/; deterministic; run to rebuild).

- shell_bead.ply: a hollow glass shell with a glass bead inside (Genevaux et al. 2006,
  figs. 1 and 11): outer sphere of radius 1 (icosphere, subdivision 4), a spherical cavity
  of radius 0.75 (icosphere, subdivision 4, faces wound inwards so that its normals point
  into the cavity, i.e. out of the glass), and a solid bead of radius 0.3 (subdivision 3)
  resting near the cavity's bottom, centered at (0, -0.42, 0) (0.03 of air below it).
  Three watertight components, analytic normals stored; 11,520 triangles.
- armadillo.ply: copied unchanged from the shared asset collection
  (../shared/assets/meshes/armadillo.ply, Stanford 3D Scanning Repository terms: see
  assets/README.md).

    .venv/bin/python scripts/make_sh_assets.py [--shared ../shared/assets]
"""

from __future__ import annotations

import argparse
import shutil
from pathlib import Path

import numpy as np
import trimesh
from trimesh.exchange.ply import export_ply

ROOT = Path(__file__).resolve().parent.parent
OUT = ROOT / "assets" / "meshes"

OUTER, CAVITY, BEAD, BEAD_CENTER = 1.0, 0.75, 0.3, (0.0, -0.42, 0.0)


def sphere_part(radius: float, subdivisions: int, center=(0.0, 0.0, 0.0), inward=False
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Vertices, faces and analytic normals of an icosphere (wound inwards: normals in)."""
    s = trimesh.creation.icosphere(subdivisions=subdivisions, radius=1.0)
    unit = s.vertices / np.linalg.norm(s.vertices, axis=1, keepdims=True)
    faces = s.faces[:, ::-1] if inward else s.faces
    return unit * radius + np.asarray(center), faces, -unit if inward else unit


def shell_bead() -> trimesh.Trimesh:
    parts = [sphere_part(OUTER, 4), sphere_part(CAVITY, 4, inward=True),
             sphere_part(BEAD, 3, BEAD_CENTER)]
    verts, faces, normals, off = [], [], [], 0
    for v, f, n in parts:
        verts.append(v)
        faces.append(f + off)
        normals.append(n)
        off += len(v)
    return trimesh.Trimesh(np.concatenate(verts), np.concatenate(faces),
                           vertex_normals=np.concatenate(normals), process=False)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--shared", default=str(ROOT.parent / "shared" / "assets"))
    args = ap.parse_args()
    OUT.mkdir(parents=True, exist_ok=True)
    m = shell_bead()
    assert m.is_watertight and m.is_winding_consistent and m.volume > 0
    assert len(m.split(only_watertight=True)) == 3
    (OUT / "shell_bead.ply").write_bytes(export_ply(m, vertex_normal=True))
    print(f"wrote {OUT / 'shell_bead.ply'} ({len(m.faces)} triangles)")
    src = Path(args.shared) / "meshes" / "armadillo.ply"
    shutil.copyfile(src, OUT / "armadillo.ply")
    print(f"copied {src} -> {OUT / 'armadillo.ply'}")


if __name__ == "__main__":
    main()

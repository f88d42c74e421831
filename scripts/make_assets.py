"""Generate the procedural meshes shipped in assets/meshes (deterministic; run to rebuild).

- sphere.ply: icosphere, subdivision 5 (20,480 triangles), radius 1, smooth normals
  computed by trimesh at load time (no normals stored).
- slab.ply: a thin box 1.6 x 1.6 x 0.16 (x, y, z) centered at the origin, flat-shaded: each
  face has its own vertices and stored face normals, so shading normals are exact.
- vgroove.ply: a slab 1.6 x 1.6 (x, y) whose +z face is a sawtooth (v-groove) profile along
  x: 8 grooves of period 0.2 and depth 0.07 (facets tilted 35 degrees), flat back at
  z = -0.1, valleys at z = 0.02, ridges at z = 0.09. Watertight, flat-shaded (stored facet
  normals); the ridges are parallel to y.
- sawtooth.ply: the same construction with 16 asymmetric teeth (period 0.1, depth 0.05,
  ridge at 3/4 of each period: facets tilted 34 and 63 degrees), flat back at z = -0.1,
  valleys at z = 0.02.
- torus.ply: torus about the z axis, major radius 0.7, minor radius 0.3 (128 x 64 sections,
  16,384 triangles), analytic normals stored: a thick ring where most light is trapped by
  total internal reflection.
- globe.obj: UV sphere, radius 1, 96 longitude x 48 latitude segments, with analytic
  normals and UVs stored: u = atan2(x, -z) / 2 pi (as the environment map; the seam, at -z,
  duplicated), v = 0 at the -y pole and 1 at the +y pole (OpenGL: the top row of a lat-long
  image is the north pole). OBJ, not PLY: trimesh 4/5 drops a PLY's stored normals when
  the file also has UVs (the normals at the seam and poles would then be one-sided).
- ../textures/globe_roughness.png: 256 x 128 8-bit grayscale roughness map over the globe's
  UVs with exactly two values: 0 on "continents" (a few smooth blobs, procedural) and 255
  on "oceans" (with roughness_range [0.05, 0.4]: alpha 0.05 and 0.4).
- ../textures/gradient_roughness.png: 256 x 128 8-bit grayscale map, a smooth ramp in
  longitude, 255 (1 - cos(2 pi u)) / 2 (continuous across the seam): roughness that varies
  with no jump (``configs/suite/globe_gradient.yaml``).

    .venv/bin/python scripts/make_assets.py
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import trimesh
from trimesh.exchange.obj import export_obj
from trimesh.exchange.ply import export_ply

OUT = Path(__file__).resolve().parent.parent / "assets" / "meshes"
TEXTURES = OUT.parent / "textures"


def flat_box(extents) -> trimesh.Trimesh:
    box = trimesh.creation.box(extents=extents)
    tri = box.vertices[box.faces]  # (F, 3, 3) unshared corners
    normals = np.repeat(box.face_normals, 3, axis=0)
    return trimesh.Trimesh(tri.reshape(-1, 3), np.arange(len(tri) * 3).reshape(-1, 3),
                           vertex_normals=normals, process=False)


def flat_shaded(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    """The same closed surface with unshared corners carrying their facet's normal."""
    tri = mesh.vertices[mesh.faces]  # (F, 3, 3)
    normals = np.repeat(mesh.face_normals, 3, axis=0)  # (3F, 3)
    return trimesh.Trimesh(tri.reshape(-1, 3), np.arange(len(tri) * 3).reshape(-1, 3),
                           vertex_normals=normals, process=False)


def vgroove_slab(width: float = 1.6, grooves: int = 8, depth: float = 0.07,
                 z_back: float = -0.1, z_valley: float = 0.02, ridge: float = 0.5
                 ) -> trimesh.Trimesh:
    """Slab with a sawtooth top (profile in x, extruded along y), closed, shared vertices.

    The profile's top polyline has valleys at x = -w/2 + k p and ridges a fraction ``ridge``
    of the period p = w / grooves after each (0.5: symmetric v-grooves). Every face (back,
    sides, end caps) is split at the same x stations as the top, so all edges are shared by
    exactly two triangles (no T-junctions).
    """
    h = width / 2
    if ridge == 0.5:
        xs = np.linspace(-h, h, 2 * grooves + 1)  # valley, ridge, valley, ...
    else:
        p = width / grooves
        xs = np.sort(np.concatenate([-h + p * np.arange(grooves + 1),
                                     -h + p * (np.arange(grooves) + ridge)]))
    zt = np.where(np.arange(len(xs)) % 2 == 0, z_valley, z_valley + depth)
    n = len(xs)
    verts = []
    for y in (-h, h):  # per end: top profile points, then back points at the same x
        verts += [(x, y, z) for x, z in zip(xs, zt)]
        verts += [(x, y, z_back) for x in xs]
    verts = np.asarray(verts, np.float64)
    top = lambda e, i: e * 2 * n + i  # noqa: E731  (e: 0 = y- end, 1 = y+ end)
    bot = lambda e, i: e * 2 * n + n + i  # noqa: E731
    faces = []
    for i in range(n - 1):
        faces += [(top(0, i), top(0, i + 1), top(1, i + 1)), (top(0, i), top(1, i + 1), top(1, i))]
        faces += [(bot(0, i), bot(1, i + 1), bot(0, i + 1)), (bot(0, i), bot(1, i), bot(1, i + 1))]
        faces += [(bot(0, i), bot(0, i + 1), top(0, i + 1)), (bot(0, i), top(0, i + 1), top(0, i))]
        faces += [(bot(1, i), top(1, i + 1), bot(1, i + 1)), (bot(1, i), top(1, i), top(1, i + 1))]
    # side walls at x = -h and x = +h
    faces += [(bot(0, 0), top(0, 0), top(1, 0)), (bot(0, 0), top(1, 0), bot(1, 0))]
    faces += [(bot(0, n - 1), top(1, n - 1), top(0, n - 1)),
              (bot(0, n - 1), bot(1, n - 1), top(1, n - 1))]
    mesh = trimesh.Trimesh(verts, np.asarray(faces), process=False)
    trimesh.repair.fix_normals(mesh)  # outward winding, whatever the order above
    return mesh


def torus(major: float = 0.7, minor: float = 0.3, n_major: int = 128, n_minor: int = 64
          ) -> trimesh.Trimesh:
    """Torus about z with exact normals stored (shared vertices, closed)."""
    a = 2 * np.pi * np.arange(n_major) / n_major
    b = 2 * np.pi * np.arange(n_minor) / n_minor
    A, B = np.meshgrid(a, b, indexing="ij")  # (n_major, n_minor)
    nrm = np.stack([np.cos(A) * np.cos(B), np.sin(A) * np.cos(B), np.sin(B)], -1)
    center = np.stack([major * np.cos(A), major * np.sin(A), np.zeros_like(A)], -1)
    verts = (center + minor * nrm).reshape(-1, 3)
    idx = np.arange(n_major * n_minor).reshape(n_major, n_minor)
    i0, j0 = np.meshgrid(np.arange(n_major), np.arange(n_minor), indexing="ij")
    i1, j1 = (i0 + 1) % n_major, (j0 + 1) % n_minor
    q = [idx[i0, j0], idx[i1, j0], idx[i1, j1], idx[i0, j1]]
    faces = np.concatenate([np.stack([q[0], q[1], q[2]], -1).reshape(-1, 3),
                            np.stack([q[0], q[2], q[3]], -1).reshape(-1, 3)])
    mesh = trimesh.Trimesh(verts, faces, vertex_normals=nrm.reshape(-1, 3), process=False)
    if mesh.volume < 0:
        mesh = trimesh.Trimesh(verts, faces[:, ::-1], vertex_normals=nrm.reshape(-1, 3),
                               process=False)
    return mesh


def uv_sphere(n_lon: int = 96, n_lat: int = 48) -> trimesh.Trimesh:
    """Unit UV sphere with normals and UVs stored (seam and pole vertices duplicated)."""
    u = np.arange(n_lon + 1) / n_lon  # (n_lon + 1,) seam column repeated at u = 1
    v = np.arange(n_lat + 1) / n_lat  # 0 at the -y pole, 1 at the +y pole
    U, V = np.meshgrid(u, v, indexing="ij")  # (n_lon + 1, n_lat + 1)
    phi, theta = 2 * np.pi * U, np.pi * (1.0 - V)  # theta from +y
    # u = atan2(x, -z) / 2 pi, like the environment map: the seam faces -z (away from a
    # camera on +z), u grows towards +x.
    nrm = np.stack([np.sin(phi) * np.sin(theta), np.cos(theta), -np.cos(phi) * np.sin(theta)],
                   -1)
    nrm[:, 0] = (0.0, -1.0, 0.0)  # exact poles
    nrm[:, -1] = (0.0, 1.0, 0.0)
    idx = np.arange((n_lon + 1) * (n_lat + 1)).reshape(n_lon + 1, n_lat + 1)
    faces = []
    for i in range(n_lon):
        for j in range(n_lat):
            a, b, c, d = idx[i, j], idx[i + 1, j], idx[i + 1, j + 1], idx[i, j + 1]
            if j > 0:  # not at the -y pole (where a and b coincide)
                faces.append((a, b, c))
            if j < n_lat - 1:  # not at the +y pole (where c and d coincide)
                faces.append((a, c, d))
    faces = np.asarray(faces)
    verts = nrm.reshape(-1, 3)
    mesh = trimesh.Trimesh(verts, faces, vertex_normals=verts, process=False)
    if mesh.volume < 0:
        faces = faces[:, ::-1]
        mesh = trimesh.Trimesh(verts, faces, vertex_normals=verts, process=False)
    mesh.visual = trimesh.visual.TextureVisuals(
        uv=np.stack([U.ravel(), V.ravel()], -1))
    return mesh


def globe_roughness(width: int = 256, height: int = 128) -> np.ndarray:
    """Two-level map (0 continents, 255 oceans) over lat-long UVs: smooth blobs, thresholded.

    Row 0 is the top of the image = v = 1 = the +y pole. The blobs are sums of Gaussians in
    3D on the unit sphere (so nothing is stretched at the poles or cut at the seam).
    """
    u = (np.arange(width) + 0.5) / width
    v = 1.0 - (np.arange(height) + 0.5) / height
    U, V = np.meshgrid(u, v, indexing="xy")  # (H, W)
    phi, theta = 2 * np.pi * U, np.pi * (1.0 - V)
    p = np.stack([np.sin(phi) * np.sin(theta), np.cos(theta), -np.cos(phi) * np.sin(theta)],
                 -1)  # (H, W, 3)
    rng = np.random.default_rng(20240607)
    field = np.zeros((height, width))
    for _ in range(24):
        c = rng.normal(size=3)
        c /= np.linalg.norm(c)
        s = rng.uniform(0.15, 0.35)
        field += rng.uniform(0.6, 1.0) * np.exp(-((p - c) ** 2).sum(-1) / (2 * s * s))
    land = field > np.quantile(field, 0.6)  # 40% continents
    return np.where(land, 0, 255).astype(np.uint8)


def gradient_roughness(width: int = 256, height: int = 128) -> np.ndarray:
    """Smooth ramp in longitude, 0 at u = 0 and 255 at u = 1/2, the same in every row."""
    u = (np.arange(width) + 0.5) / width
    row = np.round(255.0 * 0.5 * (1.0 - np.cos(2.0 * np.pi * u)))
    return np.repeat(row[None, :], height, 0).astype(np.uint8)


def main() -> None:
    OUT.mkdir(parents=True, exist_ok=True)
    sphere = trimesh.creation.icosphere(subdivisions=5, radius=1.0)
    (OUT / "sphere.ply").write_bytes(export_ply(sphere))
    slab = flat_box((1.6, 1.6, 0.16))
    (OUT / "slab.ply").write_bytes(export_ply(slab, vertex_normal=True))
    vgroove = vgroove_slab()
    assert vgroove.is_watertight and vgroove.is_volume
    (OUT / "vgroove.ply").write_bytes(export_ply(flat_shaded(vgroove), vertex_normal=True))
    saw = vgroove_slab(grooves=16, depth=0.05, ridge=0.75)
    assert saw.is_watertight and saw.is_volume
    (OUT / "sawtooth.ply").write_bytes(export_ply(flat_shaded(saw), vertex_normal=True))
    ring = torus()
    assert ring.is_watertight and ring.is_volume
    (OUT / "torus.ply").write_bytes(export_ply(ring, vertex_normal=True))
    globe = uv_sphere()
    obj = export_obj(globe, include_normals=True, include_texture=True, write_texture=False,
                     include_color=False, digits=7)
    obj = "".join(line + "\n" for line in obj.splitlines()
                  if not line.startswith(("mtllib", "usemtl")))  # no material file
    (OUT / "globe.obj").write_text(obj)
    TEXTURES.mkdir(parents=True, exist_ok=True)
    from PIL import Image  # noqa: PLC0415

    Image.fromarray(globe_roughness(), mode="L").save(TEXTURES / "globe_roughness.png",
                                                       optimize=True)
    Image.fromarray(gradient_roughness(), mode="L").save(TEXTURES / "gradient_roughness.png",
                                                          optimize=True)
    for name, m in (("sphere", sphere), ("slab", slab), ("vgroove", vgroove), ("sawtooth", saw),
                    ("torus", ring)):
        print(f"wrote {OUT / (name + '.ply')} ({len(m.faces)} triangles)")
    print(f"wrote {OUT / 'globe.obj'} ({len(globe.faces)} triangles)")
    print(f"wrote {TEXTURES / 'globe_roughness.png'}, {TEXTURES / 'gradient_roughness.png'}")


if __name__ == "__main__":
    main()

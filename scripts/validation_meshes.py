"""The procedural meshes and roughness maps of the validation set (deterministic; CC0, ours).

Every mesh is closed and outward-wound (watertight once coincident vertices are merged,
consistent winding, positive volume), centered near the origin and about unit size (the
scenes scale and frame them). Written by ``scripts/validation_set.py generate`` to
``assets/meshes/procedural/`` and ``assets/textures/procedural/``; see :data:`FAMILIES` for
which family each belongs to.

- Smooth welded meshes (icosphere blobs and ellipsoids, shells, superquadrics) are binary PLY
  without normals: shading normals are trimesh's, computed at load (SCENE_SPEC.md).
- Meshes with creases (boxes, grooves, a disc, a lens) are binary PLY with split vertices
  carrying their facet's (or the analytic) normal, like ``assets/meshes/slab.ply``.
- Meshes with UVs (for roughness maps) are OBJ with normals and UVs, like
  ``assets/meshes/globe.obj`` (trimesh drops a PLY's stored normals when it also has UVs):
  UV seams are split vertices whose normals are those of the welded surface.

    .venv/bin/python scripts/validation_set.py generate    # writes these and the scenes
"""

from __future__ import annotations

import io
import sys
from pathlib import Path
from typing import Callable

import numpy as np
import trimesh
from trimesh.exchange.obj import export_obj
from trimesh.exchange.ply import export_ply

sys.path.insert(0, str(Path(__file__).resolve().parent))
from make_assets import flat_box, flat_shaded, vgroove_slab  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
MESH_DIR = ROOT / "assets" / "meshes" / "procedural"
TEXTURE_DIR = ROOT / "assets" / "textures" / "procedural"
MESH_SEED = 20260601
"""Seed of the meshes' and maps' own randomness (noise displacements, blobs); fixed, apart
from the scenes' ``--seed``, so that every scene seed uses the same committed meshes."""


# family -> mesh files (relative to assets/meshes). The shipped meshes are used with new
# transforms, materials, maps and views; the chart's scenes stay in configs/suite.
FAMILIES: dict[str, tuple[str, ...]] = {
    "sphere": ("sphere.ply", "globe.obj", "procedural/ellipsoid_uv.obj",
               "procedural/egg.ply", "procedural/sphere_lowpoly.ply"),
    "blob": ("procedural/blob_smooth.ply", "procedural/blob_lumpy.ply",
             "procedural/blob_potato.ply", "procedural/blob_bumpy.ply",
             "procedural/blob_uv.obj"),
    "torus": ("torus.ply", "procedural/torus_thin.ply", "procedural/torus_fat.ply",
              "procedural/torus_flat.ply", "procedural/torus_uv.obj"),
    "slab": ("slab.ply", "procedural/box_thick.ply", "procedural/box_thin.ply",
             "procedural/cube.ply", "procedural/disc.ply", "procedural/lens.ply"),
    "groove": ("vgroove.ply", "sawtooth.ply", "procedural/vgroove_deep.ply",
               "procedural/vgroove_fine.ply", "procedural/sawtooth_steep.ply",
               "procedural/vgroove_thick.ply"),
    "shell": ("shell_bead.ply", "procedural/shell_thick.ply", "procedural/shell_thin.ply",
              "procedural/shell_offcenter.ply", "procedural/shell_ellipsoid.ply"),
    "superquadric": ("procedural/sq_roundcube.ply", "procedural/sq_cylinder.ply",
                     "procedural/sq_octa.ply", "procedural/sq_star.ply",
                     "procedural/sq_pillow_uv.obj"),
    "model": ("spot.ply", "suzanne.ply", "teapot.ply", "wingnut.ply", "bunny.ply",
              "armadillo.ply"),
}
FLAT_FAMILIES = ("slab", "groove")
"""Families whose meshes are plates with their thin axis along object z (views kept off
edge-on)."""
ROUGHNESS_MAPS = ("procedural/rough_blobs2.png", "procedural/rough_fbm.png",
                  "procedural/rough_stripes.png", "procedural/rough_checker.png",
                  "globe_roughness.png", "gradient_roughness.png")
"""Roughness maps (relative to assets/textures) for meshes with UVs."""


# --------------------------------------------------------------------------------------
# Building blocks
# --------------------------------------------------------------------------------------

def _welded_normals(verts: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted vertex normals of the surface with coincident vertices merged (so that
    split seam and pole vertices get the normal of the closed surface), (V, 3)."""
    key = np.round(verts, 7)
    _, inv = np.unique(key, axis=0, return_inverse=True)
    inv = inv.reshape(-1)
    tri = verts[faces]  # (F, 3, 3)
    fn = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])  # (F, 3) area-weighted
    acc = np.zeros((inv.max() + 1, 3))
    for k in range(3):
        np.add.at(acc, inv[faces[:, k]], fn)
    n = acc[inv]
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-30)


def _outward(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    if mesh.volume < 0:
        return trimesh.Trimesh(mesh.vertices, mesh.faces[:, ::-1], process=False)
    return mesh


def _grid_faces(n_u: int, n_v: int, skip_poles: bool) -> np.ndarray:
    """Two triangles per cell of an (n_u + 1) x (n_v + 1) vertex grid (seams duplicated);
    at the poles (rows 0 and n_v of a sphere) the degenerate triangle of each cell is left
    out."""
    idx = np.arange((n_u + 1) * (n_v + 1)).reshape(n_u + 1, n_v + 1)
    faces = []
    for i in range(n_u):
        for j in range(n_v):
            a, b, c, d = idx[i, j], idx[i + 1, j], idx[i + 1, j + 1], idx[i, j + 1]
            if not (skip_poles and j == 0):
                faces.append((a, b, c))
            if not (skip_poles and j == n_v - 1):
                faces.append((a, c, d))
    return np.asarray(faces, dtype=np.int64)


def uv_surface(point: Callable[[np.ndarray, np.ndarray], np.ndarray], n_u: int, n_v: int,
               sphere: bool) -> trimesh.Trimesh:
    """A closed parametric surface with UVs and welded normals stored.

    Args:
        point: maps u, v in [0, 1] (arrays of one shape S) to positions (S + (3,)); periodic
            in u; periodic in v too for a torus, or with v = 0 and v = 1 the poles of a
            sphere-like surface.
        n_u, n_v: cells along u and v.
        sphere: pole topology (else torus topology).
    """
    u = np.arange(n_u + 1) / n_u
    v = np.arange(n_v + 1) / n_v
    U, V = np.meshgrid(u, v, indexing="ij")  # (n_u + 1, n_v + 1)
    verts = point(U, V).reshape(-1, 3)
    faces = _grid_faces(n_u, n_v, skip_poles=sphere)
    mesh = _outward(trimesh.Trimesh(verts, faces, process=False))
    normals = _welded_normals(np.asarray(mesh.vertices), np.asarray(mesh.faces))
    out = trimesh.Trimesh(mesh.vertices, mesh.faces, vertex_normals=normals, process=False)
    out.visual = trimesh.visual.TextureVisuals(uv=np.stack([U.ravel(), V.ravel()], -1))
    return out


def sphere_dir(U: np.ndarray, V: np.ndarray) -> np.ndarray:
    """Unit directions of a lat-long grid, u = atan2(x, -z) / 2 pi, v = 0 at -y (as globe)."""
    phi, theta = 2 * np.pi * U, np.pi * (1.0 - V)
    return np.stack([np.sin(phi) * np.sin(theta), np.cos(theta), -np.cos(phi) * np.sin(theta)],
                    -1)


def noise_radius(d: np.ndarray, rng: np.random.Generator, amp: float, freq: float,
                 terms: int = 12) -> np.ndarray:
    """1 + amp * a smooth random function of the direction d (..., 3), in [1 - amp, 1 + amp]
    (a sum of plane waves in random directions, normalized): a star-shaped blob."""
    f = np.zeros(d.shape[:-1])
    for _ in range(terms):
        k = rng.normal(size=3)
        k /= np.linalg.norm(k)
        fk = freq * rng.uniform(0.6, 1.4)
        f += rng.uniform(0.5, 1.0) * np.sin(fk * np.pi * (d @ k) + rng.uniform(0, 2 * np.pi))
    f /= np.abs(f).max()
    return 1.0 + amp * f


def ico(subdivisions: int) -> trimesh.Trimesh:
    return trimesh.creation.icosphere(subdivisions=subdivisions, radius=1.0)


def radial(mesh: trimesh.Trimesh, r: np.ndarray | Callable) -> trimesh.Trimesh:
    """A welded sphere mesh with each vertex moved to radius r (array or function of the
    unit direction)."""
    d = mesh.vertices / np.linalg.norm(mesh.vertices, axis=1, keepdims=True)
    rad = r(d) if callable(r) else r
    return _outward(trimesh.Trimesh(d * np.asarray(rad)[..., None], mesh.faces, process=False))


def cube_sphere(n: int) -> trimesh.Trimesh:
    """Welded unit-direction mesh from an equal-angle subdivided cube (n x n cells a face):
    even sampling of cube-like shapes (superquadrics)."""
    s = np.tan(np.pi / 4 * np.linspace(-1, 1, n + 1))
    A, B = np.meshgrid(s, s, indexing="ij")
    one = np.ones_like(A)
    verts, faces = [], []
    for axis in range(3):
        for sign in (-1.0, 1.0):
            p = np.zeros(A.shape + (3,))
            p[..., axis] = sign * one
            p[..., (axis + 1) % 3] = A
            p[..., (axis + 2) % 3] = B
            base = sum(len(x) for x in verts)
            verts.append(p.reshape(-1, 3))
            faces.append(_cell_faces(n) + base)
    v = np.concatenate(verts)
    f = np.concatenate(faces)
    mesh = trimesh.Trimesh(v / np.linalg.norm(v, axis=1, keepdims=True), f, process=False)
    mesh.merge_vertices()
    mesh.update_faces(mesh.nondegenerate_faces())
    # each cube face's winding depends on its axis and sign: make every face point outward
    # (for a star-shaped surface: normal along the position)
    tri = mesh.vertices[mesh.faces]
    fn = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    flip = (fn * tri.mean(1)).sum(1) < 0
    faces = np.where(flip[:, None], mesh.faces[:, ::-1], mesh.faces)
    return trimesh.Trimesh(mesh.vertices, faces, process=False)


def _cell_faces(n: int) -> np.ndarray:
    idx = np.arange((n + 1) * (n + 1)).reshape(n + 1, n + 1)
    a, b = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel()
    c, d = idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    return np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])


def superellipsoid_radius(d: np.ndarray, e1: float, e2: float, radii=(1.0, 1.0, 1.0)
                          ) -> np.ndarray:
    """Radius along unit directions d (N, 3) of the superellipsoid
    ((|x/a|^(2/e2) + |z/c|^(2/e2))^(e2/e1) + |y/b|^(2/e1)) = 1 (y is the polar axis)."""
    x, y, z = (np.abs(d[:, k]) / radii[k] for k in range(3))
    f = (x ** (2 / e2) + z ** (2 / e2)) ** (e2 / e1) + y ** (2 / e1)
    return f ** (-e1 / 2)


def shell(outer: trimesh.Trimesh, inner: trimesh.Trimesh) -> trimesh.Trimesh:
    """A solid between two closed surfaces: the inner one's faces wound inwards (its normals
    point into the cavity, i.e. out of the glass)."""
    n = len(outer.vertices)
    v = np.concatenate([outer.vertices, inner.vertices])
    f = np.concatenate([outer.faces, inner.faces[:, ::-1] + n])
    return trimesh.Trimesh(v, f, process=False)


def _appender(verts: list, normals: list):
    """add(v, n): append a block of vertices and their normals; returns the block's first
    index in the concatenation."""
    def add(v, n) -> int:
        base = sum(len(x) for x in verts)
        verts.append(np.asarray(v, float))
        normals.append(np.asarray(n, float))
        return base
    return add


def _add_rim(add, faces: list, ring: np.ndarray, h: float, a: np.ndarray) -> None:
    """The cylindrical side between the rings (S, 2) at z = +h and -h, its own vertices
    (split from the caps) with radial normals; a: the rings' S angles."""
    segments = len(a)
    radial_n = np.c_[np.cos(a), np.sin(a), np.zeros(segments)]
    b = add(np.concatenate([np.c_[ring, np.full(segments, h)], np.c_[ring, np.full(segments, -h)]]),
            np.concatenate([radial_n, radial_n]))
    for i in range(segments):
        j = (i + 1) % segments
        faces += [(b + segments + i, b + segments + j, b + j), (b + segments + i, b + j, b + i)]


def disc(radius: float, height: float, segments: int = 128) -> trimesh.Trimesh:
    """Cylinder (axis z) with flat caps and a smooth side, split at the rims (normals
    stored)."""
    a = 2 * np.pi * np.arange(segments) / segments
    ring = np.stack([radius * np.cos(a), radius * np.sin(a)], -1)  # (S, 2)
    h = height / 2
    verts, normals, faces = [], [], []
    add = _appender(verts, normals)

    for z, s in ((h, 1.0), (-h, -1.0)):  # caps: center + ring
        b = add(np.concatenate([[[0, 0, z]], np.c_[ring, np.full(segments, z)]]),
                np.tile([0, 0, s], (segments + 1, 1)))
        for i in range(segments):
            j = (i + 1) % segments
            faces.append((b, b + 1 + i, b + 1 + j) if s > 0 else (b, b + 1 + j, b + 1 + i))
    _add_rim(add, faces, ring, h, a)
    return _with_normals(np.concatenate(verts), np.asarray(faces), np.concatenate(normals))


def lens(aperture: float, center_thickness: float, edge_thickness: float,
         segments: int = 96, rings: int = 20) -> trimesh.Trimesh:
    """Biconvex lens (axis z): two spherical caps joined by a short cylindrical rim, split at
    the rims, analytic normals stored."""
    sag = (center_thickness - edge_thickness) / 2
    rc = (aperture ** 2 + sag ** 2) / (2 * sag)  # sphere radius of each cap
    a = 2 * np.pi * np.arange(segments) / segments
    rho = aperture * np.arange(1, rings + 1) / rings  # (R,)
    verts, normals, faces = [], [], []
    add = _appender(verts, normals)

    h = edge_thickness / 2
    for s in (1.0, -1.0):
        cz = s * (h + sag - rc)  # the cap's sphere center on the axis
        pts = [[0.0, 0.0, s * (h + sag)]]
        for r in rho:
            z = cz + s * np.sqrt(rc ** 2 - r ** 2)
            pts += [[r * np.cos(t), r * np.sin(t), z] for t in a]
        pts = np.asarray(pts)
        nrm = (pts - [0, 0, cz]) / rc
        b = add(pts, nrm)
        ring0 = lambda k, i: b + 1 + k * segments + (i % segments)  # noqa: E731
        for i in range(segments):
            faces.append((b, ring0(0, i), ring0(0, i + 1)))
            for k in range(rings - 1):
                faces += [(ring0(k, i), ring0(k + 1, i), ring0(k + 1, i + 1)),
                          (ring0(k, i), ring0(k + 1, i + 1), ring0(k, i + 1))]
        if s < 0:  # the bottom cap was built with the top's winding
            for f in range(len(faces) - segments * (1 + 2 * (rings - 1)), len(faces)):
                faces[f] = faces[f][::-1]
    ring = np.c_[aperture * np.cos(a), aperture * np.sin(a)]
    _add_rim(add, faces, ring, h, a)
    return _with_normals(np.concatenate(verts), np.asarray(faces), np.concatenate(normals))


def _with_normals(v: np.ndarray, f: np.ndarray, n: np.ndarray) -> trimesh.Trimesh:
    """Mesh with stored normals, its winding made outward (checked on the welded surface)."""
    welded = trimesh.Trimesh(v, f, process=False)
    welded.merge_vertices()
    if welded.volume < 0:
        f = f[:, ::-1]
    return trimesh.Trimesh(v, f, vertex_normals=n, process=False)


# --------------------------------------------------------------------------------------
# The library
# --------------------------------------------------------------------------------------

def build_meshes() -> dict[str, trimesh.Trimesh]:
    """Every procedural mesh, by file name (in ``assets/meshes/procedural``)."""
    rng = np.random.default_rng(MESH_SEED)
    m: dict[str, trimesh.Trimesh] = {}
    # sphere family
    m["ellipsoid_uv.obj"] = uv_surface(
        lambda U, V: sphere_dir(U, V) * [1.0, 0.72, 0.55], 64, 32, sphere=True)
    m["egg.ply"] = radial(ico(4), lambda d: (1 + 0.18 * d[:, 1]) / np.sqrt(
        (d[:, 0] / 0.7) ** 2 + d[:, 1] ** 2 + (d[:, 2] / 0.7) ** 2))
    m["sphere_lowpoly.ply"] = ico(2)  # 320 faces: smooth normals over a faceted outline
    # blob family (star-shaped noise displacements of an icosphere)
    m["blob_smooth.ply"] = radial(ico(4), lambda d: noise_radius(d, rng, 0.12, 1.2))
    m["blob_lumpy.ply"] = radial(ico(4), lambda d: noise_radius(d, rng, 0.25, 2.2))
    m["blob_potato.ply"] = radial(ico(4), lambda d: noise_radius(d, rng, 0.15, 1.6)
                                  / np.sqrt((d[:, 0] / 1.0) ** 2 + (d[:, 1] / 0.65) ** 2
                                            + (d[:, 2] / 0.8) ** 2))
    m["blob_bumpy.ply"] = radial(ico(5), lambda d: noise_radius(d, rng, 0.07, 5.0, terms=24))

    def blob_uv(U, V):
        d = sphere_dir(U, V)
        return d * noise_radius(d, rng, 0.18, 1.8)[..., None]

    m["blob_uv.obj"] = uv_surface(blob_uv, 64, 32, sphere=True)
    # torus family (major radius R, minor radii r_radial, r_z; about the y axis)
    def torus_pt(R, r, rz=None):
        rz = r if rz is None else rz
        return lambda U, V: np.stack(
            [(R + r * np.cos(2 * np.pi * V)) * np.cos(2 * np.pi * U),
             rz * np.sin(2 * np.pi * V),
             -(R + r * np.cos(2 * np.pi * V)) * np.sin(2 * np.pi * U)], -1)

    m["torus_thin.ply"] = _no_uv(uv_surface(torus_pt(0.78, 0.13), 96, 24, sphere=False))
    m["torus_fat.ply"] = _no_uv(uv_surface(torus_pt(0.55, 0.42), 72, 36, sphere=False))
    m["torus_flat.ply"] = _no_uv(uv_surface(torus_pt(0.65, 0.3, 0.12), 80, 32, sphere=False))
    m["torus_uv.obj"] = uv_surface(torus_pt(0.66, 0.27), 64, 32, sphere=False)
    # slab family (thin axis z)
    m["box_thick.ply"] = flat_box((1.4, 1.0, 0.5))
    m["box_thin.ply"] = flat_box((1.8, 1.2, 0.05))
    m["cube.ply"] = flat_box((1.0, 1.0, 1.0))
    m["disc.ply"] = disc(0.85, 0.22)
    m["lens.ply"] = lens(0.85, 0.42, 0.04)
    # groove family (profile along x, flat back, thin axis z)
    m["vgroove_deep.ply"] = flat_shaded(vgroove_slab(grooves=6, depth=0.2, z_valley=0.0))
    m["vgroove_fine.ply"] = flat_shaded(vgroove_slab(grooves=20, depth=0.04))
    m["sawtooth_steep.ply"] = flat_shaded(vgroove_slab(grooves=10, depth=0.12, ridge=0.85))
    m["vgroove_thick.ply"] = flat_shaded(vgroove_slab(grooves=8, depth=0.1, z_back=-0.6))
    # shell family (inner surface reversed)
    m["shell_thick.ply"] = shell(ico(4), radial(ico(3), 0.6))
    m["shell_thin.ply"] = shell(ico(4), radial(ico(4), 0.9))
    off = radial(ico(3), 0.55)
    off = trimesh.Trimesh(off.vertices + [0.0, 0.3, 0.0], off.faces, process=False)
    m["shell_offcenter.ply"] = shell(ico(4), off)
    ell = trimesh.Trimesh(ico(4).vertices * [1.0, 0.75, 0.8], ico(4).faces, process=False)
    ell_in = trimesh.Trimesh(ico(3).vertices * [0.8, 0.5, 0.6], ico(3).faces, process=False)
    m["shell_ellipsoid.ply"] = shell(ell, ell_in)
    # superquadric family (y is the polar axis)
    cs = cube_sphere(24)
    m["sq_roundcube.ply"] = radial(cs, lambda d: superellipsoid_radius(d, 0.25, 0.25))
    m["sq_cylinder.ply"] = radial(cs, lambda d: superellipsoid_radius(d, 0.25, 1.0,
                                                                        (0.8, 1.0, 0.8)))
    m["sq_octa.ply"] = radial(ico(4), lambda d: superellipsoid_radius(d, 1.6, 1.6))
    m["sq_star.ply"] = radial(cs, lambda d: superellipsoid_radius(d, 0.6, 2.6,
                                                                    (1.0, 0.75, 1.0)))

    def pillow(U, V):
        d = sphere_dir(U, V)
        r = superellipsoid_radius(d.reshape(-1, 3), 1.0, 0.35, (1.0, 0.55, 1.0))
        return d * r.reshape(d.shape[:-1])[..., None]

    m["sq_pillow_uv.obj"] = uv_surface(pillow, 64, 32, sphere=True)
    return m


def _no_uv(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    """A uv_surface without its UVs and normals, seams welded: a PLY whose shading normals
    trimesh computes at load."""
    keep = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False)
    keep.merge_vertices()
    return trimesh.Trimesh(keep.vertices, keep.faces, process=False)


def build_textures() -> dict[str, np.ndarray]:
    """Roughness maps (256 x 128, 8-bit grayscale), by file name."""
    w, h = 256, 128
    u = (np.arange(w) + 0.5) / w
    v = 1.0 - (np.arange(h) + 0.5) / h
    U, V = np.meshgrid(u, v, indexing="xy")  # (H, W), row 0 at v = 1
    d = sphere_dir(U, V)  # (H, W, 3): smooth on a sphere and across the u seam
    rng = np.random.default_rng(MESH_SEED + 1)
    out = {}
    blobs = noise_radius(d, rng, 1.0, 2.0)
    out["rough_blobs2.png"] = np.where(blobs > np.quantile(blobs, 0.5), 255, 0)
    fbm = sum(noise_radius(d, rng, 1.0, f) / f for f in (1.0, 2.0, 4.0, 8.0))
    out["rough_fbm.png"] = np.round(255 * (fbm - fbm.min()) / np.ptp(fbm))
    out["rough_stripes.png"] = np.round(255 * 0.5 * (1 + np.tanh(3 * np.sin(2 * np.pi * 5 * V))))
    out["rough_checker.png"] = 255 * ((np.floor(8 * U) + np.floor(4 * V)) % 2)
    return {k: np.asarray(x, np.uint8) for k, x in out.items()}


def mesh_bytes(name: str, mesh: trimesh.Trimesh) -> bytes:
    if name.endswith(".obj"):
        obj = export_obj(mesh, include_normals=True, include_texture=True, write_texture=False,
                         include_color=False, digits=5)
        return "".join(line + "\n" for line in obj.splitlines()
                       if not line.startswith(("mtllib", "usemtl"))).encode()
    has_normals = "vertex_normals" in mesh._cache
    return export_ply(mesh, vertex_normal=has_normals)


def write_all(mesh_dir: Path = MESH_DIR, texture_dir: Path = TEXTURE_DIR) -> list[Path]:
    """Write every procedural mesh and map (only where the bytes changed); returns paths."""
    from PIL import Image  # noqa: PLC0415

    written = []
    mesh_dir.mkdir(parents=True, exist_ok=True)
    for name, mesh in build_meshes().items():
        p = mesh_dir / name
        data = mesh_bytes(name, mesh)
        if not p.is_file() or p.read_bytes() != data:
            p.write_bytes(data)
        written.append(p)
    texture_dir.mkdir(parents=True, exist_ok=True)
    for name, img in build_textures().items():
        p = texture_dir / name
        buf = io.BytesIO()
        Image.fromarray(img, mode="L").save(buf, format="PNG", optimize=True)
        if not p.is_file() or p.read_bytes() != buf.getvalue():
            p.write_bytes(buf.getvalue())
        written.append(p)
    return written


def check_closed(mesh: trimesh.Trimesh) -> dict:
    """Watertight (coincident vertices merged), consistently wound, positive volume."""
    w = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False)
    w.merge_vertices(merge_tex=True, merge_norm=True)
    return {"watertight": bool(w.is_watertight), "winding": bool(w.is_winding_consistent),
            "volume": float(w.volume), "faces": len(mesh.faces)}

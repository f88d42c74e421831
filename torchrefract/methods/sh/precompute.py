"""The offline step: sample the refracted path mapping R(p, omega) over the surface and the
outer hemisphere and compress it into real SH (Genevaux et al. 2006, secs. 3-4).

For every surface sample o_i (:mod:`.layout`) and every view direction omega_j of the
direction set (:func:`.basis.view_directions`, in o_i's tangent frame), one path is traced
through the mesh (:mod:`.paths`); the samples of o_i, r_j = (exit direction x, y, z in
object space, length inside / radius, exit cosine, throughput), are compressed with one
matrix product W = M R (eq. 10, M from :func:`.basis.projection_matrix`) up to band 8.
The order actually used and the ringing window (sec. 4.3) are applied when shading: the
projection's coefficients of bands <= L do not depend on the bands kept above L, so one
table serves every order and window.

The coefficients are stored as float16 (the paper found 8 bits per weight enough, fig. 5).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import torch
from tqdm.auto import tqdm

from torchrefract.geometry.mesh import MeshData
from torchrefract.methods.sh.basis import MAX_ORDER, projection_matrix, view_directions
from torchrefract.methods.sh.layout import Layout, build_layout, lattice_rate
from torchrefract.methods.sh.paths import trace_paths
from torchrefract.methods.sh.tracer import intersector

CHANNELS = ("dir_x", "dir_y", "dir_z", "length", "cos_exit", "throughput")
"""What each coefficient vector holds (length: inside the object over the mesh's radius)."""

PATHS_PER_CHUNK = 1 << 19
"""Paths traced per batch (bounds the memory: ~0.2 GB of temporaries)."""

EPS = 1e-5
"""Ray origin offset off the surface, in units of the mesh's bounding radius."""


@dataclass(frozen=True)
class Settings:
    """What the table depends on besides the mesh (part of its cache key)."""

    ior: float
    rings: int
    samples: int
    max_events: int
    branch: str = "tir"


@dataclass(frozen=True)
class SHTable:
    """The compressed refracted-path mapping of one mesh and IOR.

    Attributes:
        layout: the surface samples (object space).
        coeffs: (S, K, C) float16, K = 45 even coefficients up to band 8, C = ``CHANNELS``.
        radius: the mesh's bounding radius (object units; lengths are stored over it).
        settings: what it was computed for.
        mesh_hash: content hash of the object-space mesh (:func:`.cache.mesh_hash`).
        stats: ``seconds``, ``paths``, ``rays``, ``tracer`` of the computation.
    """

    layout: Layout
    coeffs: torch.Tensor
    radius: float
    settings: Settings
    mesh_hash: str
    stats: dict = field(default_factory=dict)

    @property
    def nbytes(self) -> int:
        """Memory of the table (coefficients, lattice, sample frames)."""
        lay = self.layout
        return sum(t.numel() * t.element_size() for t in
                   (self.coeffs, lay.lattice, lay.position, lay.frame))


def precompute(mesh: MeshData, settings: Settings, mesh_hash: str, tracer: str = "auto",
               progress: str | None = None) -> SHTable:
    """Trace and compress the mapping of ``mesh`` (object space) at ``settings``.

    Args:
        mesh: the object-space mesh (``load_mesh(path)`` without transform).
        settings: IOR, direction rings, target sample count, interface limit.
        mesh_hash: recorded in the table.
        tracer: ``auto``, ``embree`` or ``mitsuba`` (:mod:`.tracer`).
        progress: a progress bar's description (None: no bar).

    Returns:
        :class:`SHTable`.
    """
    t0 = time.perf_counter()
    layout = build_layout(mesh.vertices, mesh.faces, mesh.normals,
                          lattice_rate(mesh.num_faces, settings.samples))
    intersect, backend = intersector(mesh.vertices, mesh.faces, tracer)
    tri_v = mesh.vertices[mesh.faces]  # (F, 3, 3)
    tri_n = mesh.normals[mesh.faces]
    radius = float(mesh.face_sphere[1])
    m = projection_matrix(settings.rings, MAX_ORDER)  # (K, J)
    omega_local = view_directions(settings.rings)  # (J, 3)
    n_dir = omega_local.shape[0]
    s_total = layout.num_samples
    chunk = max(1, PATHS_PER_CHUNK // n_dir)
    coeffs = torch.empty((s_total, m.shape[0], len(CHANNELS)), dtype=torch.float16)
    rays = 0
    with tqdm(total=s_total, desc=progress or "sh", unit="sample", disable=progress is None,
              leave=False) as bar:
        for s0 in range(0, s_total, chunk):
            s1 = min(s_total, s0 + chunk)
            frame = layout.frame[s0:s1]  # (Sc, 3, 3) rows t, b, n
            omega = torch.einsum("jk,skr->sjr", omega_local, frame).reshape(-1, 3)
            p = layout.position[s0:s1, None, :].expand(-1, n_dir, 3).reshape(-1, 3)
            n = frame[:, None, 2, :].expand(-1, n_dir, 3).reshape(-1, 3)
            ends = trace_paths(intersect, tri_v, tri_n, p, n, omega, settings.ior,
                               settings.max_events, EPS * radius, settings.branch)
            rays += int(ends.events.sum()) + p.shape[0]
            r = torch.cat([ends.direction, (ends.length / radius)[:, None],
                           ends.cos_exit[:, None], ends.throughput[:, None]], 1)
            r = r.view(s1 - s0, n_dir, len(CHANNELS))
            coeffs[s0:s1] = torch.einsum("kj,sjc->skc", m, r).to(torch.float16)  # eq. 10
            bar.update(s1 - s0)
    stats = {"seconds": time.perf_counter() - t0, "paths": s_total * n_dir, "rays": rays,
             "tracer": backend, "samples": s_total, "rate": layout.rate}
    return SHTable(layout=layout, coeffs=coeffs, radius=radius, settings=settings,
                   mesh_hash=mesh_hash, stats=stats)


__all__ = ["CHANNELS", "EPS", "PATHS_PER_CHUNK", "SHTable", "Settings", "precompute"]

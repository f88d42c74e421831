"""The offline step: sample the refracted path mapping R(p, omega) over the surface and the
outer hemisphere and compress it into real SH (Genevaux et al. 2006, secs. 3-4).

For every surface sample o_i (:mod:`.layout`) and every view direction omega_j of the
direction set (:func:`.basis.view_directions`, in o_i's tangent frame), one path is traced
through the mesh (:mod:`.paths`); the samples of o_i, r_j = (exit direction x, y, z in
object space, length inside / radius, exit cosine, throughput, rough-interface gain), are
compressed with one
matrix product W = M R (eq. 10, M from :func:`.basis.projection_matrix`) up to band 8.
The order actually used and the ringing window (sec. 4.3) are applied when shading: the
projection's coefficients of bands <= L do not depend on the bands kept above L, so one
table serves every order and window.

The coefficients are stored as float16 (the paper found 8 bits per weight enough, fig. 5).
With ``branches: 2`` the reflected branch of each path (:attr:`.paths.PathEnds.branch`)
adds 7 channels (:data:`BRANCH_CHANNELS`) after these.
"""

from __future__ import annotations

import functools
import os
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import torch
from tqdm.auto import tqdm

from torchrefract.geometry.mesh import MeshData
from torchrefract.methods.sh.basis import MAX_ORDER, projection_matrix, view_directions
from torchrefract.methods.sh.layout import Layout, build_layout, lattice_rate
from torchrefract.methods.sh import native as sh_native
from torchrefract.methods.sh.paths import geometric_normals, trace_paths
from torchrefract.methods.sh.tracer import EmbreeNative, intersector

CHANNELS = ("dir_x", "dir_y", "dir_z", "length", "cos_exit", "throughput", "rough_gain")
"""What each coefficient vector holds (length: inside the object over the mesh's radius;
rough_gain: :attr:`.paths.PathEnds.gain`)."""

BRANCH_CHANNELS = ("b_dir_x", "b_dir_y", "b_dir_z", "b_length", "b_cos_exit", "b_energy",
                   "b_rough_gain")
"""With ``branches: 2``, the reflected branch's (:attr:`.paths.PathEnds.branch`), after
:data:`CHANNELS`: the same quantities, its throughput being the energy it carries (F at
the split times the rest; 0 where the path never split)."""


def channels(settings: "Settings") -> tuple[str, ...]:
    """The channels a table at ``settings`` stores."""
    return CHANNELS + (BRANCH_CHANNELS if settings.branches == 2 else ())

PATHS_PER_CHUNK = 1 << 19
"""Paths traced per batch (bounds the memory: ~0.2 GB of temporaries)."""

MAX_WORKERS = 8
"""Most chunks traced at once (:func:`precompute_workers`)."""

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
    branches: int = 1


@dataclass(frozen=True)
class SHTable:
    """The compressed refracted-path mapping of one mesh and IOR.

    Attributes:
        layout: the surface samples (object space).
        coeffs: (S, K, C) float16, K = 45 even coefficients up to band 8, C = ``CHANNELS``
            (and ``BRANCH_CHANNELS`` after them with ``branches: 2``: :func:`channels`).
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

    @functools.cached_property
    def padded(self) -> torch.Tensor:
        """(S, 45, 8) float32 coefficients, channels zero-padded: the native kernel's
        layout (:func:`.native.padded_coeffs`), made once per table."""
        from torchrefract.methods.sh.native import padded_coeffs  # noqa: PLC0415

        return padded_coeffs(self.coeffs[:, :, :len(CHANNELS)])

    @functools.cached_property
    def padded_branch(self) -> torch.Tensor:
        """:attr:`padded` of the reflected branch's channels (``branches: 2``; the
        kernel's second table)."""
        from torchrefract.methods.sh.native import padded_coeffs  # noqa: PLC0415

        c = len(CHANNELS)
        return padded_coeffs(self.coeffs[:, :, c:2 * c])

    @property
    def nbytes(self) -> int:
        """Memory of the table (coefficients, lattice, sample frames)."""
        lay = self.layout
        return sum(t.numel() * t.element_size() for t in
                   (self.coeffs, lay.lattice, lay.position, lay.frame))


def precompute_workers() -> int:
    """Chunks traced at once: the cores this process may use over torch's intra-op
    threads (at 1 torch thread on 2 cores: 2). Embree (embreex) and torch's ops release
    the GIL, so threads of this process run them side by side."""
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        cores = os.cpu_count() or 1
    return max(1, min(MAX_WORKERS, cores // max(1, torch.get_num_threads())))


def _native_tracer(mesh: MeshData, backend: str, tracer: str) -> EmbreeNative | None:
    """The mesh as a scene for the native path tracer (``csrc/sh_paths.c``), where the
    backend is Embree and the native library runs; else None (the tensor path code)."""
    if backend != "embree" or tracer == "torch" or not sh_native.available():
        return None
    try:
        return EmbreeNative(mesh.vertices.numpy(), mesh.faces.numpy())
    except (ImportError, OSError, AttributeError):
        return None


def _trace_chunk(layout: Layout, s0: int, s1: int, intersect, tri_v: torch.Tensor,
                 tri_n: torch.Tensor, radius: float, m: torch.Tensor,
                 omega_local: torch.Tensor, settings: Settings,
                 embree: EmbreeNative | None = None, g_n: torch.Tensor | None = None
                 ) -> tuple[torch.Tensor, int]:
    """(s1 - s0, K, C) float16 weights of samples s0..s1 (eq. 10) and the rays cast; the
    paths in C where ``embree`` (and ``g_n``, :func:`.paths.geometric_normals`) is given,
    else in torch (the same values)."""
    n_dir = omega_local.shape[0]
    frame = layout.frame[s0:s1]  # (Sc, 3, 3) rows t, b, n
    omega = torch.einsum("jk,skr->sjr", omega_local, frame).reshape(-1, 3)
    p = layout.position[s0:s1, None, :].expand(-1, n_dir, 3).reshape(-1, 3)
    n = frame[:, None, 2, :].expand(-1, n_dir, 3).reshape(-1, 3)
    ends = None
    if embree is not None:
        ends = sh_native.trace_paths(embree, tri_n, g_n, p, n, omega, settings.ior,
                                     settings.max_events, EPS * radius, settings.branch,
                                     branches=settings.branches)
    if ends is None:
        ends = trace_paths(intersect, tri_v, tri_n, p, n, omega, settings.ior,
                           settings.max_events, EPS * radius, settings.branch,
                           settings.branches)
    ws = []
    for e in [ends] if ends.branch is None else [ends, ends.branch]:
        r = torch.cat([e.direction, (e.length / radius)[:, None], e.cos_exit[:, None],
                       e.throughput[:, None], e.gain[:, None]], 1)
        r = r.view(s1 - s0, n_dir, len(CHANNELS))
        ws.append(torch.einsum("kj,sjc->skc", m, r).to(torch.float16))  # eq. 10
    # (the main path's channels as a branches: 1 table's, bit for bit)
    w = ws[0] if len(ws) == 1 else torch.cat(ws, 2)
    rays = int(ends.events.sum()) + p.shape[0]
    if ends.branch is not None:  # a branch's rays: its interfaces and its last cast
        rays += int(ends.branch.events.sum()) + int((ends.branch.throughput > 0).sum())
    return w, rays


def precompute(mesh: MeshData, settings: Settings, mesh_hash: str, tracer: str = "auto",
               progress: str | None = None, workers: int | None = None) -> SHTable:
    """Trace and compress the mapping of ``mesh`` (object space) at ``settings``.

    Args:
        mesh: the object-space mesh (``load_mesh(path)`` without transform).
        settings: IOR, direction rings, target sample count, interface limit.
        mesh_hash: recorded in the table.
        tracer: ``auto``, ``embree`` or ``mitsuba`` (:mod:`.tracer`); with Embree the
            paths run in C (``csrc/sh_paths.c``) where the native library builds, else in
            torch (``torch``: Embree from torch's path code, the reference; same table).
        progress: a progress bar's description (None: no bar).
        workers: chunks of samples traced at once by threads of this process (None:
            :func:`precompute_workers`; Mitsuba: 1, its own kernels are threaded). The
            table does not depend on it.

    Returns:
        :class:`SHTable`.
    """
    t0 = time.perf_counter()
    layout = build_layout(mesh.vertices, mesh.faces, mesh.normals,
                          lattice_rate(mesh.num_faces, settings.samples))
    intersect, backend = intersector(mesh.vertices, mesh.faces,
                                     "embree" if tracer == "torch" else tracer)
    tri_v = mesh.vertices[mesh.faces]  # (F, 3, 3)
    tri_n = mesh.normals[mesh.faces]
    embree = _native_tracer(mesh, backend, tracer)
    g_n = geometric_normals(tri_v) if embree is not None else None
    radius = float(mesh.face_sphere[1])
    m = projection_matrix(settings.rings, MAX_ORDER)  # (K, J)
    omega_local = view_directions(settings.rings)  # (J, 3)
    n_dir = omega_local.shape[0]
    s_total = layout.num_samples
    chunk = max(1, PATHS_PER_CHUNK // n_dir)
    starts = list(range(0, s_total, chunk))
    workers = precompute_workers() if workers is None else max(1, int(workers))
    workers = 1 if backend != "embree" else min(workers, len(starts))
    coeffs = torch.empty((s_total, m.shape[0], len(channels(settings))), dtype=torch.float16)
    rays = 0

    def run(s0: int) -> tuple[int, torch.Tensor, int]:
        s1 = min(s_total, s0 + chunk)
        return (s0, *_trace_chunk(layout, s0, s1, intersect, tri_v, tri_n, radius, m,
                                  omega_local, settings, embree, g_n))

    with tqdm(total=s_total, desc=progress or "sh", unit="sample", disable=progress is None,
              leave=False) as bar:
        if workers == 1:
            results = map(run, starts)
            pool = None
        else:
            pool = ThreadPoolExecutor(workers, thread_name_prefix="sh-precompute")
            results = pool.map(run, starts)
        try:
            for s0, w, cast in results:
                coeffs[s0:s0 + w.shape[0]] = w
                rays += cast
                bar.update(w.shape[0])
        finally:
            if pool is not None:
                pool.shutdown(cancel_futures=True)
    stats = {"seconds": time.perf_counter() - t0, "paths": s_total * n_dir, "rays": rays,
             "tracer": backend, "paths_in": "c" if embree is not None else "torch",
             "samples": s_total, "rate": layout.rate, "workers": workers,
             "torch_threads": torch.get_num_threads()}
    return SHTable(layout=layout, coeffs=coeffs, radius=radius, settings=settings,
                   mesh_hash=mesh_hash, stats=stats)


__all__ = ["BRANCH_CHANNELS", "CHANNELS", "EPS", "MAX_WORKERS", "PATHS_PER_CHUNK", "SHTable",
           "Settings", "channels", "precompute", "precompute_workers"]

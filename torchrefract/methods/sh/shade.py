"""Shading with the precomputed mapping (Genevaux et al. 2006, secs. 3 and 5; rough lobes
ours).

Per object pixel (all pixels of a batch, compacted):

1. Front interface: the SG fits of the Walter BRDF and BTDF (de Rousiers' eqs. 8-9,
   :func:`torchrefract.methods.rousiers.lobes.front_lobes`) give the reflected lobe
   (E_r, k_r, axis) and the transmitted one's energy E_t1 and sharpness k_t1.
2. The refraction map (eq. 2): the front hit's face and barycentrics pick the three
   surface samples around it (:func:`.layout.interpolation`); the view direction, turned
   into object space (the scene's rotation; sec. 5.4's remapping) and into each sample's
   tangent frame, evaluates each sample's SH (eqs. 3-7, order ``order``, window of sec.
   4.3); the three values are blended with the barycentric weights S_oi. Out come the exit
   direction, the length inside, the exit cosine and the path's throughput.
3. The lobe leaving (ours, so that ``sh`` renders rough glass): the front lobe's spread,
   var1 = 1 / k_t1 inside, is a spread of equivalent smooth view directions (Snell's
   derivative), which the mapping carries to the exit: the mapping is read again at four
   view directions one standard deviation away, and the mean squared change of the exit
   direction is the lobe's geometric variance (as ``rousiers``' bounding rays, measured on
   the precomputed paths instead of the depth buffer). The exit interface's own roughness
   adds the table's transmitted lobe at the stored exit cosine, and the rough interfaces
   met inside (ours: the stored gain G, :attr:`.paths.PathEnds.gain`) their spread
   alpha^2 / 2 G: k = 1 / (1/k_t2 + var_geo + alpha^2 / 2 G).
4. L = E_r L_env(axis_r, k_r) + E_t1 W2 exp(-sigma d) L_env(exit, k), the environment
   read from the SG-pre-convolved pyramid, sphere lights included; W2 per ``exit_weight``.
5. ``branches: 2``: the reflected branch's channels (the table's second half) are read
   the same way (steps 2-3, its own spread, exit cosine and length) and its lobe added
   with E_t1 W2' E_b, E_b its stored energy, the main path's W2 times (1 - E_b)
   (``conserve``: W2 and W2' the exit's conserving weights, so a smooth white furnace
   stays at 1; ``path``: W2 the main path's throughput, W2' = 1).

An index-matched object (IOR 1) has no interface: it is invisible (no table needed).

Steps 1-5 run as one fused kernel where it can (csrc/sh_shade.c, :func:`_render_fused`: the
fused methods' frame, and the adaptive lattice's levels in their driver); this tensor code
is the reference, the differentiable path and the rest (more than 64 lights).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from types import SimpleNamespace

import numpy as np
import torch

from torchrefract.geometry.gbuffer import GBuffer
from torchrefract.geometry.mesh import MeshData, rotation_matrix
from torchrefract.kept import KeptByIdentity
from torchrefract.kernels import native
from torchrefract.kernels.index import put_, take, where_in, where_true
from torchrefract.lighting.lights import Lighting, incident_radiance_sg
from torchrefract.methods.rousiers.lobes import front_lobes, sg_lobe, spread_energies
from torchrefract.methods.rousiers.pixels import Pixels, object_pixels
from torchrefract.methods.rousiers.shade import composite
from torchrefract.methods.sh import native as sh_native
from torchrefract.methods.sh.basis import num_even, real_sh_even, window
from torchrefract.methods.sh.layout import interpolation
from torchrefract.methods.sh.options import SHOptions
from torchrefract.methods.sh.precompute import CHANNELS, SHTable
from torchrefract.optics.exit_rule import CRITICAL_MARGIN, critical_cosine, leaving_weight
from torchrefract.optics.materials import MaterialBatch
from torchrefract.optics.sgfit import load_sg_table
from torchrefract.optics.smooth import normalize, tangent_frame
from torchrefract.shading import fused
from torchrefract.shading.background import background
from torchrefract.shading.bounces import escape_fraction

PASSES = ("lobe_sigma", "path_length")

CHUNK = 8192
"""Pixels evaluated at once (bounds the gathered weights: 8192 x 3 x 45 x 6 floats)."""

MAX_SPREAD = 0.35
"""Largest angular offset (radians, ~20 degrees) at which the mapping is re-read for the
lobe's spread; wider lobes are extrapolated linearly from it."""

ROUGH = 1e-3
"""Front roughness from which the lobe's spread is measured (below: a sharp ray)."""


@dataclass(frozen=True)
class SceneTable:
    """What one batch item shades with.

    Attributes:
        table: the precomputed mapping, or None (IOR 1: nothing to map).
        mesh: the object-space mesh the table was made for.
        rotation: (3, 3) float32 object-to-world rotation; scale, translate: the rest of
            the scene's transform.
    """

    table: SHTable | None
    mesh: MeshData
    rotation: torch.Tensor
    scale: float
    translate: torch.Tensor

    @functools.cached_property
    def pose(self) -> tuple:
        """The transform (scale, rotation, translation) as one hashable key, made once
        (:func:`check_mesh` asks for it per view and pass)."""
        return (self.scale, tuple(self.rotation.flatten().tolist()),
                tuple(self.translate.tolist()))


def scene_table(table: SHTable | None, mesh: MeshData, transform) -> SceneTable:
    """A :class:`SceneTable` for a scene's ``transform`` (SCENE_SPEC: scale, rotate,
    translate)."""
    r = torch.from_numpy(rotation_matrix(transform.rotate_deg).astype(np.float32))
    return SceneTable(table=table, mesh=mesh, rotation=r, scale=float(transform.scale),
                      translate=torch.tensor(transform.translate, dtype=torch.float32))


_MATCHED = KeptByIdentity(64)
"""check_mesh's verdicts: per batch face table (the mesh cache's tensor of a posed mesh,
the same object render after render) and (face offset, face count, pose), the object-space
mesh found there."""


def check_mesh(g: GBuffer, b: int, item: SceneTable) -> None:
    """Static by design: the G-buffer's mesh of batch item ``b`` must be the precomputed
    mesh under the scene's transform (compared once per face table, offset and pose:
    the faces of a posed mesh are read only, so a verdict holds while they live).

    Raises:
        ValueError: another mesh (face count or positions differ), naming both.
    """
    mesh = item.mesh
    nf = int(g.meshes.num_faces[b])
    if nf != mesh.num_faces:
        raise ValueError(f"method 'sh': batch item {b} shows a mesh of {nf} faces, but its "
                         f"precomputed table is for {mesh.num_faces}; re-run prepare() on "
                         "the scenes rendered (a deformed or other mesh needs its own table)")
    off = int(g.meshes.face_offset[b])
    key = (off, nf, item.pose)
    if _MATCHED.get(g.meshes.tri_vertices, key) is mesh:
        return
    world = g.meshes.tri_vertices[off:off + nf]  # (F, 3, 3)
    expect = (mesh.vertices[mesh.faces] * item.scale) @ item.rotation.T + item.translate
    err = float((world - expect).abs().max())
    tol = 1e-4 * max(1.0, float(expect.abs().max()))
    if not err <= tol:
        raise ValueError(f"method 'sh': batch item {b}'s mesh differs from its precomputed "
                         f"table's by up to {err:.3g} (tolerance {tol:.3g}); re-run prepare() "
                         "on the scenes rendered (a deformed mesh needs its own table)")
    _MATCHED.put(g.meshes.tri_vertices, key, mesh)


def evaluate(table: SHTable, faces: torch.Tensor, bary: torch.Tensor, omega: torch.Tensor,
             order: int, weights: torch.Tensor, channels: int | None = None, first: int = 0
             ) -> torch.Tensor:
    """Eq. 2: the mapping at surface points for view directions.

    Args:
        table: the precomputed mapping.
        faces: (N,) mesh-local faces; bary: (N, 3) barycentrics of the points.
        omega: (N, E, 3) unit view directions (towards the viewer, object space), E per point.
        order: highest band; weights: (K,) window of the even coefficients up to it.
        channels: the first ``channels`` of :data:`.precompute.CHANNELS` (None: all).
        first: 0, or ``len(CHANNELS)``: the reflected branch's channels
            (:data:`.precompute.BRANCH_CHANNELS`, ``branches: 2``).

    Returns:
        (N, E, channels) the interpolated channels.
    """
    samples, s_w = interpolation(table.layout.lattice, table.layout.rate, faces, bary)  # (N, 3)
    return evaluate_samples(table, samples, s_w, omega, order, weights, channels, first=first)


def _padded(table: SHTable, first: int) -> torch.Tensor:
    """The native kernel's table of the main path (``first`` 0) or of the branch."""
    return table.padded if first == 0 else table.padded_branch


def evaluate_samples(table: SHTable, samples: torch.Tensor, s_w: torch.Tensor,
                     omega: torch.Tensor, order: int, weights: torch.Tensor,
                     channels: int | None = None, rest_channels: int | None = None,
                     first: int = 0) -> torch.Tensor:
    """:func:`evaluate` from the points' three samples (N, 3) and their weights S_oi (N, 3)
    (:func:`.layout.interpolation`): the native kernel (:mod:`.native`) where it runs and
    no gradient is wanted through ``omega``, else the tensor code in chunks of
    :data:`CHUNK` points (the same values to float32 rounding).

    ``rest_channels``: only the first ``rest_channels`` are evaluated for the directions
    after the first (``omega[:, 1:]``), the others are 0 (None: all ``channels``).
    ``first``: as :func:`evaluate`.
    """
    c = len(CHANNELS) if channels is None else channels
    cr = c if rest_channels is None else min(rest_channels, c)
    if first not in (0, len(CHANNELS)) or table.coeffs.shape[-1] < first + c:
        raise ValueError(f"sh table of {table.coeffs.shape[-1]} channels: no channels "
                         f"{first}..{first + c}")
    if sh_native.available() and native.no_grad_through(omega, s_w, weights):
        out = sh_native.evaluate(_padded(table, first), table.layout.frame, samples, s_w,
                                 omega, order, weights, c, cr)
        if out is not None:
            return out
    parts = []
    for c0 in range(0, omega.shape[0], CHUNK):
        sl = slice(c0, c0 + CHUNK)
        if cr == c or omega.shape[1] == 1:
            parts.append(_evaluate_tensor(table, samples[sl], s_w[sl], omega[sl], order,
                                          weights, c, first))
            continue
        head = _evaluate_tensor(table, samples[sl], s_w[sl], omega[sl, :1], order, weights, c,
                                first)
        rest = _evaluate_tensor(table, samples[sl], s_w[sl], omega[sl, 1:], order, weights, cr,
                                first)
        parts.append(torch.cat([head, torch.nn.functional.pad(rest, (0, c - cr))], 1))
    return torch.cat(parts, 0) if len(parts) != 1 else parts[0]


def _evaluate_tensor(table: SHTable, samples: torch.Tensor, s_w: torch.Tensor,
                     omega: torch.Tensor, order: int, weights: torch.Tensor, channels: int,
                     first: int = 0) -> torch.Tensor:
    """The tensor code of :func:`evaluate_samples` (differentiable in ``omega``)."""
    k = num_even(order)
    frames = table.layout.frame[samples]  # (N, 3, 3, 3): per sample, rows t, b, n
    local = torch.einsum("ner,nsar->nsea", omega, frames)  # (N, 3, E, 3)
    y = real_sh_even(local, order)  # (N, 3, E, K)
    w = table.coeffs.index_select(0, samples.reshape(-1))[:, :k, first:first + channels].float()
    w = w.view(*samples.shape, k, channels) * weights[None, None, :, None]  # (N, 3, K, c)
    vals = torch.einsum("nsek,nskc->nsec", y, w)  # (N, 3, E, c)
    return (s_w[:, :, None, None] * vals).sum(1)


def _snell_spread(px: Pixels, var1: torch.Tensor) -> torch.Tensor:
    """Per-axis variance of the smooth view directions whose refracted rays spread like the
    front lobe (variance ``var1`` inside): in the plane of incidence d theta_o / d theta_t =
    eta cos_t / cos_o, across it eta; averaged over the two axes."""
    eta = px.ior
    cos_o = px.cos1.clamp(min=0.05)
    sin2_t = (1.0 - cos_o * cos_o) / (eta * eta)
    cos_t = torch.sqrt((1.0 - sin2_t).clamp(min=0.0))
    m1 = eta * cos_t / cos_o
    return var1 * 0.5 * (m1 * m1 + eta * eta)


def _map_values(table: SHTable, faces: torch.Tensor, bary: torch.Tensor, omega: torch.Tensor,
                r: torch.Tensor | None, order: int, weights: torch.Tensor, first: int = 0
                ) -> torch.Tensor:
    """(n, E, C) the mapping at the front hits (``faces``, ``bary``) for the view ``omega``
    (n, 3) (object space) and, with ``r`` (n,), the four views at angle r around it (E = 5;
    only the exit direction, 3 channels, at those): the native kernel where it runs and no
    gradient is wanted (samples and directions made there), else the tensor code.
    ``first``: as :func:`evaluate`."""
    if sh_native.available() and native.no_grad_through(omega, weights, *(
            () if r is None else (r,))):
        out = sh_native.evaluate_points(_padded(table, first), table.layout.frame,
                                        table.layout.lattice, table.layout.rate, faces, bary,
                                        omega, r, order, weights, len(CHANNELS), 3)
        if out is not None:
            return out
    samples, s_w = interpolation(table.layout.lattice, table.layout.rate, faces, bary)
    dirs = [omega]
    if r is not None:
        u, v = tangent_frame(omega)
        dirs += [normalize(omega + r[:, None] * t) for t in (u, -u, v, -v)]
    # all channels at the view itself, the exit direction (3) at the offsets
    return evaluate_samples(table, samples, s_w, torch.stack(dirs, 1), order, weights, None, 3,
                            first)


def _map_pixels(g: GBuffer, px: Pixels, bi: int, sel: torch.Tensor, item: SceneTable,
                options: SHOptions, var_view: torch.Tensor, rough: bool, first: int = 0):
    """Exit direction (world), length (world), exit cosine, throughput and the geometric
    variance of the pixels ``sel`` (positions in ``px``) of one batch item; of the main
    path, or of the reflected branch (``first``: as :func:`evaluate`)."""
    table = item.table
    weights = window(options.order, options.window, options.window_width)
    b_idx = take(px.idx, sel)
    off = int(g.meshes.face_offset[bi])
    faces = take(g.front.tri.reshape(-1), b_idx).long() - off  # the layer's are int32
    bary = take(g.front.bary.reshape(-1, 3), b_idx)
    omega = take(px.view, sel) @ item.rotation  # world -> object: R^T w
    r = var_v = None
    if rough:
        var_v = take(var_view, sel)
        r = torch.sqrt(var_v).clamp(max=MAX_SPREAD)
    vals = _map_values(table, faces, bary, omega, r, options.order, weights, first)
    exit_obj = vals[:, 0, :3]
    center = normalize(exit_obj)
    var_geo = torch.zeros_like(center[:, 0])
    if rough:
        r2 = (r ** 2).clamp(min=1e-12)
        diff = normalize(vals[:, 1:, :3]) - center[:, None, :]  # (n, 4, 3): chords ~ angles
        var_geo = (diff * diff).sum(-1).mean(1) * (var_v / r2)
        # the rough interfaces met between the entry and the exit (PathEnds.gain): Beckmann
        # slopes' variance per axis alpha^2 / 2 times the path's gain
        a = take(px.alpha, sel)
        var_geo = var_geo + (0.5 * a * a) * vals[:, 0, 6].clamp(min=0.0)
    weak = exit_obj.norm(dim=-1) < 1e-3  # ringing cancelled the vector: go straight
    center = torch.where(weak[:, None], -omega, center)
    direction = center @ item.rotation.T  # object -> world
    length = (vals[:, 0, 3] * table.radius * item.scale).clamp(min=0.0)
    return (direction, length, vals[:, 0, 4].clamp(0.0, 1.0), vals[:, 0, 5].clamp(0.0, 1.0),
            var_geo)


def _map_items(g: GBuffer, px: Pixels, bis: list[int], items: tuple[SceneTable, ...],
               options: SHOptions, var_view: torch.Tensor, rough: torch.Tensor,
               outs: tuple[torch.Tensor, ...], first: int = 0) -> None:
    """:func:`_map_pixels` for the batch items ``bis`` (one table), written into ``outs``
    (direction, length, exit cosine, throughput, variance; per object pixel): in one
    native call where it runs and no gradient is wanted, else item by item."""
    table = items[bis[0]].table
    weights = window(options.order, options.window, options.window_width)
    if sh_native.available() and native.no_grad_through(px.view, var_view, px.alpha, weights):
        sel = where_in(px.bi, bis, g.shape[0])
        eye = torch.eye(3)
        per_item = {
            "face_offset": g.meshes.face_offset, "rough": rough,
            "rotation": torch.stack([it.rotation if it.table is not None else eye
                                     for it in items]),
            "scale": torch.tensor([it.scale for it in items], dtype=torch.float32)}
        pixels = {"pix": px.idx, "item": px.bi, "tri": g.front.tri.reshape(-1),
                  "bary": g.front.bary.reshape(-1, 3), "view": px.view,
                  "var_view": var_view, "alpha": px.alpha}
        out = dict(zip(("direction", "length", "cos_exit", "throughput", "var_geo"), outs))
        if sh_native.map_pixels(_padded(table, first), table.layout.frame,
                                table.layout.lattice, table.layout.rate, options.order,
                                weights, table.radius, MAX_SPREAD, sel, pixels, per_item,
                                out):
            return
    for bi in bis:
        sel = where_true(px.bi == bi)
        vals = _map_pixels(g, px, bi, sel, items[bi], options, var_view, bool(rough[bi]),
                           first)
        for dst, v in zip(outs, vals):
            put_(dst, sel, v)


def _tables_of(g: GBuffer, px: Pixels, items: tuple[SceneTable, ...],
               materials: MaterialBatch, two: bool, matched: torch.Tensor,
               length: torch.Tensor, length_fallback: torch.Tensor) -> list[list[int]]:
    """The batch items with object pixels grouped by their table (checked:
    :func:`_check_item`); an item without a table (IOR 1) has its pixels marked
    ``matched`` and their ``length`` the layers' gap instead."""
    mapped: dict[int, list[int]] = {}
    counts = torch.bincount(px.bi, minlength=len(items)).tolist()
    for bi, item in enumerate(items):
        if counts[bi] == 0:
            continue
        if item.table is None:  # IOR 1: no interface
            sel = where_true(px.bi == bi)
            put_(matched, sel, torch.ones(sel.numel(), dtype=torch.bool))
            put_(length, sel, take(length_fallback, sel))
            continue
        _check_item(g, bi, item, materials, two)
        mapped.setdefault(id(item.table), []).append(bi)
    return list(mapped.values())


def _check_item(g: GBuffer, bi: int, item: SceneTable, materials: MaterialBatch,
                two: bool) -> None:
    """Batch item ``bi``'s table is for its mesh (:func:`check_mesh`), its IOR and, with
    ``two`` (``branches: 2``), has the branch channels.

    Raises:
        ValueError: naming what differs.
    """
    check_mesh(g, bi, item)
    if float(materials.ior[bi]) != item.table.settings.ior:
        raise ValueError(f"method 'sh': batch item {bi} has IOR "
                         f"{float(materials.ior[bi])}, its table "
                         f"{item.table.settings.ior}; re-run prepare()")
    if two and item.table.coeffs.shape[-1] < 2 * len(CHANNELS):
        raise ValueError(f"method 'sh': batch item {bi}'s table has no branch "
                         "channels (branches: 1); re-run prepare()")


_FRAME_OPTIONS = SimpleNamespace(tir="conserve", bounces=SimpleNamespace(enabled=False))
"""What ``shading.fused._frame`` reads of a method's options, for ``sh``'s frame: the escape
fraction's grid (read under ``exit_weight: conserve``), no internal bounces."""


def _render_fused(g: GBuffer, lighting: Lighting, materials: MaterialBatch,
                  options: SHOptions, items: tuple[SceneTable, ...], radiance: torch.Tensor
                  ) -> tuple[torch.Tensor, dict[str, torch.Tensor]] | None:
    """:func:`render_sh` by csrc/sh_shade.c over ``radiance`` (B*H*W, 3, the background;
    written in place), the adaptive lattice's levels too where ``g`` carries them; None
    where it does not run (the fused kernels off, a gradient wanted, more than 64 lights,
    no shown item with a table): the tensor code then runs."""
    if lighting.light_pos.shape[1] > 64 or not sh_native.available():
        return None
    b, h, w = g.shape
    counts = torch.bincount(g.object_views(), minlength=b).tolist()
    shown = [bi for bi in range(b) if counts[bi]]
    if shown and all(items[bi].table is None for bi in shown):
        return None  # (nothing to map: the tensor code's few ops)
    made = fused._frame(g, lighting, materials, _FRAME_OPTIONS, radiance, sg_env=True,
                        march=False)
    if made is None:
        return None
    frame, keep, radiance, _ = made
    passes = {k: torch.zeros(b * h * w) for k in PASSES}
    views = {k: v.view(b, h, w, 1) for k, v in passes.items()}
    if not shown:
        return radiance.view(b, h, w, 3), views
    two = options.branches == 2
    tables: dict[int, SHTable] = {}  # the shown items' tables, in order
    for bi in shown:
        if items[bi].table is not None:
            _check_item(g, bi, items[bi], materials, two)
            tables.setdefault(id(items[bi].table), items[bi].table)
    index = {key: i for i, key in enumerate(tables)}
    eye = torch.eye(3)
    per_item = {"face_offset": g.meshes.face_offset,
                "rotation": torch.stack([it.rotation if it.table is not None else eye
                                         for it in items]),
                "scale": torch.tensor([it.scale for it in items], dtype=torch.float32)}
    specs = [{"padded": _padded(t, 0), "branch": _padded(t, len(CHANNELS)) if two else None,
              "frame": t.layout.frame, "lattice": t.layout.lattice, "rate": t.layout.rate,
              "radius": t.radius} for t in tables.values()]
    job = sh_native.shade_job(
        frame, specs, torch.tensor([index.get(id(it.table), -1) for it in items]),
        options.order, window(options.order, options.window, options.window_width),
        MAX_SPREAD, per_item, {"tri": g.front.tri.reshape(-1), "bary": g.front.bary.reshape(-1, 3)},
        two, options.exit_weight == "conserve", passes, keep)
    if job is None or not fused._run("sh_shade", job, g, radiance, views,
                                     lib=sh_native.library()):
        return None
    return radiance.view(b, h, w, 3), views


def _incident(lighting: Lighting, bi: torch.Tensor, origin: torch.Tensor,
              direction: torch.Tensor, sharpness: torch.Tensor) -> torch.Tensor:
    """``incident_radiance_sg``: in one fused kernel call where it runs (the fused methods'
    own lookups, ``fused.incident_sg``), else the tensor code (gradients, a matte
    recording)."""
    out = fused.incident_sg(lighting, bi, origin, direction, sharpness)
    return incident_radiance_sg(lighting, bi, origin, direction, sharpness) if out is None \
        else out


def _exit_lobe(table, px, options: SHOptions, var1: torch.Tensor, esc: torch.Tensor | None,
               cos_out: torch.Tensor, var_g: torch.Tensor, thr_path: torch.Tensor
               ) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`render_sh`'s exit interface (leaving: eta = 1 / ior): its lobe sharpness at
    the exit cosine ``cos_out`` (held just outside TIR, where interpolation may dip below
    the critical angle), widened by the path's ``var_g``, and the leaving weight
    (``exit_weight``: the path's ``thr_path``, or ``conserve``'s with the escape fraction
    ``esc``)."""
    eta2 = 1.0 / px.ior
    cos_in = torch.maximum(cos_out, critical_cosine(px.ior) + CRITICAL_MARGIN).clamp(max=1.0)
    conserve = options.exit_weight == "conserve"
    made = fused.exit_lobes(cos_in, eta2, px.alpha, px.dist, var1 if conserve else None)
    if made is None:  # the tensor code: gradients, the fused kernels off
        k_t2 = sg_lobe(table, cos_in, eta2, px.alpha, px.dist, "transmit")[1]
        e_t2, e_r2 = spread_energies(table, cos_in, var1, eta2, px.alpha, px.dist) \
            if conserve else (None, None)
    else:
        k_t2, e_t2, e_r2 = made
    k_out = 1.0 / (1.0 / k_t2 + var_g).clamp(min=1e-12)
    if not conserve:
        return k_out, thr_path
    no_tir = torch.zeros_like(cos_out, dtype=torch.bool)
    return k_out, leaving_weight("conserve", no_tir, e_t2, e_r2, esc)


def _object_light(lighting: Lighting, materials: MaterialBatch, px, front,
                  matched: torch.Tensor, path: tuple, branch: tuple | None) -> torch.Tensor:
    """(N, 3) light of the object pixels ``px``: the front reflection and the transmitted
    lobe of ``path`` (exit direction, length inside, sharpness, weight), absorbed over its
    length (sec. 5.4), and ``branch``'s alike where given; an index-matched pixel
    (``matched``) reflects nothing and lets all the light through. Finite, >= 0."""
    direction, length, k, weight = path
    e_r = torch.where(matched, torch.zeros_like(front.e_r), front.e_r)
    e_t1 = torch.where(matched, torch.ones_like(front.e_t1), front.e_t1)
    absorption = take(materials.absorption, px.bi)
    att = torch.exp(-absorption * length[:, None])  # (N, 3)
    l_refl = _incident(lighting, px.bi, px.p1, front.axis_r, front.k_r)
    l_trans = _incident(lighting, px.bi, px.p1, direction, k)
    l_obj = e_r[:, None] * l_refl + (e_t1 * weight)[:, None] * att * l_trans
    if branch is not None:
        direction_b, length_b, k_b, weight_b = branch
        att_b = torch.exp(-absorption * length_b[:, None])
        l_b = _incident(lighting, px.bi, px.p1, direction_b, k_b)
        l_obj = l_obj + (e_t1 * weight_b)[:, None] * att_b * l_b
    return torch.nan_to_num(l_obj, nan=0.0, posinf=0.0, neginf=0.0).clamp(min=0.0)


def render_sh(g: GBuffer, lighting: Lighting, materials: MaterialBatch, options: SHOptions,
              items: tuple[SceneTable, ...]) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """Shade a G-buffer with the precomputed refracted-path mapping (module docstring).

    Args:
        g: G-buffer of B views at (H, W) (sub-)pixels.
        lighting: environment maps (SG pyramids) and lights.
        materials: IOR, roughness, distribution and absorption per scene.
        options: method settings.
        items: per batch item, its table and transform (``SH.prepare``).

    Returns:
        radiance: (B, H, W, 3) float32, background included.
        passes: ``lobe_sigma`` (per-axis spread of the transmitted lobe, radians) and
            ``path_length`` (world length inside), (B, H, W, 1) on object pixels.

    Raises:
        ValueError: a batch item's mesh or IOR is not its table's (``check_mesh``).
    """
    b, h, w = g.shape
    if len(items) != b:
        raise ValueError(f"method 'sh': {len(items)} prepared tables for {b} views")
    radiance = background(g, lighting)
    done = _render_fused(g, lighting, materials, options, items, radiance)
    if done is not None:
        return done
    idx = g.object_index()
    values = {k: torch.zeros(b * h * w) for k in PASSES}
    if idx.numel() > 0:
        table = load_sg_table()
        px = object_pixels(g, materials)
        front = fused.front_lobes(px.view, px.n1, px.cos1, px.ior, px.alpha, px.dist)
        if front is None:  # the tensor code: gradients, the fused kernels off
            front = front_lobes(table, px.view, px.n1, px.cos1, px.ior, px.alpha, px.dist)
        var1 = 1.0 / front.k_t1.clamp(min=1e-12)
        var_view = _snell_spread(px, var1)
        n = idx.numel()
        direction, length = px.d.clone(), torch.zeros(n)
        cos_exit, thr, var_geo = torch.ones(n), torch.ones(n), torch.zeros(n)
        length_fallback = take((g.back.dist - g.front.dist).reshape(-1), idx).clamp(min=0.0)
        matched = torch.zeros(n, dtype=torch.bool)
        two = options.branches == 2
        if two:  # the reflected branch's (energy 0: none)
            direction_b, length_b = px.d.clone(), torch.zeros(n)
            cos_b, energy_b, var_geo_b = torch.ones(n), torch.zeros(n), torch.zeros(n)
        mapped = _tables_of(g, px, items, materials, two, matched, length, length_fallback)
        rough = torch.zeros(b).index_add_(0, px.bi, (px.alpha > ROUGH).float()) > 0
        outs = (direction, length, cos_exit, thr, var_geo)
        outs_b = (direction_b, length_b, cos_b, energy_b, var_geo_b) if two else None
        for bis in mapped:
            _map_items(g, px, bis, items, options, var_view, rough, outs)
            if two:
                _map_items(g, px, bis, items, options, var_view, rough, outs_b,
                           len(CHANNELS))
        esc = escape_fraction(table, materials.ior, px.dist_b, px.alpha, px.bi) \
            if options.exit_weight == "conserve" else None
        exit_args = (table, px, options, var1, esc)
        k, weight2 = _exit_lobe(*exit_args, cos_exit, var_geo, thr)
        branch = None
        if two:
            # the branch carries its energy; conserve: the main path's share less it
            energy_b = torch.where(matched, torch.zeros_like(energy_b), energy_b)
            k_b, weight_b = _exit_lobe(*exit_args, cos_b, var_geo_b, torch.ones_like(thr))
            branch = (direction_b, length_b, k_b, weight_b * energy_b)
            if options.exit_weight == "conserve":
                weight2 = weight2 * (1.0 - energy_b)
        # Index-matched: invisible (the straight ray, unblurred, all the light).
        weight2 = torch.where(matched, torch.ones_like(weight2), weight2)
        k = torch.where(matched, torch.full_like(k, float("inf")), k)
        l_obj = _object_light(lighting, materials, px, front, matched,
                              (direction, length, k, weight2), branch)
        composite(g, lighting, px, radiance, l_obj)
        put_(values["lobe_sigma"], idx,
             torch.nan_to_num(torch.rsqrt(k.clamp(min=1e-12)), nan=0.0, posinf=0.0))
        put_(values["path_length"], idx, torch.nan_to_num(length, nan=0.0, posinf=0.0))
    return radiance.view(b, h, w, 3), {k: v.view(b, h, w, 1) for k, v in values.items()}


__all__ = ["CHUNK", "PASSES", "SceneTable", "check_mesh", "evaluate", "evaluate_samples",
           "render_sh", "scene_table"]

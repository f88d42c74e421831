"""The refracted path of one view ray through the real mesh (sec. 3, eq. 1).

The camera ray d = -omega enters the object at the surface sample p (refracted with the
sample's shading normal; the front reflection is the shading's, not the path's). It is then
cast against the mesh (:mod:`.tracer`); at every interface it meets, the exact dielectric
Fresnel term F picks *the most significant branch* (sec. 3, after Hakura and Snyder 2001):
the reflected ray where F > 1/2 (total internal reflection included, F = 1), else the
refracted one; inside or outside follows from the side of the flat triangle hit, so a path
that leaves the object and enters it again (a torus seen edge-on, a bead in a shell) is
followed too. (``branch: tir``, ours: the reflected ray only under total internal
reflection; the greedy rule's switch at F = 1/2, e.g. at grazing views of a sphere, is a
jump in the mapping that rings over the whole hemisphere once compressed.) It ends when
it leaves the object and meets nothing more, or after ``max_events`` interfaces (then it
leaves there, refracted: at the critical angle under TIR, the usual clamp). Intersections
use the flat triangles, refraction the interpolated shading normals (SCENE_SPEC.md).

Recorded per path: the final direction, the length travelled inside (sec. 5.4, for
absorption exp(-sigma d)), the cosine at the last exit (for the rough exit lobe), the
throughput of the branches taken after the entry (the product of F or 1 - F), and the
rough-interface gain G (ours): the summed variance of the path's direction per unit
microfacet slope variance at the interfaces between the entry and the last exit, whose
roughness the entry's and exit's lobes do not carry. Tilting the normal by delta turns a
refracted ray by (eta cos_i / cos_t - 1) delta in the plane of incidence and (eta - 1)
delta across it, a reflected one by 2 delta and 2 cos_i delta; G adds the mean of the two
squared factors per interface, so the shading's lobe widens by (alpha^2 / 2) G.

With ``branches=2`` (ours, the Fresnel share a single path loses inside a shell or at a
bead): at the first interface where the path refracts out from inside (not at the last
one allowed), the reflected ray is followed too, as a second path of the same wavefront
with the same rules and the same interface limit; its ends are recorded alike, its
throughput starting from the main path's there times F (:attr:`PathEnds.branch`).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from torchrefract.methods.sh.tracer import Intersector
from torchrefract.optics.smooth import dot, face_forward, fresnel_dielectric, normalize, \
    reflect, refract, snell_cos


GRAZING_COS = 0.05
"""The smallest cos_t in a refraction's gain (eta cos_i / cos_t grows without bound at
grazing exits; a lobe there is wide already)."""


def interface_gains(cos_i: torch.Tensor, eta: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """An interface's rough-interface gain (module docstring) if the path refracts there
    and if it reflects: ((eta cos_i / cos_t - 1)^2 + (eta - 1)^2) / 2, cos_t as ``refract``
    computes it (at least GRAZING_COS), and 2 (1 + cos_i^2). csrc/sh_paths.c's
    ``interface_gains`` does the same operations."""
    cos_t, _ = snell_cos(cos_i, eta)
    turn = eta * cos_i / cos_t.clamp(min=GRAZING_COS)
    e1 = eta - 1.0
    return 0.5 * ((turn - 1.0) * (turn - 1.0) + e1 * e1), 2.0 * (1.0 + cos_i * cos_i)


@dataclass(frozen=True)
class PathEnds:
    """What the precomputation stores per (sample, view direction); all (P,) or (P, 3).

    Attributes:
        direction: unit direction in which the path finally leaves (object space).
        length: length inside the object (object units).
        cos_exit: cosine between the path and the inward normal at its last exit (1 where
            it never met an exit).
        throughput: product of the Fresnel factors of the branches taken after the entry.
        events: interfaces met after the entry.
        gain: the rough-interface gain G at the last exit (module docstring; 0 where the
            path met no interface between the entry and its last exit).
        branch: with ``branches=2``, the reflected branch's ends (a :class:`PathEnds`
            without ``branch``): direction, length (from the entry), exit cosine,
            throughput = the energy it carries (the main path's throughput at the split
            times F times its own factors after it; 0 where the path never split, its
            other channels then the main path's), events = the interfaces the branch met
            after the split (0: no split); else None.
    """

    direction: torch.Tensor
    length: torch.Tensor
    cos_exit: torch.Tensor
    throughput: torch.Tensor
    events: torch.Tensor
    branch: "PathEnds | None" = None
    gain: torch.Tensor | None = None


def geometric_normals(tri_vertices: torch.Tensor) -> torch.Tensor:
    """(F, 3, 3) corners -> (F, 3) unit flat normals, outward by the winding."""
    g_n = torch.cross(tri_vertices[:, 1] - tri_vertices[:, 0],
                      tri_vertices[:, 2] - tri_vertices[:, 0], dim=-1)
    return normalize(g_n)


@dataclass
class _Rays:
    """:func:`trace_paths`' per-row state (rows ``count..`` hold the reflected branches
    with ``branches=2``, live once split off): where each ray is and what its path has
    gathered so far."""

    origin: torch.Tensor       # (R, 3)
    direction: torch.Tensor    # (R, 3) unit
    inside: torch.Tensor       # (R,) bool
    length: torch.Tensor       # (R,) inside so far
    cos_exit: torch.Tensor     # (R,) at the last exit so far
    throughput: torch.Tensor   # (R,)
    events: torch.Tensor       # (R,) int64
    gain: torch.Tensor         # (R,) G so far
    gain_exit: torch.Tensor    # (R,) G at the last exit so far

    @classmethod
    def entering(cls, rows: int, count: int, p: torch.Tensor, n: torch.Tensor,
                 omega: torch.Tensor, ior: float, eps: float) -> "_Rays":
        """The ``count`` view rays refracted in at their entry points (just inside)."""
        d0 = -omega
        t1, _ = refract(d0, face_forward(n, d0), 1.0 / ior)
        direction, origin = torch.zeros(rows, 3), torch.zeros(rows, 3)
        direction[:count] = t1
        origin[:count] = p - eps * n
        return cls(origin=origin, direction=direction, inside=torch.ones(rows, dtype=torch.bool),
                   length=torch.zeros(rows), cos_exit=torch.ones(rows),
                   throughput=torch.ones(rows), events=torch.zeros(rows, dtype=torch.int64),
                   gain=torch.zeros(rows), gain_exit=torch.zeros(rows))


def _interface(d: torch.Tensor, t: torch.Tensor, face: torch.Tensor, uv: torch.Tensor,
               g_n: torch.Tensor, tri_normals: torch.Tensor, ior: float
               ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """The interface rays ``d`` hit on ``face`` at ``uv``: whether they leave (the side of
    the flat triangle decides), its geometric and shading normals facing against ``d``
    (the shading one replaced by the geometric one where it lies behind) and the relative
    index ``eta``."""
    ng = g_n[face]  # (L, 3) outward by winding
    w = torch.cat([1.0 - uv.sum(1, keepdim=True), uv], 1)  # (L, 3)
    ns = normalize((w[:, :, None] * tri_normals[face]).sum(1))
    leaving = dot(d, ng) > 0
    ng_f = torch.where(leaving[:, None], -ng, ng)
    ns_f = torch.where((dot(ns, ng_f) < 0)[:, None], -ns, ns)
    ns_f = torch.where((dot(d, ns_f) >= 0)[:, None], ng_f, ns_f)
    eta = torch.where(leaving, torch.full_like(t, ior), torch.full_like(t, 1.0 / ior))
    return leaving, ng_f, ns_f, eta


def _split_off(r: _Rays, split: torch.Tensor, live: torch.Tensor, count: int,
               exits: torch.Tensor, x: torch.Tensor, ng_f: torch.Tensor, r_dir: torch.Tensor,
               f: torch.Tensor, g_r: torch.Tensor, ins: torch.Tensor, eps: float
               ) -> torch.Tensor:
    """``branches=2``: at the first refraction out of a main path, its reflected branch
    starts in row ``count`` further (before the main path moves on). Returns the live
    positions that split."""
    main = live < count
    fork = (exits & main & ~split[live.clamp(max=count - 1)]).nonzero(as_tuple=True)[0]
    src = live[fork]
    br = src + count
    split[src] = True
    r.origin[br] = x[fork] + (eps * -1.0) * -ng_f[fork]
    r.direction[br] = normalize(r_dir[fork])
    r.throughput[br] = r.throughput[src] * f[fork]
    r.gain[br] = r.gain[src] + g_r[fork]
    r.gain_exit[br] = r.gain_exit[src]
    r.length[br] = r.length[src]
    r.cos_exit[br] = r.cos_exit[src]
    r.inside[br] = ins[fork]
    return fork


def _ends(r: _Rays, count: int, split: torch.Tensor | None) -> PathEnds:
    """The main paths' ends (rows ``:count``), with their branches' where ``split`` is
    given (``branches=2``)."""
    m, fork_ends = slice(0, count), None
    if split is not None:
        b, s1 = slice(count, 2 * count), split[:, None]
        fork_ends = PathEnds(direction=torch.where(s1, r.direction[b], r.direction[m]),
                             length=torch.where(split, r.length[b], r.length[m]),
                             cos_exit=torch.where(split, r.cos_exit[b], r.cos_exit[m]),
                             throughput=torch.where(split, r.throughput[b], 0.0),
                             events=r.events[b],
                             gain=torch.where(split, r.gain_exit[b], r.gain_exit[m]))
    return PathEnds(direction=r.direction[m], length=r.length[m], cos_exit=r.cos_exit[m],
                    throughput=r.throughput[m], events=r.events[m], branch=fork_ends,
                    gain=r.gain_exit[m])


def trace_paths(intersect: Intersector, tri_vertices: torch.Tensor, tri_normals: torch.Tensor,
                p: torch.Tensor, n: torch.Tensor, omega: torch.Tensor, ior: float,
                max_events: int, eps: float, branch: str = "greedy", branches: int = 1
                ) -> PathEnds:
    """Follow the most significant Fresnel branch of P view rays (module docstring).

    Args:
        intersect: nearest-hit function of the mesh (:func:`.tracer.intersector`).
        tri_vertices: (F, 3, 3) corners; tri_normals: (F, 3, 3) unit shading normals.
        p: (P, 3) entry points; n: (P, 3) their outward shading normals.
        omega: (P, 3) unit directions towards the viewer (outer side: omega . n > 0).
        ior: index inside (outside 1).
        max_events: most interfaces followed after the entry.
        eps: origin offset off a surface (object units).
        branch: ``greedy`` (the paper: reflect where F > 1/2) or ``tir`` (reflect only
            under total internal reflection, F = 1).
        branches: 1, or 2: also the reflected branch at the first refraction out from
            inside (module docstring).

    Returns:
        :class:`PathEnds`.
    """
    count = p.shape[0]
    r = _Rays.entering(count * (2 if branches == 2 else 1), count, p, n, omega, ior, eps)
    split = torch.zeros(count, dtype=torch.bool)  # the main path has split off its branch
    live = torch.arange(count)
    g_n = geometric_normals(tri_vertices)
    for k in range(max_events + 1):
        if live.numel() == 0:
            break
        o, d = r.origin[live], r.direction[live]
        t, face, uv = intersect(o, d)
        # Misses end: outside, the path has left for good; inside, the mesh leaks (an open
        # mesh): it leaves as it goes.
        keep = (face >= 0).nonzero(as_tuple=True)[0]
        live, o, d, t, face, uv = live[keep], o[keep], d[keep], t[keep], face[keep], uv[keep]
        if live.numel() == 0:
            break
        ins = r.inside[live]
        r.length[live] += torch.where(ins, t, torch.zeros_like(t))
        x = o + t[:, None] * d
        leaving, ng_f, ns_f, eta = _interface(d, t, face, uv, g_n, tri_normals, ior)
        cos_i = (-dot(d, ns_f)).clamp(0.0, 1.0)
        f = fresnel_dielectric(cos_i, eta)
        t_dir, tir = refract(d, ns_f, eta)
        r_dir = reflect(d, ns_f)
        g_t, g_r = interface_gains(cos_i, eta)
        last = k == max_events
        if last:  # leave here, refracted (at the critical angle under TIR)
            take_r = torch.zeros_like(leaving)
        else:
            take_r = tir if branch == "tir" else f > 0.5
        new_d = torch.where(take_r[:, None], r_dir, t_dir)
        exits = ~take_r & leaving
        fork = None
        if branches == 2 and not last:  # the first refraction out of a main path: split
            fork = _split_off(r, split, live, count, exits, x, ng_f, r_dir, f, g_r, ins, eps)
        # the reflected branch stays on the incident side, the refracted crosses
        side = torch.where(take_r, -1.0, 1.0)
        r.origin[live] = x + (eps * side)[:, None] * -ng_f
        r.direction[live] = normalize(new_d)
        r.throughput[live] *= torch.where(take_r, f, 1.0 - f)
        r.events[live] += 1
        r.cos_exit[live] = torch.where(exits, cos_i, r.cos_exit[live])
        g_live = r.gain[live]
        r.gain_exit[live] = torch.where(exits, g_live, r.gain_exit[live])
        r.gain[live] = g_live + torch.where(take_r, g_r, g_t)
        r.inside[live] = torch.where(take_r, ins, ~ins)
        if last:
            break
        if fork is not None and fork.numel() > 0:
            live = torch.cat([live, live[fork] + count])
    return _ends(r, count, split if branches == 2 else None)


__all__ = ["GRAZING_COS", "PathEnds", "geometric_normals", "interface_gains", "trace_paths"]

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
    # rows count.. hold the reflected branches (branches=2), live once split off
    rows = count * (2 if branches == 2 else 1)
    d0 = -omega
    n_in = face_forward(n, d0)
    t1, _ = refract(d0, n_in, 1.0 / ior)
    direction = torch.zeros(rows, 3)
    direction[:count] = t1
    origin = torch.zeros(rows, 3)
    origin[:count] = p - eps * n  # just inside the surface
    inside = torch.ones(rows, dtype=torch.bool)
    length = torch.zeros(rows)
    cos_exit = torch.ones(rows)
    throughput = torch.ones(rows)
    events = torch.zeros(rows, dtype=torch.int64)
    gain = torch.zeros(rows)  # G so far; at the last exit so far
    gain_exit = torch.zeros(rows)
    split = torch.zeros(count, dtype=torch.bool)  # the main path has split off its branch
    live = torch.arange(count)
    g_n = geometric_normals(tri_vertices)
    for k in range(max_events + 1):
        if live.numel() == 0:
            break
        o, d = origin[live], direction[live]
        t, face, uv = intersect(o, d)
        hit = face >= 0
        # Misses end: outside, the path has left for good; inside, the mesh leaks (an open
        # mesh): it leaves as it goes.
        keep = hit.nonzero(as_tuple=True)[0]
        live, o, d, t, face, uv = live[keep], o[keep], d[keep], t[keep], face[keep], uv[keep]
        if live.numel() == 0:
            break
        ins = inside[live]
        length[live] += torch.where(ins, t, torch.zeros_like(t))
        x = o + t[:, None] * d
        ng = g_n[face]  # (L, 3) outward by winding
        w = torch.cat([1.0 - uv.sum(1, keepdim=True), uv], 1)  # (L, 3)
        ns = normalize((w[:, :, None] * tri_normals[face]).sum(1))
        leaving = dot(d, ng) > 0  # the side of the flat triangle decides
        ng_f = torch.where(leaving[:, None], -ng, ng)  # facing against d
        ns_f = torch.where((dot(ns, ng_f) < 0)[:, None], -ns, ns)
        ns_f = torch.where((dot(d, ns_f) >= 0)[:, None], ng_f, ns_f)  # shading normal behind
        eta = torch.where(leaving, torch.full_like(t, ior), torch.full_like(t, 1.0 / ior))
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
            main = live < count
            fork = (exits & main & ~split[live.clamp(max=count - 1)]).nonzero(as_tuple=True)[0]
            src = live[fork]
            br = src + count
            split[src] = True
            origin[br] = x[fork] + (eps * -1.0) * -ng_f[fork]
            direction[br] = normalize(r_dir[fork])
            throughput[br] = throughput[src] * f[fork]
            gain[br] = gain[src] + g_r[fork]
            gain_exit[br] = gain_exit[src]
            length[br] = length[src]
            cos_exit[br] = cos_exit[src]
            inside[br] = ins[fork]
        # the reflected branch stays on the incident side, the refracted crosses
        side = torch.where(take_r, -1.0, 1.0)
        origin[live] = x + (eps * side)[:, None] * -ng_f
        direction[live] = normalize(new_d)
        throughput[live] *= torch.where(take_r, f, 1.0 - f)
        events[live] += 1
        cos_exit[live] = torch.where(exits, cos_i, cos_exit[live])
        g_live = gain[live]
        gain_exit[live] = torch.where(exits, g_live, gain_exit[live])
        gain[live] = g_live + torch.where(take_r, g_r, g_t)
        inside[live] = torch.where(take_r, ins, ~ins)
        if last:
            break
        if fork is not None and fork.numel() > 0:
            live = torch.cat([live, live[fork] + count])
    if branches != 2:
        return PathEnds(direction=direction, length=length, cos_exit=cos_exit,
                        throughput=throughput, events=events, gain=gain_exit)
    m, b = slice(0, count), slice(count, rows)
    s1 = split[:, None]
    fork_ends = PathEnds(direction=torch.where(s1, direction[b], direction[m]),
                         length=torch.where(split, length[b], length[m]),
                         cos_exit=torch.where(split, cos_exit[b], cos_exit[m]),
                         throughput=torch.where(split, throughput[b], 0.0),
                         events=events[b],
                         gain=torch.where(split, gain_exit[b], gain_exit[m]))
    return PathEnds(direction=direction[m], length=length[m], cos_exit=cos_exit[m],
                    throughput=throughput[m], events=events[m], branch=fork_ends,
                    gain=gain_exit[m])


__all__ = ["GRAZING_COS", "PathEnds", "geometric_normals", "interface_gains", "trace_paths"]

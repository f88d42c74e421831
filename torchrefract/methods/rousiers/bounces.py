"""Internal bounces (``internal_bounces``: K > 0 or ``auto``; ours, beyond the paper): the
rough interface seen from inside, for :func:`torchrefract.shading.bounces.follow`.

At the first exit the table's internal reflection lobe (E_ri, k_ri: leaving the glass,
eta = 1 / ior) carries E_ri of the light back inside; one ray stands for it, along the
mirror direction about the interface normal, and is marched to the next interface (front or
back layer), where the table again splits it into a transmitted lobe (read from the
pyramid) and a reflected one, K times. The ray is the lobe's mode, not the SG fit's axis:
near the critical angle the fitted axis swings off the mirror direction with roughness and
angle, so a ray along it crossed folds of the geometry as roughness changed (per-pixel
flicker in a roughness sweep; figures: docs/decisions_rousiers.md).

A lobe's angular variance is carried along: the front lobe's 1/k_t1, plus 1/k_r at each
reflection (a reflection keeps angular spread; the curvature of the reflecting surface is
not modelled), magnified by the exit refraction (d theta_out / d theta_in)^2 where it
leaves. The ``tir`` rule applies at the last interface only; under ``conserve`` a lobe that
has grown wide is let out before that, gradually: at each interface the fraction
1 - exp(-var / ``DIFFUSE_VAR``) of what it reflects inside leaves there as at the last
interface (the bounces not followed, summed in closed form), the rest goes on as a ray. A
bounce whose march finds no next interface (the image-space march lost it) leaves along its
own direction with the escape fraction of trapped light
(:func:`torchrefract.shading.bounces.escape_fraction`; 1 for smooth glass).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import torch

from torchrefract.geometry.gbuffer import GBuffer, interpolate
from torchrefract.kernels.index import take
from torchrefract.lighting.lights import Lighting, incident_radiance_sg
from torchrefract.methods.rousiers.lobes import (
    FrontLobes,
    sg_lobe,
    spread_energies,
    true_angle_transmit,
)
from torchrefract.methods.rousiers.options import DIFFUSE_VAR, RousiersOptions
from torchrefract.methods.rousiers.pixels import Pixels
from torchrefract.optics import microfacet as mf
from torchrefract.optics.exit_rule import (
    clamp_to_critical,
    critical_cosine,
    last_interface,
    leaving_weight,
)
from torchrefract.optics.materials import MaterialBatch
from torchrefract.optics.sgfit import lobe_axis
from torchrefract.optics.smooth import dot, face_forward, normalize, reflect
from torchrefract.shading.bounces import Arrival, Shading, escape_fraction, follow


def follow_bounces(g: GBuffer, table, lighting: Lighting, materials: MaterialBatch,
                   options: RousiersOptions, px: Pixels, front: FrontLobes, xi,
                   l_trans: torch.Tensor, matched: torch.Tensor,
                   reflected: Callable[[torch.Tensor], torch.Tensor] | None = None):
    """The light the first exit (``xi``: :class:`.exit.ExitInterface`) reflects back
    inside, followed bounce by bounce; ``l_trans`` the light its transmitted lobe reads.
    ``reflected`` maps the table's internal reflection energy at ``xi`` (N,) to the one a
    method whose exit leaves by several lobes uses (``gsr``: its lobes', to match their
    transmitted energies).
    Returns the radiance leaving through all interfaces from inside (N, 3) and the
    :class:`torchrefract.shading.bounces.BounceResult`."""
    ex, bi = xi.ex, px.bi
    n_pix = px.idx.numel()
    # The exit's internal reflection lobe uses the roughness at the exit point.
    uv_x = interpolate(ex.bary, take(g.meshes.tri_uvs, ex.tri.clamp(min=0)))
    alpha_x = torch.where(ex.found, materials.roughness_at(bi, uv_x), px.alpha)
    a_x = alpha_x.clamp(min=mf.ALPHA_MIN)
    _, k_ri, _, _ = sg_lobe(table, xi.cos2, xi.eta, a_x, px.dist, "reflect")
    e_ri = spread_energies(table, xi.cos2, xi.var1, xi.eta, a_x, px.dist)[1]
    if reflected is not None:
        e_ri = reflected(e_ri)
    p_ri = normalize(reflect(front.p_t1, xi.n_in))  # the lobe's ray: mirror (docstring)
    w1 = front.e_t1[:, None] * xi.att
    first = Shading(radiance=w1 * l_trans, direction=p_ri,
                    reflectance=torch.where(ex.found & ~matched, e_ri, torch.zeros_like(e_ri)),
                    var=xi.var1 + 1.0 / k_ri.clamp(min=1e-12))
    arrive = Arrival(pix=torch.arange(n_pix), batch=bi, p=xi.p2, t=front.p_t1,
                     normal=ex.normal, uv=uv_x, found=ex.found, w=w1, var=xi.var1)
    shade = interface_shader(table, lighting, materials, options.tir, first)
    res = follow(g, arrive, shade, materials.absorption, options.bounces, n_pix,
                 options.refine_steps)
    return torch.where(matched[:, None], xi.att * l_trans, res.radiance), res


def interface_shader(table, lighting: Lighting, materials: MaterialBatch, tir_mode: str,
                     first: Shading):
    """The interface model for :func:`torchrefract.shading.bounces.follow`: ``first`` at
    the first exit (computed by the cone-traced path), :func:`shade_inside` after."""
    dist_b = materials.distribution_index()

    def shade(a: Arrival, k: int, last: bool) -> Shading:
        if k == 0:
            return first
        return shade_inside(table, lighting, materials, dist_b, tir_mode, a, last)

    return shade


@dataclass
class _Split:
    """One rough interface met from inside: the view side, where TIR holds, the cosine the
    transmitted lobe leaves with (``cos_t``), and the table's lobes (sharpness, axis angle,
    energy; ``t_r`` is ``None`` where the reflected lobe is not looked up)."""

    view: torch.Tensor
    n_view: torch.Tensor
    cos: torch.Tensor
    cos_t: torch.Tensor
    tir: torch.Tensor
    k_t: torch.Tensor
    t_t: torch.Tensor
    e_t: torch.Tensor
    k_r: torch.Tensor
    t_r: torch.Tensor | None
    e_r: torch.Tensor


def _split(table, a: Arrival, eta: torch.Tensor, cos_crit: torch.Tensor, alpha: torch.Tensor,
           dist: torch.Tensor, tir_mode: str, last: bool) -> _Split:
    """The table's transmitted and reflected lobes where the rays ``a`` arrive."""
    n_view = face_forward(a.normal, a.t)  # inside, facing the arriving ray
    view = -a.t
    cos = dot(view, n_view).clamp(0.0, 1.0)
    tir = cos < cos_crit
    # the light leaving under TIR (the last interface's rule; under ``conserve`` the
    # diffuse part at every interface) leaves at the critical angle
    cos_t = clamp_to_critical(cos, tir, cos_crit) \
        if (last and tir_mode == "clamp") or tir_mode == "conserve" else cos
    _, k_t, t_t, e_t = sg_lobe(table, cos_t, eta, alpha, dist, "transmit")
    # The reflected lobe goes on (its spread), except at ``conserve``'s last interface,
    # where all of it leaves with the transmitted lobe: not looked up there.
    t_r = None
    if not (last and tir_mode == "conserve"):
        _, k_r, t_r, e_r = sg_lobe(table, cos, eta, alpha, dist, "reflect")
    else:
        k_r = torch.full_like(k_t, float("inf"))  # var unchanged: nothing follows it
    if not last or tir_mode == "conserve":  # the split: averaged over the lobe carried
        e_t, e_r = spread_energies(table, cos, a.var, eta, alpha, dist)
    return _Split(view=view, n_view=n_view, cos=cos, cos_t=cos_t, tir=tir, k_t=k_t, t_t=t_t,
                  e_t=e_t, k_r=k_r, t_r=t_r, e_r=e_r)


def _leaving(table, s: _Split, a: Arrival, ior: torch.Tensor, alpha: torch.Tensor,
             dist: torch.Tensor, esc: torch.Tensor | None, tir_mode: str, last: bool):
    """What leaves the interface (direction, sharpness, weight) and what is reflected on
    (the reflectance), per ``tir`` rule (module docstring)."""
    p_t = normalize(lobe_axis(s.view, s.n_view, s.t_t, "transmit"))
    sin2 = (1.0 - s.cos_t * s.cos_t).clamp(min=0.0)
    mag2 = (ior * s.cos_t / torch.sqrt((1.0 - ior * ior * sin2).clamp(min=1e-4))) ** 2
    # The small-angle magnification diverges at the critical angle (cos_out -> 0) and
    # would turn a lobe near grazing exit into a uniform blur; a lobe cannot spread past
    # the hemisphere, so it is bounded at 2x (a heuristic; docs/decisions_rousiers.md).
    mag2 = mag2.clamp(max=4.0)
    k_out = 1.0 / (1.0 / s.k_t.clamp(min=1e-12) + mag2 * a.var)
    w_out, refl = s.e_t, s.e_r
    if tir_mode == "conserve":
        # What this interface reflects inside leaves here too, in closed form, after the
        # losses of the bounces not followed (escape_fraction): all of it at the last
        # interface, elsewhere the reflected lobe's diffuse part (DIFFUSE_VAR: a single
        # ray cannot stand for a lobe that wide, and following it through a non-convex
        # shape is chaotic, per-pixel flicker as roughness changes). It leaves with the
        # transmitted lobe (at the critical angle under TIR, ``cos_t``).
        go_on = torch.zeros_like(s.e_r) if last else \
            torch.exp(-(a.var + 1.0 / s.k_r.clamp(min=1e-12)) / DIFFUSE_VAR)
        w_out = leaving_weight("conserve", s.tir, s.e_t, (1.0 - go_on) * s.e_r, esc)
        refl = go_on * s.e_r
    elif last and tir_mode == "clamp":  # TIR light leaves at the critical angle: all that
        # this interface keeps at the true angle (the model loses some to masking)
        e_true = true_angle_transmit(table, s.e_t, s.tir, s.cos, 1.0 / ior, alpha, dist)
        w_out, refl = last_interface("clamp", s.tir, e_true, s.e_r, esc)
    elif last:  # reflect: under TIR the internal reflection lobe is read instead
        p_r = normalize(lobe_axis(s.view, s.n_view, s.t_r, "reflect"))
        p_t = torch.where(s.tir[:, None], p_r, p_t)
        k_out = torch.where(s.tir, 1.0 / (1.0 / s.k_r.clamp(min=1e-12) + a.var), k_out)
        w_out, refl = last_interface("reflect", s.tir, s.e_t, s.e_r, esc)
    return p_t, k_out, w_out, refl


def shade_inside(table, lighting: Lighting, materials: MaterialBatch, dist_b: torch.Tensor,
                 tir_mode: str, a: Arrival, last: bool) -> Shading:
    """The rough interface seen from inside at a later bounce (module docstring): the
    table's transmitted lobe leaves, its reflected lobe goes on (``last``: the ``tir``
    rule's interface)."""
    bi = a.batch
    ior = take(materials.ior, bi)
    dist = take(dist_b, bi)
    alpha = materials.roughness_at(bi, a.uv).clamp(min=mf.ALPHA_MIN)
    s = _split(table, a, 1.0 / ior, critical_cosine(ior), alpha, dist, tir_mode, last)
    # The fraction of trapped light that eventually leaves (escape_fraction), looked up
    # once where ``conserve`` (its last interface, the diffuse part at every other) or a
    # lost ray needs it.
    lost_any = bool((~a.found).any())
    esc = escape_fraction(table, materials.ior, dist_b, alpha, bi) \
        if lost_any or tir_mode == "conserve" else None
    p_t, k_out, w_out, refl = _leaving(table, s, a, ior, alpha, dist, esc, tir_mode, last)
    # Lost rays (the march found no next interface) leave along their current
    # direction with the lobe they carry, and with what light trapped inside eventually
    # lets out (escape_fraction: 1 for smooth glass; a found ray's last interface keeps
    # that too under conserve, so losing or finding the interface changes less).
    p_t = torch.where(a.found[:, None], p_t, a.t)
    k_out = torch.where(a.found, k_out, 1.0 / a.var.clamp(min=1e-12))
    w_out = torch.where(a.found, w_out, esc if lost_any else torch.ones_like(s.cos))
    refl = torch.where(a.found, refl, torch.zeros_like(refl))
    l_out = incident_radiance_sg(lighting, bi, a.p, p_t, k_out)
    # the reflected lobe goes on along the mirror direction (module docstring)
    p_next = normalize(reflect(a.t, s.n_view))
    return Shading(radiance=a.w * w_out[:, None] * l_out, direction=p_next, reflectance=refl,
                   var=a.var + 1.0 / s.k_r.clamp(min=1e-12))


__all__ = ["follow_bounces", "interface_shader", "shade_inside"]

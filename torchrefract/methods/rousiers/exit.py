"""Step 4: the exit interface and the lobe leaving through it (sec. 4.3, "Radiance
computation"), per exit rule (``tir``) and width (``spread``).

The mean back normal n_bar is the proxy surface; the SG table for leaving the glass
(eta = 1 / ior) at the angle between p_t1 and it gives the exit lobe (E_t2, k_t2, p_t2).

How wide the exit lobe is (``spread``). The paper (``paper``) assumes all rays reach the
exit parallel (sec. 3.2, assumption 1): the front lobe's own spread only enters through the
footprint's NDF, convolved with the exit roughness as if it were roughness (eq. 10). That
drops the spread on a flat slab (the image would show only the exit roughness) and
overstates it on convex shapes: inside a ball lens a ray tilted by delta meets a normal
tilted by 2 delta, so it leaves tilted by (2 - eta) delta, not sqrt(eta^2 + 4 (eta - 1)^2)
delta. ``paper+front`` adds the front lobe's variance 1/k_t1 magnified by the exit
refraction (d theta_out / d theta_in = ior cos(theta_in) / cos(theta_out)). ``rays``
(default, ours) measures the mapping directly: the four marched bounding rays are refracted
out at their own exit normals, and their angles to the central exit direction give the
geometric part of the lobe's variance (:func:`.cone.geometric_variance`), added to the exit
roughness's lobe (which then uses the exact exit normal, not the NDF). It costs nothing
extra: the rays are marched anyway.

The exit rule (``tir``; weights: :mod:`torchrefract.optics.exit_rule`). ``conserve``
(default; ours): what the exit reflects inside (all of it under TIR) leaves there too, with
the transmitted lobe (its incident angle clamped to the critical angle), times the fraction
of trapped light that eventually escapes (:func:`torchrefract.shading.bounces.
escape_fraction`), so the image is continuous in roughness and IOR at the critical angle
and a white furnace keeps what Mitsuba keeps; its energies are averaged over the front lobe
arriving at the exit (:func:`torchrefract.optics.sgfit.spread_cosines`, variance 1/k_t1).
``clamp`` (the paper's, sec. 4.3, and Wyman's): the incident angle is clamped to the critical
angle and all the transmitted light leaves with that lobe (weight 1, as ``specular`` does,
so the smooth limit matches it); the exit's reflection outside TIR is lost. ``reflect``
reads the environment with the table's internal reflection lobe under TIR instead. With
internal bounces the first exit is not the last interface (``split``): the table's own
split between the transmitted and the internally reflected lobe applies.
Rays whose exit is not found fall back to the front lobe alone (direction p_t1).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from torchrefract.geometry.gbuffer import GBuffer
from torchrefract.kernels.index import take
from torchrefract.kernels.march import Exit
from torchrefract.lighting.lights import Lighting, incident_radiance_sg
from torchrefract.methods.rousiers.lobes import FrontLobes, sg_lobe, spread_energies
from torchrefract.methods.rousiers.pixels import Pixels
from torchrefract.optics import microfacet as mf
from torchrefract.optics.exit_rule import clamp_to_critical, critical_cosine, leaving_weight
from torchrefract.optics.materials import MaterialBatch
from torchrefract.optics.ndf import combine_exponents
from torchrefract.optics.sgfit import lobe_axis
from torchrefract.optics.smooth import dot, face_forward, normalize
from torchrefract.shading.bounces import escape_fraction


@dataclass
class ExitInterface:
    """The exit interface of N pixels, seen from inside.

    Attributes:
        ex: the central ray's exit; p2 (N, 3) the exit point (the front hit where not
            found); att (N, 3) the absorption exp(-sigma s) along the way.
        p_t1, k_t1: the front lobe arriving (axis, sharpness); var1 = 1 / k_t1 its spread.
        n_in: (N, 3) the proxy normal, inward, facing against p_t1; view2 = -p_t1;
            cos2 = view2 . n_in; eta = 1 / ior.
        cos_crit, tir: (N,) the critical cosine and where the exit is beyond it (found).
        mag2: (N,) (d theta_out / d theta_in)^2 at the exit.
        kappa_g: (N,) the footprint NDF's exponent (eq. 11; ``spread: paper``, ``paper+front``).
        var_geo: (N,) the bounding rays' variance (``spread: rays``).
    """

    ex: Exit
    p2: torch.Tensor
    att: torch.Tensor
    p_t1: torch.Tensor
    k_t1: torch.Tensor
    var1: torch.Tensor
    n_in: torch.Tensor
    view2: torch.Tensor
    cos2: torch.Tensor
    eta: torch.Tensor
    cos_crit: torch.Tensor
    tir: torch.Tensor
    mag2: torch.Tensor
    kappa_g: torch.Tensor | None = None
    var_geo: torch.Tensor | None = None


def exit_interface(g: GBuffer, px: Pixels, front: FrontLobes, ex: Exit, n_bar: torch.Tensor,
                   kappa_g: torch.Tensor | None, materials: MaterialBatch) -> ExitInterface:
    """Step 4's geometry: the proxy surface of normal n_bar where the front lobe leaves
    (``kappa_g``: the footprint NDF's exponent, eq. 11, where ``spread`` uses it)."""
    p_t1, ior = front.p_t1, px.ior
    n_in = face_forward(-n_bar, p_t1)  # inward, facing against p_t1
    view2 = -p_t1
    cos2 = dot(view2, n_in).clamp(0.0, 1.0)
    cos_crit = critical_cosine(ior)
    tir = (cos2 < cos_crit) & ex.found
    sin2 = (1.0 - cos2 * cos2).clamp(min=0.0)
    cos_out = torch.sqrt((1.0 - ior * ior * sin2).clamp(min=1e-4))
    mag2 = (ior * cos2 / cos_out) ** 2  # (d theta_out / d theta_in)^2 at the exit
    p2 = torch.where(ex.found[:, None], ex.position, px.p1)
    path = torch.where(ex.found, ex.dist,
                       take((g.back.dist - g.front.dist).reshape(-1), px.idx).clamp(min=0.0))
    att = torch.exp(-take(materials.absorption, px.bi) * path[:, None])
    return ExitInterface(ex=ex, p2=p2, att=att, p_t1=p_t1, k_t1=front.k_t1,
                         var1=1.0 / front.k_t1.clamp(min=1e-12), n_in=n_in, view2=view2,
                         cos2=cos2, eta=1.0 / ior, cos_crit=cos_crit, tir=tir, mag2=mag2,
                         kappa_g=kappa_g)


def exit_lobe(table, px: Pixels, xi: ExitInterface, materials: MaterialBatch, spread: str,
              mode: str, alpha_exit: torch.Tensor
              ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Direction (N, 3), sharpness and weight (N,) of the light leaving through an exit
    interface of roughness ``alpha_exit`` (N,), under the exit rule ``mode`` (``split``
    with internal bounces) and the width ``spread`` (module docstring)."""
    if spread == "rays":
        alpha2 = alpha_exit
    else:  # eq. 10: the footprint's NDF convolved with the BTDF's
        kappa_d = mf.blinn_phong_from_alpha(alpha_exit).clamp(min=0.0)
        alpha2 = mf.alpha_from_blinn_phong(combine_exponents(xi.kappa_g, kappa_d))
    if mode == "reflect":
        p_t2, k_t2, weight2 = _reflected_under_tir(table, px, xi, alpha2)
    else:
        p_t2, k_t2, weight2 = _transmitted(table, px, xi, materials, mode, alpha2, alpha_exit)
    if spread == "paper+front":  # front spread carried through the exit
        k = 1.0 / (1.0 / k_t2 + xi.mag2 / xi.k_t1)
    elif spread == "rays":
        k = 1.0 / (1.0 / k_t2 + xi.var_geo).clamp(min=1e-12)
    else:
        k = k_t2
    # Fallback where the exit is not found: leave with the front lobe.
    found = xi.ex.found
    p_out = torch.where(found[:, None], p_t2, xi.p_t1)
    k = torch.where(found, k, xi.k_t1)
    weight2 = torch.where(found, weight2, torch.ones_like(weight2))
    return p_out, k, weight2


def _transmitted(table, px: Pixels, xi: ExitInterface, materials: MaterialBatch, mode: str,
                 alpha2: torch.Tensor, alpha_exit: torch.Tensor):
    """The exit's transmitted lobe (axis, sharpness) and its weight under ``split``,
    ``clamp`` or ``conserve`` (the last two: at the critical angle under TIR)."""
    cos_in = xi.cos2 if mode == "split" else clamp_to_critical(xi.cos2, xi.tir, xi.cos_crit)
    _, k_t2, t_t2, e_t2 = sg_lobe(table, cos_in, xi.eta, alpha2, px.dist, "transmit")
    p_t2 = normalize(lobe_axis(xi.view2, xi.n_in, t_t2, "transmit"))
    if mode == "split":  # the energy averaged over the arriving lobe
        weight2 = spread_energies(table, xi.cos2, xi.var1, xi.eta, alpha2, px.dist)[0]
    elif mode == "clamp":  # the paper's: all the light arriving under TIR leaves
        weight2 = leaving_weight("clamp", xi.tir, e_t2, kept=torch.ones_like(e_t2))
    else:
        # The paper's clamp, made continuous: what the exit reflects inside (all of it
        # under TIR) leaves here too, after the losses of the bounces it would take on its
        # way out (escape_fraction); both energies at the true angles of the arriving lobe.
        esc = escape_fraction(table, materials.ior, px.dist_b, alpha_exit, px.bi)
        e_t2, e_r2 = spread_energies(table, xi.cos2, xi.var1, xi.eta, alpha2, px.dist)
        weight2 = leaving_weight("conserve", xi.tir, e_t2, e_r2, esc)
    return p_t2, k_t2, weight2


def _reflected_under_tir(table, px: Pixels, xi: ExitInterface, alpha2: torch.Tensor):
    """``tir: reflect``: under TIR the table's internal reflection lobe is read instead of
    the transmitted one (axis, sharpness, weight)."""
    _, k_t2, t_t2, e_t2 = sg_lobe(table, xi.cos2, xi.eta, alpha2, px.dist, "transmit")
    _, k_ti, t_ti, e_ti = sg_lobe(table, xi.cos2, xi.eta, alpha2, px.dist, "reflect")
    p_t2 = normalize(lobe_axis(xi.view2, xi.n_in, t_t2, "transmit"))
    p_ti = normalize(lobe_axis(xi.view2, xi.n_in, t_ti, "reflect"))
    p_t2 = torch.where(xi.tir[:, None], p_ti, p_t2)
    k_t2 = torch.where(xi.tir, k_ti, k_t2)
    return p_t2, k_t2, leaving_weight("reflect", xi.tir, e_t2, e_ti)


def transmitted_radiance(table, lighting: Lighting, px: Pixels, xi: ExitInterface,
                         materials: MaterialBatch, spread: str, mode: str,
                         coverage: tuple[torch.Tensor, torch.Tensor] | None
                         ) -> tuple[torch.Tensor, torch.Tensor]:
    """Step 5's transmitted part: the environment read from the SG pyramid (sec. 4.1)
    around the exit lobe (N, 3), and the lobe's sharpness (N,) (for the passes).

    With a roughness map, ``coverage`` holds the roughness levels (B, L) and their coverage
    ratios over the footprint (N, L) (sec. 5.1): one exit lobe per level, summed with those
    ratios; where nothing is covered, the front roughness."""
    bi, p2 = px.bi, xi.p2
    if coverage is None:
        p_out, k, weight2 = exit_lobe(table, px, xi, materials, spread, mode, px.alpha)
        return incident_radiance_sg(lighting, bi, p2, p_out, k) * weight2[:, None], k
    levels, c = coverage
    no_cov = c.sum(-1) < 0.5  # nothing covered: use the front roughness
    alpha = px.alpha
    l_trans = torch.zeros_like(px.p1)
    k = torch.zeros_like(alpha)
    for li in range(levels.shape[1]):
        a_l = torch.where(no_cov, alpha, levels[bi, li].clamp(min=mf.ALPHA_MIN))
        w_l = torch.where(no_cov, torch.full_like(alpha, 1.0 / levels.shape[1]), c[:, li])
        p_l, k_l, wt_l = exit_lobe(table, px, xi, materials, spread, mode, a_l)
        l_trans = l_trans + (w_l * wt_l)[:, None] * incident_radiance_sg(
            lighting, bi, p2, p_l, k_l)
        k = k + w_l / k_l.clamp(min=1e-12)  # coverage-weighted variance (for the pass)
    return l_trans, 1.0 / k.clamp(min=1e-12)


__all__ = ["ExitInterface", "exit_interface", "exit_lobe", "transmitted_radiance"]

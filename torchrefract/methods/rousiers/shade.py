"""The method's steps 1-5 over the object pixels of a batch (package docstring)."""

from __future__ import annotations

import torch

from torchrefract.geometry.gbuffer import GBuffer
from torchrefract.shading import fused
from torchrefract.kernels.index import put_, take, where_true
from torchrefract.lighting.lights import Lighting, incident_radiance_sg
from torchrefract.methods.rousiers.bounces import follow_bounces
from torchrefract.methods.rousiers.cone import (
    back_ndf,
    coverage_mips,
    footprint_coverage,
    geometric_variance,
    trace_cone,
)
from torchrefract.methods.rousiers.exit import exit_interface, transmitted_radiance
from torchrefract.methods.rousiers.lobes import front_lobes
from torchrefract.methods.rousiers.options import DIFFUSE_VAR, RousiersOptions
from torchrefract.methods.rousiers.pixels import Pixels, object_pixels
from torchrefract.optics.materials import MaterialBatch
from torchrefract.optics.sgfit import load_sg_table
from torchrefract.shading.background import background, light_in_front
from torchrefract.shading.bounces import bounce_passes

PASSES = ("exit_found", "tir", "lobe_sigma", "footprint")


def render_rousiers(g: GBuffer, lighting: Lighting, materials: MaterialBatch,
                    options: RousiersOptions = RousiersOptions()
                    ) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """Shade a G-buffer with de Rousiers' rough refraction (package docstring).

    Args:
        g: G-buffer of B views at (H, W) (sub-)pixels.
        lighting: environment maps (SG pyramids built once per file) and lights.
        materials: IOR, roughness, distribution and absorption per scene.
        options: method settings.

    Returns:
        radiance: (B, H, W, 3) float32, background included.
        passes: ``exit_found``, ``tir`` (0/1), ``lobe_sigma`` (per-axis angular spread of
            the final transmitted lobe, radians), ``footprint`` (pixels, major extent).
    """
    b, h, w = g.shape
    radiance = background(g, lighting)
    mips = coverage_mips(g, materials, options.roughness_levels) if materials.has_maps \
        else None
    done = fused.rousiers(g, lighting, materials, options, radiance, DIFFUSE_VAR, mips)
    if done is not None:  # the fused kernel ran (shading.fused says where it does)
        return done
    idx = g.object_index()
    bounce = options.bounces.enabled
    if idx.numel() == 0:  # the same passes as a batch with object pixels
        return radiance.view(b, h, w, 3), object_passes(g, idx, bounce, None, None)
    table = load_sg_table()
    px = object_pixels(g, materials)
    # 1. Front interface lobes (eqs. 8-9).
    front = front_lobes(table, px.view, px.n1, px.cos1, px.ior, px.alpha, px.dist)
    # 2. Cone tracing: the axis and four bounding rays (eq. 12), their footprint.
    cone = trace_cone(g, px.bi, px.p1, front.p_t1, front.k_t1, options)
    # 3. The back layer over the footprint: its NDF (eq. 11) gives the proxy normal; with
    # ``spread: rays`` the exact exit normal, the bounding rays giving the geometry's part.
    n_bar, kappa_g = (cone.exact_n, None) if options.spread == "rays" else \
        back_ndf(g, cone, px.bi)
    # 4. Exit interface: view side is inside (looking back along p_t1).
    xi = exit_interface(g, px, front, cone.ex, n_bar, kappa_g, materials)
    if options.spread == "rays":  # none found its exit: the front lobe's magnified spread
        xi.var_geo = geometric_variance(g, cone, px.bi, front.p_t1, px.ior,
                                        xi.mag2 / front.k_t1)
    # 5. The environment from the SG-pre-convolved pyramid (sec. 4.1) around each lobe.
    l_refl = incident_radiance_sg(lighting, px.bi, px.p1, front.axis_r, front.k_r)
    coverage = footprint_coverage(g, materials, options.roughness_levels, px.bi, cone, mips) \
        if mips is not None else None
    # With internal bounces the first exit is not the last interface: the table's own split
    # between the transmitted and the internally reflected lobe applies (no TIR rule).
    l_trans, k = transmitted_radiance(table, lighting, px, xi, materials, options.spread,
                                      "split" if bounce else options.tir, coverage)
    passes = finish(g, table, lighting, materials, options, px, front, cone, xi, radiance,
                    l_refl, l_trans, torch.rsqrt(k.clamp(min=1e-12)))
    return radiance.view(b, h, w, 3), passes


def finish(g: GBuffer, table, lighting: Lighting, materials: MaterialBatch, options, px: Pixels,
           front, cone, xi, radiance: torch.Tensor, l_refl: torch.Tensor,
           l_trans: torch.Tensor, lobe_sigma: torch.Tensor, reflected=None
           ) -> dict[str, torch.Tensor]:
    """What follows the exit lobe, for ``rousiers`` and the methods built on its steps
    (``lean``, ``gsr``): an index-matched object left invisible, the internal bounces
    (``reflected``: :func:`.bounces.follow_bounces`) or the exit's transmitted light, the
    object composited over ``radiance``; returns the passes (:func:`object_passes`) with
    the final transmitted lobe's per-axis spread ``lobe_sigma`` (N,)."""
    bounce = options.bounces.enabled
    e_r, e_t, l_trans, matched = index_matched(lighting, px, front, l_trans)
    res = None
    if bounce:
        l_through, res = follow_bounces(g, table, lighting, materials, options, px, front,
                                        xi, l_trans, matched, reflected)
        l_obj = e_r[:, None] * l_refl + l_through
    else:
        l_obj = e_r[:, None] * l_refl + e_t[:, None] * xi.att * l_trans
    composite(g, lighting, px, radiance, l_obj)
    found = cone.ex.found
    values = {"exit_found": found.float(), "tir": xi.tir.float(),
              "lobe_sigma": lobe_sigma.float(),
              "footprint": torch.where(found, cone.major, torch.zeros_like(cone.major)).float()}
    return object_passes(g, px.idx, bounce, values, res)


def composite(g: GBuffer, lighting: Lighting, px: Pixels, radiance: torch.Tensor,
               l_obj: torch.Tensor) -> None:
    """The object's radiance written over the background (N, 3), except where a light lies
    in front of the object."""
    hidden = light_in_front(lighting, px.bi, take(g.eye, px.bi), px.d,
                            take(g.front.dist.reshape(-1), px.idx))
    put_(radiance, px.idx, torch.where(hidden[:, None], take(radiance, px.idx),
                                       l_obj.to(radiance.dtype)))


def object_passes(g: GBuffer, idx: torch.Tensor, bounce: bool,
            values: dict[str, torch.Tensor] | None, res) -> dict[str, torch.Tensor]:
    """The passes (B, H, W, 1), ``values`` (N,) on the object pixels ``idx`` (zero
    elsewhere): the exit found, TIR, the final transmitted lobe's per-axis spread k^-1/2,
    the footprint's major extent; with bounces those of
    :func:`torchrefract.shading.bounces.bounce_passes` (``res``)."""
    b, h, w = g.shape
    out = {}
    for name in PASSES:
        v = torch.zeros(b * h * w)
        if values is not None:
            put_(v, idx, values[name])
        out[name] = v.view(b, h, w, 1)
    if bounce:
        out.update(bounce_passes(g, idx, res))
    return out


def index_matched(lighting: Lighting, px: Pixels, front, l_trans: torch.Tensor):
    """An index-matched object (IOR exactly 1) has no interface at all: it is invisible
    (the microfacet model would still lose the masking-shadowing energy there). Returns the
    front reflection's and transmission's energies, l_trans (the unrefracted environment
    where matched) and the mask."""
    matched = px.ior == 1.0
    e_r = torch.where(matched, torch.zeros_like(front.e_r), front.e_r)
    e_t = torch.where(matched, torch.ones_like(front.e_t1), front.e_t1)
    if bool(matched.any()):  # looked up only where some scene has IOR 1
        sel = where_true(matched)
        plain = incident_radiance_sg(lighting, take(px.bi, sel), take(px.p1, sel),
                                     take(px.d, sel), torch.full((sel.numel(),), float("inf")))
        l_trans = put_(l_trans.clone(), sel, plain)
    return e_r, e_t, l_trans, matched


__all__ = ["composite", "finish", "index_matched", "object_passes", "render_rousiers"]

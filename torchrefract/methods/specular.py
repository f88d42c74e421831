"""Method ``specular``: two-sided image-space refraction (Wyman 2005), done exactly.

Per covered pixel: refract the camera ray at the front hit (Snell, shading normal), march the
refracted ray through the back-face buffer to its exit (Oliveira and Brauwers 2007; exact
triangle hit, see :mod:`torchrefract.kernels.march`), refract again with the IOR ratio inverted, and
look the environment up. The front surface's Fresnel reflection is added:

    L = F1 L_env(reflect(d)) + (1 - F1) W2 exp(-sigma s) L_env(T2)

with exact unpolarized dielectric Fresnel terms F1 (entry) and F2 (exit), s the path length
inside and sigma the absorption. The exit weight W2 is the ``tir`` rule's:

- ``conserve`` (default; ours): W2 = (1 - F2) + F2 P_esc. What the exit reflects inside
  (all of it under total internal reflection) leaves there too, along the refracted
  (critical-angle) direction, times the fraction of trapped light that eventually escapes
  (:func:`torchrefract.shading.bounces.escape_fraction`: 1 for smooth glass, below 1 for rough
  glass, which loses light to masking at every bounce). The image is continuous at the
  critical angle and smooth glass keeps its energy (the white furnace).
- ``clamp`` (Wyman's and de Rousiers' choice): W2 = 1 - F2, and under TIR the light leaves
  along the critical-angle direction with weight 1 (rough glass: what the interface keeps,
  less its masking loss), standing in for the light that escapes after further bounces;
  the exit's reflection outside TIR is lost.
- ``reflect``: under TIR the light is reflected once and the environment looked up in that
  direction.

Rough glass: the rays follow the smooth surface (no blur: see ``prefiltered`` and
``rousiers``), but the interfaces' energies are the rough surface's
(:func:`torchrefract.optics.sgfit.interface_energies`: F1, 1 - F1, F2, 1 - F2 become the Walter
BSDF's reflected and transmitted energies, which add up to less than 1), so the object has
the brightness of rough glass. The light reaching the exit is the entry's rough transmitted
lobe, not the one ray: under ``tir: conserve`` and with internal bounces, the exit's
energies are averaged over that lobe (:func:`torchrefract.optics.sgfit.spread_cosines`, around the
lobe's axis, which tilts towards grazing: ``shading.paths.spread_exit``), and each internal reflection
adds its lobe's spread to the next interface's average; the papers' ``clamp`` and
``reflect`` keep the one ray's. Rays whose exit is not found (they leave the frame, miss the
back layer) fall back to the refracted direction T1, never to garbage.

``internal_bounces`` (K > 0 or ``auto``, :mod:`torchrefract.shading.bounces`): the exit interface
reflects F2 of the light back inside (all of it under TIR); that part is marched to the next
interface, where (1 - F) leaves along the refracted ray and F is reflected again, K times;
the ``tir`` rule then applies at the last interface.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from torchrefract.geometry.gbuffer import GBuffer
from torchrefract.shading import fused
from torchrefract.kernels.index import put_, take
from torchrefract.lighting.lights import Lighting, incident_radiance
from torchrefract.methods.base import Method, Shaded, uniform_roughness
from torchrefract.optics.exit_rule import TIR_RULES, last_interface
from torchrefract.optics.materials import MaterialBatch
from torchrefract.optics.sgfit import (
    load_sg_table,
    sg_lookup,
    spread_interface_energies,
)
from torchrefract.optics.smooth import (
    dot,
    face_forward,
    fresnel_dielectric,
    reflect,
    refract,
)
from torchrefract.options import nested, option
from torchrefract.shading.background import background
from torchrefract.shading.bounces import (
    Arrival,
    BounceSettings,
    Shading,
    bounce_passes,
    escape_fraction,
    follow,
)
from torchrefract.shading.paths import Paths, path_passes, trace_paths


@dataclass(frozen=True)
class SpecularOptions:
    """Settings of ``specular`` (``method_options`` in a scene)."""

    tir: str = option("conserve", choices=TIR_RULES)
    """Exit rule (module docstring): ``conserve``, ``clamp`` (the papers') or ``reflect``."""
    march_steps: int = option(24, minimum=1, maximum=4096, integer=True)
    """Coarse samples along the refracted ray (over the bounding sphere's chord); as
    ``rousiers``' central ray (64 gave the same accuracy and flicker out of sample:
    docs/decisions.md, "`specular`'s `march_steps` = 24")."""
    refine_steps: int = option(10, minimum=0, maximum=64, integer=True)
    """Bisection iterations after the coarse search."""
    bounces: BounceSettings = nested(BounceSettings)
    """Internal reflections (keys ``internal_bounces``, ``bounce_tolerance``,
    ``max_internal_bounces``, ``bounce_march_steps``)."""


def _interface(lighting: Lighting, materials: MaterialBatch, tir_mode: str, paths: Paths):
    """The interface seen from inside: (1 - F) leaves along the refracted ray, F is
    mirrored back inside (rough surfaces: the energies of ``sgfit.interface_energies``,
    averaged over the lobe of directions the light arrives with: the first exit's are the
    ``paths``', later ones carry the entry lobe's variance plus each reflection lobe's); at
    the last interface the ``tir`` rule lets TIR light leave (``clamp``: critical angle;
    ``reflect``: the mirror direction; ``conserve``: the reflected part leaves too, after
    the losses of the bounces not followed), as without bounces."""
    dist_b = materials.distribution_index()

    def shade(a: Arrival, k: int, last: bool) -> Shading:
        eta = materials.ior[a.batch]
        n_view = face_forward(a.normal, a.t)
        cos = -dot(a.t, n_view)
        f = fresnel_dielectric(cos, eta)
        t_out, tir = refract(a.t, n_view, eta)
        r = reflect(a.t, n_view)
        one, zero = torch.ones_like(f), torch.zeros_like(f)
        alpha = materials.roughness_at(a.batch, a.uv)
        rough = bool((alpha > 0).any())
        var = torch.zeros_like(f)
        if rough:
            table = load_sg_table()
            dist = dist_b[a.batch]
            if k == 0:  # the first exit: all paths, in order
                e_t, e_r = paths.e_t2, paths.e_r2
            else:
                e_t, e_r = spread_interface_energies(table, cos, a.var, eta, alpha, dist)
            if not last:  # the reflected lobe's spread, for the next interface
                k_r = sg_lookup(table, cos, 1.0 / eta, alpha, dist, "reflect")[1]
                var = a.var + torch.where(alpha > 0, 1.0 / k_r, zero)
        else:
            e_t, e_r = 1.0 - f, f
        # The fraction of trapped light that eventually leaves (escape_fraction; 1 when
        # smooth), looked up once where ``conserve``'s last interface or a lost ray needs it.
        lost_any = bool((~a.found).any())
        esc = escape_fraction(table, materials.ior, dist_b, alpha, a.batch) \
            if rough and (lost_any or (last and tir_mode == "conserve")) else one
        if last:
            if tir_mode == "reflect":
                t_out = torch.where(tir[:, None], r, t_out)
            w_out, refl = last_interface(tir_mode, tir, e_t, e_r, esc)
        else:  # smooth TIR: e_t = 0, e_r = 1
            w_out, refl = e_t, e_r
        # Lost rays (no interface found) leave along their current direction, with what
        # light trapped inside eventually lets out (escape_fraction; 1 for smooth glass),
        # as rousiers' bounces do.
        t_out = torch.where(a.found[:, None], t_out, a.t)
        w_out = torch.where(a.found, w_out, esc)
        refl = torch.where(a.found, refl, zero)
        l_out = incident_radiance(lighting, a.batch, a.p, t_out)
        return Shading(radiance=a.w * w_out[:, None] * l_out, direction=r, reflectance=refl,
                       var=var)

    return shade


def render_specular(g: GBuffer, lighting: Lighting, materials: MaterialBatch,
                    options: SpecularOptions = SpecularOptions()
                    ) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """Shade a G-buffer with two-sided specular refraction.

    Args:
        g: G-buffer of B views at (H, W) (sub-)pixels.
        lighting: environment maps and lights of the B scenes.
        materials: IOR, absorption, and roughness (for the interfaces' energies only:
            the rays follow the smooth surface).
        options: method settings.

    Returns:
        radiance: (B, H, W, 3) float32, background included.
        passes: ``exit_found`` and ``tir`` (B, H, W, 1) floats (1 where true, object pixels).
    """
    b, h, w = g.shape
    radiance = background(g, lighting)
    done = fused.specular(g, lighting, materials, options, radiance)
    if done is not None:  # the fused kernel ran (shading.fused says where it does)
        return done
    paths = trace_paths(g, lighting, materials, options)
    if paths.idx.numel() > 0:
        bi = paths.batch
        l_refl = incident_radiance(lighting, bi, paths.p1, paths.refl)
        att = torch.exp(-take(materials.absorption, bi) * paths.path[:, None])  # (N, 3)
        f1 = paths.f1[:, None]
        if options.bounces.enabled:
            n = paths.idx.numel()
            first = Arrival(pix=torch.arange(n), batch=bi, p=paths.p2, t=paths.t1,
                            normal=paths.n2, uv=paths.uv2, found=paths.found,
                            w=paths.e1[:, None] * att, var=paths.var)
            res = follow(g, first, _interface(lighting, materials, options.tir, paths),
                         materials.absorption, options.bounces, n, options.refine_steps)
            l_obj = f1 * l_refl + res.radiance
        else:
            l_trans = incident_radiance(lighting, bi, paths.p2, paths.t2)
            l_obj = f1 * l_refl + paths.e1[:, None] * paths.w2[:, None] * att * l_trans
        put_(radiance, paths.idx,
             torch.where(paths.hidden[:, None], take(radiance, paths.idx), l_obj))
    passes = path_passes(g, paths)
    if options.bounces.enabled:
        passes.update(bounce_passes(g, paths.idx, res if paths.idx.numel() else None))
    return radiance.view(b, h, w, 3), passes


class Specular(Method):
    """Two-sided image-space refraction (Wyman 2005), done exactly (module docstring)."""

    name = "specular"
    Options = SpecularOptions
    excluded_options = ("bounce_rays",)  # its lobes are rays: nothing for four rays to split

    def shades_samples(self, options, materials) -> bool:
        return True  # each sample's paths, marched through g.marched

    def strips(self, scenes, options) -> str | None:
        return uniform_roughness(scenes)

    def marches_front(self, options) -> bool:
        return options.bounces.enabled

    def shade(self, g, lighting, materials, options, state) -> Shaded:
        return Shaded(*render_specular(g, lighting, materials, options))


METHOD = Specular()

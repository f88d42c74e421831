"""Method ``prefiltered``: the baseline engines ship (Filament, Unity HDRP, three.js).

One refracted ray through the object, exactly as ``specular`` traces it (entry refraction,
march to the exit through the back-face buffer, exit refraction), then the environment is
read from the SG-pre-convolved pyramid with a blur chosen from the roughness and the IOR
instead of a sharp lookup. The object's thickness enters through the exact exit point (the
engines' "solid" refraction models approximate that point from a thickness value) and the
Beer-Lambert path length. The interfaces' weights and the exit rule (``tir``) are
``specular``'s: the rough surface's energies (the engines' split-sum "DFG" term, here for
both reflection and transmission), ``tir: conserve`` by default.

Blur (small-slope approximation): a microfacet tilted by a slope angle delta deviates a
refracted ray by delta (1 - 1/eta) on entry and delta (eta - 1) on exit, and a reflected one
by 2 delta. With the per-axis slope variance alpha^2 / 2 of a Beckmann surface (used for GGX
too, whose slope variance is unbounded), the per-axis angular variance of the exit direction
is sigma_t^2 = alpha^2 / 2 ((1 - 1/eta)^2 + (eta - 1)^2), and an SG exp(k (cos - 1)) with
that variance has k = 1 / sigma^2; reflection gets k_r = 1 / (2 alpha^2). Unlike
``rousiers`` it ignores the lobe's footprint on a curved back surface and the angular
dependence of the BTDF lobe.
"""

from __future__ import annotations

import torch

from torchrefract.geometry.gbuffer import GBuffer
from torchrefract.shading import fused
from torchrefract.kernels.index import put_, take
from torchrefract.lighting.lights import Lighting, incident_radiance_sg
from torchrefract.methods.base import Method, Shaded, uniform_roughness
from torchrefract.methods.specular import SpecularOptions
from torchrefract.optics.materials import MaterialBatch
from torchrefract.options import option_keys
from torchrefract.shading.background import background
from torchrefract.shading.bounces import BounceSettings
from torchrefract.shading.paths import path_passes, trace_paths

PrefilteredOptions = SpecularOptions
"""Settings of ``prefiltered``: ``specular``'s exit rule and march steps (no bounces)."""


def blur_sharpness(alpha: torch.Tensor, eta: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """SG sharpness of the transmitted (two interfaces) and reflected lobes.

    Args:
        alpha: (...) roughness; eta: (...) IOR inside / outside.

    Returns:
        k_t, k_r: (...) sharpness, ``inf`` for a smooth surface (a plain lookup).
    """
    a2 = alpha * alpha
    spread = (1.0 - 1.0 / eta) ** 2 + (eta - 1.0) ** 2
    var_t, var_r = 0.5 * a2 * spread, 2.0 * a2
    inf = torch.full_like(a2 * spread, float("inf"))
    k_t = torch.where(var_t > 0, 1.0 / torch.where(var_t > 0, var_t, 1.0), inf)
    k_r = torch.where(var_r > 0, 1.0 / torch.where(var_r > 0, var_r, 1.0), inf)
    return k_t, k_r


def render_prefiltered(g: GBuffer, lighting: Lighting, materials: MaterialBatch,
                       options: PrefilteredOptions = PrefilteredOptions()
                       ) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """Shade a G-buffer with one refracted ray and roughness-blurred environment lookups.

    Args:
        g: G-buffer of B views.
        lighting: environment maps (their SG pyramids are built once per file) and lights.
        materials: IOR, roughness and absorption per scene.
        options: method settings.

    Returns:
        radiance (B, H, W, 3) and passes (``exit_found``, ``tir``, ``blur_sigma``: the
        transmitted lobe's per-axis angular spread in radians).
    """
    b, h, w = g.shape
    radiance = background(g, lighting)
    done = fused.prefiltered(g, lighting, materials, options, radiance)
    if done is not None:  # the fused kernel ran (shading.fused says where it does)
        return done
    paths = trace_paths(g, lighting, materials, options)
    k_pass = torch.zeros(b * h * w)
    if paths.idx.numel() > 0:
        bi = paths.batch
        # The roughness at the front hit (the map at its UV when there is one).
        alpha = materials.roughness_at(bi, take(g.front.uv.reshape(-1, 2), paths.idx))
        k_t, k_r = blur_sharpness(alpha, take(materials.ior, bi))
        l_refl = incident_radiance_sg(lighting, bi, paths.p1, paths.refl, k_r)
        l_trans = incident_radiance_sg(lighting, bi, paths.p2, paths.t2, k_t)
        att = torch.exp(-take(materials.absorption, bi) * paths.path[:, None])
        f1 = paths.f1[:, None]
        l_obj = f1 * l_refl + paths.e1[:, None] * paths.w2[:, None] * att * l_trans
        put_(radiance, paths.idx,
             torch.where(paths.hidden[:, None], take(radiance, paths.idx), l_obj))
        put_(k_pass, paths.idx, torch.rsqrt(k_t))  # angular std (radians); 0 when smooth
    passes = path_passes(g, paths)
    passes["blur_sigma"] = k_pass.view(b, h, w, 1)
    return radiance.view(b, h, w, 3), passes


class Prefiltered(Method):
    """One refracted ray and roughness-blurred environment lookups (module docstring)."""

    name = "prefiltered"
    Options = PrefilteredOptions
    excluded_options = tuple(option_keys(BounceSettings))  # one ray: no internal reflections

    def shades_samples(self, options, materials) -> bool:
        return True  # each sample's paths, marched through g.marched

    def strips(self, scenes, options) -> str | None:
        if options.bounces.enabled:  # (its options exclude them; a hand-made Options)
            return "prefiltered with internal bounces"
        return uniform_roughness(scenes)

    def shade(self, g, lighting, materials, options, state) -> Shaded:
        return Shaded(*render_prefiltered(g, lighting, materials, options))


METHOD = Prefiltered()

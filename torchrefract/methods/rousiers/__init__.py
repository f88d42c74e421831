"""Method ``rousiers``: de Rousiers et al. 2012, Real-Time Rendering of Rough Refraction.

Per object pixel (all pixels of the batch at once, compacted; :func:`render_rousiers` in
:mod:`.shade` runs these steps):

1. Front interface (:mod:`.lobes`): the SG fit of the Walter BTDF and BRDF (``sgfit``,
   eqs. 8-9) gives the transmitted lobe (energy E_t1, sharpness k_t1, axis p_t1) and the
   reflected lobe (E_r, k_r, p_r) for the view angle, the IOR and the local roughness.
2. Cone tracing (sec. 4.3, :mod:`.cone`): four rays at theta_b = acos(0.25^(1 / (k_t1 + 1)))
   (eq. 12) around p_t1 bound 75% of the lobe; they and the axis are marched through the
   back-face buffer (``march``). The screen positions of the four exits give the footprint.
3. Geometry filtering (sec. 4.2, :mod:`.cone`): the back-face NDF mip (Toksvig, ``ndf``) is
   read at the footprint's scale; its spread gives kappa_G (eq. 11), which is convolved
   with the exit roughness's Blinn-Phong exponent (eq. 10).
4. Exit interface (:mod:`.exit`): the mean back normal is the proxy surface; the SG table
   for leaving the glass (eta = 1 / ior) at the angle between p_t1 and that normal, with
   the convolved roughness, gives the exit lobe (E_t2, k_t2, p_t2), per exit rule (``tir``)
   and lobe width (``spread``; ours by default, ``paper`` the paper's).
5. The environment is read from the SG-pre-convolved pyramid (``sgenv``, sec. 4.1) around
   p_t2 with the lobe's sharpness; the front reflection likewise around p_r.

    L = E_r L_env(p_r, k_r) + E_t1 E_t2 exp(-sigma s) L_env(p_t2, k)

With ``internal_bounces`` (ours, beyond the paper; :mod:`.bounces`) the light the exit
reflects inside is followed from interface to interface. The measurements behind the
defaults and constants are in docs/decisions_rousiers.md.
"""

from __future__ import annotations

from torchrefract.methods.base import Method, Shaded, uniform_roughness
from torchrefract.methods.rousiers.cone import bounding_angle
from torchrefract.methods.rousiers.options import DIFFUSE_VAR, RousiersOptions
from torchrefract.methods.rousiers.shade import render_rousiers


class Rousiers(Method):
    """de Rousiers et al. 2012, rough refraction by cone tracing (package docstring)."""

    name = "rousiers"
    Options = RousiersOptions

    def shades_samples(self, options, materials) -> bool:
        # the NDF mips (spread: paper) are read over the frame, and the plane cone's exit
        # normals at its resolution, which the one-sample frame's back layer coarsens
        # (docs/decisions.md, "Sparse supersampling"); a roughness map's coverage is read
        # from that layer (Marched.frame_back) at the footprint's own scale
        return options.spread == "rays" and options.cone_rays == "march"

    def strips(self, scenes, options) -> str | None:
        if options.spread != "rays":
            return "rousiers options other than spread: rays"
        if options.cone_rays != "march":
            return ("cone_rays: plane (it reads the back layer's normals, a strip holds its "
                    "own only)")
        return uniform_roughness(scenes)

    def marches_front(self, options) -> bool:
        return options.bounces.enabled

    def shade(self, g, lighting, materials, options, state) -> Shaded:
        return Shaded(*render_rousiers(g, lighting, materials, options))


METHOD = Rousiers()

__all__ = ["DIFFUSE_VAR", "METHOD", "Rousiers", "RousiersOptions", "bounding_angle",
           "render_rousiers"]

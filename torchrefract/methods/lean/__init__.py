"""Methods ``lean`` and ``gsr``: Dai and Wyman 2012, Real-Time Rough Refraction via LEAN
Mapping and Gaussian Sum Reduction (I3D poster; seed 003).

de Rousiers et al. reduce the back surface inside the cone's footprint to one mean normal
and one isotropic spread (Toksvig), with roughness maps split into a few fixed levels. Dai and
Wyman keep the back layer's normal distribution as moments:

1. Front interface: the SG lobes of the rough front surface (``rousiers``' step 1; the
   Gaussian BTDF whose width comes from the local roughness).
2. The cone is marched through the back layer (``rousiers``' step 2): its footprint.
3. LEAN (Olano and Baker 2010, :mod:`.moments`): per back pixel the first and second moments
   of the normal's slopes, the second including the pixel's own microfacet variance from its
   (varying) roughness, MIP-filtered linearly; at the footprint Sigma = M - B B^T is an
   anisotropic Gaussian NDF, roughness and geometry in one.
4. Exit: the NDF and the front lobe convolved through the exit refraction into an
   anisotropic outgoing lobe (:mod:`.lobes`), read by EWA (Mavridis and Papaioannou 2011,
   :mod:`torchrefract.lighting.ewa`) from the SG pyramid or, with ``env_lookup: mip``, a box
   MIP at the lobe's variance (Lee et al. 2008, :mod:`torchrefract.lighting.env_mips`).
5. ``gsr`` (Runnalls 2007): the normals split into K hemisphere subdivisions before the
   merge, so a footprint over two facets (a v-groove, a crease) gives two lobes, each with
   its own exit refraction and energy, summed.

Internal bounces, ``tir`` rules, sphere lights and absorption are ``rousiers``'. Where the
poster says it fails (ghosting at subdivision boundaries, sawtooth transmission, lobes that
do not shrink on curved back surfaces) the tests measure it (tests/test_lean.py). Ours,
beyond the poster (each an option, the poster's way kept): ``spread: rays`` (the marched
bounding rays give the lobe's width, so curved back surfaces focus it; ``gsr`` splits only
where the normals form separate groups), ``roughness_lobes: 2`` (a roughness map's jump
inside a footprint gives a sharp and a wide lobe, not their average). Measurements:
docs/decisions_lean.md.
"""

from __future__ import annotations

from torchrefract.methods.base import Method, Shaded
from torchrefract.methods.lean.moments import reads_no_moments
from torchrefract.methods.lean.options import GsrOptions, LeanOptions
from torchrefract.methods.lean.shade import render_lean


class Lean(Method):
    """LEAN-mapped rough refraction (package docstring, steps 1-4)."""

    name = "lean"
    Options = LeanOptions

    def shades_samples(self, options, materials) -> bool:
        # without a moments pyramid each sample reads its own G-buffer and the marched
        # layers only (the pyramid and the plane cone's exit normals are the frame's)
        return (reads_no_moments(1, options.spread, materials.has_maps)
                and options.cone_rays == "march")

    def shade(self, g, lighting, materials, options, state) -> Shaded:
        return Shaded(*render_lean(g, lighting, materials, options, 1, options.spread))


class Gsr(Method):
    """Gaussian sum reduction: K lobes per footprint (package docstring, step 5)."""

    name = "gsr"
    Options = GsrOptions

    def shade(self, g, lighting, materials, options, state) -> Shaded:
        return Shaded(*render_lean(g, lighting, materials, options, options.subdivisions,
                                   options.spread))


LEAN = Lean()
GSR = Gsr()

__all__ = ["GSR", "Gsr", "GsrOptions", "LEAN", "Lean", "LeanOptions", "render_lean"]

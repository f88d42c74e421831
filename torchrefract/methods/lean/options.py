"""Settings of ``lean`` and ``gsr`` (Dai and Wyman 2012); the march and exit rule are
``rousiers``' (:mod:`torchrefract.methods.rousiers.options` explains them)."""

from __future__ import annotations

from dataclasses import dataclass

from torchrefract.optics.exit_rule import TIR_RULES
from torchrefract.options import nested, option
from torchrefract.shading.bounces import BounceSettings


@dataclass(frozen=True)
class _Shared:
    """Fields both methods share (module docstring)."""

    tir: str = option("conserve", choices=TIR_RULES)
    """Exit rule: ``conserve``, ``clamp`` (the papers') or ``reflect``."""
    cone_rays: str = option("march", choices=("march", "plane"))
    """Footprint rays: marched (de Rousiers) or intersected with the exit's tangent plane."""
    march_steps: int = option(24, minimum=1, maximum=4096, integer=True)
    """Coarse samples of the central ray's march."""
    cone_march_steps: int = option(4, minimum=1, maximum=4096, integer=True)
    """Coarse samples of each bounding ray's march."""
    refine_steps: int = option(8, minimum=0, maximum=64, integer=True)
    """Bisection iterations of the central ray and the internal bounces."""
    cone_refine_steps: int = option(3, minimum=0, maximum=64, integer=True)
    """Bisection iterations of each bounding ray."""
    ewa_taps: int = option(4, minimum=1, maximum=16, integer=True)
    """Isotropic taps along an anisotropic lobe's major axis (EWA, Mavridis and Papaioannou
    2011; 1: one isotropic lobe of the same variance)."""
    roughness_lobes: int = option(2, choices=(1, 2))
    """Exit lobes per subdivision for the roughness over the footprint: 2 (ours) matches the
    mean and spread of the microfacet variance (a roughness map's jump gives a sharp and a
    wide lobe), 1 merges them (the poster)."""
    env_lookup: str = option("sg", choices=("sg", "mip"))
    """``sg``: the exact SG-pre-convolved pyramid; ``mip``: a box MIP read at the lobe's
    variance, two levels interpolated (Lee et al. 2008, the poster's)."""
    spread: str = option("rays", choices=("paper", "rays"))
    """The exit lobes' geometric width (:mod:`.lobes`): ``paper`` (each lobe: its NDF and
    the front lobe convolved through the exit, the poster) or ``rays`` (ours: the four
    marched bounding rays' exit directions give the width, so a curved back surface focuses
    the lobe; ``gsr`` splits into its subdivisions' lobes, as ``paper``, only as far as the
    footprint's normals form separate groups (:func:`.moments.separation`): a smooth
    surface is not ghosted)."""
    bounces: BounceSettings = nested(BounceSettings)
    """Internal reflections (keys ``internal_bounces``, ``bounce_tolerance``,
    ``max_internal_bounces``, ``bounce_march_steps``, ``bounce_rays``)."""


@dataclass(frozen=True)
class LeanOptions(_Shared):
    """Settings of ``lean`` (``method_options`` in a scene)."""


@dataclass(frozen=True)
class GsrOptions(_Shared):
    """Settings of ``gsr`` (``method_options`` in a scene)."""

    subdivisions: int = option(4, minimum=1, maximum=8, integer=True)
    """Hemisphere subdivisions K: the footprint's normals give K Gaussians, each its own exit
    lobe (1 is ``lean`` with ``spread: paper``)."""


__all__ = ["GsrOptions", "LeanOptions"]

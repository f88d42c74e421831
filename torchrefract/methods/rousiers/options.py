"""Settings of ``rousiers`` and its one fixed constant (measurements behind the defaults:
docs/decisions_rousiers.md)."""

from __future__ import annotations

from dataclasses import dataclass

from torchrefract.optics.exit_rule import TIR_RULES
from torchrefract.options import nested, option
from torchrefract.shading.bounces import BounceSettings

DIFFUSE_VAR = 0.2
"""Internal bounces under ``tir: conserve``: the angular variance (per axis, radians^2;
~26 degrees standard deviation) at which a reflected lobe counts as diffuse. At each
interface the fraction 1 - exp(-var / DIFFUSE_VAR) of what it reflects inside leaves there
in closed form, as at the last interface (:mod:`.bounces`): one ray cannot stand for a lobe
that wide. Chosen on the suite (docs/decisions_rousiers.md)."""


@dataclass(frozen=True)
class RousiersOptions:
    """Settings of ``rousiers`` (``method_options`` in a scene)."""

    tir: str = option("conserve", choices=TIR_RULES)
    """Exit rule (:mod:`.exit`): ``conserve``, ``clamp`` (the paper's) or ``reflect``."""
    cone_rays: str = option("march", choices=("march", "plane"))
    """Footprint rays: ``march`` (the paper: march the four bounding rays) or ``plane``
    (intersect them with the exit point's tangent plane: 5x fewer march steps; less
    accurate where the exit magnifies, near the critical angle at high IOR:
    docs/decisions.md, "Marched cone rays by default")."""
    spread: str = option("rays", choices=("paper", "paper+front", "rays"))
    """How the exit lobe gets its width beyond the exit roughness (:mod:`.exit`):
    ``paper`` (footprint NDF convolved with the BTDF, eq. 10), ``paper+front`` (that, plus
    the front lobe's spread magnified by the exit refraction) or ``rays`` (the four marched
    bounding rays refracted at their own exit normals)."""
    march_steps: int = option(24, minimum=1, maximum=4096, integer=True)
    """Coarse samples of the central ray's march (bisection then refines the hit and the
    exact triangle is intersected)."""
    cone_march_steps: int = option(4, minimum=1, maximum=4096, integer=True)
    """Coarse samples of each bounding ray's march (only the footprint and the lobe's
    spread need them)."""
    refine_steps: int = option(8, minimum=0, maximum=64, integer=True)
    """Bisection iterations after the coarse search of the central ray and the internal
    bounces (fewer lose more exits where the ray leaves near a silhouette)."""
    cone_refine_steps: int = option(3, minimum=0, maximum=64, integer=True)
    """Bisection iterations of each bounding ray's march (the exit is then the exact hit
    with the triangle found there, walked to the one containing it)."""
    roughness_levels: int = option(4, minimum=2, maximum=16, integer=True)
    """With a roughness map: how many roughness levels the exit interface is split into
    (coverage ratios, sec. 5.1)."""
    bounces: BounceSettings = nested(BounceSettings)
    """Internal reflections (keys ``internal_bounces``, ``bounce_tolerance``,
    ``max_internal_bounces``, ``bounce_march_steps``, ``bounce_rays``)."""


__all__ = ["DIFFUSE_VAR", "RousiersOptions"]

"""Settings of ``sh`` (``method_options`` in a scene; measurements: docs/decisions_sh.md)."""

from __future__ import annotations

from dataclasses import dataclass

from torchrefract.methods.sh.basis import MAX_ORDER, WINDOWS
from torchrefract.methods.sh.tracer import TRACERS
from torchrefract.options import option

EXIT_WEIGHTS = ("conserve", "path")
BRANCHES = ("tir", "greedy")


@dataclass(frozen=True)
class SHOptions:
    """Settings of ``sh``. The first six choose the precomputed table (and its cache
    file); the others only how it is read."""

    view_rings: int = option(32, minimum=2, maximum=64, integer=True)
    """Polar rings of the view directions per surface sample; 2 rings^2 directions in all
    (32: the paper's 2048)."""
    surface_samples: int = option(32768, minimum=16, maximum=1 << 22, integer=True)
    """Target number of surface samples (the per-triangle lattice rate follows; a mesh
    denser than this gets one sample per vertex)."""
    max_bounces: int = option(16, minimum=1, maximum=256, integer=True)
    """Most interfaces a precomputed path meets after entering (then it leaves as it is)."""
    branch: str = option("tir", choices=BRANCHES)
    """Which branch a precomputed path follows at an interface: ``greedy`` (the paper's
    most significant Fresnel branch: reflected where F > 1/2) or ``tir`` (ours: reflected
    only under total internal reflection; the greedy switch at F = 1/2 is a jump in the
    mapping that rings over the whole hemisphere: on a sphere the order-8 median direction
    error falls from 0.045 to 0.009 rad, docs/decisions_sh.md)."""
    branches: int = option(1, choices=(1, 2))
    """Branches stored per path: 1 (the followed path only) or 2 (also the Fresnel-reflected
    branch at the first interface where the path refracts out from inside, e.g. the cavity
    wall or a bead, with its share F of the energy; the main path's weight is reduced by the
    same share at shading; a second table of 7 channels, docs/decisions_sh.md)."""
    tracer: str = option("auto", choices=TRACERS)
    """Ray caster of the precomputation: ``embree`` (embreex), ``mitsuba`` (LLVM variant)
    or ``auto`` (the first available)."""
    order: int = option(MAX_ORDER, minimum=0, maximum=MAX_ORDER, integer=True)
    """Highest SH band evaluated (the paper's figure 12: 1, 4, 8)."""
    window: str = option("gauss", choices=WINDOWS)
    """Ringing window on the SH weights (sec. 4.3): the semi-Gaussian, or ``none``."""
    window_width: float = option(1.0, minimum=0.05, maximum=100.0)
    """Width of the semi-Gaussian in units of (order + 1): exp(-(l / (w (L + 1)))^2 / 2)."""
    exit_weight: str = option("conserve", choices=EXIT_WEIGHTS)
    """Energy leaving along the path: ``conserve`` (ours: all that entered leaves along it,
    less the rough exit's losses, as ``tir: conserve`` of the other methods) or ``path``
    (the traced branch's Fresnel product only: the light of the branches not followed is
    lost)."""


__all__ = ["EXIT_WEIGHTS", "SHOptions"]

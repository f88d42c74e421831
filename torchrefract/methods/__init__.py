"""Rendering methods. Each is a pure function of a GBuffer, the lighting and the materials.

Registry: name -> (options parser, render function). ``torchrefract.render`` dispatches here.
"""

from __future__ import annotations

from .prefiltered import PrefilteredOptions, render_prefiltered
from .rousiers import RousiersOptions, render_rousiers
from .specular import SpecularOptions, render_specular

METHODS = {
    "specular": (SpecularOptions.from_dict, render_specular),
    "prefiltered": (PrefilteredOptions.from_dict, render_prefiltered),
    "rousiers": (RousiersOptions.from_dict, render_rousiers),
}

__all__ = ["METHODS", "PrefilteredOptions", "RousiersOptions", "SpecularOptions",
           "render_prefiltered", "render_rousiers", "render_specular"]

"""Rendering methods. Each is a pure function of a GBuffer, the lighting and the materials.

Registry: name -> (options parser, render function). ``torchrefract.render`` dispatches here.
"""

from __future__ import annotations

from .prefiltered import PrefilteredOptions, render_prefiltered
from .specular import SpecularOptions, render_specular

METHODS = {
    "specular": (SpecularOptions.from_dict, render_specular),
    "prefiltered": (PrefilteredOptions.from_dict, render_prefiltered),
}

__all__ = ["METHODS", "PrefilteredOptions", "SpecularOptions", "render_prefiltered",
           "render_specular"]

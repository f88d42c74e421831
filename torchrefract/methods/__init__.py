"""Rendering methods. Each is a pure function of a GBuffer, the lighting and the materials.

Registry: name -> (options parser, render function). ``torchrefract.render`` dispatches here.
"""

from __future__ import annotations

from torchrefract.auto import AutoOptions, render_auto
from torchrefract.methods.prefiltered import PrefilteredOptions, render_prefiltered
from torchrefract.methods.reference import ReferenceOptions, render_reference_method
from torchrefract.methods.rousiers import RousiersOptions, render_rousiers
from torchrefract.methods.specular import SpecularOptions, render_specular

METHODS = {
    "specular": (SpecularOptions.from_dict, render_specular),
    "prefiltered": (PrefilteredOptions.from_dict, render_prefiltered),
    "rousiers": (RousiersOptions.from_dict, render_rousiers),
    "reference": (ReferenceOptions.from_dict, render_reference_method),
    "auto": (AutoOptions.from_dict, render_auto),  # resolved per scene by render()
}

# Methods that need the Scene objects themselves (not only the tensors).
NEEDS_SCENES = ("reference",)

__all__ = ["METHODS", "NEEDS_SCENES", "AutoOptions", "PrefilteredOptions", "ReferenceOptions",
           "RousiersOptions", "SpecularOptions", "render_prefiltered", "render_reference_method",
           "render_rousiers", "render_specular"]

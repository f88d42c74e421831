"""Rendering methods. Each is a pure function of a GBuffer, the lighting and material tensors.

Registry: name -> (options parser, render function). ``torchrefract.render`` dispatches here.
"""

from __future__ import annotations

from .specular import SpecularOptions, render_specular

METHODS = {
    "specular": (SpecularOptions.from_dict, render_specular),
}

__all__ = ["METHODS", "SpecularOptions", "render_specular"]

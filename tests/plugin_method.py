"""A third-party method for tests/test_methods.py: the object's pixels in one flat color,
the environment elsewhere (a method outside the package, registered by name)."""

from dataclasses import dataclass

import torch

from torchrefract.methods.base import Method, Shaded
from torchrefract.options import option
from torchrefract.shading.background import background


@dataclass(frozen=True)
class FlatOptions:
    gray: float = option(0.25, minimum=0.0, maximum=1.0)
    """The object's radiance (all three channels)."""


class Flat(Method):
    name = "flat"
    Options = FlatOptions

    def shade(self, g, lighting, materials, options, state) -> Shaded:
        b, h, w = g.shape
        rgb = background(g, lighting).view(b, h, w, 3)
        rgb = torch.where(g.front.mask[..., None], torch.full_like(rgb, options.gray), rgb)
        return Shaded(rgb, {"flat": g.front.mask[..., None].float()})


METHOD = Flat()

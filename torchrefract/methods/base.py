"""The method interface: what every renderer of a G-buffer implements.

A method is an object with a ``name``, an ``Options`` dataclass (fields made with
:func:`torchrefract.options.option`), ``prepare`` (per-scene or per-mesh work done before
shading: Mitsuba's scene, a precomputed transfer; cached by the method) and ``shade``, a
pure function of the G-buffer, the lighting, the materials, the options and that state.
The registry (:mod:`torchrefract.methods.registry`) finds methods by name.

Example (a method that shows the environment behind the object, unrefracted)::

    class Clear(Method):
        name = "clear"

        def shade(self, g, lighting, materials, options, state):
            ...
            return Shaded(radiance, {})

    torchrefract.register_method("clear", Clear())
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Sequence

import torch

from torchrefract.options import parse_options


@dataclass(frozen=True)
class NoOptions:
    """A method without settings."""


@dataclass(frozen=True)
class Shaded:
    """What ``shade`` returns for B views at (H, W) (sub-)pixels.

    Attributes:
        radiance: (B, H, W, 3) linear RGB, background included.
        passes: the method's own buffers, name -> (B, H, W, C), on object pixels and 0 at
            every other (sub-)pixel (so that one sample per pixel needs no masking:
            ``result.finish_pass``; tests/test_methods.py holds every method to it).
    """

    radiance: torch.Tensor
    passes: dict[str, torch.Tensor]


class Method:
    """Base of every method: set ``name`` and ``Options``; implement ``shade`` (and
    ``prepare`` where a method needs the scenes themselves or precomputes)."""

    name: str = ""
    Options: type = NoOptions
    excluded_options: tuple[str, ...] = ()
    """Keys of ``Options``' nested groups this method does not accept."""
    shades_object_index: bool = True
    """``shade`` reads the object (sub-)pixels ``g.object_index()`` names, so adaptive
    supersampling (:mod:`torchrefract.geometry.adaptive`) may name fewer; a method that
    renders the scene its own way (``reference``) sets False and is sampled uniformly."""
    devices: tuple[str, ...] = ("cpu", "cuda")
    """Device types ``shade`` runs on (``RenderSettings.device``). A method whose shading
    is not torch code on the G-buffer's device (Mitsuba's ``reference``) lists ``cpu``
    alone: it shades on the CPU and :func:`torchrefract.render` moves its result."""

    def shades_samples(self, options: Any, materials: Any) -> bool:
        """Whether ``shade``, with these options and materials, reads the G-buffer only at
        the (sub-)pixels it shades and the frame around them only through the marched
        layers (``g.marched``): then a G-buffer of scattered samples may be shaded, and a
        supersampled render shades only the pixels whose samples can differ
        (:mod:`torchrefract.geometry.subsamples`). Default False."""
        return False

    def strips(self, scenes: Sequence[Any], options: Any) -> str | None:
        """Why ``shade`` cannot render these scenes in strips of rows over the frame's
        marched layers (:mod:`torchrefract.large`: frames too large for one G-buffer), or
        None where it can: its fused kernel reads the frame only through the marched layers
        and its own (sub-)pixels. Default: it cannot."""
        return f"method {self.name!r} has no strips"

    def marches_front(self, options: Any) -> bool:
        """Whether ``shade`` marches the front layer's ids as well as the back layer's
        (internal bounces meet the front faces from inside), so that strips keep both for
        the whole frame. Default False."""
        return False

    def parse(self, options: dict | None, source: str | None = None) -> Any:
        """``method_options`` checked and turned into ``Options`` (ConfigError otherwise)."""
        return parse_options(self.Options, options, source, self.name, self.excluded_options)

    def prepare(self, scenes: Sequence[Any], options: Any) -> Any:
        """State for :meth:`shade` from the batch's scenes (default: none)."""
        return None

    def shade(self, g, lighting, materials, options, state) -> Shaded:
        """Shade a G-buffer: radiance (B, H, W, 3) and the method's passes."""
        raise NotImplementedError(f"method {self.name!r} has no shade()")

    def __repr__(self) -> str:
        return f"<method {self.name!r}>"


def uniform_roughness(scenes: Sequence[Any]) -> str | None:
    """:meth:`Method.strips`' reason where a scene has a roughness map (the strips' fused
    kernels read one roughness per view), else None."""
    if any(s.material.roughness_map is not None for s in scenes):
        return "a roughness map (strips need uniform roughness)"
    return None


class Planned(Method):
    """A method of the design that is not implemented yet: its scenes load (any options),
    and rendering raises NotImplementedError naming the issue that builds it."""

    def __init__(self, name: str, issue: str):
        self.name, self.issue = name, issue

    def parse(self, options: dict | None, source: str | None = None) -> Any:
        return dict(options or {})

    def prepare(self, scenes, options):
        raise NotImplementedError(
            f"method {self.name!r} is not implemented yet ({self.issue}); render with "
            f"method='rousiers' (CLI: --method rousiers) meanwhile")

    def shade(self, g, lighting, materials, options, state) -> Shaded:
        return self.prepare((), options)


__all__ = ["Method", "NoOptions", "Planned", "Shaded", "uniform_roughness"]

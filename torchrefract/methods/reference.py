"""Method ``reference``: Mitsuba 3 path tracing of the same scene (ground truth, timing).

The image comes from :func:`torchrefract.reference.render_reference` (Mitsuba's LLVM
variant when it works on the machine, else ``scalar_rgb``); the G-buffer passes come from
our own visibility passes as for every method, so a reference render has the same channels.
With ``samples_per_pixel = n`` Mitsuba renders the n x n sub-pixel grid (``spp`` samples
each), which the renderer box-filters like any other method.
Needs the ``reference`` extra: ``pip install 'torchrefract[reference]'``.
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np
import torch

from ..checks import check_number, check_option_keys
from ..gbuffer import GBuffer
from ..lighting import Lighting
from ..materials import MaterialBatch
from ..scene import Camera, Scene


@dataclass(frozen=True)
class ReferenceOptions:
    """Settings of ``reference`` (``method_options`` in a scene)."""

    spp: int = 64
    """Samples per (sub-)pixel."""
    seed: int = 0
    """Sampler seed."""
    max_depth: int = 64
    """Longest path: 64 is the spec's truth; 3 is what a two-interface method models."""

    METHOD = "reference"

    @classmethod
    def from_dict(cls, d: dict, source: str | None = None) -> "ReferenceOptions":
        check_option_keys(d, [f.name for f in fields(cls)], cls.METHOD, source)
        return cls(
            spp=check_number(d.get("spp", 64), "method_options.spp", source, minimum=1,
                             maximum=1 << 20, integer=True),
            seed=check_number(d.get("seed", 0), "method_options.seed", source, minimum=0,
                              integer=True),
            max_depth=check_number(d.get("max_depth", 64), "method_options.max_depth",
                                   source, minimum=1, maximum=1024, integer=True),
        )


def render_reference_method(g: GBuffer, lighting: Lighting, materials: MaterialBatch,
                            options: ReferenceOptions = ReferenceOptions(), *,
                            scenes: tuple[Scene, ...] = ()
                            ) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """Render each scene with Mitsuba 3 at the G-buffer's (sub-)pixel grid.

    Returns:
        radiance (B, H, W, 3) and no extra passes (the geometry passes come from ``g``).
    """
    from ..reference import render_reference  # noqa: PLC0415 (optional dependency)

    n = g.supersample
    out = []
    for s in scenes:
        c = s.camera
        sub = s.replace(camera=Camera(eye=c.eye, target=c.target, up=c.up,
                                      yfov_deg=c.yfov_deg, width=c.width * n,
                                      height=c.height * n, samples_per_pixel=1))
        rgb, _ = render_reference(sub, spp=options.spp, seed=options.seed,
                                  max_depth=options.max_depth)
        out.append(torch.from_numpy(np.ascontiguousarray(rgb)))
    return torch.stack(out).float(), {}

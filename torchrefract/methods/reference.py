"""Method ``reference``: Mitsuba 3 path tracing of the same scene (ground truth, timing).

The image comes from :func:`torchrefract.truth.mitsuba.render_reference` (Mitsuba's LLVM
variant when it works on the machine, else ``scalar_rgb``); the G-buffer passes come from
our own visibility passes as for every method, so a reference render has the same channels.
With ``samples_per_pixel = n`` Mitsuba renders the n x n sub-pixel grid (``spp`` samples
each), which the renderer box-filters like any other method.

``denoise: true`` runs Intel Open Image Denoise (PyPI ``pyoidn``, ``RT`` filter, ``hdr``,
quality ``high``) on the Mitsuba image at the output resolution: the sub-pixel grid is
box-filtered first, denoised, and repeated back onto the grid, so the renderer's own box
filter returns exactly the denoised pixels (what a user denoising a Mitsuba render at
``samples_per_pixel**2 * spp`` samples per pixel gets). Color only, no albedo or normal
buffers: OIDN wants auxiliary images with the same pixel filter as the color (our G-buffer
is one point sample per sub-pixel, Mitsuba's color is box-filtered random samples, and OIDN
warns that aliased auxiliaries put artifacts on edges), and the albedo of a rough glass
object over a visible environment map has no clean definition (OIDN's guidance of 1 for
glass plus the environment behind it would need a second, noisy Mitsuba pass).
Needs the ``reference`` extra: ``pip install 'torchrefract[reference]'``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from torchrefract.geometry.gbuffer import GBuffer
from torchrefract.lighting.lights import Lighting
from torchrefract.methods.base import Method, Shaded
from torchrefract.optics.materials import MaterialBatch
from torchrefract.options import option
from torchrefract.scene.model import Camera, Scene


@dataclass(frozen=True)
class ReferenceOptions:
    """Settings of ``reference`` (``method_options`` in a scene)."""

    spp: int = option(64, minimum=1, maximum=1 << 20, integer=True)
    """Samples per (sub-)pixel."""
    seed: int = option(0, minimum=0, integer=True)
    """Sampler seed."""
    max_depth: int = option(64, minimum=1, maximum=1024, integer=True)
    """Longest path: 64 is the spec's truth; 3 is what a two-interface method models."""
    denoise: bool = option(False, boolean=True)
    """Denoise the image with Intel Open Image Denoise (``pyoidn``; HDR color only)."""


_PYOIDN_HINT = ("method 'reference' with denoise: true needs Intel Open Image Denoise (PyPI "
                "'pyoidn'): pip install 'torchrefract[reference]'")


def _pyoidn():
    """Import ``pyoidn`` or raise an ImportError that says how to install it."""
    try:
        import pyoidn  # noqa: PLC0415 (optional dependency)
    except ImportError as exc:
        raise ImportError(f"{_PYOIDN_HINT} ({exc})") from exc
    return pyoidn


def denoise_oidn(rgb: torch.Tensor, n: int = 1) -> torch.Tensor:
    """Denoise a linear HDR image with OIDN at pixel resolution.

    Args:
        rgb: (H*n, W*n, 3) linear radiance on an n x n sub-pixel grid.
        n: sub-pixels per pixel side.

    Returns:
        (H*n, W*n, 3) float32: the denoised (H, W) image repeated n x n times, so that a box
        filter of it gives the denoised pixels exactly.

    Example:
        >>> denoise_oidn(torch.rand(64, 64, 3)).shape    # doctest: +SKIP
        torch.Size([64, 64, 3])
    """
    oidn = _pyoidn()
    x = torch.nan_to_num(rgb.float(), nan=0.0, posinf=0.0).clamp(min=0.0)  # OIDN: >= 0
    if n > 1:
        x = F.avg_pool2d(x.permute(2, 0, 1)[None], n)[0].permute(1, 2, 0)  # (H, W, 3)
    out = oidn.denoise(np.ascontiguousarray(x.numpy()), hdr=True, quality="high")
    y = torch.from_numpy(np.asarray(out, dtype=np.float32)).clamp(min=0.0)  # (H, W, 3)
    if n > 1:
        y = y.repeat_interleave(n, 0).repeat_interleave(n, 1)  # (H*n, W*n, 3)
    return y.contiguous()


def render_reference_method(g: GBuffer, lighting: Lighting, materials: MaterialBatch,
                            options: ReferenceOptions = ReferenceOptions(), *,
                            scenes: tuple[Scene, ...] = ()
                            ) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """Render each scene with Mitsuba 3 at the G-buffer's (sub-)pixel grid.

    Returns:
        radiance (B, H, W, 3) and no extra passes (the geometry passes come from ``g``).
    """
    from torchrefract.truth.mitsuba import render_reference  # noqa: PLC0415 (optional dependency)

    if options.denoise:
        _pyoidn()  # fail before minutes of path tracing, not after
    n = g.supersample
    out = []
    for s in scenes:
        c = s.camera
        sub = s.replace(camera=Camera(eye=c.eye, target=c.target, up=c.up,
                                      yfov_deg=c.yfov_deg, width=c.width * n,
                                      height=c.height * n, samples_per_pixel=1))
        rgb, _ = render_reference(sub, spp=options.spp, seed=options.seed,
                                  max_depth=options.max_depth)
        img = torch.from_numpy(np.ascontiguousarray(rgb))  # (H*n, W*n, 3)
        out.append(denoise_oidn(img, n) if options.denoise else img)
    return torch.stack(out).float(), {}


class Reference(Method):
    """Mitsuba 3 path tracing of the same scenes (module docstring)."""

    name = "reference"
    shades_object_index = False  # Mitsuba renders every sub-pixel itself
    devices = ("cpu",)  # Mitsuba renders on its own; the result is moved
    Options = ReferenceOptions

    def prepare(self, scenes, options):
        return tuple(scenes)  # Mitsuba renders the scenes themselves

    def shade(self, g, lighting, materials, options, state) -> Shaded:
        return Shaded(*render_reference_method(g, lighting, materials, options, scenes=state))


METHOD = Reference()

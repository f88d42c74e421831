"""``auto``'s first pass: evidence from the scene itself, not from similar scenes.

Each scene is rendered small (``PASS_SIZE`` pixels on its longer side, one sample per
pixel) with two variants, a cheap one and the most accurate one, and the pass measures how
far their images diverge on the object's pixels. Where the cheap image is close to the
accurate one, the cheap variant cannot be far behind it against any truth; where they
diverge, the table cannot tell which is right on this scene, and the accurate one is kept
(docs/decisions.md, "`auto`'s first pass"; figures in docs/validation.md).

Divergence: the mean over object pixels (coverage > 0.5 in the pass) of the largest
per-channel difference of the two 8-bit sRGB previews, in [0, 1]. It follows LDR-FLIP
between the two pass images (correlation 0.94 on the validation set's 64 scenes, FLIP about
3.3x it) without FLIP's package, which only the reference extras install. It is a
continuous function of the images, so of roughness and IOR wherever the variants' images
are.
"""

from __future__ import annotations

import dataclasses
import time

import numpy as np

from torchrefract.scene.model import Scene

PASS_SIZE = 32
"""Pixels on the pass's longer side (never more than the scene's own): at 32 the pass costs
~12 ms of one core against ~200 for the accurate variant at 128x128 with 2x2 sampling, and
its divergence ranks the validation scenes as at 64 (docs/validation.md)."""


def small(scene: Scene, size: int = PASS_SIZE) -> Scene:
    """``scene`` at ``size`` pixels on its longer side (aspect and field of view kept), one
    sample per pixel."""
    c = scene.camera
    k = min(1.0, size / max(c.width, c.height))
    cam = dataclasses.replace(c, width=max(1, round(c.width * k)),
                              height=max(1, round(c.height * k)), samples_per_pixel=1)
    return scene.replace(camera=cam)


def srgb01(rgb: np.ndarray) -> np.ndarray:
    """Linear (..., 3) radiance -> its 8-bit sRGB preview as floats in [0, 1]."""
    from torchrefract.output.images import linear_to_srgb8  # noqa: PLC0415

    return linear_to_srgb8(rgb).astype(np.float64) / 255.0


def divergence(a: np.ndarray, b: np.ndarray, coverage: np.ndarray) -> float:
    """Mean over object pixels (``coverage`` > 0.5) of the largest per-channel difference of
    the sRGB previews of two linear (H, W, 3) images; 0 without object pixels."""
    obj = coverage > 0.5
    if not obj.any():
        return 0.0
    return float(np.abs(srgb01(a) - srgb01(b)).max(-1)[obj].mean())


def divergences(scenes: list[Scene], cheap: tuple[str, dict], accurate: tuple[str, dict]
                ) -> tuple[list[float], float]:
    """Per scene the divergence of ``cheap``'s pass image from ``accurate``'s ((method,
    options) each), and the pass's seconds. Scenes of one pass resolution render in one
    batch per variant."""
    from torchrefract.render import render  # noqa: PLC0415
    from torchrefract.settings import current  # noqa: PLC0415

    # every pixel shaded, as the ramp was fitted (no lattice to interpolate at this size)
    settings = current().replace(adaptive=False)
    t0 = time.perf_counter()
    smalls = [small(s) for s in scenes]
    groups: dict[tuple[int, int], list[int]] = {}
    for i, s in enumerate(smalls):
        groups.setdefault((s.camera.width, s.camera.height), []).append(i)
    out = [0.0] * len(scenes)
    for idx in groups.values():
        imgs = []
        for method, opts in (cheap, accurate):
            r = render([smalls[i].replace(method=method, method_options=dict(opts))
                        for i in idx], settings=settings)
            imgs.append(r.radiance.detach().cpu().numpy())
        cov = r.coverage.detach().cpu().numpy()
        for j, i in enumerate(idx):
            out[i] = divergence(imgs[0][j], imgs[1][j], cov[j])
    return out, time.perf_counter() - t0


__all__ = ["PASS_SIZE", "divergence", "divergences", "small"]

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

Per region (``auto_regions``): inside the ramp, where the scene-level weight would render
both variants over the whole object, each variant is rendered only where it weighs. The
pass's per-pixel divergence (blurred by ``REGION_BLUR`` pass pixels, scaled up to the
scene's pixels) through the same ramp gives r(x) in [0, 1]; the accurate variant's weight is
r(x) against a threshold that slides with the scene-level weight w (:func:`region_weights`),
so it is 0 everywhere at w = 0 and 1 everywhere at w = 1 (continuous with the single picks)
and exactly 0 or 1 on the pixels whose divergence is clearly low or high (measured on the
validation set: docs/validation.md, "Per-pixel choice").
"""

from __future__ import annotations

import dataclasses
import time

import numpy as np
import torch

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


def divergence_map(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(H, W) largest per-channel difference of the sRGB previews of two linear (H, W, 3)
    images."""
    return np.abs(srgb01(a) - srgb01(b)).max(-1)


def object_mean(div_map: np.ndarray, coverage: np.ndarray) -> float:
    """Mean of a divergence map over object pixels (``coverage`` > 0.5); 0 without any."""
    obj = coverage > 0.5
    return float(div_map[obj].mean()) if obj.any() else 0.0


def divergence(a: np.ndarray, b: np.ndarray, coverage: np.ndarray) -> float:
    """Mean over object pixels (``coverage`` > 0.5) of the largest per-channel difference of
    the sRGB previews of two linear (H, W, 3) images; 0 without object pixels."""
    return object_mean(divergence_map(a, b), coverage)


REGION_BLUR = 1.0
"""Standard deviation, in pass pixels, of the Gaussian that smooths the per-pixel divergence
before it is scaled up (object pixels only, normalized by the blurred coverage)."""
REGION_WIDTH = 1.0
"""Width of the accurate variant's per-pixel ramp in r (:func:`region_weights`): 1, r itself
at w = 1/2; narrower, a harder split (fitted on the fit half: docs/validation.md)."""


def divergences(scenes: list[Scene], cheap: tuple[str, dict], accurate: tuple[str, dict]
                ) -> tuple[list[float], float]:
    """Per scene the divergence of ``cheap``'s pass image from ``accurate``'s ((method,
    options) each), and the pass's seconds (:func:`divergence_maps` without its maps)."""
    div, _, secs = divergence_maps(scenes, cheap, accurate)
    return div, secs


def divergence_maps(scenes: list[Scene], cheap: tuple[str, dict], accurate: tuple[str, dict]
                    ) -> tuple[list[float], list[tuple[np.ndarray, np.ndarray]], float]:
    """:func:`divergences`, and per scene its pass's (h, w) per-pixel divergence (the
    largest channel difference of the sRGB previews) and coverage. Scenes of one pass
    resolution render in one batch per variant."""
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
    maps: list[tuple[np.ndarray, np.ndarray]] = [None] * len(scenes)  # type: ignore[list-item]
    for idx in groups.values():
        imgs = []
        for method, opts in (cheap, accurate):
            r = render([smalls[i].replace(method=method, method_options=dict(opts))
                        for i in idx], settings=settings)
            imgs.append(r.radiance.detach().cpu().numpy())
        cov = r.coverage.detach().cpu().numpy()
        for j, i in enumerate(idx):
            m = divergence_map(imgs[0][j], imgs[1][j])
            out[i], maps[i] = object_mean(m, cov[j]), (m, cov[j])
    return out, maps, time.perf_counter() - t0


def _blur(x: torch.Tensor, sigma: float) -> torch.Tensor:
    """(1, 1, h, w) separable Gaussian blur (zero outside), radius 2 sigma."""
    r = max(1, int(round(2 * sigma)))
    t = torch.arange(-r, r + 1, dtype=torch.float64)
    g = torch.exp(-0.5 * (t / sigma) ** 2)
    g = g / g.sum()
    x = torch.nn.functional.conv2d(x, g.view(1, 1, 1, -1), padding=(0, r))
    return torch.nn.functional.conv2d(x, g.view(1, 1, -1, 1), padding=(r, 0))


def local_ramp(div_map: np.ndarray, coverage: np.ndarray, size: tuple[int, int],
               ramp: tuple[float, float], blur: float = REGION_BLUR) -> torch.Tensor:
    """r(x) (height, width) float32 in [0, 1]: the pass's per-pixel divergence on its object
    pixels (coverage > 0.5), blurred, normalized by the blurred coverage, scaled up
    bilinearly to ``size`` (the scene's pixels) and put through the ramp (lo, hi)."""
    obj = torch.from_numpy(coverage > 0.5).to(torch.float64)[None, None]
    d = torch.from_numpy(np.asarray(div_map, np.float64))[None, None] * obj
    if blur > 0:
        d, obj = _blur(d, blur), _blur(obj, blur)
    d = torch.nn.functional.interpolate(d, size=size, mode="bilinear", align_corners=False)
    obj = torch.nn.functional.interpolate(obj, size=size, mode="bilinear", align_corners=False)
    d = d / obj.clamp(min=1e-6)
    lo, hi = ramp
    return ((d - lo) / (hi - lo)).clamp(0.0, 1.0)[0, 0].to(torch.float32)


def region_weights(r: torch.Tensor, w: float, width: float = REGION_WIDTH) -> torch.Tensor:
    """The accurate variant's per-pixel weight for local ramp values ``r`` (:func:`local_ramp`)
    at scene-level weight ``w`` (its weight over the whole object without regions):
    clip((r - t) / width + 1/2, 0, 1), the threshold t = 1 + width / 2 - w (1 + width)
    sliding from above every r at w = 0 (weight 0 everywhere) to below every r at w = 1
    (weight 1 everywhere): continuous in w and in r."""
    t = 1.0 + width / 2.0 - w * (1.0 + width)
    return ((r - t) / width + 0.5).clamp(0.0, 1.0)


__all__ = ["PASS_SIZE", "REGION_BLUR", "REGION_WIDTH", "divergence", "divergence_map",
           "divergence_maps", "divergences", "local_ramp", "object_mean", "region_weights",
           "small"]

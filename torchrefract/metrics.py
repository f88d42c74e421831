"""Image error metrics against a reference (SCENE_SPEC.md, "Accuracy metrics").

- relMSE: mean over the selected pixels and channels of (x - ref)^2 / (ref^2 + 0.01).
- FLIP: NVIDIA's LDR-FLIP (``flip-evaluator``) of the sRGB previews (8-bit, exposure 0),
  averaged over the selected pixels of the per-pixel error map.
- PSNR: of the sRGB previews in [0, 1].
Each is given over the whole image and over object pixels (coverage > 0.5).
"""

from __future__ import annotations

import numpy as np

from .image_files import linear_to_srgb8


def relmse(x: np.ndarray, ref: np.ndarray, mask: np.ndarray | None = None) -> float:
    """Relative MSE of (H, W, 3) linear images over ``mask`` (H, W) (all pixels if None)."""
    e = (x.astype(np.float64) - ref) ** 2 / (ref.astype(np.float64) ** 2 + 0.01)
    return float(e[mask].mean() if mask is not None else e.mean())


def flip_map(x: np.ndarray, ref: np.ndarray, exposure: float = 0.0) -> np.ndarray:
    """(H, W) LDR-FLIP error map of the sRGB previews of two linear (H, W, 3) images."""
    import flip_evaluator  # noqa: PLC0415

    def srgb01(img):
        return np.ascontiguousarray(linear_to_srgb8(img, exposure).astype(np.float32) / 255.0)

    err, _, _ = flip_evaluator.evaluate(srgb01(ref), srgb01(x), "LDR", applyMagma=False)
    return np.asarray(err, dtype=np.float64).reshape(x.shape[:2])


def psnr(x: np.ndarray, ref: np.ndarray, mask: np.ndarray | None = None,
         exposure: float = 0.0) -> float:
    a = linear_to_srgb8(x, exposure).astype(np.float64) / 255.0
    b = linear_to_srgb8(ref, exposure).astype(np.float64) / 255.0
    e = (a - b) ** 2
    mse = float(e[mask].mean() if mask is not None else e.mean())
    return float("inf") if mse == 0 else 10.0 * np.log10(1.0 / mse)


def compare(x: np.ndarray, ref: np.ndarray, coverage: np.ndarray, exposure: float = 0.0
            ) -> dict[str, float]:
    """All metrics, whole image and object pixels (coverage > 0.5)."""
    obj = coverage > 0.5
    fm = flip_map(x, ref, exposure)
    return {
        "relmse": relmse(x, ref), "relmse_object": relmse(x, ref, obj),
        "flip": float(fm.mean()), "flip_object": float(fm[obj].mean()) if obj.any() else 0.0,
        "psnr": psnr(x, ref, None, exposure), "psnr_object": psnr(x, ref, obj, exposure),
    }


def flip_magma(x: np.ndarray, ref: np.ndarray, exposure: float = 0.0) -> np.ndarray:
    """(H, W, 3) uint8 error-map image: LDR-FLIP of the sRGB previews in the magma map."""
    import flip_evaluator  # noqa: PLC0415

    def srgb01(img):
        return np.ascontiguousarray(linear_to_srgb8(img, exposure).astype(np.float32) / 255.0)

    err, _, _ = flip_evaluator.evaluate(srgb01(ref), srgb01(x), "LDR", applyMagma=True)
    return np.clip(np.asarray(err) * 255.0 + 0.5, 0, 255).astype(np.uint8)

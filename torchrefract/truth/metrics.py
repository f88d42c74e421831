"""Image error metrics against a reference (SCENE_SPEC.md, "Accuracy metrics").

- relMSE: mean over the selected pixels and channels of (x - ref)^2 / (ref^2 + 0.01).
- FLIP: NVIDIA's LDR-FLIP (``flip-evaluator``) of the sRGB previews (8-bit, exposure 0),
  averaged over the selected pixels of the per-pixel error map.
- HDR-FLIP: NVIDIA's HDR-FLIP of the linear radiance (the LDR-FLIP maximum over the
  exposures FLIP chooses from the reference, ACES tone mapping, 67 pixels per degree), averaged
  like FLIP. It sees highlights above 1 that the 8-bit preview clips; the exposure range
  comes from the reference, so every test image of one reference is scored alike.
- PSNR: of the sRGB previews in [0, 1].
Each is given over the whole image and over object pixels (coverage > 0.5).
"""

from __future__ import annotations

import numpy as np

from torchrefract.output.images import linear_to_srgb8


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


# FLIP's ACES tone curve (a x^2 + b x + c) / (d x^2 + e x + f) and the display value 0.85
# that its automatic exposure range maps the reference's max and median luminance to.
_ACES = (0.6 * 0.6 * 2.51, 0.6 * 0.03, 0.0, 0.6 * 0.6 * 2.43, 0.6 * 0.59, 0.14)


def hdr_flip_exposures(ref: np.ndarray) -> dict[str, float]:
    """HDR-FLIP's exposure range for a linear (H, W, 3) reference, as FLIP computes it.

    ``startExposure = log2(x / Y_max)``, ``stopExposure = log2(x / Y_median)`` where the ACES
    curve reaches 0.85 at x (FLIP's own rule, same values). FLIP exits the process on a
    reference whose median or maximum luminance is 0 (a mostly black image); here the median
    falls back to the mean luminance and a black reference to luminance 1.
    """
    y = ref.astype(np.float64) @ np.array([0.2126, 0.7152, 0.0722])  # (H, W) luminance
    t = 0.85
    a, b, c = (_ACES[0] - t * _ACES[3], _ACES[1] - t * _ACES[4], _ACES[2] - t * _ACES[5])
    x = (-b + np.sqrt(b * b - 4.0 * a * c)) / (2.0 * a)
    y_max = float(y.max())
    flat = y.ravel()
    y_med = float(np.partition(flat, flat.size // 2)[flat.size // 2])  # FLIP: element n/2
    if not y_max > 0:
        y_max = y_med = 1.0
    elif not y_med > 0:
        y_med = float(y.mean())
    start, stop = float(np.log2(x / y_max)), float(np.log2(x / y_med))
    return {"startExposure": start, "stopExposure": stop,
            "numExposures": max(2, int(np.ceil(stop - start)))}


def hdr_flip_map(x: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """(H, W) HDR-FLIP error map of two linear (H, W, 3) images (negatives and NaN -> 0).

    Example:
        >>> ref = np.full((32, 32, 3), 2.0, np.float32)
        >>> float(hdr_flip_map(ref, ref).max())
        0.0
    """
    import flip_evaluator  # noqa: PLC0415

    def lin(img):
        return np.ascontiguousarray(np.nan_to_num(img.astype(np.float32), nan=0.0, posinf=0.0)
                                    .clip(min=0.0))

    r = lin(ref)
    err, _, _ = flip_evaluator.evaluate(r, lin(x), "HDR", applyMagma=False,
                                        parameters=hdr_flip_exposures(r))
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
    hm = hdr_flip_map(x, ref)  # exposure-free: FLIP picks its exposures from the reference
    return {
        "relmse": relmse(x, ref), "relmse_object": relmse(x, ref, obj),
        "flip": float(fm.mean()), "flip_object": float(fm[obj].mean()) if obj.any() else 0.0,
        "hdrflip": float(hm.mean()),
        "hdrflip_object": float(hm[obj].mean()) if obj.any() else 0.0,
        "psnr": psnr(x, ref, None, exposure), "psnr_object": psnr(x, ref, obj, exposure),
    }


def flip_magma(x: np.ndarray, ref: np.ndarray, exposure: float = 0.0) -> np.ndarray:
    """(H, W, 3) uint8 error-map image: LDR-FLIP of the sRGB previews in the magma map."""
    import flip_evaluator  # noqa: PLC0415

    def srgb01(img):
        return np.ascontiguousarray(linear_to_srgb8(img, exposure).astype(np.float32) / 255.0)

    err, _, _ = flip_evaluator.evaluate(srgb01(ref), srgb01(x), "LDR", applyMagma=True)
    return np.clip(np.asarray(err) * 255.0 + 0.5, 0, 255).astype(np.uint8)

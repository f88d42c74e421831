"""Textures over mesh UVs: the roughness map of SCENE_SPEC.md.

UVs follow trimesh/OpenGL: (0, 0) is the bottom-left of the image; texel (c, r), row r from
the top, is centered at u = (c + 0.5) / W, v = 1 - (r + 0.5) / H. Lookups are bilinear and
wrap in both directions. Roughness maps are read as raw values (8-bit / 255, 16-bit /
65535, no sRGB decoding; RGB averaged; alpha ignored).
"""

from __future__ import annotations

import functools
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from torchrefract.checks import ConfigError, file_version


@functools.lru_cache(maxsize=16)
def _load(path: str, _mtime: int, _size: int) -> torch.Tensor:
    from PIL import Image  # noqa: PLC0415

    try:
        with Image.open(path) as im:
            mode = im.mode
            arr = np.asarray(im)
    except Exception as exc:
        raise ConfigError(f"roughness_map {path!r}: cannot be read as an image ({exc})") \
            from None
    if arr.size == 0 or arr.ndim < 2 or arr.shape[0] < 1 or arr.shape[1] < 1:
        raise ConfigError(f"roughness_map {path!r}: empty image")
    if arr.dtype == np.uint8:
        val = arr.astype(np.float32) / 255.0
    elif arr.dtype == np.uint16 or mode.startswith("I;16"):
        val = arr.astype(np.float32) / 65535.0
    elif arr.dtype == bool:
        val = arr.astype(np.float32)
    else:
        raise ConfigError(f"roughness_map {path!r}: unsupported pixel type {arr.dtype} "
                          f"(mode {mode}); use 8- or 16-bit grayscale or RGB")
    if val.ndim == 3:
        val = val[..., :3].mean(-1) if val.shape[-1] >= 3 else val[..., 0]
    return torch.from_numpy(np.ascontiguousarray(val))


def load_roughness_map(path: str | Path) -> torch.Tensor:
    """(H, W) float32 values in [0, 1] of a grayscale/RGB image (cached per file version)."""
    return _load(*file_version(path, "roughness_map"))


def sample_uv(tex: torch.Tensor, uv: torch.Tensor) -> torch.Tensor:
    """Bilinear, wrapping lookup of a (H, W) texture at UVs (..., 2) -> (...)."""
    h, w = tex.shape
    lead = uv.shape[:-1]
    uv = uv.reshape(-1, 2).to(tex.dtype)
    x = (uv[:, 0] - torch.floor(uv[:, 0])) * w - 0.5  # in [-0.5, W - 0.5)
    y = (1.0 - uv[:, 1])
    y = (y - torch.floor(y)) * h - 0.5
    img = F.pad(tex[None, None], (1, 1, 1, 1), mode="circular")  # (1, 1, H+2, W+2)
    gx = 2.0 * (x + 1.0) / (w + 1) - 1.0
    gy = 2.0 * (y + 1.0) / (h + 1) - 1.0
    out = F.grid_sample(img, torch.stack([gx, gy], -1).view(1, 1, -1, 2), mode="bilinear",
                        padding_mode="border", align_corners=True)
    return out.view(-1).reshape(lead)

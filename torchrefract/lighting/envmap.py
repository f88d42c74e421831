"""Environment maps: loading, validation and the exact lookup of SCENE_SPEC.md (Mitsuba 3).

A direction d = (x, y, z) in the map's frame looks up ``u = atan2(x, -z) / (2 pi)`` wrapped
to [0, 1) and ``v = acos(y) / pi``. Column c is centered at u = (c + 0.5) / W and the image
wraps horizontally; row r sits at v = r / (H - 1) (row 0 is the +Y pole). Lookups are
bilinear. ``rotate_deg`` turns the map about +Y: a world direction is rotated by
-rotate_deg before the lookup. All of this is Mitsuba 3's ``envmap`` emitter.
"""

from __future__ import annotations

import functools
import math
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from torchrefract.checks import RADIANCE_LIMIT, ConfigError, file_version
from torchrefract.kept import KeptByIdentity
from torchrefract.output.images import read_exr, read_hdr


def _read_envmap(path: str) -> torch.Tensor:
    """Read and validate a map file (uncached; :func:`load_envmap` caches it)."""
    p = Path(path)
    suffix = p.suffix.lower()
    if suffix == ".exr":
        ch = read_exr(p)
        if all(c in ch for c in "RGB"):
            img = np.stack([ch["R"], ch["G"], ch["B"]], -1)
        elif "Y" in ch:
            img = np.repeat(ch["Y"][..., None], 3, -1)
        else:
            raise ConfigError(f"envmap {path!r}: no R, G, B (or Y) channels, found {sorted(ch)}")
    elif suffix in (".hdr", ".pic", ".rgbe"):
        img = read_hdr(p)
    else:
        raise ConfigError(f"envmap {path!r}: unsupported format {suffix!r} (use .exr or .hdr)")
    validate_texels(img, path)
    return torch.from_numpy(np.ascontiguousarray(img, dtype=np.float32))


def validate_texels(img: np.ndarray, name: str) -> None:
    """Raise ConfigError for an empty image or any NaN, Inf, negative or too bright
    (``RADIANCE_LIMIT``) texel."""
    if img.ndim != 3 or img.shape[0] < 2 or img.shape[1] < 1 or img.shape[2] != 3:
        raise ConfigError(f"envmap {name!r}: expected an (H >= 2, W >= 1, 3) image, "
                          f"got shape {img.shape}")
    bad = ~np.isfinite(img)
    if bad.any():
        r, c, _ = np.argwhere(bad)[0]
        raise ConfigError(f"envmap {name!r}: {int(bad.sum())} NaN/Inf values, first at "
                          f"row {r}, column {c}: {img[r, c].tolist()}")
    neg = img < 0
    if neg.any():
        r, c, _ = np.argwhere(neg)[0]
        raise ConfigError(f"envmap {name!r}: {int(neg.sum())} negative values, first at "
                          f"row {r}, column {c}: {img[r, c].tolist()}")
    big = img > RADIANCE_LIMIT
    if big.any():
        r, c, _ = np.argwhere(big)[0]
        raise ConfigError(f"envmap {name!r}: {int(big.sum())} values above {RADIANCE_LIMIT:g}, "
                          f"first at row {r}, column {c}: {img[r, c].tolist()}")


def load_envmap(path: str | Path) -> torch.Tensor:
    """Load a lat-long map (OpenEXR or Radiance .hdr) as (H, W, 3) float32 linear RGB.

    Cached per path and file version; the returned tensor must not be modified in place.

    Raises:
        ConfigError: unreadable file, wrong channels, empty image, NaN/Inf or negative texels.
    """
    return _load_versioned(*file_version(path, "envmap"))


@functools.lru_cache(maxsize=8)
def _load_versioned(path: str, _mtime: int, _size: int) -> torch.Tensor:
    return _read_envmap(path)


def rotate_y(d: torch.Tensor, angle_deg: torch.Tensor | float) -> torch.Tensor:
    """Rotate directions (..., 3) about +Y by ``angle_deg`` (right-handed)."""
    a = torch.as_tensor(angle_deg, dtype=d.dtype, device=d.device) * (math.pi / 180.0)
    c, s = torch.cos(a), torch.sin(a)
    x, y, z = d.unbind(-1)
    return torch.stack([c * x + s * z, y, -s * x + c * z], -1)


def direction_to_uv(d: torch.Tensor) -> torch.Tensor:
    """Map-frame unit directions (..., 3) -> (u, v) in [0, 1) x [0, 1] (..., 2)."""
    x, y, z = d.unbind(-1)
    u = torch.atan2(x, -z) * (0.5 / math.pi)
    u = u - torch.floor(u)
    v = torch.acos(y.clamp(-1.0, 1.0)) * (1.0 / math.pi)
    return torch.stack([u, v], -1)


_PADDED = KeptByIdentity(4)


def _padded(texels: torch.Tensor) -> torch.Tensor:
    """(1, 3, H, W + 2) channels-first copy of ``texels`` with one wrapped column on each
    side. Kept for the last few maps that need no gradient (the loaded maps are cached and
    read by every lookup of a batch: copying a 1024x512 map took 3.5 ms per lookup), keyed
    by the tensor itself and its version counter (an in-place change makes a new copy)."""
    def pad(t: torch.Tensor) -> torch.Tensor:
        img = t.permute(2, 0, 1)  # (3, H, W)
        return torch.cat([img[:, :, -1:], img, img[:, :, :1]], dim=2)[None]

    if texels.requires_grad:
        return pad(texels)
    out = _PADDED.get(texels, texels._version)
    return out if out is not None else _PADDED.put(texels, texels._version, pad(texels))


def lookup(texels: torch.Tensor, d: torch.Tensor, rotate_deg: float | torch.Tensor = 0.0,
           scale: float | torch.Tensor = 1.0) -> torch.Tensor:
    """Bilinear environment lookup of world directions; differentiable in texels and d.

    Args:
        texels: (H, W, 3) lat-long radiance.
        d: (..., 3) world directions (need not be normalized, must be nonzero).
        rotate_deg: rotation of the map about +Y.
        scale: radiance multiplier.

    Returns:
        (..., 3) radiance.

    Example:
        >>> env = torch.rand(8, 16, 3)
        >>> lookup(env, torch.tensor([[0.0, 1.0, 0.0]])).shape
        torch.Size([1, 3])
    """
    h, w, _ = texels.shape
    lead = d.shape[:-1]
    d = d.reshape(-1, 3)
    d = d / d.norm(dim=-1, keepdim=True).clamp(min=1e-30)
    d = rotate_y(d, -torch.as_tensor(rotate_deg, dtype=d.dtype))
    uv = direction_to_uv(d)  # (N, 2)
    # Continuous texel coordinates: x = u W - 0.5 (column centers at (c + 0.5) / W),
    # y = v (H - 1) (row r at v = r / (H - 1)). One wrapped column is padded on each side
    # so that x in [-0.5, W - 0.5) interpolates across the seam.
    x = uv[:, 0] * w - 0.5 + 1.0  # index into the padded image
    y = uv[:, 1] * (h - 1)
    img = _padded(texels)  # (1, 3, H, W + 2)
    gx = 2.0 * x / (w + 1) - 1.0
    gy = 2.0 * y / (h - 1) - 1.0
    grid = torch.stack([gx, gy], -1).view(1, 1, -1, 2).to(img.dtype)
    out = F.grid_sample(img, grid, mode="bilinear", padding_mode="border",
                        align_corners=True)  # (1, 3, 1, N)
    out = out[0, :, 0].transpose(0, 1) * torch.as_tensor(scale, dtype=img.dtype)
    return out.reshape(*lead, 3)

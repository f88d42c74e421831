"""Environment convolution on the fly (Lee, Kim and Choi 2008, as Dai and Wyman 2012 use it):
a box-filtered MIP pyramid of the lat-long map, read at the level whose texel spans the
lobe's width, interpolated between the two nearest levels.

A Gaussian lobe of per-axis angular variance s^2 maps to the level whose box (variance
w^2 / 12 for a box of width w) has the same variance: w = sqrt(12) s, level
l = log2(w / dtheta) with dtheta = pi / (H - 1) the map's row spacing. It is an approximation
of the exact SG pyramid (:mod:`torchrefract.lighting.sg_pyramid`, the default): a box, not a
Gaussian, and lat-long distortion away from the equator is ignored. ``env_lookup: mip`` of
``lean`` / ``gsr`` selects it; the chart compares the two.
"""

from __future__ import annotations

import functools
import math
import os

import torch

from torchrefract.lighting import envmap
from torchrefract.optics.ndf import build_box_mips


def env_mips(texels: torch.Tensor) -> tuple[torch.Tensor, ...]:
    """Box MIP levels (H_l, W_l, 3) of a lat-long map (H, W, 3), down to one row."""
    return tuple(m[0] for m in build_box_mips(texels[None], max_levels=32))


@functools.lru_cache(maxsize=8)
def _cached(path: str, _mtime: int, _size: int) -> tuple[torch.Tensor, ...]:
    return env_mips(envmap.load_envmap(path))


def env_mips_for(path: str) -> tuple[torch.Tensor, ...]:
    """:func:`env_mips` of a map file, built once per file version."""
    st = os.stat(path)
    return _cached(str(path), st.st_mtime_ns, st.st_size)


def mip_level(mips: tuple[torch.Tensor, ...], variance: torch.Tensor) -> torch.Tensor:
    """Fractional level (N,) of a lobe of per-axis angular variance (N,) (module docstring)."""
    dtheta = math.pi / max(mips[0].shape[0] - 1, 1)
    width = torch.sqrt(12.0 * variance.clamp(min=0.0))
    lvl = torch.log2((width / dtheta).clamp(min=1e-30))
    return lvl.clamp(0.0, len(mips) - 1.0)


def mip_lookup(mips: tuple[torch.Tensor, ...], d: torch.Tensor, variance: torch.Tensor,
               rotate_deg: float | torch.Tensor = 0.0, scale: float | torch.Tensor = 1.0
               ) -> torch.Tensor:
    """Radiance (N, 3) of lobes around directions d (N, 3) with per-axis variance (N,):
    bilinear within the two levels around :func:`mip_level`, linear between them."""
    lvl = mip_level(mips, variance)
    l0 = torch.floor(lvl).long()
    frac = lvl - l0.to(lvl.dtype)
    out = torch.zeros_like(d)
    for li in range(len(mips)):
        w = torch.where(l0 == li, 1.0 - frac, torch.zeros_like(frac)) \
            + torch.where(l0 + 1 == li, frac, torch.zeros_like(frac))
        sel = (w > 0).nonzero(as_tuple=True)[0]
        if sel.numel() == 0:
            continue
        out[sel] += w[sel, None] * envmap.lookup(mips[li], d[sel], rotate_deg, scale)
    return out


__all__ = ["env_mips", "env_mips_for", "mip_level", "mip_lookup"]

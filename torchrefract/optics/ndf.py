"""Back-face geometry filtering (de Rousiers et al. 2012, sec. 4.2): NDF and depth mips.

Level 0 is the back layer itself; level l averages 2^l x 2^l pixels (plain 2x2 reductions,
``avg_pool2d`` / ``max_pool2d``). The NDF of a texel is Toksvig's: the average of the unit
normals it covers, whose direction is the mean normal and whose length |n| < 1 measures the
spread. Following the paper, direction and length are stored separately so both interpolate
smoothly, and the spread converts to a Blinn-Phong-like lobe exponent (eq. 11):

    sigma^2 = (1 - |n|) / |n|,   kappa_G = 2 / sigma^2 = 2 |n| / (1 - |n|).

(The transcription of eq. 11 in the seed text reads ``2(1 - |n|)/|n|``, which is sigma^2
times 2; the exponent must grow as the normals agree, so we use 2/sigma^2 as the text says.)
Depth mips keep the min and max back-face depth per texel for empty-space skipping.
Shapes are channels-last ``(B, H_l, W_l, C)``; only covered pixels contribute.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F

from torchrefract.kernels import native
from torchrefract.stages import timed

KAPPA_MAX = 1e6  # exponent used for a perfectly flat footprint (|n| = 1)


@dataclass(frozen=True)
class NDFMips:
    """Mip pyramids of the back layer.

    Attributes:
        direction: per level (B, H_l, W_l, 3) unit mean normal (zeros where empty).
        length: per level (B, H_l, W_l, 1) Toksvig length |n| in [0, 1] (0 where empty).
        coverage: per level (B, H_l, W_l, 1) fraction of covered pixels.
        depth_min: per level (B, H_l, W_l, 1) min back depth (+inf where empty).
        depth_max: per level (B, H_l, W_l, 1) max back depth (-inf where empty).
    """

    direction: tuple[torch.Tensor, ...]
    length: tuple[torch.Tensor, ...]
    coverage: tuple[torch.Tensor, ...]
    depth_min: tuple[torch.Tensor, ...]
    depth_max: tuple[torch.Tensor, ...]

    @property
    def levels(self) -> int:
        return len(self.direction)


def _sum2x2(x: torch.Tensor) -> torch.Tensor:
    """2x2 sums of (B, H, W, C), ceil mode (odd sizes keep their last row/column)."""
    y = F.avg_pool2d(x.permute(0, 3, 1, 2), kernel_size=2, stride=2, ceil_mode=True,
                     divisor_override=1)
    return y.permute(0, 2, 3, 1)


def _max2x2(x: torch.Tensor) -> torch.Tensor:
    y = F.max_pool2d(x.permute(0, 3, 1, 2), kernel_size=2, stride=2, ceil_mode=True)
    return y.permute(0, 2, 3, 1)


@timed("mips")
def build_ndf_mips(normal: torch.Tensor, mask: torch.Tensor, depth: torch.Tensor,
                   max_levels: int = 16) -> NDFMips:
    """Build NDF (Toksvig) and min/max depth mips of a layer.

    Args:
        normal: (B, H, W, 3) unit normals of the layer.
        mask: (B, H, W) bool coverage.
        depth: (B, H, W) depth of the layer.
        max_levels: at most this many levels (stops at 1x1).

    Returns:
        NDFMips with level 0 at full resolution.

    Example:
        >>> n = torch.zeros(1, 4, 4, 3); n[..., 2] = 1
        >>> m = build_ndf_mips(n, torch.ones(1, 4, 4, dtype=torch.bool), torch.ones(1, 4, 4))
        >>> m.levels, tuple(m.direction[2].shape)
        (3, (1, 1, 1, 3))
    """
    w = mask[..., None].to(normal.dtype)  # (B, H, W, 1)
    acc_n = normal * w  # sum of unit normals
    acc_w = w
    big = torch.finfo(depth.dtype).max
    dmin = torch.where(mask, depth, torch.full_like(depth, big))[..., None]
    dmax = torch.where(mask, depth, torch.full_like(depth, -big))[..., None]
    dirs, lens, covs, mins, maxs = [], [], [], [], []
    level = 0
    while True:
        mean = acc_n / acc_w.clamp(min=1e-12)  # average unit normal, |mean| <= 1
        ln = mean.norm(dim=-1, keepdim=True)
        dirs.append(torch.where(ln > 1e-12, mean / ln.clamp(min=1e-12), torch.zeros_like(mean)))
        lens.append(ln.clamp(max=1.0))
        # coverage of level l: covered fraction of its 2^l x 2^l pixels
        covs.append(acc_w / (4.0 ** level))
        mins.append(torch.where(dmin >= big, torch.full_like(dmin, float("inf")), dmin))
        maxs.append(torch.where(dmax <= -big, torch.full_like(dmax, float("-inf")), dmax))
        level += 1
        if level >= max_levels or (acc_n.shape[1] == 1 and acc_n.shape[2] == 1):
            break
        acc_n = _sum2x2(acc_n)
        acc_w = _sum2x2(acc_w)
        dmin = -_max2x2(-dmin)
        dmax = _max2x2(dmax)
    return NDFMips(tuple(dirs), tuple(lens), tuple(covs), tuple(mins), tuple(maxs))


def kappa_from_length(length: torch.Tensor) -> torch.Tensor:
    """Toksvig length |n| -> lobe exponent kappa_G = 2 |n| / (1 - |n|) (eq. 11)."""
    ln = length.clamp(0.0, 1.0)
    return (2.0 * ln / (1.0 - ln).clamp(min=2.0 / KAPPA_MAX)).clamp(max=KAPPA_MAX)


def combine_exponents(kappa_g: torch.Tensor, kappa_d: torch.Tensor) -> torch.Tensor:
    """Convolution of two lobes by their exponents, eq. 10: k_G k_D / (k_G + k_D)."""
    return kappa_g * kappa_d / (kappa_g + kappa_d).clamp(min=1e-12)


def sample_mips(mips: NDFMips, batch: torch.Tensor, xy: torch.Tensor, level: torch.Tensor
                ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Trilinear NDF lookup: bilinear within the two mip levels around ``level``, then lerp.

    Args:
        mips: the pyramids.
        batch: (N,) int64 view index.
        xy: (N, 2) level-0 pixel coordinates (x right, y down; centers at +0.5).
        level: (N,) fractional mip level (clamped to the pyramid).

    Returns:
        direction (N, 3) unit mean normal, length (N,) Toksvig length, coverage (N,).
        Directions are averaged weighted by coverage, so empty texels do not pull them.
    """
    lv = level.clamp(0.0, mips.levels - 1.0)
    l0 = torch.floor(lv).long()
    frac = (lv - l0.to(lv.dtype))[:, None]
    l1 = (l0 + 1).clamp(max=mips.levels - 1)
    out_n = torch.zeros(xy.shape[0], 3, dtype=xy.dtype)
    out_w = torch.zeros(xy.shape[0], 1, dtype=xy.dtype)
    for lvl in range(mips.levels):
        w = torch.where(l0 == lvl, 1.0 - frac[:, 0], torch.zeros_like(frac[:, 0])) \
            + torch.where(l1 == lvl, frac[:, 0], torch.zeros_like(frac[:, 0]))
        sel = (w > 0).nonzero(as_tuple=True)[0]
        if sel.numel() == 0:
            continue
        # Unnormalized mean normal (direction * length) times coverage is linear in the
        # underlying normals, so it interpolates exactly like a box-filtered sum.
        vec = mips.direction[lvl] * mips.length[lvl] * mips.coverage[lvl]  # (B, h, w, 3)
        cov = mips.coverage[lvl]
        img = torch.cat([vec, cov], -1).permute(0, 3, 1, 2)  # (B, 4, h, w)
        h, wd = img.shape[-2:]
        scale = 2.0 ** lvl
        gx = (xy[sel, 0] / scale) / wd * 2.0 - 1.0  # align_corners=False convention
        gy = (xy[sel, 1] / scale) / h * 2.0 - 1.0
        grid = torch.stack([gx, gy], -1)
        vals = _gather_bilinear(img, batch[sel], grid)  # (S, 4)
        out_n[sel] += w[sel, None] * vals[:, :3]
        out_w[sel] += w[sel, None] * vals[:, 3:]
    mean = out_n / out_w.clamp(min=1e-12)
    ln = mean.norm(dim=-1)
    direction = mean / ln[:, None].clamp(min=1e-12)
    return direction, ln.clamp(max=1.0), out_w[:, 0]


def _gather_bilinear(img: torch.Tensor, batch: torch.Tensor, grid: torch.Tensor) -> torch.Tensor:
    """Bilinear samples of per-view images (B, C, h, w) at normalized grid points (N, 2)."""
    b = img.shape[0]
    out = torch.zeros(grid.shape[0], img.shape[1], dtype=img.dtype)
    for i in range(b):
        sel = (batch == i).nonzero(as_tuple=True)[0]
        if sel.numel() == 0:
            continue
        g = grid[sel].view(1, 1, -1, 2).to(img.dtype)
        v = F.grid_sample(img[i:i + 1], g, mode="bilinear", padding_mode="zeros",
                          align_corners=False)  # (1, C, 1, S)
        out[sel] = v[0, :, 0].transpose(0, 1)
    return out


@timed("mips")
def build_box_mips(x: torch.Tensor, max_levels: int = 16) -> tuple[torch.Tensor, ...]:
    """Box-filtered mips of any per-pixel quantity (B, H, W, C): level l averages 2^l x 2^l
    pixels (empty pixels count as 0, e.g. for coverage ratios of roughness levels). The
    native kernel where it runs (csrc/box.c, the same bits), else the tensor code."""
    done = native.box_mips(x, max_levels)
    if done is not None:
        return done
    out = [x]
    acc = x
    level = 0
    while level + 1 < max_levels and (acc.shape[1] > 1 or acc.shape[2] > 1):
        acc = _sum2x2(acc)
        level += 1
        out.append(acc / (4.0 ** level))
    return tuple(out)


def sample_box_mips(mips: tuple[torch.Tensor, ...], batch: torch.Tensor, xy: torch.Tensor,
                    level: torch.Tensor) -> torch.Tensor:
    """Trilinear lookup of :func:`build_box_mips` at level-0 pixel coordinates xy (N, 2) and
    fractional levels (N,) -> (N, C)."""
    n_levels = len(mips)
    lv = level.clamp(0.0, n_levels - 1.0)
    l0 = torch.floor(lv).long()
    frac = lv - l0.to(lv.dtype)
    l1 = (l0 + 1).clamp(max=n_levels - 1)
    out = torch.zeros(xy.shape[0], mips[0].shape[-1], dtype=xy.dtype)
    for lvl in range(n_levels):
        w = torch.where(l0 == lvl, 1.0 - frac, torch.zeros_like(frac)) \
            + torch.where(l1 == lvl, frac, torch.zeros_like(frac))
        sel = (w > 0).nonzero(as_tuple=True)[0]
        if sel.numel() == 0:
            continue
        img = mips[lvl].permute(0, 3, 1, 2)  # (B, C, h, w)
        h, wd = img.shape[-2:]
        scale = 2.0 ** lvl
        grid = torch.stack([(xy[sel, 0] / scale) / wd * 2.0 - 1.0,
                            (xy[sel, 1] / scale) / h * 2.0 - 1.0], -1)
        out[sel] += w[sel, None] * _gather_bilinear(img, batch[sel], grid)
    return out

"""Environment maps pre-convolved with normalized spherical Gaussians (de Rousiers 2012, sec. 4.1).

Level i of the pyramid holds the lat-long map convolved on the sphere with the normalized
spherical Gaussian (SG) kernel of sharpness k_i::

    K(d, w) = k / (2 pi (1 - exp(-2 k))) * exp(k (dot(d, w) - 1))      (integrates to 1)

Level 0 is the map itself (k = inf, a delta kernel); the sharpness decreases level by level,
geometrically, and the resolution shrinks with the kernel width (MIP-like). Past the widest
level the pyramid ends with the k -> 0 limit, the solid-angle mean of the map. A lookup for
any sharpness reads the two enclosing levels bilinearly (SCENE_SPEC.md conventions, exactly
those of :func:`torchrefract.lighting.envmap.lookup`) and blends them (paper, sec. 4.1: "a MIP-map of
2D textures ... convolved with spherical Gaussian functions of decreasing exponent").

How a level is computed (exact on the sphere, poles and seam included): the function
convolved is the map as the renderer (and Mitsuba 3) sees it, the bilinear interpolant of
the texels. Along longitude the lat-long grid is uniform, so for one output row and one
source row the convolution is circular in phi, and the kernel's Fourier series is known::

    K(theta_o, theta_s, dphi) = c_k exp(-2k sin^2((theta_o - theta_s) / 2))
                                    * exp(-2a sin^2(dphi / 2)),  a = k sin(theta_o) sin(theta_s)
    Fourier coefficient m of exp(-2a sin^2(dphi / 2)) = I_m(a) exp(-a)   (scaled Bessel, "ive")

Each output row is then a sum over source rows of (DFT of the row) x (kernel spectrum), with
the linear interpolation between columns applied exactly as the factor sinc^2(m / W), and
evaluated at the level's columns by an inverse FFT. Across latitude the integral of (linear
interpolant) x (kernel) x sin(theta) uses 3 Gauss-Legendre points between consecutive rows;
for wide kernels those points are first gathered onto a grid of a quarter kernel width
(cubic Lagrange weights: the kernel is interpolated to ~1e-4 of its peak). Only rows within
the kernel's reach (exp(-20) of its peak) enter a sum. A row at a pole has a = 0, hence only
m = 0: each pole value averages all longitudes, and that row is constant. ive(m, a) comes from
the samples of exp(-2a sin^2(dphi / 2)) at spacing <= 0.52 / sqrt(k) (aliasing < 1e-30):
a short cosine sum as a matrix product where a is large, an FFT near the poles. Every row is
finally divided by what the same sums give for a constant map (1 up to the quadrature's
~1e-4), so constants stay exact.

Cost for a 1024 x 512 map with the defaults (34 levels, k from 26457 (one texel) to 0.5):
~2 s on 2 CPU threads, 90 MB (float32, map included).

Example:
    >>> env = torch.rand(16, 32, 3)
    >>> pyr = build_sg_pyramid(env)
    >>> d = torch.tensor([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0]])
    >>> sg_lookup_env(pyr, d, torch.tensor([10.0, float("inf")])).shape
    torch.Size([2, 3])
"""

from __future__ import annotations

import functools
import hashlib
import inspect
import math
import struct
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np
import torch
import torch.nn.functional as F

from torchrefract.checks import ConfigError, check_tensor_shape, file_version
from torchrefract.kernels.index import take
from torchrefract.lighting import envmap
from torchrefract.lighting.envmap import direction_to_uv, rotate_y
from torchrefract.optics.sgfit import default_cache_dir
from torchrefract.output.atomic import atomic_path

# Bump when the pyramid's contents change for the same parameters (disk cache key).
_FORMAT_VERSION = 2

__all__ = ["SGPyramid", "build_sg_pyramid", "sg_lookup_env", "sg_pyramid_for",
           "default_sharpness_levels", "sg_kernel", "clear_sg_cache"]


# --------------------------------------------------------------------------------------
# The pyramid
# --------------------------------------------------------------------------------------

def _pad_level(im: torch.Tensor) -> torch.Tensor:
    """(3, h, w) -> (3, h + 1, w + 2): one wrapped column each side (the horizontal seam)
    and the last row repeated once (no bilinear tap at the bottom pole reads a neighbour)."""
    padded = torch.cat([im[:, :, -1:], im, im[:, :, :1]], dim=2)  # (3, h, w + 2)
    return torch.cat([padded, padded[:, -1:]], dim=1)  # (3, h + 1, w + 2)


@dataclass(frozen=True)
class SGPyramid:
    """An environment map pre-convolved with normalized SGs of decreasing sharpness.

    Level 0 (the map) is kept padded in ``base``; the filtered levels and the k = 0 mean
    level live in one packed texture (``atlas``), so that one ``grid_sample`` reads any mix
    of them. Each image has one wrapped column on either side and its last row repeated.
    Level 0 stays separate because float32 coordinates into a tall atlas would shift its
    reads by up to ~3e-4 texel (visible next to a bright sun); the filtered levels are
    smooth at the texel scale and do not care. ``levels`` gives all back as views.

    Attributes:
        base: (3, H + 1, W + 2) the padded map; texel (r, c) is ``base[:, r, 1 + c]``.
        atlas: (3, Ha, Wa) the packed filtered levels, channels first.
        rects: per level (y0, x0, H, W): texel (r, c) of level i >= 1 is
            ``atlas[:, y0 + r, x0 + 1 + c]``; rects[0] = (0, 0, H, W) refers to ``base``.
            One more entry than ``sharpness``: the last is the k = 0 level, a constant
            (2, 1) image of the solid-angle mean radiance.
        sharpness: (inf, k_1, ..., k_n), strictly decreasing, k_n > 0: the SG sharpness of
            each level in ``levels`` (level 0 is the unfiltered map).
    """

    base: torch.Tensor
    atlas: torch.Tensor
    rects: tuple[tuple[int, int, int, int], ...]
    sharpness: tuple[float, ...]

    def __post_init__(self) -> None:
        if len(self.rects) != len(self.sharpness) + 1:
            raise ValueError(f"SGPyramid: {len(self.rects)} rects for {len(self.sharpness)} "
                             "levels; expected one more (the k = 0 mean level)")
        k = self.sharpness
        if not k or k[0] != math.inf or any(not (a > b) for a, b in zip(k, k[1:])) \
                or (len(k) > 1 and not k[-1] > 0):
            raise ValueError(f"SGPyramid: sharpness must be (inf, k_1 > ... > k_n > 0), got {k}")

    @property
    def levels(self) -> tuple[torch.Tensor, ...]:
        """Per-level lat-long images (H_i, W_i, 3) (views); level 0 is the map."""
        _, _, h, w = self.rects[0]
        out = [self.base[:, :h, 1:1 + w].permute(1, 2, 0)]
        out += [self.atlas[:, y0:y0 + h, x0 + 1:x0 + 1 + w].permute(1, 2, 0)
                for (y0, x0, h, w) in self.rects[1:-1]]
        return tuple(out)

    @property
    def mean(self) -> torch.Tensor:
        """(3,) solid-angle mean radiance of the map: the limit k -> 0."""
        y0, x0, _, _ = self.rects[-1]
        return self.atlas[:, y0, x0 + 1]

    @property
    def nbytes(self) -> int:
        """Memory held by the pyramid (padded map and atlas)."""
        return sum(t.numel() * t.element_size() for t in (self.base, self.atlas))

    def to(self, *args, **kwargs) -> "SGPyramid":
        """Move / cast like ``Tensor.to`` (e.g. ``pyr.to("cuda")``, ``pyr.to(torch.float64)``)."""
        return SGPyramid(self.base.to(*args, **kwargs), self.atlas.to(*args, **kwargs),
                         self.rects, self.sharpness)

    @classmethod
    def from_levels(cls, levels: Sequence[torch.Tensor], sharpness: Sequence[float],
                    mean: torch.Tensor) -> "SGPyramid":
        """Pack lat-long levels (H_i, W_i, 3) (level 0 = the map, sharpness[0] = inf) and the
        (3,) mean radiance into a pyramid. Differentiable w.r.t. the levels and the mean."""
        base = _pad_level(levels[0].permute(2, 0, 1))
        imgs = [lv.permute(2, 0, 1) for lv in levels[1:]] + \
               [mean.reshape(3, 1, 1).expand(3, 2, 1)]
        atlas_w = max(im.shape[2] for im in imgs) + 2
        rects, y, x, shelf_h = [], 0, 0, 0
        for im in imgs:  # shelf packing, levels come largest first
            h, w = im.shape[1:]
            if x + w + 2 > atlas_w:
                y, x, shelf_h = y + shelf_h, 0, 0
            rects.append((y, x, h, w))
            x += w + 2
            shelf_h = max(shelf_h, h + 1)
        atlas = imgs[0].new_zeros(3, y + shelf_h, atlas_w)
        for (y0, x0, h, w), im in zip(rects, imgs):
            atlas[:, y0:y0 + h + 1, x0:x0 + w + 2] = _pad_level(im)
        h0, w0 = levels[0].shape[:2]
        return cls(base, atlas, ((0, 0, h0, w0),) + tuple(rects),
                   tuple(float(k) for k in sharpness))


# --------------------------------------------------------------------------------------
# Kernel and level parameters
# --------------------------------------------------------------------------------------

def sg_kernel(cos_angle: torch.Tensor, sharpness: float | torch.Tensor) -> torch.Tensor:
    """Normalized SG K = k / (2 pi (1 - exp(-2k))) * exp(k (cos - 1)); integrates to 1 on S^2."""
    k = torch.as_tensor(sharpness, dtype=cos_angle.dtype, device=cos_angle.device)
    return k / (2 * math.pi * -torch.expm1(-2 * k)) * torch.exp(k * (cos_angle - 1))


def _texel_angle(h: int, w: int) -> float:
    """Largest texel spacing (radians): rows pi / (H - 1), columns 2 pi / W at the equator."""
    return max(math.pi / (h - 1), 2 * math.pi / w)


def default_sharpness_levels(h: int, w: int, *, levels_per_octave: int = 2,
                             min_sharpness: float = 0.5,
                             max_sharpness: float | None = None,
                             finest_sigma_texels: float = 1.0) -> tuple[float, ...]:
    """Finite level sharpnesses for an (h, w) grid, decreasing geometrically.

    From ``max_sharpness`` (default: a kernel whose angular standard deviation 1/sqrt(k) is
    ``finest_sigma_texels`` texels of the grid) down to exactly ``min_sharpness``, with at
    most a factor 2^(1 / levels_per_octave) between neighbours.
    """
    if max_sharpness is None:
        max_sharpness = 1.0 / (finest_sigma_texels * _texel_angle(h, w)) ** 2
        if max_sharpness <= min_sharpness and min_sharpness > 0:
            return ()  # a map of a few texels: its lookups blend the map and its mean
    if not (max_sharpness > min_sharpness > 0):
        raise ValueError(f"sharpness levels: need max_sharpness > min_sharpness > 0, got "
                         f"{max_sharpness} and {min_sharpness}")
    n = math.ceil(levels_per_octave * math.log2(max_sharpness / min_sharpness) - 1e-9) + 1
    r = (min_sharpness / max_sharpness) ** (1.0 / (n - 1))
    return tuple(max_sharpness * r ** i for i in range(n))


def _level_shape(k: float, h: int, w: int, texels_per_sigma: float, min_rows: int,
                 max_rows: int) -> tuple[int, int]:
    """Rows and columns of a level: ``texels_per_sigma`` samples per 1/sqrt(k), within bounds."""
    sigma = 1.0 / math.sqrt(k)
    rows = math.ceil(texels_per_sigma * math.pi / sigma) + 1
    rows = max(min(rows, max_rows, h), min(min_rows, h), 2)
    cols = w if rows == h else max(1, round(w * (rows - 1) / (h - 1)))
    return rows, cols


# --------------------------------------------------------------------------------------
# Convolution on the sphere
# --------------------------------------------------------------------------------------

def _gauss_legendre01(q: int) -> tuple[np.ndarray, np.ndarray]:
    x, wq = np.polynomial.legendre.leggauss(q)
    return (x + 1) / 2, wq / 2


def _row_weights_exact(h: int) -> torch.Tensor:
    """(h,) integral of each row's tent (linear interpolation weight) times sin(theta)."""
    dt = math.pi / (h - 1)
    t0 = np.arange(h - 1) * dt  # interval [t0, t1] between rows r and r + 1
    t1 = t0 + dt
    ds = (np.sin(t1) - np.sin(t0)) / dt
    down = np.cos(t0) - ds  # int (t1 - t) / dt sin t: row r's share of the interval
    up = ds - np.cos(t1)  # int (t - t0) / dt sin t: row r + 1's share
    wts = np.zeros(h)
    wts[:-1] += down
    wts[1:] += up
    return torch.from_numpy(wts)


def _solid_angle_mean(texels: torch.Tensor) -> torch.Tensor:
    """(3,) mean over the sphere of the bilinear interpolant of an (H, W, 3) lat-long map."""
    h, w, _ = texels.shape
    wr = _row_weights_exact(h).to(texels)  # sums to 2
    return (texels.mean(dim=1) * wr[:, None]).sum(0) / 2


class _Source:
    """The map's bilinear interpolant sampled for quadrature: Gauss-Legendre sub-rows between
    consecutive texel rows, each row's FFT over longitude, quadrature weights."""

    def __init__(self, texels: torch.Tensor, quad_points: int, m_keep: int,
                 chunk_elems: int = 1 << 22):
        h, w, _ = texels.shape
        self.h, self.w = h, w
        dtype, dev = texels.dtype, texels.device
        dt = math.pi / (h - 1)
        xg, wg = _gauss_legendre01(quad_points)
        xg_t = torch.as_tensor(xg, dtype=dtype, device=dev)
        th = (torch.arange(h - 1, dtype=torch.float64)[:, None] + torch.from_numpy(xg)) * dt
        self.theta = th.reshape(-1).to(dtype=dtype, device=dev)  # (J,), ascending
        wts = torch.from_numpy(wg)[None, :] * dt * torch.sin(th)  # (h - 1, q): sin(theta) dtheta
        self.weight = wts.reshape(-1).to(dtype=dtype, device=dev)
        # Linear interpolation in theta at the sub-rows, then the DFT of each sub-row over
        # longitude, keeping only the frequencies the levels use (all when they wrap past W).
        keep = w if m_keep + 1 >= w else m_keep + 1
        x = xg_t.view(1, -1, 1, 1)
        rows_per = max(1, chunk_elems // (quad_points * w * 3))
        parts = []
        for r0 in range(0, h - 1, rows_per):
            lo, hi = texels[r0:r0 + rows_per], texels[r0 + 1:r0 + rows_per + 1]
            sub = (1 - x) * lo[:len(hi), None] + x * hi[:, None]  # (rows, q, w, 3)
            parts.append(torch.fft.fft(sub.reshape(-1, w, 3), dim=1)[:, :keep])
        self.spectrum = torch.cat(parts)  # (J, keep, 3) complex

    def nodes(self, m_max: int, spacing: float
              ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Latitude quadrature nodes and their weighted spectra for one level.

        Returns theta (Jn,) ascending; the nodes' weights for a constant map of 1, (Jn,)
        (its m = 0 term, 2 pi w_j); and (M + 1, 6, Jn), the real view of
        w_j * dphi * sinc^2(m / W) * e^{-i m dphi / 2} F_j(m), with F_j(m) = sum_c f_j(c)
        e^{-i m phi_c} the DFT for column centers phi_c = (c + 0.5) dphi. sinc^2 is the exact
        spectrum of the linear interpolation between columns (the tent); m past W / 2 reads
        the periodic DFT (the interpolant has those frequencies).

        When ``spacing`` (the kernel's scale / 4) is well above the sub-row spacing, the
        sub-rows are gathered onto a uniform grid of that spacing with cubic Lagrange
        weights: sum_j K(theta_j) G_j ~ sum_n K(theta_n) sum_j L_n(theta_j) G_j, i.e. the
        kernel is interpolated cubically between nodes (error ~0.07 (spacing / sigma)^4 of
        its peak), which cuts the kernel work of wide levels.
        """
        w = self.w
        dev, dtype = self.weight.device, self.weight.dtype
        m = torch.arange(m_max + 1, device=dev)
        dphi = 2 * math.pi / w
        mf = m.to(dtype)
        phase = torch.polar(torch.sinc(mf / w) ** 2 * dphi, -mf * (dphi / 2))  # (M + 1,)
        g = self.spectrum[:, m % w, :] * phase[None, :, None] * self.weight[:, None, None]
        g = torch.view_as_real(g).reshape(-1, (m_max + 1) * 6)  # (J, (M + 1) * 6)
        g = torch.cat([g, self.weight[:, None] * (2 * math.pi)], 1)  # + the constant map
        theta = self.theta
        n_sub = len(theta)
        n_c = math.ceil(math.pi / spacing) + 1
        if n_c >= 4 and spacing > 1.5 * math.pi / n_sub:
            hc = math.pi / (n_c - 1)
            i = torch.floor(theta / hc).long()
            s0 = (i - 1).clamp(0, n_c - 4)  # stencil s0 .. s0 + 3, shifted inside at the ends
            x = theta / hc - s0.to(dtype)  # (J,) in [0, 3]
            lag = [-(x - 1) * (x - 2) * (x - 3) / 6, x * (x - 2) * (x - 3) / 2,
                   -x * (x - 1) * (x - 3) / 2, x * (x - 1) * (x - 2) / 6]
            gc = g.new_zeros(n_c, g.shape[1])
            for o, lw in enumerate(lag):
                gc = gc.index_add(0, s0 + o, g * lw[:, None])
            g = gc
            theta = torch.arange(n_c, dtype=torch.float64).mul(hc).to(dtype=dtype, device=dev)
        ones = g[:, -1].contiguous()
        g = g[:, :-1].reshape(-1, m_max + 1, 6).permute(1, 2, 0).contiguous()
        return theta, ones, g


def _spectrum_size(k: float) -> int:
    """Highest longitude frequency M kept for SG(k): ive(m, k) / ive(0, k) ~ exp(-m^2 / 2k)
    is below 1e-8 past it."""
    return math.ceil(6.1 * math.sqrt(k)) + 2


def _convolve_level(src: _Source, k: float, rows: int, cols: int,
                    chunk_elems: int = 1 << 21) -> torch.Tensor:
    """(rows, cols, 3) lat-long samples of the bilinear source convolved with SG(k)."""
    dtype, dev = src.weight.dtype, src.weight.device
    sigma = 1.0 / math.sqrt(k)
    m_max = _spectrum_size(k)
    # Samples of the phi-kernel over the circle: spacing <= 0.52 / sqrt(k), no aliasing.
    n_phi = 2 * m_max + 2
    theta_j, ones, g = src.nodes(m_max, sigma / 4)  # (Jn,), (Jn,), (M + 1, 6, Jn)
    n_nodes = len(theta_j)
    c_k = k / (2 * math.pi * -math.expm1(-2 * k))
    theta_o = torch.arange(rows, dtype=torch.float64) * (math.pi / (rows - 1))
    theta_o = theta_o.to(dtype=dtype, device=dev)
    # Reach in theta: 2k sin^2(dtheta / 2) > 20 contributes < 2e-9 of the kernel's peak.
    s = math.sqrt(10.0 / k)
    reach = math.pi if s >= 1 else 2 * math.asin(s)
    # exp(-2a sin^2(dphi / 2)) is even in dphi: sample half the circle, n = 0 .. N / 2.
    n_half = n_phi // 2 + 1
    dphi = 2 * math.pi / n_phi
    sin2_half = torch.sin(torch.arange(n_half, dtype=dtype, device=dev) * (dphi / 2)) ** 2
    # Its spectrum (a DCT-I): ive(m, a) = sum_n c_n cos(m n dphi) E_n / N, c = 1, 2, .., 2, 1.
    # Where a is large E_n vanishes past a few samples and this short sum, as one matrix
    # product, beats the FFT; near the poles (small a) the FFT does it.
    n_dct = n_half // 4 + 1  # the matrix product is used below that many samples only
    nm = (torch.arange(m_max + 1)[:, None] * torch.arange(n_dct)[None, :]) % n_phi  # exact
    cw = torch.full((n_dct,), 2.0, dtype=torch.float64)
    cw[0] = 1.0
    dct = (torch.cos(nm * dphi) * cw / n_phi).to(dtype=dtype, device=dev)  # (M + 1, n_dct)
    band = min(n_nodes, int(2 * reach / math.pi * n_nodes) + 4)  # nodes one row reaches
    step = n_nodes / (rows - 1)  # nodes per output row
    # Row chunks: small enough that the chunk's union of bands is ~1.5 bands (little
    # wasted kernel work), large enough for efficient batched matmuls, within memory.
    per_row = max(1, min(int(band / (2 * step)) + 1, chunk_elems // (band * n_phi)))
    per_row = max(per_row, min(rows, 4))
    out_spec, norm = [], []
    for o0 in range(0, rows, per_row):
        th = theta_o[o0:o0 + per_row]  # (co,)
        ja = int(torch.searchsorted(theta_j, th[0] - reach))
        jb = int(torch.searchsorted(theta_j, th[-1] + reach, right=True))
        tj = theta_j[ja:jb]  # (cj,)
        a = k * torch.sin(tj)[:, None] * torch.sin(th)[None, :]  # (cj, co)
        # Samples with 2a sin^2(dphi / 2) > 40 are below 5e-18: left out.
        s_min = math.sqrt(20.0 / max(float(a.min()), 1e-30))
        n_c = n_half if s_min >= 1 else min(n_half, int(2 * math.asin(s_min) / dphi) + 2)
        if 4 * n_c < n_half:
            # (Exponents clamped at -60, e^-60 ~ 1e-26: denormals make exp and FFTs ~10x
            # slower.)
            e = torch.exp((sin2_half[:n_c, None] * (-2 * a.reshape(1, -1))).clamp_min(-60))
            ive = (dct[:, :n_c] @ e).view(m_max + 1, *a.shape)  # (M + 1, cj, co)
        else:
            e = torch.exp((sin2_half[:, None, None] * (-2 * a)).clamp_min(-60))  # (N/2+1, cj, co)
            # Real even signal: its DFT is N * irfft of its half.
            ive = torch.fft.irfft(e, n=n_phi, dim=0)[:m_max + 1]  # (M + 1, cj, co)
        kt = c_k * torch.exp((-2 * k * torch.sin((tj[:, None] - th[None, :]) / 2) ** 2)
                             .clamp_min(-60))  # (cj, co)
        khat = ive * kt  # (M + 1, cj, co)
        out_spec.append(torch.bmm(g[:, :, ja:jb].contiguous(), khat))  # (M + 1, 6, co)
        norm.append(ones[ja:jb] @ khat[0])  # (co,) the same sums for a constant map of 1
    # Divided by what the same discrete sums give for a constant map (1 up to ~1e-4, the
    # latitude quadrature's error): constants stay exact.
    spec = torch.cat(out_spec, dim=2) / torch.cat(norm)  # (M + 1, 6, rows)
    spec = spec.reshape(m_max + 1, 3, 2, rows).permute(1, 3, 0, 2)  # (3, rows, M + 1, 2)
    spec = torch.view_as_complex(spec.contiguous())  # (3, rows, M + 1)
    # Evaluate the real Fourier series at phi_c = (c + 0.5) 2pi / cols, folding m mod cols:
    # L = Re sum_{|m| <= M} X_m e^{i m phi_c} = X_0 + 2 Re sum_{m >= 1} X_m e^{i m phi_c}.
    m = torch.arange(m_max + 1, device=dev)
    ph = torch.polar(torch.full((m_max + 1,), 2.0, dtype=dtype, device=dev),
                     m.to(dtype) * (math.pi / cols))
    ph[0] = 1.0
    spec = spec * ph  # (3, rows, M + 1)
    folded = spec.new_zeros(3, rows, cols).index_add(2, m % cols, spec)
    out = torch.fft.ifft(folded, dim=2).real * cols  # (3, rows, cols)
    # Exact values are >= 0; FFT round-off may leave -1e-7 relative.
    return out.permute(1, 2, 0).clamp_min(0)


def build_sg_pyramid(texels: torch.Tensor, sharpness_levels: Sequence[float] | None = None, *,
                     levels_per_octave: int = 2, min_sharpness: float = 0.5,
                     max_sharpness: float | None = None, finest_sigma_texels: float = 1.0,
                     texels_per_sigma: float = 5.0, min_rows: int = 16, max_rows: int = 512,
                     quad_points: int = 3) -> SGPyramid:
    """Pre-convolve a lat-long map with normalized SGs of decreasing sharpness (sec. 4.1).

    Args:
        texels: (H, W, 3) lat-long radiance (SCENE_SPEC.md layout), float32 or float64.
            Differentiable: gradients flow from every level back to it.
        sharpness_levels: the finite SG sharpnesses, strictly decreasing and > 0. Default:
            :func:`default_sharpness_levels`: from a kernel one texel wide (1/sqrt(k) =
            ``finest_sigma_texels`` texels of the finest level grid, see ``max_rows``) down
            to k = 0.5, with ``levels_per_octave`` levels per factor 2.
        levels_per_octave: levels per halving of the sharpness (default levels only).
        min_sharpness, max_sharpness, finest_sigma_texels: range of the default levels.
        texels_per_sigma: samples per angular standard deviation 1/sqrt(k) in a level: sets
            each level's resolution. Bilinear reads of a level err by up to ~1/(8
            texels_per_sigma^2) of a peak (0.5% at 5); levels whose grid is capped by the
            map's or ``max_rows`` rows have fewer samples per sigma and err more.
        min_rows, max_rows: bounds on the rows of a level. ``max_rows`` (default 512) bounds
            the memory and build time for large maps (a 4k map's levels are no bigger than
            a 1k map's); level 0 is always the full map.
        quad_points: Gauss-Legendre points per source row interval (latitude quadrature).

    Returns:
        The pyramid: level 0 is the map itself, level i the map convolved with SG(k_i),
        then the mean radiance (k = 0).

    Example:
        >>> pyr = build_sg_pyramid(torch.ones(16, 32, 3), [8.0, 2.0])
        >>> [tuple(lv.shape) for lv in pyr.levels], pyr.sharpness
        ([(16, 32, 3), (16, 32, 3), (16, 32, 3)], (inf, 8.0, 2.0))
    """
    if not torch.is_tensor(texels):
        raise ConfigError(f"build_sg_pyramid: texels must be a torch tensor, got "
                          f"{type(texels).__name__}")
    check_tensor_shape(texels, (None, None, 3), "build_sg_pyramid: texels")
    h, w, _ = texels.shape
    if h < 2 or w < 1:
        raise ConfigError(f"build_sg_pyramid: texels need H >= 2 and W >= 1, got {h}x{w}")
    if not texels.is_floating_point():
        texels = texels.float()
    for name, value, low in (("levels_per_octave", levels_per_octave, 1),
                             ("min_rows", min_rows, 2), ("max_rows", max_rows, 2),
                             ("quad_points", quad_points, 1)):
        if not isinstance(value, int) or value < low:
            raise ConfigError(f"build_sg_pyramid: {name} must be an integer >= {low}, "
                              f"got {value!r}")
    for name, value in (("texels_per_sigma", texels_per_sigma),
                        ("finest_sigma_texels", finest_sigma_texels)):
        if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
            raise ConfigError(f"build_sg_pyramid: {name} must be a number > 0, got {value!r}")
    # The finest grid a level may use: the map's own, or max_rows rows.
    top_h = max(2, min(h, max_rows))
    top_w = w if top_h == h else max(1, round(w * (top_h - 1) / (h - 1)))
    if sharpness_levels is None:
        ks = default_sharpness_levels(top_h, top_w, levels_per_octave=levels_per_octave,
                                      min_sharpness=min_sharpness, max_sharpness=max_sharpness,
                                      finest_sigma_texels=finest_sigma_texels)
    else:
        ks = tuple(float(k) for k in sharpness_levels)
        if any(not (math.isfinite(k) and k > 0) for k in ks) or \
                any(not (a > b) for a, b in zip(ks, ks[1:])):
            raise ConfigError(f"build_sg_pyramid: sharpness_levels must be finite, > 0 and "
                              f"strictly decreasing, got {list(ks)}")
    # Kernels narrower than half a texel are not resolved by the latitude quadrature (and
    # barely change the bilinear map): lookups that sharp blend the map with level 1.
    k_limit = 4.0 / _texel_angle(h, w) ** 2
    if ks and ks[0] > k_limit * (1 + 1e-9):
        raise ConfigError(f"build_sg_pyramid: sharpness {ks[0]:.6g} is sharper than a "
                          f"{h}x{w} map resolves (1/sqrt(k) < half a texel); use at most "
                          f"{k_limit:.6g}")
    levels = [texels]
    if ks:
        src = _Source(texels, quad_points, _spectrum_size(ks[0]))
        for k in ks:
            rows, cols = _level_shape(k, h, w, texels_per_sigma, min_rows, max_rows)
            levels.append(_convolve_level(src, k, rows, cols))
    return SGPyramid.from_levels(levels, (math.inf,) + ks, _solid_angle_mean(texels))


# --------------------------------------------------------------------------------------
# Lookup
# --------------------------------------------------------------------------------------

def _blend_weights(pyr: SGPyramid, k: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Lower level index i (N,) and weight t (N,) of level i + 1, for sharpness k (N,).

    The blend is linear in the effective sharpness kappa = 1 / (v0 + 1 / k), where
    v0 = texel^2 / 6 is the variance of the map's own bilinear tent (level 0 has
    kappa = 1 / v0, the mean level kappa = 0). A feature of Gaussian shape and variance v
    has its blurred peak proportional to 1 / (v + 1 / k), so this blend is exact at such a
    peak; for a delta-like source with a factor sqrt(2) between levels it errs by at most
    ~0.7% of the peak (linear in log k: 1.5%). Between the map and level 1 the map keeps
    most of the weight only while the kernel is narrower than about a texel (a blend
    linear in 1 / k would mix in its unfiltered spikes far longer: 3x the error measured
    at k = 2 k_1). Near k = 0 it is exact to first order in k.
    """
    _, _, h0, w0 = pyr.rects[0]
    v0 = _texel_angle(h0, w0) ** 2 / 6
    ks = torch.tensor(pyr.sharpness[1:], dtype=k.dtype, device=k.device)  # (n,)
    kap_levels = torch.cat([ks.new_tensor([1 / v0]), ks / (1 + v0 * ks), ks.new_zeros(1)])
    i = torch.searchsorted(-ks, -k)  # (N,) in [0, n]: how many levels are sharper than k
    inf = torch.isinf(k)
    k_safe = torch.where(inf, torch.zeros_like(k), k)  # no inf / inf (nor NaN gradients)
    kap = torch.where(inf, torch.full_like(k, 1 / v0), k_safe / (1 + v0 * k_safe))
    hi, lo = take(kap_levels, i), take(kap_levels, i + 1)
    return i, (hi - kap) / (hi - lo)


def sg_lookup_env(pyramid: SGPyramid, directions: torch.Tensor,
                  sharpness: torch.Tensor | float, rotate_deg: torch.Tensor | float = 0.0,
                  scale: torch.Tensor | float = 1.0) -> torch.Tensor:
    """Radiance of the environment convolved with a normalized SG around each direction.

    Reads the two pyramid levels enclosing ``sharpness`` (bilinear within each, SCENE_SPEC.md
    conventions) and blends them. ``sharpness = inf`` is the plain bilinear lookup
    (:func:`torchrefract.lighting.envmap.lookup`), ``0`` the mean radiance. Differentiable w.r.t.
    directions, sharpness, rotation, scale and the pyramid (hence the texels).

    Args:
        pyramid: from :func:`build_sg_pyramid` or :func:`sg_pyramid_for`.
        directions: (..., 3) world directions (need not be normalized, must be nonzero).
        sharpness: (...) or scalar SG sharpness k >= 0 (broadcast to ``directions.shape[:-1]``).
        rotate_deg: rotation of the map about +Y, scalar or broadcastable to (...).
        scale: radiance multiplier, scalar or broadcastable to (...).

    Returns:
        (..., 3) radiance, in the pyramid's dtype.

    Example:
        >>> pyr = build_sg_pyramid(torch.ones(16, 32, 3), [8.0, 2.0])
        >>> sg_lookup_env(pyr, torch.tensor([0.0, 0.0, -1.0]), 4.0)
        tensor([1., 1., 1.])
    """
    atlas = pyramid.atlas
    if directions.shape[-1:] != (3,):
        raise ValueError(f"sg_lookup_env: directions must have shape (..., 3), got "
                         f"{tuple(directions.shape)}")
    lead = directions.shape[:-1]
    dtype = atlas.dtype
    d = directions.to(dtype).reshape(-1, 3)
    k = torch.as_tensor(sharpness, dtype=dtype, device=d.device)
    if bool(torch.isnan(k).any()) or bool((k < 0).any()):
        raise ValueError("sg_lookup_env: sharpness must be >= 0 (inf allowed), got "
                         f"min {float(k.min())}, NaN: {bool(torch.isnan(k).any())}")
    k = k.expand(lead).reshape(-1)
    rot = torch.as_tensor(rotate_deg, dtype=dtype, device=d.device)
    rot = rot if rot.dim() == 0 else rot.expand(lead).reshape(-1)
    d = d / d.norm(dim=-1, keepdim=True).clamp(min=1e-30)
    uv = direction_to_uv(rotate_y(d, -rot))  # (N, 2)

    i, t = _blend_weights(pyramid, k)  # (N,), (N,)
    rects = torch.tensor(pyramid.rects, dtype=dtype, device=d.device)  # (L + 1, 4)

    def sample(img: torch.Tensor, level: torch.Tensor, uv: torch.Tensor) -> torch.Tensor:
        """Bilinear reads (3, N') of levels (N',) packed in img, at uv (N', 2)."""
        y0, x0, h, w = take(rects, level).unbind(-1)  # (N',) each
        # Texel coordinates as envmap.lookup: x = u W - 0.5 (+1 padded column), y = v (H - 1).
        x = x0 + 1 + uv[:, 0] * w - 0.5
        y = y0 + uv[:, 1] * (h - 1)
        ha, wa = img.shape[1:]
        grid = torch.stack([2 * x / (wa - 1) - 1, 2 * y / (ha - 1) - 1], -1)  # (N', 2)
        return F.grid_sample(img[None], grid.view(1, 1, -1, 2), mode="bilinear",
                             padding_mode="border", align_corners=True)[0, :, 0]  # (3, N')

    # Upper level (i + 1 >= 1): always from the atlas. Lower level: the map where i = 0,
    # else the atlas; each image is read only where some query needs it.
    hi = sample(pyramid.atlas, i + 1, uv)  # (3, N)
    on_map = i == 0
    if bool(on_map.all()):
        lo = sample(pyramid.base, i, uv)
    elif not bool(on_map.any()):
        lo = sample(pyramid.atlas, i, uv)
    else:
        lo = sample(pyramid.atlas, i.clamp(min=1), uv)
        idx = on_map.nonzero()[:, 0]
        lo = lo.index_copy(1, idx, sample(pyramid.base, i[idx], uv[idx]))
    out = lo * (1 - t) + hi * t  # (3, N)
    out = out.transpose(0, 1).reshape(*lead, 3)
    sc = torch.as_tensor(scale, dtype=dtype, device=d.device)
    return out * (sc if sc.dim() == 0 else sc.expand(lead)[..., None])


# --------------------------------------------------------------------------------------
# Caching per map file
# --------------------------------------------------------------------------------------

def _cache_dir(cache_dir: str | Path | bool | None) -> Path | None:
    """``False``: no disk cache; ``None`` / ``True``: the package's cache folder
    (:func:`torchrefract.optics.sgfit.default_cache_dir`, shared with the SG table and the native
    kernels); else that folder."""
    if cache_dir is False:
        return None
    if cache_dir is None or cache_dir is True:
        return default_cache_dir()
    return Path(cache_dir)


_BUILD_SIGNATURE = inspect.signature(build_sg_pyramid)


def _params_key(params: tuple) -> str:
    """The build's full parameters, defaults included (a changed default changes the key)."""
    bound = _BUILD_SIGNATURE.bind(None, **dict(params))
    bound.apply_defaults()
    items = sorted((k, v) for k, v in bound.arguments.items() if k != "texels")
    return repr((_FORMAT_VERSION, items))


def _save_npz(path: Path, pyr: SGPyramid) -> None:
    """Write a pyramid to the disk cache atomically: concurrent workers never read a
    partial file."""
    # An open handle: np.savez would append .npz to the temporary name.
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        np.savez(fh, base=pyr.base.detach().cpu().numpy(),
                 atlas=pyr.atlas.detach().cpu().numpy(),
                 rects=np.asarray(pyr.rects, dtype=np.int64),
                 sharpness=np.asarray(pyr.sharpness[1:], dtype=np.float64))


def _npz_member(path: Path, name: str) -> np.ndarray:
    """Member ``name`` of an uncompressed ``.npz`` (what :func:`_save_npz` writes) mapped
    from the file copy-on-write, not read: a render reads a few of the pyramid's levels (a
    lobe's sharpness picks two), so only their pages come into memory, where reading the
    file held the whole atlas in every render process (docs/decisions.md, "Peak memory").
    The pages stay the file's (the cache's writes replace the file, never change it in
    place), and processes that map one file share them. Falls back to reading the member."""
    try:
        with zipfile.ZipFile(path) as z:
            info = z.getinfo(name + ".npy")
        if info.compress_type != zipfile.ZIP_STORED:
            raise ValueError("compressed member")
        with open(path, "rb") as fh:
            fh.seek(info.header_offset)
            local = fh.read(30)  # the member's local header: name and extra lengths at 26
            n_name, n_extra = struct.unpack("<HH", local[26:30])
            fh.seek(info.header_offset + 30 + n_name + n_extra)
            version = np.lib.format.read_magic(fh)
            read_header = (np.lib.format.read_array_header_1_0 if version == (1, 0)
                           else np.lib.format.read_array_header_2_0)
            shape, fortran, dtype = read_header(fh)
            offset = fh.tell()
        if fortran or dtype.hasobject:
            raise ValueError("not a plain C-ordered array")
        return np.memmap(path, dtype=dtype, mode="c", offset=offset, shape=shape)
    except (OSError, ValueError, KeyError, zipfile.BadZipFile):
        with np.load(path) as z:
            return z[name]


def _load_npz(path: Path) -> SGPyramid | None:
    """The pyramid in the disk cache (None where unreadable). The texels are mapped from
    the file (:func:`_npz_member`), which torch takes as they are (no copy)."""
    try:
        with np.load(path) as z:
            rects, sharpness = z["rects"], z["sharpness"]
        return SGPyramid(torch.from_numpy(_npz_member(path, "base")),
                         torch.from_numpy(_npz_member(path, "atlas")),
                         tuple(tuple(int(v) for v in r) for r in rects),
                         (math.inf,) + tuple(float(k) for k in sharpness))
    except Exception:  # unreadable or stale: rebuild (and overwrite)
        return None


@functools.lru_cache(maxsize=4)
def _pyramid_cached(path: str, _mtime: int, _size: int, params: tuple,
                    cache_dir: str | None) -> SGPyramid:
    kwargs = dict(params)
    disk = None
    if cache_dir is not None:
        h = hashlib.sha256(Path(path).read_bytes())
        h.update(_params_key(params).encode())
        disk = Path(cache_dir) / f"sgenv_{h.hexdigest()[:32]}.npz"
        if disk.exists():
            pyr = _load_npz(disk)
            if pyr is not None:
                return pyr
    # Not envmap.load_envmap: its cache is keyed by the path alone and would hand back the
    # old texels of a file rewritten since; this function is already cached per version.
    texels = envmap._read_envmap(path)
    with torch.no_grad():
        pyr = build_sg_pyramid(texels, **kwargs)
    if disk is not None:
        try:
            _save_npz(disk, pyr)
        except OSError:
            pass  # read-only home etc.: the in-memory cache still holds it
        else:  # the same texels, mapped from the file: the built ones are freed
            pyr = _load_npz(disk) or pyr
    return pyr


def sg_pyramid_for(path: str | Path, *, cache_dir: str | Path | bool | None = None,
                   device: torch.device | str | None = None, **params) -> SGPyramid:
    """The SG pyramid of a map file, built once per file version and parameters.

    Kept in memory (keyed by resolved path, modification time, size and parameters; the 4
    most recent) and on disk as ``.npz`` keyed by a hash of the file's bytes and the
    parameters, so a sweep over many scenes, or many worker processes, builds it once.

    Args:
        path: .exr or .hdr lat-long map (see :func:`torchrefract.lighting.envmap.load_envmap`).
        cache_dir: folder of the disk cache; default ``$TORCHREFRACT_CACHE`` or
            ``~/.cache/torchrefract``; ``False`` keeps it in memory only.
        device: where the pyramid is wanted (default the CPU); a copy on another device is
            kept in memory too.
        **params: keyword arguments of :func:`build_sg_pyramid` (no gradient is recorded).

    Returns:
        The pyramid (float32; must not be modified in place).
    """
    version = file_version(path, "envmap")
    if "sharpness_levels" in params and params["sharpness_levels"] is not None:
        params["sharpness_levels"] = tuple(float(k) for k in params["sharpness_levels"])
    key = tuple(sorted(params.items()))
    cd = _cache_dir(cache_dir)
    args = (*version, key, None if cd is None else str(cd))
    if device is None or torch.device(device).type == "cpu":
        return _pyramid_cached(*args)
    return _pyramid_on(*args, str(torch.device(device)))


@functools.lru_cache(maxsize=4)
def _pyramid_on(*args) -> SGPyramid:
    """The cached pyramid of ``args[:-1]`` copied to device ``args[-1]`` (kept)."""
    return _pyramid_cached(*args[:-1]).to(args[-1])


def clear_sg_cache() -> None:
    """Drop the in-memory pyramids (the disk cache is left alone)."""
    _pyramid_cached.cache_clear()
    _pyramid_on.cache_clear()

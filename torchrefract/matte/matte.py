"""The environment matte: per pixel, the L lobes the method read the environment with.

A :class:`Matte` of B views at (H, W) pixels holds, per pixel, up to L lobes (world
direction, SG sharpness, RGB weight), the sphere lights' additive RGB term and the fraction
of the lobes' energy folded into other lobes, such that (module
:mod:`torchrefract.matte.record`, eq. 1)

    radiance = sum_l weight_l * L_env(direction_l, sharpness_l) + lights

where ``L_env(d, k)`` is the scene's map (its rotation and scale applied) convolved with the
normalized SG of sharpness k (de Rousiers et al. 2012, sec. 4.1; a plain bilinear lookup for
``PLAIN``). Every lookup of the render lands in the matte: the front reflection, the
transmitted exit lobe(s) (one per roughness level with a roughness map), each followed
internal bounce's exit lobe, and the background (camera rays that miss the object: direction
the camera ray, sharpness ``PLAIN``). With n x n supersampling each sub-pixel's lobes enter
with weight 1 / n^2.

L lobes at most: a pixel's lookups are ranked by energy (mean RGB weight); the L strongest
are kept, each other one is folded into the kept lobe nearest in direction (its weight
added there), and the folded fraction of the pixel's energy is recorded (``folded``). With
nothing folded, a relit image with the render's own map equals the render to float32
rounding (:func:`torchrefract.matte.relight`).

As passes (the EXR channels and the datasets' tensors, :func:`to_passes`), lobe i is
``matte.lobe<i>.direction`` (3: ``.X .Y .Z``), ``matte.lobe<i>.sharpness`` (1) and
``matte.lobe<i>.weight`` (3: ``.X .Y .Z`` hold R, G, B), then ``matte.lights`` (3, RGB) and
``matte.folded`` (1). ``PLAIN`` (1e30) stands for k = inf in every form (no Inf leaves the
renderer); empty slots have weight 0, direction 0 and sharpness 0.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from torchrefract.checks import ConfigError
from torchrefract.matte.record import Entries

PLAIN = 1.0e30
"""Sharpness written for a plain (unfiltered, bilinear) lookup, k = inf."""

DEFAULT_LOBES = 8
"""Lobes per pixel kept by default (docs/matte.md, "How many lobes": folded energy < 1% of
the object pixels' energy on the suite scenes measured there, at their 2x2 sampling)."""


@dataclass(frozen=True)
class Matte:
    """The environment matte of B views at (H, W) pixels with L lobe slots.

    Attributes:
        direction: (B, H, W, L, 3) unit world directions (0 in empty slots).
        sharpness: (B, H, W, L) SG sharpness; ``PLAIN`` for a plain lookup.
        weight: (B, H, W, L, 3) RGB weight (throughput: Fresnel / microfacet energies,
            absorption, exit rule, coverage, the box filter's share).
        lights: (B, H, W, 3) what sphere lights add (seen directly or through the glass).
        folded: (B, H, W) fraction of the lobes' energy folded into other lobes (left
            out: read in another lobe's direction).
        merged: (B, H, W) fraction of the energy in lobes merged across the sub-pixels of
            a supersampled pixel (a lobe per sub-pixel did not fit; :func:`_merge_siblings`).
    """

    direction: torch.Tensor
    sharpness: torch.Tensor
    weight: torch.Tensor
    lights: torch.Tensor
    folded: torch.Tensor
    merged: torch.Tensor

    @property
    def lobes(self) -> int:
        return self.sharpness.shape[-1]


def build(entries: Entries, radiance: torch.Tensor, shape: tuple[int, int, int], n: int, lobes: int,
          has_lights: torch.Tensor) -> Matte:
    """The matte of a render from its recorded lookups.

    Args:
        entries: the lookups with their weights and sub-pixels
            (:func:`torchrefract.matte.record.weights`).
        radiance: (B, H, W, 3) the rendered (box-filtered) image.
        shape: (B, H, W) pixels; n: supersampling factor (sub-pixel grid n H x n W).
        lobes: L, the lobe slots per pixel.
        has_lights: (B,) bool, the views with sphere lights (elsewhere ``lights`` is 0).

    Returns:
        :class:`Matte`.
    """
    b, h, w = shape
    p_count = b * h * w
    hs, ws = h * n, w * n
    sub = entries.sub
    bi = sub // (hs * ws)
    y = (sub // ws) % hs
    x = sub % ws
    pix = bi * h * w + (y // n) * w + (x // n)  # (M,)
    wt = entries.weight / (n * n)  # the box filter's share
    energy = wt.mean(-1)
    # env part of the image as recorded, per pixel: the lights' term is what remains
    env = torch.zeros(p_count, 3, dtype=wt.dtype).index_add_(0, pix, wt * entries.value)
    lights = radiance.reshape(-1, 3).to(wt.dtype) - env
    lights = torch.where(has_lights.repeat_interleave(h * w)[:, None], lights,
                         torch.zeros_like(lights)).clamp(min=0.0)
    total = torch.zeros(p_count, dtype=wt.dtype).index_add_(0, pix, energy)
    direction_in = entries.direction.to(wt.dtype)
    k_in = entries.sharpness.to(wt.dtype)
    k_in = torch.where(torch.isfinite(k_in), k_in, torch.full_like(k_in, PLAIN)).clamp(max=PLAIN)
    merged = torch.zeros(p_count, dtype=wt.dtype)
    if n > 1:
        pix, direction_in, k_in, wt, energy, merged = _merge_siblings(
            pix, sub, direction_in, k_in, wt, energy, lobes, p_count)
    # rank the lookups within each pixel by energy (descending)
    order = torch.argsort(energy, descending=True, stable=True)
    order = order[torch.argsort(pix[order], stable=True)]  # by pixel, then energy
    pix_s = pix[order]
    counts = torch.bincount(pix_s, minlength=p_count)
    start = torch.cumsum(counts, 0) - counts
    rank = torch.arange(pix_s.numel()) - start[pix_s]
    keep = rank < lobes
    # The directions as the lookups got them (unit up to float32 rounding; the lookups
    # normalize): normalizing again would move a lookup next to a sun by a texel fraction.
    d_s, k_s, w_s = direction_in[order], k_in[order], wt[order]
    direction = torch.zeros(p_count, lobes, 3, dtype=wt.dtype)
    sharp = torch.zeros(p_count, lobes, dtype=wt.dtype)
    weight = torch.zeros(p_count, lobes, 3, dtype=wt.dtype)
    slot = pix_s[keep] * lobes + rank[keep]
    direction.view(-1, 3)[slot] = d_s[keep]
    sharp.view(-1)[slot] = k_s[keep]
    weight.view(-1, 3)[slot] = w_s[keep]
    folded = torch.zeros(p_count, dtype=wt.dtype)
    rest = ~keep
    if bool(rest.any()):
        fp = pix_s[rest]
        cand = direction[fp]  # (F, L, 3): the pixel's kept lobes
        cos = (cand * d_s[rest][:, None, :]).sum(-1)  # (F, L)
        near = cos.argmax(-1)
        weight.view(-1, 3).index_add_(0, fp * lobes + near, w_s[rest])
        folded.index_add_(0, fp, w_s[rest].mean(-1))
    den = total.clamp(min=1e-30)
    folded = torch.where(total > 0, folded / den, torch.zeros_like(folded))
    merged = torch.where(total > 0, merged / den, torch.zeros_like(merged))
    return Matte(direction=direction.view(b, h, w, lobes, 3).float(),
                 sharpness=sharp.view(b, h, w, lobes).float(),
                 weight=weight.view(b, h, w, lobes, 3).float(),
                 lights=lights.view(b, h, w, 3).float(), folded=folded.view(b, h, w).float(),
                 merged=merged.view(b, h, w).float())


def _merge_siblings(pix, sub, d, k, wt, energy, lobes: int, p_count: int):
    """Supersampled pixels with more lookups than ``lobes``: the sub-pixels' lookups of
    equal rank (by energy within their sub-pixel: the main exit lobe with the main exit
    lobe, the reflection with the reflection, ...) merged into one lobe each, moment
    matched (the Gaussian-sum reduction of Dai and Wyman 2012 and Runnalls 2007, on the
    sphere): weight summed, axis the energy-weighted mean direction m, per-axis variance
    sum_i e_i (1 / k_i + (1 - d_i . m)) / sum_i e_i (the lobes' own spread plus that of
    their axes: 1 - cos ~ theta^2 / 2 per axis), sharpness its inverse. A merged lobe reads
    the map blurred over the pixel's footprint instead of at the n^2 sub-pixel directions:
    an approximation (docs/matte.md), so pixels that fit in ``lobes`` are left exact.
    Returns the new (pix, d, k, wt, energy) and the merged energy per pixel."""
    counts = torch.bincount(pix, minlength=p_count)
    over = counts[pix] > lobes
    merged = torch.zeros(p_count, dtype=wt.dtype)
    if not bool(over.any()):
        return pix, d, k, wt, energy, merged
    keep = ~over
    sel = over.nonzero().squeeze(1)
    s_sub, s_e = sub[sel], energy[sel]
    order = torch.argsort(s_e, descending=True, stable=True)
    order = order[torch.argsort(s_sub[order], stable=True)]
    ss = s_sub[order]
    c = torch.bincount(ss)
    start = torch.cumsum(c, 0) - c
    srank = torch.empty_like(order)
    srank[order] = torch.arange(order.numel()) - start[ss]
    r = int(srank.max()) + 1
    gkey = pix[sel] * r + srank
    uniq, gid = torch.unique(gkey, return_inverse=True)
    g = uniq.numel()
    e = s_e.clamp(min=0.0)
    ge = torch.zeros(g, dtype=wt.dtype).index_add_(0, gid, e)
    gw = torch.zeros(g, 3, dtype=wt.dtype).index_add_(0, gid, wt[sel])
    dn = torch.nn.functional.normalize(d[sel], dim=-1)
    gm = torch.nn.functional.normalize(
        torch.zeros(g, 3, dtype=wt.dtype).index_add_(0, gid, e[:, None] * dn), dim=-1)
    inv_k = torch.where(k[sel] >= 0.5 * PLAIN, torch.zeros_like(e), 1.0 / k[sel].clamp(min=1e-12))
    spread = (1.0 - (dn * gm[gid]).sum(-1)).clamp(min=0.0)
    gv = torch.zeros(g, dtype=wt.dtype).index_add_(0, gid, e * (inv_k + spread)) \
        / ge.clamp(min=1e-30)
    gk = torch.where(gv > 1e-12, 1.0 / gv.clamp(min=1e-12), torch.full_like(gv, PLAIN))
    gn = torch.bincount(gid, minlength=g)
    gpix = uniq // r
    merged.index_add_(0, gpix, torch.where(gn > 1, ge, torch.zeros_like(ge)))
    # a group of one keeps its lookup exactly
    one = gn == 1
    first = torch.zeros(g, dtype=torch.long).index_put_((gid,), torch.arange(sel.numel()))
    gm = torch.where(one[:, None], d[sel][first], gm)
    gk = torch.where(one, k[sel][first], gk)
    ks = keep.nonzero().squeeze(1)
    return (torch.cat([pix[ks], gpix]), torch.cat([d[ks], gm]), torch.cat([k[ks], gk]),
            torch.cat([wt[ks], gw]), torch.cat([energy[ks], ge]), merged)


def to_passes(m: Matte) -> dict[str, torch.Tensor]:
    """The matte as render passes, name -> (B, H, W, C) (module docstring's names)."""
    out = {}
    for i in range(m.lobes):
        out[f"matte.lobe{i}.direction"] = m.direction[..., i, :]
        out[f"matte.lobe{i}.sharpness"] = m.sharpness[..., i, None]
        out[f"matte.lobe{i}.weight"] = m.weight[..., i, :]
    out["matte.lights"] = m.lights
    out["matte.folded"] = m.folded[..., None]
    out["matte.merged"] = m.merged[..., None]
    return out


def from_passes(passes: dict[str, torch.Tensor], layout: str = "hwc") -> Matte:
    """A :class:`Matte` from render passes (``RenderResult.passes``) or a dataset sample's
    ``passes`` (``layout="chw"``: (C, H, W) or (B, C, H, W) tensors, the loaders' default).

    Raises:
        ConfigError: no ``matte.*`` passes (render with ``passes: [matte]``).
    """
    if layout not in ("hwc", "chw"):
        raise ConfigError(f"from_passes: layout must be 'hwc' or 'chw', got {layout!r}")

    def get(name: str) -> torch.Tensor:
        t = passes[name]
        if layout == "chw":
            t = t.movedim(-3, -1)
        return t if t.dim() == 4 else t[None]  # (B, H, W, C)

    n = 0
    while f"matte.lobe{n}.weight" in passes:
        n += 1
    if n == 0 or "matte.lights" not in passes:
        raise ConfigError("from_passes: no matte passes (matte.lobe0.weight, matte.lights) "
                          f"among {sorted(passes)[:8]}...; render with passes: [matte]")
    return Matte(
        direction=torch.stack([get(f"matte.lobe{i}.direction") for i in range(n)], -2),
        sharpness=torch.cat([get(f"matte.lobe{i}.sharpness") for i in range(n)], -1),
        weight=torch.stack([get(f"matte.lobe{i}.weight") for i in range(n)], -2),
        lights=get("matte.lights"), folded=get("matte.folded")[..., 0],
        merged=get("matte.merged")[..., 0])


__all__ = ["DEFAULT_LOBES", "Matte", "PLAIN", "build", "from_passes", "to_passes"]

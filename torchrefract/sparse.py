"""A render pass at n x n samples per pixel by sparse supersampling
(:mod:`torchrefract.geometry.subsamples`): the one-sample pass, then the picked pixels'
sub-pixel samples shaded (:func:`torchrefract.result.finish_pass` over their G-buffer) and
their box-filtered pixels written over the one-sample image and passes."""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass

import torch

from torchrefract.geometry import adaptive, subsamples
from torchrefract.geometry.gbuffer import GBuffer, build_sparse
from torchrefract.kernels import native
from torchrefract.matte import render_hook
from torchrefract.result import RenderResult, finish_pass, front_roughness
from torchrefract.settings import current


def applies(scenes, entry, options, materials) -> bool:
    """Whether a pass of ``scenes`` (one resolution, method and options) is rendered by
    sparse supersampling: n x n samples per pixel, adaptive shading on, a method that
    shades its samples alone (``Method.shades_samples``), no matte passes asked for (they
    record every sample of one G-buffer), on the CPU (elsewhere adaptive.plan's n x n
    G-buffer)."""
    return (scenes[0].camera.samples_per_pixel > 1 and current().adaptive
            and current().torch_device().type == "cpu"
            and entry.shades_object_index and entry.shades_samples(options, materials)
            and not render_hook.requested(scenes))


@dataclass(frozen=True)
class Pending:
    """What the samples' pass needs of the first: the one-sample G-buffer ``g`` (marching
    the n x n ids), both layers' rasterized ids at n x n ``ids``, the pixels ``picked`` by
    their G-buffer and the ``region`` (B, H, W) or None."""

    g: GBuffer
    ids: tuple[torch.Tensor, torch.Tensor]
    picked: torch.Tensor
    region: torch.Tensor | None


def gbuffer(meshes, cameras) -> tuple[GBuffer, tuple[torch.Tensor, torch.Tensor],
                                     torch.Tensor | None]:
    """The one-sample G-buffer, the ids at n x n and their sub-pixel flags of a sparse
    pass (``gbuffer.build_sparse`` with the sub-pixel test's tolerances)."""
    return build_sparse(meshes, cameras, subsamples.FOLDS)


def first_pass(g: GBuffer, ids: tuple[torch.Tensor, torch.Tensor],
               flags: torch.Tensor | None, materials, region: torch.Tensor | None
               ) -> tuple[GBuffer, adaptive.Lattice | None, Pending]:
    """For the one-sample G-buffer ``g``, the ids at n x n ``ids`` and their sub-pixel
    ``flags`` (:func:`gbuffer`): the G-buffer and lattice of the first pass
    (adaptive.lattice over the pixels not picked: a picked pixel is its samples' box
    filter) and what :func:`supersample` needs."""
    alpha = front_roughness(g, materials)
    picked = subsamples.edges(g, ids, alpha, region, flags)
    g = dataclasses.replace(g, marched=subsamples.marched(g, ids))
    first, lattice = adaptive.lattice(g, alpha, region=~picked if region is None else
                                      region & ~picked)
    return first, lattice, Pending(g, ids, picked, region)


def supersample(result: RenderResult, pending: Pending, scenes, entry, lighting, materials,
                options, state, budget: int) -> RenderResult:
    """``result`` (the first pass, on the CPU) with the pixels ``pending`` picked by their
    G-buffer, and those its radiance picks (``subsamples.refined``), replaced by their
    n x n samples' box filter (written over the result's own tensors where no gradient
    flows)."""
    t0 = time.perf_counter()
    g = pending.g
    lit = (lighting.light_radius > 0).any(1)  # (B,): views with sphere lights
    picked = subsamples.refined(g, pending.picked, result.radiance, pending.region,
                                background=lit[:, None, None].expand(g.shape)
                                if bool(lit.any()) else None)
    fine = fine_environment(scenes, lighting)
    if any(fine):  # every background pixel of those views (the object's keep their rule)
        picked = picked | (~g.front.mask & torch.tensor(fine)[:, None, None])
    samples = subsamples.gather(g, pending.ids, [s.camera for s in scenes], picked)
    if samples is None:
        return result
    t1 = time.perf_counter()
    part = finish_pass(scenes, entry, samples.g, lighting, materials, options, state, budget,
                       None, t1)
    result = _put(result, part, samples.pixels)
    timings = dict(result.timings)
    for k, v in part.timings.items():
        timings[k] = timings.get(k, 0.0) + v
    timings["gbuffer"] = timings.get("gbuffer", 0.0) + (t1 - t0)
    return dataclasses.replace(result, timings=timings)


def fine_environment(scenes, lighting) -> list[bool]:
    """Per view, whether its environment map has detail finer than a pixel: more than one
    texel (at the equator) across the angle a pixel subtends at the image's center. Its
    background pixels then average their n x n samples as the uniform render does; where
    a texel spans a pixel or more the map is bilinear across the samples, whose mean is
    then the center sample (exactly within one texel cell), and a background pixel keeps
    its center sample, unless a sphere light's edge in view makes its neighbours' radiances
    spread (``subsamples.refined``)."""
    out = []
    for s, tex in zip(scenes, lighting.texels):
        c = s.camera
        pixel = math.radians(c.yfov_deg) / c.height
        h, w = tex.shape[0], tex.shape[1]
        texel = min(2.0 * math.pi / w, math.pi / max(h - 1, 1))
        out.append(texel < pixel)
    return out


def _put(result: RenderResult, part: RenderResult, pixels: torch.Tensor) -> RenderResult:
    """``result`` with ``part``'s pixels (B, K, 1, ...) written over its (B, H, W, ...) at
    ``pixels`` (B, K; -1: none): in place (csrc/box.c's ``put_rows``, all buffers in one
    call, else index copies), or into copies where a gradient flows."""
    b, h, w = result.coverage.shape
    names = list(result.passes)
    fulls = [result.radiance, result.coverage, *(result.passes[k] for k in names)]
    pieces = [part.radiance, part.coverage, *(part.passes[k] for k in names)]

    def channels(x: torch.Tensor) -> int:  # (B, H, W[, C]): C or 1
        return x.shape[3] if x.dim() == 4 else 1

    def rows(x: torch.Tensor) -> torch.Tensor:  # (B, H, W[, C]) -> (B H W, C or 1)
        return x.reshape(-1, channels(x))

    into = torch.arange(b)[:, None] * (h * w) + pixels
    if native.put_rows(torch.where(pixels >= 0, into, -1).reshape(-1),  # (in place)
                       [(f, x, channels(f)) for f, x in zip(fulls, pieces)]):
        return result
    ok = (pixels >= 0).reshape(-1).nonzero()[:, 0]  # the slots holding a pixel, once
    dst = into.reshape(-1).index_select(0, ok)

    def put(full: torch.Tensor, piece: torch.Tensor) -> torch.Tensor:
        src = rows(piece).index_select(0, ok).to(full.dtype)
        if full.requires_grad or src.requires_grad:
            return rows(full).index_copy(0, dst, src).view(full.shape)
        full.view(-1, src.shape[1]).index_copy_(0, dst, src)  # (in place: a view)
        return full

    put_all = [put(f, x) for f, x in zip(fulls, pieces)]
    return dataclasses.replace(result, radiance=put_all[0], coverage=put_all[1],
                               passes=dict(zip(names, put_all[2:])))


__all__ = ["Pending", "applies", "fine_environment", "first_pass", "gbuffer", "supersample"]

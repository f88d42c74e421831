"""Record every environment lookup of a render, and the weight the image gives it.

The tensor shading of every method ends in environment lookups made by two functions,
:func:`torchrefract.lighting.lights.incident_radiance` (a plain bilinear read) and
:func:`~torchrefract.lighting.lights.incident_radiance_sg` (the SG-pre-convolved pyramid,
de Rousiers et al. 2012 sec. 4.1). Whatever a method does to a lookup's result afterwards
(Fresnel and microfacet energies, Beer-Lambert absorption, the ``tir`` rule, internal
bounces, roughness-map coverage, lights covering part of a lobe, the box filter of
supersampling), the image is linear in it:

    radiance(pixel) = sum_j  w_j * L_env(d_j, k_j)  +  lights(pixel)                   (1)

with w_j = d radiance(pixel) / d L_env(d_j, k_j) per RGB channel. So the recorder does not
hook the methods: each lookup made while a :func:`recording` is active returns its value
plus a zero tensor ``z`` that requires a gradient (:func:`tap`), and after the render one
backward pass through the image gives every lookup's RGB weight exactly, where the
method applied it (:func:`weights`; two more passes, with the sub-pixel's column and row as
output gradients, tell which sub-pixel each lookup ended in). Lookups that a method threw
away (a ``torch.where`` that picked a light, a tile's copy of the background) get weight 0.
The lights' term of (1) is what remains of the image.

The recorder is scoped by a context variable, set by :func:`torchrefract.render` for one
render pass (like :mod:`torchrefract.stages`); outside a recording :func:`tap` costs one
context-variable read.
"""

from __future__ import annotations

import contextvars
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Iterator

import torch

KINDS = ("plain", "sg", "mip")
"""How a lookup read the map: ``plain`` bilinear (:func:`torchrefract.lighting.envmap.lookup`),
``sg`` the SG pyramid (:func:`torchrefract.lighting.sg_pyramid.sg_lookup_env`), ``mip`` a box
MIP (``lean``'s ``env_lookup: mip``; not relightable exactly: rejected for mattes)."""


@dataclass
class Lookup:
    """One batched environment lookup of N rays (all tensors detached, (N, ...)).

    Attributes:
        z: (N, 3) the zero tensor added to the lookup's result (its gradient is the weight).
        value: (N, 3) the environment radiance read (the scene's map, rotation and scale).
        origin: (N, 3) ray origins (world); direction: (N, 3) world directions.
        sharpness: (N,) SG sharpness (inf: a plain lookup).
        batch: (N,) the view of each ray.
        kind: ``plain`` or ``sg`` (or ``mip``).
    """

    z: torch.Tensor
    value: torch.Tensor
    origin: torch.Tensor
    direction: torch.Tensor
    sharpness: torch.Tensor
    batch: torch.Tensor
    kind: str


@dataclass
class Recorder:
    """The lookups of one render pass, in the order they were made."""

    lookups: list[Lookup] = field(default_factory=list)


_CURRENT: contextvars.ContextVar[Recorder | None] = contextvars.ContextVar(
    "torchrefract_matte_recorder", default=None)


@contextmanager
def recording() -> Iterator[Recorder]:
    """Record the environment lookups made inside (gradients enabled for the block)."""
    rec = Recorder()
    token = _CURRENT.set(rec)
    try:
        with torch.enable_grad():
            yield rec
    finally:
        _CURRENT.reset(token)


def active() -> bool:
    """Whether a recording is active in this context."""
    return _CURRENT.get() is not None


def tap(value: torch.Tensor, origin: torch.Tensor, direction: torch.Tensor,
        sharpness: torch.Tensor | None, batch: torch.Tensor, kind: str) -> torch.Tensor:
    """``value`` (N, 3), recorded when a recording is active (returned as ``value + z``).

    Args:
        value: the environment radiance of N rays (before any light replaces it).
        origin, direction: (N, 3) the rays; sharpness: (N,) SG sharpness, None for a plain
            lookup; batch: (N,) their views; kind: one of :data:`KINDS`.
    """
    rec = _CURRENT.get()
    if rec is None or value.shape[0] == 0:
        return value
    z = torch.zeros(value.shape, dtype=value.dtype, requires_grad=True)
    k = torch.full(value.shape[:1], float("inf"), dtype=value.dtype) if sharpness is None \
        else sharpness.detach().to(value.dtype).expand(value.shape[:1])
    rec.lookups.append(Lookup(z=z, value=value.detach(), origin=origin.detach(),
                              direction=direction.detach(), sharpness=k.clone(),
                              batch=batch.detach().clone(), kind=kind))
    return value + z


@dataclass(frozen=True)
class Entries:
    """Every recorded lookup with a nonzero weight, flattened (M entries).

    Attributes:
        sub: (M,) flat index of the sub-pixel (b * Hs * Ws + y * Ws + x) the lookup ends in.
        weight: (M, 3) d image / d lookup per RGB channel, at the sub-pixel level (the box
            filter's 1 / n^2 is applied by :func:`torchrefract.matte.matte.build`).
        value: (M, 3) the radiance read; origin, direction: (M, 3); sharpness: (M,)
            (inf: plain); kind: (M,) int, index into :data:`KINDS`.
    """

    sub: torch.Tensor
    weight: torch.Tensor
    value: torch.Tensor
    origin: torch.Tensor
    direction: torch.Tensor
    sharpness: torch.Tensor
    kind: torch.Tensor


def weights(rec: Recorder, radiance: torch.Tensor, eps: float = 0.0) -> Entries:
    """The weight of every recorded lookup in ``radiance`` and the sub-pixel it lands in.

    Args:
        rec: the recording.
        radiance: (B, Hs, Ws, 3) the sub-pixel image computed from the recorded lookups
            (with the autograd graph).
        eps: entries whose weight is at most this (max over RGB) are dropped.

    Returns:
        :class:`Entries`. Each lookup contributes to one sub-pixel (the methods write one
        value per sub-pixel); its column and row come from two more backward passes with
        the column and row index as output gradient (ratio to the weight, rounded; the
        rows are offset by the view's, which the lookup knows).
    """
    b, hs, ws, _ = radiance.shape
    none3 = torch.zeros(0, 3)
    empty = Entries(sub=torch.zeros(0, dtype=torch.long), weight=none3, value=none3,
                    origin=none3, direction=none3, sharpness=torch.zeros(0),
                    kind=torch.zeros(0, dtype=torch.long))
    zs = [lk.z for lk in rec.lookups]
    if not zs or not radiance.requires_grad:
        return empty
    dt = radiance.dtype
    col = torch.arange(ws, dtype=dt).view(1, 1, ws, 1).expand_as(radiance)
    row = torch.arange(hs, dtype=dt).view(1, hs, 1, 1).expand_as(radiance)
    outs = []
    for k, go in enumerate((torch.ones_like(radiance), col + 1.0, row + 1.0)):
        g = torch.autograd.grad(radiance, zs, grad_outputs=go, retain_graph=k < 2,
                                allow_unused=True)
        outs.append([torch.zeros_like(z) if x is None else x for x, z in zip(g, zs)])
    parts = []
    for lk, w, gx, gy in zip(rec.lookups, *outs):
        mag = w.abs().amax(-1)
        keep = mag > eps
        if not bool(keep.any()):
            continue
        sel = keep.nonzero().squeeze(1)
        w, gx, gy = w[sel], gx[sel], gy[sel]
        c = w.abs().argmax(-1, keepdim=True)  # the channel read for the position
        wc = w.gather(1, c)[:, 0]
        fx, fy = gx.gather(1, c)[:, 0] / wc, gy.gather(1, c)[:, 0] / wc
        x, y = fx.round().long() - 1, fy.round().long() - 1
        ok = (x >= 0) & (x < ws) & (y >= 0) & (y < hs) \
            & ((fx - fx.round()).abs() < 0.05) & ((fy - fy.round()).abs() < 0.05)
        if not bool(ok.all()):  # a lookup spread over several sub-pixels: not expected
            raise RuntimeError("matte: a lookup contributes to several sub-pixels; please "
                               "report the scene")
        bi = lk.batch[sel]
        parts.append((bi * hs * ws + y * ws + x, w, lk.value[sel], lk.origin[sel],
                      lk.direction[sel], lk.sharpness[sel],
                      torch.full_like(bi, KINDS.index(lk.kind))))
    if not parts:
        return empty
    cat = [torch.cat(p) for p in zip(*parts)]
    return Entries(sub=cat[0], weight=cat[1].detach(), value=cat[2], origin=cat[3],
                   direction=cat[4], sharpness=cat[5], kind=cat[6])


__all__ = ["Entries", "KINDS", "Lookup", "Recorder", "active", "recording", "tap", "weights"]

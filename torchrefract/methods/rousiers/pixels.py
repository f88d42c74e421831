"""The object pixels of a batch (compacted) and what every step reads there."""

from __future__ import annotations

from dataclasses import dataclass

import torch

from torchrefract.geometry.gbuffer import GBuffer
from torchrefract.kernels.index import take
from torchrefract.optics import microfacet as mf
from torchrefract.optics.materials import MaterialBatch
from torchrefract.optics.smooth import dot, face_forward


@dataclass
class Pixels:
    """N object pixels of B views.

    Attributes:
        idx: (N,) flat index into the B * H * W (sub-)pixels; bi: (N,) the view of each.
        d: (N, 3) the camera ray; view = -d.
        p1, n1: (N, 3) the front hit and its normal, on the view side; cos1 = view . n1.
        ior, alpha: (N,) the IOR and the front roughness (the map at the front hit's UV,
            sec. 5.1, else the uniform value; at least ``ALPHA_MIN``).
        dist_b: (B,) the microfacet distribution index per scene; dist (N,) per pixel.
    """

    idx: torch.Tensor
    bi: torch.Tensor
    d: torch.Tensor
    view: torch.Tensor
    p1: torch.Tensor
    n1: torch.Tensor
    cos1: torch.Tensor
    ior: torch.Tensor
    alpha: torch.Tensor
    dist_b: torch.Tensor
    dist: torch.Tensor


def object_pixels(g: GBuffer, materials: MaterialBatch) -> Pixels:
    """The front hits of the object pixels ``g`` shades (``g.object_index()``, with their
    views ``g.object_views()``)."""
    idx, bi = g.object_index(), g.object_views()
    d = take(g.ray_dir.reshape(-1, 3), idx)  # (N, 3)
    p1 = take(g.front.position.reshape(-1, 3), idx)
    n1 = face_forward(take(g.front.normal.reshape(-1, 3), idx), d)  # view side
    ior = take(materials.ior, bi)
    alpha = materials.roughness_at(bi, take(g.front.uv.reshape(-1, 2), idx)
                                   ).clamp(min=mf.ALPHA_MIN)
    dist_b = materials.distribution_index()
    dist = take(dist_b, bi)
    view = -d
    cos1 = dot(view, n1).clamp(0.0, 1.0)
    return Pixels(idx=idx, bi=bi, d=d, view=view, p1=p1, n1=n1, cos1=cos1, ior=ior,
                  alpha=alpha, dist_b=dist_b, dist=dist)


__all__ = ["Pixels", "object_pixels"]

"""What the camera sees without the object, and whether a light hides the object: the
two helpers every method starts from."""

from __future__ import annotations

import torch

from torchrefract.geometry.gbuffer import GBuffer
from torchrefract.kernels.index import put_, take, where_true
from torchrefract.lighting.lights import Lighting, hit_lights, incident_radiance
from torchrefract.shading import fused


def background(g: GBuffer, lighting: Lighting) -> torch.Tensor:
    """(B*H*W, 3) radiance of the camera rays without the object: environment or a light
    (a light in front of the object included, one behind it excluded).

    Without sphere lights nothing can hide the object, so every object pixel's value is
    replaced by the method's and the pixels the object covers are left at zero (not looked
    up); with lights, every pixel is looked up (a light in front of the object shows).
    A G-buffer with a ``canvas`` (adaptive shading's second pass) gets a copy of it, or
    the canvas itself where it is drawn in place (``GBuffer.draw_in_place``)."""
    if g.canvas is not None:
        return g.canvas if g.draw_in_place else g.canvas.clone()
    done = fused.background(g, lighting)
    if done is not None:  # the fused kernel ran
        return done
    b, h, w = g.shape
    d_all = g.ray_dir.reshape(-1, 3)
    batch_all = torch.arange(b).repeat_interleave(h * w)
    if lighting.light_pos.shape[1] == 0:
        sel = where_true(~g.front.mask.reshape(-1))
        out = torch.zeros_like(d_all)
        bs = take(batch_all, sel)
        return put_(out, sel, incident_radiance(lighting, bs, take(g.eye, bs),
                                                take(d_all, sel)))
    max_dist = torch.where(g.front.mask.reshape(-1), g.front.dist.reshape(-1),
                           torch.full_like(d_all[:, 0], float("inf")))
    return incident_radiance(lighting, batch_all, take(g.eye, batch_all), d_all, max_dist)


def light_in_front(lighting: Lighting, bi: torch.Tensor, o: torch.Tensor, d: torch.Tensor,
                   dist: torch.Tensor) -> torch.Tensor:
    """(N,) whether a sphere light lies between each camera ray's origin and the object."""
    if lighting.light_pos.shape[1] == 0:
        return torch.zeros_like(dist, dtype=torch.bool)
    t, _ = hit_lights(o, d, take(lighting.light_pos, bi), take(lighting.light_radius, bi),
                      take(lighting.light_radiance, bi))
    return t < dist


__all__ = ["background", "light_in_front"]

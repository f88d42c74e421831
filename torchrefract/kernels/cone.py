"""The bounding rays' footprint and spread (``rousiers``' cone tracing, sec. 4.3): one call
each, the backend chosen here. The native kernel (:mod:`torchrefract.kernels.native`) runs
where no gradient flows through the inputs and it is available; the tensor code otherwise
(the same values, bit for bit)."""

from __future__ import annotations

import math

import torch

from torchrefract.geometry.camera import project
from torchrefract.kernels import native
from torchrefract.kernels.index import take
from torchrefract.optics.smooth import dot, face_forward, refract


def footprint(q: torch.Tensor, ok4: torch.Tensor, center: torch.Tensor, proj: torch.Tensor,
              bi: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Screen footprint of the four bounding rays' exits q (N, 4, 3) (found: ok4 (N, 4)),
    with the central exit (N, 3) standing in for those not found; proj (B, 16) per view,
    bi (N,) the view of each ray.

    Returns xy (N, 4, 2), the central exit's xy_c (N, 2) and the bounding box's extent
    (N, 2) in pixels."""
    if native.no_grad_through(q, center):
        res = native.footprint(q, ok4, center, proj, bi)
        if res is not None:
            return res
    return footprint_tensor(q, ok4, center, proj, bi)


def ray_spread(p_t1: torch.Tensor, exact_n: torch.Tensor, dirs: torch.Tensor,
               n4: torch.Tensor, ok4: torch.Tensor, ior: torch.Tensor,
               fallback: torch.Tensor) -> torch.Tensor:
    """The geometric part of the exit lobe's per-axis variance (N,): the bounding rays dirs
    (N, 4, 3) refracted out at their exit normals n4 (found: ok4), and their squared angles
    to the central ray p_t1 refracted out at exact_n; ``fallback`` where none found its
    exit."""
    if native.no_grad_through(p_t1, exact_n, dirs, n4, ior, fallback):
        res = native.spread(p_t1, exact_n, dirs, n4, ok4, ior, fallback)
        if res is not None:
            return res
    return ray_spread_tensor(p_t1, exact_n, dirs, n4, ok4, ior, fallback)


def footprint_tensor(q: torch.Tensor, ok4: torch.Tensor, center: torch.Tensor,
                     proj: torch.Tensor, bi: torch.Tensor
                     ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """:func:`footprint` in tensor code (differentiable)."""
    pr = take(proj, bi)
    xy, _ = project(q, pr)  # (N, 4, 2)
    xy_c, _ = project(center[:, None, :], pr)
    xy_c = xy_c[:, 0]
    xy = torch.where(ok4[..., None], xy, xy_c[:, None, :])
    return xy, xy_c, xy.max(1).values - xy.min(1).values


def ray_spread_tensor(p_t1: torch.Tensor, exact_n: torch.Tensor, dirs: torch.Tensor,
                      n4: torch.Tensor, ok4: torch.Tensor, ior: torch.Tensor,
                      fallback: torch.Tensor) -> torch.Tensor:
    """:func:`ray_spread` in tensor code (differentiable). For an SG, 75% in the cone
    (eq. 12) gives theta_b^2 ~ 2 ln 4 / k, so a ray leaving at angle a adds a^2 / (2 ln 4)
    to the per-axis variance 1/k."""
    t_c, _ = refract(p_t1, face_forward(-exact_n, p_t1), ior)
    t_k, _ = refract(dirs, face_forward(-n4, dirs), ior[:, None])
    # squared chord |t_k - t_c|^2 = 2 (1 - cos a) ~ a^2: smooth (acos' diverges at 0)
    dk = t_k - t_c[:, None, :]
    chord2 = dot(dk, dk)
    ang2 = torch.where(ok4, chord2, torch.zeros_like(chord2))
    cnt = ok4.sum(-1)
    var_geo = ang2.sum(-1) / cnt.clamp(min=1) / (2.0 * math.log(4.0))
    return torch.where(cnt > 0, var_geo, fallback)


__all__ = ["footprint", "footprint_tensor", "ray_spread", "ray_spread_tensor"]

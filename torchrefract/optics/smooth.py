"""Smooth-interface optics: reflection, refraction (Snell), exact dielectric Fresnel.

Conventions: ``d`` is the propagation direction of the incoming ray (unit), ``n`` a unit
normal on the side the ray comes from (``dot(d, n) < 0``), ``eta = n_incident / n_transmitted``.
All functions are pure, batched over leading dimensions and differentiable.
"""

from __future__ import annotations

import torch


def dot(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """(..., 3), (..., 3) -> (...) (broadcast), or any equal last axis.

    3-vectors are summed per component, in the order ``(a0 b0 + a1 b1) + a2 b2``: the values
    of ``(a * b).sum(-1)``, at a third to a quarter of its time on CPU, where a reduction
    over an axis of 3 is slow (measured on 472k float32 pairs: 0.97 against 2.74 ms).
    """
    if a.shape[-1] == 3 and b.shape[-1] == 3:
        return a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1] + a[..., 2] * b[..., 2]
    return (a * b).sum(-1)


def normalize(v: torch.Tensor, eps: float = 1e-20) -> torch.Tensor:
    return v / v.norm(dim=-1, keepdim=True).clamp(min=eps)


def tangent_frame(p: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Two unit vectors orthogonal to unit p (N, 3) and to each other: u = p x h / |p x h|
    with h the x axis (the y axis where p is within ~25 degrees of x), and v = p x u."""
    helper = torch.where(p[:, :1].abs() < 0.9, p.new_tensor([1.0, 0.0, 0.0]),
                         p.new_tensor([0.0, 1.0, 0.0]))
    u = normalize(torch.cross(p, helper, dim=-1))
    return u, torch.cross(p, u, dim=-1)


def face_forward(n: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
    """Flip ``n`` where needed so that it faces against ``d`` (dot(d, n) <= 0)."""
    return torch.where((dot(n, d) > 0)[..., None], -n, n)


def reflect(d: torch.Tensor, n: torch.Tensor) -> torch.Tensor:
    """Mirror direction of ``d`` about ``n``: d - 2 (d.n) n."""
    return d - 2.0 * dot(d, n)[..., None] * n


def snell_cos(cos_i: torch.Tensor, eta: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Snell's law for the transmitted cosine: cos_t = sqrt(1 - eta^2 (1 - cos_i^2)), 0
    under total internal reflection, and whether it is (``refract``, ``fresnel_dielectric``
    and the sh paths share it, operation for operation)."""
    sin2_t = eta * eta * (1.0 - cos_i * cos_i)
    return torch.sqrt((1.0 - sin2_t).clamp(min=0.0)), sin2_t >= 1.0


def fresnel_dielectric(cos_i: torch.Tensor, eta: torch.Tensor | float) -> torch.Tensor:
    """Exact unpolarized Fresnel reflectance of a smooth dielectric interface.

    Args:
        cos_i: (...) cosine of the incident angle, in [0, 1].
        eta: n_incident / n_transmitted (scalar or broadcastable to ``cos_i``).

    Returns:
        (...) reflectance in [0, 1]; 1 under total internal reflection.
    """
    cos_i = cos_i.clamp(0.0, 1.0)
    eta = torch.as_tensor(eta, dtype=cos_i.dtype, device=cos_i.device)
    cos_t, tir = snell_cos(cos_i, eta)
    # r_s = (eta cos_i - cos_t) / (eta cos_i + cos_t), r_p = (cos_i - eta cos_t) / (cos_i + eta cos_t)
    rs_den = (eta * cos_i + cos_t).clamp(min=1e-12)
    rp_den = (cos_i + eta * cos_t).clamp(min=1e-12)
    rs = (eta * cos_i - cos_t) / rs_den
    rp = (cos_i - eta * cos_t) / rp_den
    f = 0.5 * (rs * rs + rp * rp)
    return torch.where(tir, torch.ones_like(f), f.clamp(0.0, 1.0))


def refract(d: torch.Tensor, n: torch.Tensor, eta: torch.Tensor | float
            ) -> tuple[torch.Tensor, torch.Tensor]:
    """Snell refraction of unit ``d`` at unit normal ``n`` (facing against ``d``).

    Args:
        d: (..., 3) incident direction.
        n: (..., 3) normal with dot(d, n) <= 0.
        eta: n_incident / n_transmitted, scalar or (...).

    Returns:
        t: (..., 3) unit transmitted direction; under total internal reflection the
            direction clamped to the critical angle (tangent to the surface, as the seeds
            clamp), or -n where the ray hits head-on with no tangent part.
        tir: (...) bool, total internal reflection.
    """
    eta = torch.as_tensor(eta, dtype=d.dtype, device=d.device)
    cos_i = (-dot(d, n)).clamp(0.0, 1.0)
    cos_t, tir = snell_cos(cos_i, eta)
    # cos_t = 0 (TIR) leaves the tangent part: the critical-angle direction.
    t = eta[..., None] * d + (eta * cos_i - cos_t)[..., None] * n
    return normalize(t), tir

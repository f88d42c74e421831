"""Symmetric 2x2 covariances in closed form (anisotropic lobes: LEAN footprints, EWA taps)."""

from __future__ import annotations

import torch


def psd2(c: torch.Tensor) -> torch.Tensor:
    """Symmetric 2x2 matrices with negative eigenvalues raised to 0 (closed form)."""
    a, b, d = c[..., 0, 0], c[..., 0, 1], c[..., 1, 1]
    lam1, lam2, e1 = eig2(a, b, d)
    lam1, lam2 = lam1.clamp(min=0.0), lam2.clamp(min=0.0)
    e2 = torch.stack([-e1[..., 1], e1[..., 0]], -1)
    return lam1[..., None, None] * (e1[..., :, None] * e1[..., None, :]) \
        + lam2[..., None, None] * (e2[..., :, None] * e2[..., None, :])


def eig2(a: torch.Tensor, b: torch.Tensor, d: torch.Tensor
         ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Eigen-decomposition of symmetric [[a, b], [b, d]]: the larger and smaller eigenvalue
    and the unit eigenvector (..., 2) of the larger (closed form, differentiable away from
    isotropy; an isotropic matrix gets the first axis)."""
    half_tr = 0.5 * (a + d)
    diff = 0.5 * (a - d)
    r = torch.sqrt(diff * diff + b * b + 1e-30)
    lam1, lam2 = half_tr + r, half_tr - r
    # eigenvector of lam1: (b, lam1 - a) or (lam1 - d, b), the better conditioned
    v1 = torch.stack([b, lam1 - a], -1)
    v2 = torch.stack([lam1 - d, b], -1)
    vec = torch.where((diff >= 0)[..., None], v2, v1)
    ln = vec.norm(dim=-1, keepdim=True)
    e1 = torch.where(ln > 1e-20, vec / ln.clamp(min=1e-30),
                     torch.tensor([1.0, 0.0], dtype=a.dtype).expand_as(vec))
    return lam1, lam2, e1


__all__ = ["eig2", "psd2"]

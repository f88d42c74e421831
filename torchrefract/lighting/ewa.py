"""Anisotropic lobes read from an isotropic environment filter by elliptical weighted
averaging (Mavridis and Papaioannou 2011, as Dai and Wyman 2012 use it): the lobe is a sum of
N isotropic lobes spaced along its major axis.

A lobe of covariance with eigenvalues l1 >= l2 (major axis a) becomes N equal-weight taps at
angles z_j = (j - (N - 1) / 2) D along a, each of variance v = max(l2, c l1 / N^2): their
positions' variance D^2 (N^2 - 1) / 12 is set to l1 - v, so the sum has the lobe's variance
along both axes. c = 3 N^2 / (N^2 + 2) spaces the taps two of their own standard deviations
apart (no ripples); the price is that anisotropy beyond sqrt((N^2 + 2) / 3) : 1 in standard
deviation (2.4 : 1 for N = 4) is rounded off.
One tap is the isotropic lobe of the same total variance (l1 + l2) / 2, the poster's merge.
"""

from __future__ import annotations

import torch

from torchrefract.lighting.lights import Lighting, incident_radiance_sg
from torchrefract.optics.cov2 import eig2
from torchrefract.optics.smooth import normalize


def ewa_taps(axis: torch.Tensor, cov: torch.Tensor, e1: torch.Tensor, e2: torch.Tensor,
             taps: int) -> tuple[torch.Tensor, torch.Tensor]:
    """The taps of lobes around unit ``axis`` (N, 3) with tangent covariance ``cov``
    (N, 2, 2) in the basis (e1, e2): directions (N, T, 3) and SG sharpness 1 / v (N,)
    (module docstring); each tap weighs 1 / T."""
    l1, l2, ev = eig2(cov[:, 0, 0], cov[:, 0, 1], cov[:, 1, 1])
    l1, l2 = l1.clamp(min=1e-12), l2.clamp(min=1e-12)
    if taps == 1:
        return axis[:, None, :], 2.0 / (l1 + l2)
    c = 3.0 * taps * taps / (taps * taps + 2.0)
    v = torch.maximum(l2, l1 * (c / (taps * taps)))
    # (clamped above 0, not at it: a finite gradient where the lobe is within the taps' reach)
    spacing = torch.sqrt((12.0 * (l1 - v) / (taps * taps - 1.0)).clamp(min=1e-30))
    major = normalize(ev[:, :1] * e1 + ev[:, 1:] * e2)
    z = (torch.arange(taps, dtype=axis.dtype) - 0.5 * (taps - 1))[None, :] * spacing[:, None]
    dirs = torch.cos(z)[..., None] * axis[:, None, :] + torch.sin(z)[..., None] * major[:, None]
    return dirs, 1.0 / v


def ewa_radiance(lighting: Lighting, batch: torch.Tensor, origin: torch.Tensor,
                 axis: torch.Tensor, cov: torch.Tensor, e1: torch.Tensor, e2: torch.Tensor,
                 taps: int, env: str = "sg") -> torch.Tensor:
    """Radiance (N, 3) of anisotropic lobes (:func:`ewa_taps`), each tap read with
    :func:`torchrefract.lighting.lights.incident_radiance_sg` (lights included)."""
    dirs, k = ewa_taps(axis, cov, e1, e2, taps)
    n, t = dirs.shape[:2]
    out = incident_radiance_sg(lighting, batch.repeat_interleave(t),
                               origin.repeat_interleave(t, 0), dirs.reshape(-1, 3),
                               k.repeat_interleave(t), env)
    return out.view(n, t, 3).mean(1)


__all__ = ["ewa_radiance", "ewa_taps"]

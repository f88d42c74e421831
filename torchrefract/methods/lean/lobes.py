"""Anisotropic exit lobes (Dai and Wyman 2012): the footprint's Gaussian NDF and the front
lobe carried through the exit refraction, as a 2x2 angular covariance around the exit
direction.

Refraction linearized at a smooth interface (Snell, sin t = eta sin i, eta = ior leaving the
glass). With e_perp the normal of the plane of incidence and bases (e_perp x d, e_perp) at
each direction d (the incident i, the normal n facing against i, the outgoing o), small
deviations map diagonally:

    incident -> outgoing:  J_i = diag(m, eta),            m = eta cos i / cos t
    normal   -> outgoing:  J_n = diag(1 - m, eta cos i - cos t)

(in-plane: rotating n by delta rotates o by (1 - m) delta; across the plane the tangential
part of o is eta times that of i). m diverges at the critical angle; as for the internal
bounces (docs/decisions_rousiers.md) a lobe cannot spread past the hemisphere, so |m| is
bounded at 2. The outgoing covariance is the convolution (sum) of the parts:

    Sigma_o = I / k_t2 + J_i (I / k_t1) J_i^T + J_n Sigma_n J_n^T        (``spread: paper``)

with k_t2 the SG table's exit lobe for the footprint's mean roughness (the microfacet part)
and Sigma_n the NDF's geometric covariance. ``spread: rays`` (ours) replaces the last two
terms by the covariance of the four marched bounding rays' exit directions
(:func:`ray_covariance`): it sees how the front lobe maps through the object, so a curved
back surface focuses it (the poster's "lobes that do not shrink").
"""

from __future__ import annotations

import math

import torch

from torchrefract.optics.smooth import dot, face_forward, normalize, refract, tangent_frame

M_MAX = 2.0
"""Bound of the in-plane magnification |d theta_out / d theta_in| (module docstring)."""


def incidence_frame(i: torch.Tensor, n: torch.Tensor
                    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """e_perp (..., 3), the normal of the plane of incidence of unit i at unit n (any
    perpendicular of i at normal incidence), and cos i (...,) with n facing against i;
    also n so faced."""
    n = face_forward(n, i)
    e = torch.cross(i, n, dim=-1)
    ln = e.norm(dim=-1, keepdim=True)
    shape = i.shape
    alt = tangent_frame(i.reshape(-1, 3))[0].view(shape)
    e_perp = torch.where(ln > 1e-6, e / ln.clamp(min=1e-12), alt)
    return e_perp, (-dot(i, n)).clamp(0.0, 1.0), n


def exit_jacobians(cos_i: torch.Tensor, ior: torch.Tensor
                   ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Diagonals of J_i and J_n (module docstring) at the incident cosine ``cos_i`` (already
    clamped to the critical angle where the exit rule says so): (m, eta, 1 - m, eta cos i -
    cos t), m bounded at ``M_MAX``."""
    sin2_t = ior * ior * (1.0 - cos_i * cos_i)
    cos_t = torch.sqrt((1.0 - sin2_t).clamp(min=1e-4))
    m = (ior * cos_i / cos_t).clamp(max=M_MAX)
    perp_n = (ior * cos_i - torch.sqrt((1.0 - sin2_t).clamp(min=0.0)))
    return m, ior.expand_as(m), 1.0 - m, perp_n


def to_basis(cov: torch.Tensor, u: torch.Tensor, v: torch.Tensor, e1: torch.Tensor,
             e2: torch.Tensor) -> torch.Tensor:
    """A tangent-plane covariance (..., 2, 2) in the basis (u, v) re-expressed in (e1, e2)
    (all (..., 3) spanning the same plane, to first order)."""
    r = torch.stack([torch.stack([dot(e1, u), dot(e1, v)], -1),
                     torch.stack([dot(e2, u), dot(e2, v)], -1)], -2)
    return r @ cov @ r.transpose(-1, -2)


def paper_covariance(i: torch.Tensor, n_in: torch.Tensor, cos_i: torch.Tensor,
                     ior: torch.Tensor, var_front: torch.Tensor, cov_n: torch.Tensor,
                     u: torch.Tensor, v: torch.Tensor, o: torch.Tensor
                     ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``spread: paper``'s geometric part J_i (var_front I) J_i^T + J_n Sigma_n J_n^T
    (module docstring) around the outgoing axis o: the covariance (..., 2, 2) and its basis
    (e_perp x o, e_perp). ``cov_n`` (..., 2, 2) is in the normal's basis (u, v)."""
    e_perp, _, n_f = incidence_frame(i, n_in)
    m, eta, jn_par, jn_perp = exit_jacobians(cos_i, ior)
    e_par_n = torch.cross(e_perp, n_f, dim=-1)
    c_n = to_basis(cov_n, u, v, e_par_n, e_perp)
    jn = torch.stack([jn_par, jn_perp], -1)
    ji2 = torch.stack([m * m, eta * eta], -1) * var_front[..., None]
    cov = jn[..., :, None] * c_n * jn[..., None, :] + torch.diag_embed(ji2)
    return cov, torch.cross(e_perp, o, dim=-1), e_perp


def ray_covariance(p_t1: torch.Tensor, exact_n: torch.Tensor, dirs: torch.Tensor,
                   n4: torch.Tensor, ok4: torch.Tensor, ior: torch.Tensor,
                   e_perp: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``spread: rays``: the four bounding rays (75% of the front lobe, eq. 12 of de
    Rousiers) refracted out at their own exit normals; their deviations d_j from the central
    ray's smooth exit direction t_c give the covariance sum_j d_j d_j^T / (count ln 4) in
    the basis (e_perp x t_c, e_perp) (the anisotropic form of
    :func:`torchrefract.kernels.cone.ray_spread_tensor`, whose per-axis variance is this
    matrix's trace / 2; the same axes, e_perp x o, e_perp, at a lobe's axis o in the plane
    of incidence carry it there). Returns it (N, 2, 2) and the rays found (N,)."""
    t_c, _ = refract(p_t1, face_forward(-exact_n, p_t1), ior)
    e1 = normalize(torch.cross(e_perp, t_c, dim=-1))
    e2 = e_perp
    t_k, _ = refract(dirs, face_forward(-n4, dirs), ior[:, None])
    dk = (t_k - t_c[:, None, :]) * ok4[..., None].to(t_k.dtype)
    d2 = torch.stack([dot(dk, e1[:, None, :]), dot(dk, e2[:, None, :])], -1)  # (N, 4, 2)
    cnt = ok4.sum(-1)
    cov = (d2[..., :, None] * d2[..., None, :]).sum(1) / (
        cnt.clamp(min=1).to(d2.dtype) * math.log(4.0))[:, None, None]
    return cov, cnt


def out_basis(o: torch.Tensor, i: torch.Tensor, n_in: torch.Tensor
              ) -> tuple[torch.Tensor, torch.Tensor]:
    """The basis (e_perp x o, e_perp) at the outgoing axis o for incident i at n_in."""
    e_perp = incidence_frame(i, n_in)[0]
    return normalize(torch.cross(e_perp, o, dim=-1)), e_perp


__all__ = ["M_MAX", "exit_jacobians", "incidence_frame", "out_basis", "paper_covariance",
           "ray_covariance", "to_basis"]

"""The SG table lookups (sec. 3.1, eqs. 8-9: T(theta_o, eta, kappa) -> (alpha, kappa, p))
and step 1, the front interface's lobes."""

from __future__ import annotations

from dataclasses import dataclass

import torch

from torchrefract.kernels.index import put_, take, where_true
from torchrefract.optics.sgfit import (
    lobe_axis,
    matched_fade,
    sg_energies,
    sg_lookup,
    spread_cosines,
    spread_mean,
)
from torchrefract.optics.smooth import normalize


def sg_lobe(table, cos_theta, eta, alpha, dist: torch.Tensor, lobe: str):
    """SG table lookup (amplitude, sharpness, axis angle, energy); GGX pixels use the
    L2-optimal sharpness.

    Moment matching (the paper's fit) is dominated by GGX's heavy tails: its peak comes out
    2-5x too low. The table also stores, for each entry, the sharpness minimizing the L2
    distance to the true lobe at the same energy and axis; Beckmann's two agree within a
    few percent, so Beckmann keeps the paper's moments.
    """
    out = sg_lookup(table, cos_theta, eta, alpha, dist, lobe, sharpness="moment")
    ggx = dist == 1
    if bool(ggx.any()):
        l2 = sg_lookup(table, cos_theta, eta, alpha, dist, lobe, sharpness="l2")
        out = tuple(torch.where(ggx, b, a) for a, b in zip(out, l2))
    fade = matched_fade(eta)
    if bool((fade < 1).any()):  # near IOR 1: the roughness's energy change fades out
        a, k, t, e = out
        e0 = sg_lookup(table, cos_theta, eta, torch.full_like(alpha, table.spec.alpha_min),
                       dist, lobe)[3]
        near = fade < 1  # elsewhere exactly the unfaded values (batch-independent bits)
        e_f = torch.where(near, e0 + fade * (e - e0), e)
        a = torch.where(near, a * e_f / e.clamp(min=1e-12), a)  # scales with the energy
        out = (a, k, t, e_f)
    return out


def spread_energies(table, cos_theta: torch.Tensor, var: torch.Tensor, eta: torch.Tensor,
                    alpha: torch.Tensor, dist: torch.Tensor
                    ) -> tuple[torch.Tensor, torch.Tensor]:
    """The transmitted and reflected lobes' energies (``sg_lobe``'s, faded the same way near
    IOR 1) averaged over a lobe of arriving directions of variance ``var`` around the axis
    at ``cos_theta`` (:func:`torchrefract.optics.sgfit.spread_cosines`), (N,) each."""
    cs = spread_cosines(cos_theta, var)  # (3, N)
    args = [x.expand_as(cs) for x in (eta, alpha, dist)]
    e_t, e_r = sg_energies(table, cs, *args)
    fade = matched_fade(eta)
    if bool((fade < 1).any()):
        e_t0, e_r0 = sg_energies(table, cs, args[0], torch.full_like(cs, table.spec.alpha_min),
                                 args[2])
        near = fade < 1  # elsewhere exactly the unfaded values (batch-independent bits)
        e_t = torch.where(near, e_t0 + fade * (e_t - e_t0), e_t)
        e_r = torch.where(near, e_r0 + fade * (e_r - e_r0), e_r)
    return spread_mean(e_t), spread_mean(e_r)


def true_angle_transmit(table, e_t_clamped: torch.Tensor, tir: torch.Tensor,
                        cos_theta: torch.Tensor, eta: torch.Tensor, alpha: torch.Tensor,
                        dist: torch.Tensor) -> torch.Tensor:
    """The transmitted lobe's energy at the true incident angle ``cos_theta``, given
    ``e_t_clamped``, the lookup at that angle clamped to the critical one under ``tir``:
    the two agree elsewhere, so only the TIR points are looked up again."""
    sel = where_true(tir)
    if sel.numel() == 0:
        return e_t_clamped
    e = e_t_clamped.clone()
    put_(e, sel, sg_lobe(table, take(cos_theta, sel), take(eta, sel), take(alpha, sel),
                         take(dist, sel), "transmit")[3])
    return e


@dataclass
class FrontLobes:
    """Step 1: the front interface's reflected lobe (energy e_r, sharpness k_r, axis
    axis_r) and transmitted lobe (e_t1, k_t1, unit axis p_t1), (N,) / (N, 3)."""

    e_r: torch.Tensor
    k_r: torch.Tensor
    axis_r: torch.Tensor
    e_t1: torch.Tensor
    k_t1: torch.Tensor
    p_t1: torch.Tensor


def front_lobes(table, view: torch.Tensor, n1: torch.Tensor, cos1: torch.Tensor,
                ior: torch.Tensor, alpha: torch.Tensor, dist: torch.Tensor) -> FrontLobes:
    """Step 1 (eqs. 8-9): the SG fits of the Walter BRDF and BTDF for the view angle
    (``n1``: the normal on the view side), the IOR and the front roughness."""
    _, k_r, t_r, e_r = sg_lobe(table, cos1, ior, alpha, dist, "reflect")
    axis_r = lobe_axis(view, n1, t_r, "reflect")
    _, k_t1, t_t1, e_t1 = sg_lobe(table, cos1, ior, alpha, dist, "transmit")
    p_t1 = normalize(lobe_axis(view, n1, t_t1, "transmit"))
    return FrontLobes(e_r=e_r, k_r=k_r, axis_r=axis_r, e_t1=e_t1, k_t1=k_t1, p_t1=p_t1)


__all__ = ["FrontLobes", "front_lobes", "sg_lobe", "spread_energies", "true_angle_transmit"]

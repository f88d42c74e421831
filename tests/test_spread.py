"""The exit interface's energies averaged over the arriving lobe (``sgfit.spread_cosines``).

The light reaching an exit comes from the entry's rough transmitted lobe, not along one ray;
a rough interface's energies bend sharply with the angle (total internal reflection, grazing
masking), so the methods average them over a four-point quadrature of that lobe. Checked
here: the quadrature against Monte Carlo of the von Mises-Fisher lobe it stands for, and the
averaged exit weight of ``specular`` (``tir: conserve``) against Monte Carlo through a slab
with Mitsuba 3's own ``roughdielectric`` sampling the entry.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from torchrefract.optics.sgfit import interface_energies, load_sg_table, spread_cosines, spread_mean
from torchrefract.optics.smooth import fresnel_dielectric
from torchrefract.shading.bounces import escape_fraction
from torchrefract.shading.paths import spread_exit


def _vmf_samples(k: float, n: int, gen: torch.Generator) -> torch.Tensor:
    """(n,) cosines of vMF(k) directions with the lobe's axis (exact inverse CDF)."""
    u = torch.rand(n, generator=gen, dtype=torch.float64)
    return 1.0 + torch.log(u + (1.0 - u) * math.exp(-2.0 * k)) / k


@pytest.mark.parametrize("k", [30.0, 100.0, 1000.0])
@pytest.mark.parametrize("theta0", [0.0, 0.5, 1.0])
def test_quadrature_matches_the_lobe(k, theta0):
    """E[cos] and E[cos^2] of the angle to the normal over a vMF lobe whose axis is at
    theta0 from the normal: the four points give them within 2e-3 (Monte Carlo: 4e5
    samples, standard error < 5e-4). The lobes stay above the horizon here (no clamp)."""
    gen = torch.Generator().manual_seed(1)
    n = 400_000
    cos_a = _vmf_samples(k, n, gen)  # angle to the axis
    phi = 2.0 * math.pi * torch.rand(n, generator=gen, dtype=torch.float64)
    sin_a = torch.sqrt((1.0 - cos_a * cos_a).clamp(min=0.0))
    # the direction's cosine with a normal at theta0 from the axis
    c = math.cos(theta0) * cos_a + math.sin(theta0) * sin_a * torch.cos(phi)
    cs = spread_cosines(torch.tensor([math.cos(theta0)], dtype=torch.float64),
                        torch.tensor([1.0 / k], dtype=torch.float64))[:, 0]
    assert abs(spread_mean(cs).item() - c.mean().item()) < 2e-3
    assert abs(spread_mean(cs * cs).item() - (c * c).mean().item()) < 2e-3


def test_a_single_ray_keeps_its_cosine_exactly():
    """var 0 returns the cosine itself, bit for bit, also next to spread lobes; a lobe
    (here r ~ 0.014 rad, axes at least 0.45 rad from the normal: r < 2 theta) puts one
    point closer to the normal and one farther."""
    c = 0.1 + 0.8 * torch.rand(1000, generator=torch.Generator().manual_seed(3))
    cs = spread_cosines(c, torch.zeros(1000))
    assert torch.equal(cs, c.expand(3, -1))
    mixed = torch.where(torch.arange(1000) % 2 == 0, 0.0, 1e-4)
    cs = spread_cosines(c, mixed)
    assert torch.equal(cs[:, ::2], c[::2].expand(3, -1))
    assert (cs[0, 1::2] > c[1::2]).all() and (cs[1, 1::2] < c[1::2]).all()


def _exit_weight(table, c2: torch.Tensor, alpha: float) -> torch.Tensor:
    """``tir: conserve``'s exit weight e_t + e_r P_esc at the incident cosines c2 (IOR 1.5)."""
    eta = torch.full_like(c2, 1.0 / 1.5)
    e_t, e_r = interface_energies(table, c2, eta, torch.full_like(c2, alpha), "beckmann",
                                  fresnel_dielectric(c2, 1.0 / eta))
    return (e_t + e_r * _escape(table, alpha)).clamp(max=1.0)


@pytest.mark.parametrize("alpha", [0.3, 0.5])
def test_exit_weight_through_a_rough_slab_matches_mitsuba(mi_vectorized, alpha):
    """Light enters a rough slab (IOR 1.5, Beckmann) at cos theta_i; Mitsuba samples the
    transmitted direction, our exit weight is taken at each sample's own angle (the slab's
    faces are parallel) and averaged with Mitsuba's weights: the truth for a given exit
    model. ``spread_exit`` (the lobe's tilted axis, four points) gives it within 0.015
    at every angle, where the sharp refracted ray is off by up to 0.18 near grazing
    (measured 0.01-0.18 at alpha 0.5)."""
    mi = mi_vectorized
    table = load_sg_table()
    bsdf = mi.load_dict({"type": "roughdielectric", "distribution": "beckmann",
                         "alpha": alpha, "int_ior": 1.5, "ext_ior": 1.0})
    n = 200_000
    rng = np.random.default_rng(7)
    worst_sharp = 0.0
    import drjit as dr  # noqa: PLC0415

    for cos_i in (1.0, 0.9, 0.7, 0.5, 0.3, 0.1):
        si = dr.zeros(mi.SurfaceInteraction3f, n)
        si.wi = mi.Vector3f(math.sqrt(1.0 - cos_i * cos_i), 0.0, cos_i)
        si.sh_frame = mi.Frame3f(mi.Vector3f(0, 0, 1))
        u = rng.random((3, n)).astype(np.float32)
        bs, w = bsdf.sample(mi.BSDFContext(), si, mi.Float(u[0]), mi.Point2f(u[1], u[2]))
        w = np.array(w).reshape(3, -1)[0] * 1.5 ** 2  # radiance scaling -> energy
        wo_z = np.array(bs.wo).reshape(3, -1)[2]
        inside = wo_z < 0
        c2 = torch.from_numpy(-wo_z[inside]).double().clamp(0.0, 1.0)
        ww = torch.from_numpy(w[inside]).double()
        truth = float((ww * _exit_weight(table, c2, alpha)).sum() / ww.sum())

        c1 = torch.tensor([cos_i], dtype=torch.float64)
        cos2 = torch.sqrt(1.0 - (1.0 - c1 * c1) / 1.5 ** 2)  # the sharp ray's, inside
        a = torch.tensor([alpha], dtype=torch.float64)
        e_t2, e_r2, var = spread_exit(table, c1, torch.tensor([1.5], dtype=torch.float64), a,
                                       torch.zeros(1, dtype=torch.long), cos2, a)
        ours = float((e_t2 + e_r2 * _escape(table, alpha)).clamp(max=1.0))
        sharp = float(_exit_weight(table, cos2, alpha))
        assert var.item() > 0
        assert abs(ours - truth) < 0.015, (cos_i, ours, truth, sharp)
        worst_sharp = max(worst_sharp, abs(sharp - truth))
    assert worst_sharp > 0.05  # the case is one where the lobe matters


def _escape(table, alpha: float) -> torch.Tensor:
    return escape_fraction(table, torch.tensor([1.5]), torch.tensor([0]),
                           torch.tensor([alpha], dtype=torch.float64),
                           torch.zeros(1, dtype=torch.long))

"""Spherical Gaussian fit of the BTDF/BRDF lobes (torchrefract.optics.sgfit) and its table lookup."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from torchrefract.optics import microfacet as mf, sg_fit, sg_table, sgfit
from torchrefract.optics.smooth import fresnel_dielectric, refract

F64 = torch.float64


@pytest.fixture(autouse=True, scope="module")
def _one_thread(one_thread):
    """One intra-op thread for this module (see conftest.one_thread)."""
    yield


@pytest.fixture(scope="module")
def table() -> sg_table.SGTable:
    if not sg_table.SHIPPED_TABLE.is_file():
        pytest.skip("torchrefract/tables/sg_table_v1.npz missing (run scripts/build_sg_table.py)")
    return sg_table.read_sg_table(sg_table.SHIPPED_TABLE)


def _frame(axis: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    t = torch.tensor([0.0, 1.0, 0.0], dtype=F64)
    b = torch.linalg.cross(axis, t)
    return t, b / b.norm()


def brute_force_lobe(theta: float, eta: float, alpha: float, dist: str, lobe: str,
                     n_rho: int = 400, n_phi: int = 160) -> dict[str, float]:
    """Moments of the true lobe by quadrature of ``microfacet.eval`` over outgoing directions.

    Independent of the fit's microfacet-normal quadrature: a polar grid around the smooth
    (Snell or mirror) direction, ``rho = pi sinh(c t) / sinh(c)`` (fine near the peak, the
    whole sphere covered), midpoints in ``t`` and ``phi``.
    """
    wi = torch.tensor([math.sin(theta), 0.0, math.cos(theta)], dtype=F64)
    if lobe == "transmit":
        s, _ = refract(-wi, torch.tensor([0.0, 0.0, 1.0], dtype=F64), 1.0 / eta)
    else:
        s = torch.tensor([-math.sin(theta), 0.0, math.cos(theta)], dtype=F64)
    u, v = _frame(s)
    c = 2.5 if alpha >= 0.05 else 4.5
    t = (torch.arange(n_rho, dtype=F64) + 0.5) / n_rho
    rho = math.pi * torch.sinh(c * t) / math.sinh(c)
    drho = math.pi * c * torch.cosh(c * t) / math.sinh(c) / n_rho
    phi = (torch.arange(n_phi, dtype=F64) + 0.5) / n_phi * 2 * math.pi
    d = (torch.cos(rho)[:, None, None] * s + torch.sin(rho)[:, None, None]
         * (torch.cos(phi)[None, :, None] * u + torch.sin(phi)[None, :, None] * v))
    dw = (torch.sin(rho) * drho)[:, None] * (2 * math.pi / n_phi)
    f = mf.eval(wi, d, alpha, eta, dist, radiance=False)
    side = d[..., 2] < 0 if lobe == "transmit" else d[..., 2] > 0
    w = torch.where(side, f, torch.zeros_like(f)) * dw
    e = w.sum()
    m = (w[..., None] * d).sum((0, 1)) / e
    r = m.norm()
    p = m / r
    one_minus_r = ((w * 0.5 * ((d - p) ** 2).sum(-1)).sum() / e)  # stable 1 - |m|
    k = sg_fit.sharpness_from_mean_length(one_minus_r)
    sign = -1.0 if lobe == "transmit" else 1.0
    return {"energy": float(e), "angle": float(torch.atan2(-p[0], sign * p[2])),
            "k": float(k)}


# (distribution, lobe, theta index, eta index, alpha index) of shipped-table nodes;
# theta nodes are 90/47 deg apart, eta index 16 is 1, 22 ~ 1.49, 10 ~ 0.67, 26 ~ 2.1,
# alpha index 0 = 1e-3, 8 ~ 0.01, 14 ~ 0.047, 19 ~ 0.22, 23 = 1.
ENTRIES = [
    ("beckmann", "transmit", 0, 22, 14), ("beckmann", "transmit", 18, 22, 19),
    ("beckmann", "transmit", 36, 22, 23), ("beckmann", "transmit", 18, 10, 19),
    ("beckmann", "transmit", 30, 26, 8), ("beckmann", "reflect", 25, 22, 19),
    ("ggx", "transmit", 10, 22, 19), ("ggx", "transmit", 18, 10, 14),
    ("ggx", "transmit", 30, 26, 23), ("ggx", "reflect", 30, 22, 14),
]


@pytest.mark.parametrize("entry", ENTRIES, ids=lambda e: "-".join(map(str, e)))
def test_table_matches_brute_force(table, entry):
    dist, lobe, ti, ei, ai = entry
    theta, eta, alpha = table.theta[ti], table.eta[ei], table.alpha[ai]
    ref = brute_force_lobe(theta, eta, alpha, dist, lobe)
    e, log_k, ang, _ = table.data[sg_table.DISTRIBUTIONS.index(dist), sg_table.LOBES.index(lobe),
                                  ti, ei, ai].double().tolist()
    k = math.exp(log_k)
    width = 1.0 / math.sqrt(ref["k"])  # angular std. dev. of the lobe per axis
    assert abs(e - ref["energy"]) < 0.01 * ref["energy"], (e, ref)
    assert abs(ang - ref["angle"]) < 0.05 * width, (ang, ref, width)
    assert abs(math.log(k / ref["k"])) < 0.02, (k, ref)  # sharpness within 2%


def test_tir_entries_have_zero_transmitted_energy(table):
    d = table.data
    eta = torch.tensor(table.eta)
    theta = torch.tensor(table.theta)
    crit = torch.asin(eta.clamp(max=1.0))  # critical angle for eta < 1
    beyond = theta[:, None] > crit[None, :] + math.radians(3)  # (T, E)
    beyond &= eta[None, :] < 1
    for ai in np.nonzero(table.alpha <= 0.01)[0]:
        e_t = d[0, 0, :, :, ai, 0]  # Beckmann: no microfacet transmits there
        assert (e_t[beyond] == 0).all()
        # GGX's heavy tails keep microfacets steep enough to transmit: < 0.4% at alpha 0.01
        assert (d[1, 0, :, :, ai, 0][beyond] < 5e-3).all()
        # lookups: zero amplitude, finite parameters
        # lookups inside TIR cells (both theta neighbours beyond): exactly zero amplitude
        inner = beyond[1:-1] & beyond[:-2] & beyond[2:]
        th = theta[1:-1, None].expand_as(inner)[inner]
        et = eta[None, :].expand_as(inner)[inner]
        if table.alpha[ai] < 0.007:  # alpha neighbours also in the Beckmann-TIR range
            a, k, ang, en = sgfit.sg_lookup(table, torch.cos(th), et,
                                            torch.full_like(th, float(table.alpha[ai])))
            assert (a == 0).all() and (en == 0).all()
            assert torch.isfinite(k).all() and torch.isfinite(ang).all()
    # rough surfaces keep some energy beyond the critical angle (not forced to 0)
    assert d[0, 0, 30, 10, 23, 0] > 1e-3
    assert torch.isfinite(d).all()


@pytest.mark.parametrize("dist", sg_table.DISTRIBUTIONS)
def test_alpha_to_zero_is_snell_and_fresnel(table, dist):
    g = torch.Generator().manual_seed(0)
    n = 400
    eta = torch.exp(torch.empty(n, dtype=F64).uniform_(math.log(1 / 2.9), math.log(2.9),
                                                        generator=g))
    # stay 4 degrees below the critical angle of the next smaller eta node (the table
    # interpolates across eta, and the critical angle moves fast as eta -> 1 from below)
    step = math.exp(2 * math.log(table.spec.eta_max) / (table.spec.n_eta - 1))
    eta_lo = (eta / step).clamp(max=1.0)
    crit = torch.where(eta < 1, torch.asin(eta_lo), torch.full_like(eta, 1.5))
    theta = torch.rand(n, generator=g, dtype=F64) * (crit - math.radians(4)).clamp(
        max=math.radians(80))
    cos_o = torch.cos(theta)
    f = fresnel_dielectric(cos_o, 1.0 / eta)
    sin_t = torch.sin(theta) / eta
    for alpha in (1e-4, 0.0):
        a, k, ang, e = sgfit.sg_lookup(table, cos_o, eta, torch.full_like(eta, alpha), dist)
        assert (k > 1e5).all()
        assert (ang - torch.asin(sin_t)).abs().max() < math.radians(0.1)
        assert (e - (1 - f)).abs().max() < 0.01
        a, k, ang, e = sgfit.sg_lookup(table, cos_o, eta, torch.full_like(eta, alpha), dist,
                                       lobe="reflect")
        assert (ang - theta).abs().max() < math.radians(0.1)
        assert (e - f).abs().max() < 0.01
    # the 3D axis is the refracted direction of optics.refract
    view = torch.stack([torch.sin(theta), torch.zeros_like(theta), cos_o], -1)
    nrm = torch.tensor([0.0, 0.0, 1.0], dtype=F64).expand_as(view)
    _, _, ang, _ = sgfit.sg_lookup(table, cos_o, eta, 1e-4, dist)
    axis = sgfit.lobe_axis(view, nrm, ang, "transmit")
    t, _ = refract(-view, nrm, 1.0 / eta)
    assert (axis - t).norm(dim=-1).max() < math.radians(0.1)


def test_lookup_is_continuous(table):
    """Refining the sweep step shrinks the largest jump: no discontinuities."""
    def sweep(n, which):
        s = torch.linspace(0, 1, n, dtype=F64)
        c, e, a = torch.full_like(s, 0.6), torch.full_like(s, 1.37), torch.full_like(s, 0.08)
        if which == "theta":
            c = torch.cos(s * 1.5)
        elif which == "eta":
            e = torch.exp((s - 0.5) * 2 * math.log(2.9))
        else:
            a = torch.exp(math.log(1e-4) + s * -math.log(1e-4))
        out = sgfit.sg_lookup(table, c, e, a, "beckmann")
        return torch.stack([out[3], torch.log(out[1]), out[2]], -1)

    for which in ("theta", "eta", "alpha"):
        coarse = sweep(2001, which).diff(dim=0).abs().max(0).values
        fine = sweep(4001, which).diff(dim=0).abs().max(0).values
        assert (fine <= 0.55 * coarse + 1e-9).all(), (which, coarse, fine)


def test_gradcheck_lookup(table):
    c = torch.tensor([0.83, 0.37, 0.95], dtype=F64, requires_grad=True)
    e = torch.tensor([1.37, 0.71, 2.2], dtype=F64, requires_grad=True)
    a = torch.tensor([0.13, 0.41, 0.02], dtype=F64, requires_grad=True)
    for lobe in sg_table.LOBES:
        for sharp in ("moment", "l2"):
            assert torch.autograd.gradcheck(
                lambda c, e, a: sgfit.sg_lookup(table, c, e, a, "ggx", lobe, sharp), (c, e, a))
    # finite gradients at the edges (normal incidence, eta = 1, alpha below the table)
    c = torch.tensor([1.0, 0.0, 0.5], dtype=F64, requires_grad=True)
    e = torch.tensor([1.0, 3.0, 1 / 3], dtype=F64, requires_grad=True)
    a = torch.tensor([1e-4, 1.0, 0.0], dtype=F64, requires_grad=True)
    sum(o.sum() for o in sgfit.sg_lookup(table, c, e, a)).backward()
    assert all(torch.isfinite(t.grad).all() for t in (c, e, a))


def test_lookup_batched_shapes_and_distribution_tensor(table):
    g = torch.Generator().manual_seed(1)
    c = torch.rand(2, 3, 4, generator=g)
    e = 1 + torch.rand(2, 3, 4, generator=g)
    a = torch.rand(1, 3, 1, generator=g)
    dist = torch.tensor([0, 1, 0, 1]).bool()
    out = sgfit.sg_lookup(table, c, e, a, dist)
    assert all(o.shape == (2, 3, 4) and o.dtype == torch.float32 for o in out)
    ref_b = sgfit.sg_lookup(table, c, e, a, "beckmann")
    ref_g = sgfit.sg_lookup(table, c, e, a, "ggx")
    for o, b, gg in zip(out, ref_b, ref_g):
        assert torch.equal(o, torch.where(dist, gg, b))
    # amplitude is consistent with energy: integral of a exp(k (p.w - 1)) = E
    amp, k, _, en = ref_b
    assert torch.allclose(amp * 2 * math.pi * -torch.expm1(-2 * k) / k, en, rtol=1e-5)
    with pytest.raises(ValueError, match="lobe"):
        sgfit.sg_lookup(table, c, e, a, lobe="refract")


def test_shipped_table_equals_fresh_subtable(table):
    ei, ai = [5, 16, 22], [0, 12, 23]
    sub = sg_fit.build_sg_table(table.spec, eta_indices=ei, alpha_indices=ai)
    ref = table.data[:, :, :, ei][:, :, :, :, ai]
    assert torch.allclose(sub.data, ref, rtol=2e-5, atol=1e-7)
    assert table.spec == sg_table.SGTableSpec() and table.spec.key() == sg_table.SGTableSpec().key()


def test_sharpness_from_mean_length_inverts_coth():
    k = torch.exp(torch.linspace(math.log(1e-2), math.log(1e8), 200, dtype=F64))
    one_minus_r = 1.0 / k - 2.0 / torch.expm1(2.0 * k)
    assert torch.allclose(sg_fit.sharpness_from_mean_length(one_minus_r), k, rtol=1e-9)


def test_build_and_cache_on_demand(tmp_path, capsys):
    spec = sg_table.SGTableSpec(n_theta=6, n_eta=3, n_alpha=2, quad_h=0.3, quad_nphi=16)
    sgfit._load_cached.cache_clear()
    t1 = sgfit.load_sg_table(spec, cache_dir=tmp_path)
    assert "building the spherical Gaussian" in capsys.readouterr().err
    cached = tmp_path / f"sg_table_{spec.key()}.npz"
    assert cached.is_file() and t1.data.shape == (2, 2, 6, 3, 2, 4)
    sgfit._load_cached.cache_clear()
    t2 = sgfit.load_sg_table(spec, cache_dir=tmp_path)
    assert "building" not in capsys.readouterr().err
    assert torch.equal(t1.data, t2.data)
    assert spec.key() != sg_table.SGTableSpec().key()
    sgfit._load_cached.cache_clear()


def test_lookup_does_not_depend_on_the_batch():
    """A point's lookup is bit-identical alone, in a small batch, at an offset and in a
    large batch (a sample rendered alone and in a batch must give the same file; torch's
    vectorized atan2 rounds differently from its scalar tail, hence no atan2 here)."""
    table = sgfit.load_sg_table()
    g = torch.Generator().manual_seed(0)
    n = 1001
    c, a = torch.rand(n, generator=g), torch.rand(n, generator=g)
    e = 1.0 + 2.0 * torch.rand(n, generator=g)
    for lobe in ("transmit", "reflect"):
        full = sgfit.sg_lookup(table, c, e, a, "beckmann", lobe)
        for sl in (slice(0, 1), slice(0, 7), slice(0, 9), slice(3, 500), slice(5, n)):
            part = sgfit.sg_lookup(table, c[sl], e[sl], a[sl], "beckmann", lobe)
            for p, f in zip(part, full):
                assert torch.equal(p, f[sl]), (lobe, sl)


def test_energies_alone_equal_the_full_lookup():
    """``sg_energies`` (one 2-channel pass, used for every interface's weights) gives the
    energies of ``sg_lookup`` bit for bit, for one distribution, a uniform distribution
    tensor (one table read) and a mixed one (both)."""
    table = sgfit.load_sg_table()
    g = torch.Generator().manual_seed(1)
    n = 2001
    c, a = torch.rand(n, generator=g), torch.rand(n, generator=g)
    e = 0.4 + 2.0 * torch.rand(n, generator=g)
    for d in ("beckmann", "ggx", torch.ones(n, dtype=torch.long),
              (torch.rand(n, generator=g) > 0.5).long()):
        e_t, e_r = sgfit.sg_energies(table, c, e, a, d)
        assert torch.equal(e_t, sgfit.sg_lookup(table, c, e, a, d, "transmit")[3])
        assert torch.equal(e_r, sgfit.sg_lookup(table, c, e, a, d, "reflect")[3])
    mixed = (torch.arange(n) % 2).long()
    ggx = sgfit.sg_lookup(table, c, e, a, "ggx")[1]
    beck = sgfit.sg_lookup(table, c, e, a, "beckmann")[1]
    k = sgfit.sg_lookup(table, c, e, a, mixed)[1]
    assert torch.equal(k, torch.where(mixed == 1, ggx, beck))


@pytest.mark.parametrize("p", [sgfit._SPLIT_MIN_POINTS * 2 + 77, sgfit._SPLIT_MIN_POINTS * 5])
def test_trilinear_split_over_threads_is_bit_identical(p):
    """The table lookup split into one batch item per thread gives the single call's values
    bit for bit (padded last chunk included) and the same coordinate gradients."""
    g = torch.Generator().manual_seed(1)
    vol = torch.rand(3, 9, 7, 11, generator=g)
    grid = (torch.rand(1, p, 1, 1, 3, generator=g) * 2.2 - 1.1).requires_grad_(True)
    old = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        one = torch.nn.functional.grid_sample(vol[None], grid, mode="bilinear",
                                              padding_mode="border", align_corners=True)
        one = one.reshape(3, p)
        (g_one,) = torch.autograd.grad((one * torch.arange(p)).sum(), grid)
        for threads in (1, 2, 3):
            torch.set_num_threads(threads)
            split = sgfit._trilinear(vol, grid)
            assert torch.equal(split, one), threads
            (g_split,) = torch.autograd.grad((split * torch.arange(p)).sum(), grid)
            assert torch.allclose(g_split, g_one, rtol=1e-6, atol=1e-6), threads
    finally:
        torch.set_num_threads(old)

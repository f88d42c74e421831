"""Interface energies (``sgfit.interface_energies``) and the closed-form escape of trapped
light (``bounces.escape_fraction``) against Mitsuba 3's ``roughdielectric``.

Mitsuba's energies are Monte Carlo estimates: the mean of ``bsdf.sample``'s weight
(``f |cos| / pdf``) split into reflection (``wo.z`` on the side of ``wi.z``) and
transmission. The context is ``TransportMode.Importance``: in radiance mode Mitsuba scales
transmission by the radiance compression ``1 / eta^2`` (checked in
``test_mitsuba_importance_mode_is_the_table_convention``), which the table leaves out (a
smooth interface transmits ``1 - F``). With visible-normal sampling a weight is ``G1(wo, m)``,
in [0, 1], so the standard error of a mean over n samples is at most ``0.5 / sqrt(n)``;
the tolerances below are a fit allowance plus 4 measured standard errors.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from torchrefract.optics import sgfit
from torchrefract.optics.smooth import fresnel_dielectric
from torchrefract.shading.bounces import escape_fraction

F64 = torch.float64
IOR = 1.5
ALPHAS = (0.1, 0.3, 0.6, 1.0)
COS = (0.2, 0.5, 0.9)  # from inside: critical cos = sqrt(1 - 1/1.5^2) = 0.745, kept away
DISTS = ("beckmann", "ggx")


@pytest.fixture(autouse=True, scope="module")
def _one_thread(one_thread):
    """One intra-op thread for this module (see conftest.one_thread)."""
    yield


@pytest.fixture(scope="module")
def mi(mi_vectorized):
    return mi_vectorized


@pytest.fixture(scope="module")
def table():
    return sgfit.load_sg_table()


def _fresnel(cos: torch.Tensor, eta: torch.Tensor | float) -> torch.Tensor:
    """Smooth reflectance for the table's eta (far side / near side), as trace_paths calls it:
    fresnel_dielectric takes n_incident / n_transmitted = 1 / eta."""
    return fresnel_dielectric(cos, 1.0 / torch.as_tensor(eta, dtype=cos.dtype))


def _wi(cos: np.ndarray, inside: bool) -> np.ndarray:
    """Incident directions in the plane xz; from inside the glass they point down (z < 0)."""
    cos = np.asarray(cos, dtype=np.float64)
    return np.stack([np.sqrt(1.0 - cos * cos), np.zeros_like(cos),
                     -cos if inside else cos], -1)


def _mi_energies(mi, dist: str, alpha: float, ior: float, wi: np.ndarray, n: int,
                 seed: int = 0, mode=None):
    """Mitsuba's transmitted and reflected energy for each row of ``wi`` (K, 3).

    Returns (e_t, e_r, se_t, se_r), each (K,): means of the sample weights over ``n``
    samples per row, and their standard errors.
    """
    import drjit as dr  # noqa: PLC0415

    bsdf = mi.load_dict({"type": "roughdielectric", "distribution": dist, "alpha": alpha,
                         "int_ior": ior, "ext_ior": 1.0})
    ctx = mi.BSDFContext(mi.TransportMode.Importance if mode is None else mode)
    k = len(wi)
    w_in = np.repeat(wi, n, axis=0).astype(np.float32)
    u = np.random.default_rng(seed).random((len(w_in), 3)).astype(np.float32)
    si = dr.zeros(mi.SurfaceInteraction3f, len(w_in))
    si.wi = mi.Vector3f(*(w_in[:, i] for i in range(3)))
    si.sh_frame = mi.Frame3f(mi.Vector3f(0, 0, 1))  # identity shading frame
    bs, weight = bsdf.sample(ctx, si, mi.Float(u[:, 0]), mi.Point2f(u[:, 1], u[:, 2]))
    wo_z = np.array(bs.wo).reshape(3, -1)[2]
    w = np.array(weight).reshape(3, -1)[0].astype(np.float64)
    w = np.where(np.isfinite(w), w, 0.0)  # failed samples carry weight 0
    refl = wo_z * w_in[:, 2] > 0
    t = np.where(refl, 0.0, w).reshape(k, n)
    r = np.where(refl, w, 0.0).reshape(k, n)
    return (t.mean(1), r.mean(1), t.std(1) / math.sqrt(n), r.std(1) / math.sqrt(n))


# --------------------------------------------------------------------------------------
# Smooth limit
# --------------------------------------------------------------------------------------

@pytest.mark.parametrize("dist", DISTS)
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_interface_energies_smooth_is_exact_fresnel(table, dist, dtype):
    cos = torch.linspace(0.0, 1.0, 21, dtype=dtype)
    for eta in (IOR, 1 / IOR, 2.4, 1 / 2.4, 1.05, 1.0):
        e = torch.full_like(cos, eta)
        f = _fresnel(cos, e)
        for a in (0.0, 1e-4, table.spec.alpha_min):  # at or below the table's smallest alpha
            for d in (dist, torch.full(cos.shape, DISTS.index(dist))):
                t, r = sgfit.interface_energies(table, cos, e, torch.full_like(cos, a), d, f)
                assert torch.equal(r, f), (eta, a)
                assert torch.equal(t, 1.0 - f), (eta, a)
    # total internal reflection from inside: nothing transmitted
    cos = torch.tensor([0.1, 0.5, 0.7], dtype=dtype)
    f = _fresnel(cos, 1 / IOR)
    assert torch.equal(f, torch.ones_like(f))
    t, r = sgfit.interface_energies(table, cos, torch.full_like(cos, 1 / IOR),
                                    torch.zeros_like(cos), dist, f)
    assert torch.equal(t, torch.zeros_like(t)) and torch.equal(r, torch.ones_like(r))


def test_mitsuba_importance_mode_is_the_table_convention(mi):
    """At alpha = 1e-3 Mitsuba's importance mode transmits 1 - F (the table's convention),
    its radiance mode (1 - F) / eta^2: the estimator above must use importance mode."""
    n = 1 << 16  # standard error <= 0.5 / 256 = 0.002; bound 0.01 (5 sigma)
    for inside, cos in ((False, (0.2, 0.5, 0.9)), (True, (0.2, 0.9, 0.95))):
        eta = 1 / IOR if inside else IOR
        f = _fresnel(torch.tensor(cos, dtype=F64), eta).numpy()
        wi = _wi(np.array(cos), inside)
        t, r, _, _ = _mi_energies(mi, "beckmann", 1e-3, IOR, wi, n, seed=1)
        np.testing.assert_allclose(t, 1 - f, atol=0.01)
        np.testing.assert_allclose(r, f, atol=0.01)
        t_rad, _, _, _ = _mi_energies(mi, "beckmann", 1e-3, IOR, wi, n, seed=1,
                                      mode=mi.TransportMode.Radiance)
        np.testing.assert_allclose(t_rad, (1 - f) / eta ** 2, atol=0.01)
        if not inside:  # entering: the modes differ by (1 - F)(1 - 1 / 2.25) >= 0.37 here
            assert (t - t_rad > 0.3).all()


# --------------------------------------------------------------------------------------
# Rough interfaces against Mitsuba
# --------------------------------------------------------------------------------------

#: Allowance for the table (a fitted, trilinearly interpolated quadrature). Measured with
#: 2^20 Mitsuba samples per case (standard error <= 5e-4), over both NDFs, alpha in
#: {0.1, 0.3, 0.6, 1.0}, entering and leaving IOR 1.5, cos in {0.2, 0.5, 0.9}: max |error|
#: 0.0070 in e_t (beckmann, alpha 0.6, entering, cos 0.2) and 0.0085 in e_r (beckmann,
#: alpha 0.6, leaving, cos 0.2); typical errors are < 0.002. The error is the table's
#: linear interpolation in log alpha: it peaks between alpha nodes (0.406, 0.548, 0.741),
#: up to 0.0097 at alpha 0.45 (beckmann, leaving, cos 0.2, e_r). A missing masking-shadowing
#: loss term would be off by 1 - e_t - e_r: 0.05-0.5 for alpha >= 0.3.
FIT_TOL = 0.015


@pytest.mark.parametrize("dist", DISTS)
def test_interface_energies_match_mitsuba(mi, table, dist):
    n = 1 << 18  # per case: standard error <= 0.5 / 512 ~ 1e-3, so 4 sigma <= 0.004
    cos = np.array(COS)
    worst = 0.0
    for alpha in ALPHAS:
        for inside in (False, True):
            eta = 1 / IOR if inside else IOR
            mt, mr, st, sr = _mi_energies(mi, dist, alpha, IOR, _wi(cos, inside), n,
                                          seed=int(alpha * 10) + inside)
            c = torch.tensor(cos, dtype=F64)
            e = torch.full_like(c, eta)
            t, r = sgfit.interface_energies(table, c, e, torch.full_like(c, alpha), dist,
                                            _fresnel(c, e))
            t, r = t.numpy(), r.numpy()
            ctx = (dist, alpha, "inside" if inside else "outside", t, mt, r, mr)
            assert (np.abs(t - mt) < FIT_TOL + 4 * st).all(), ctx
            assert (np.abs(r - mr) < FIT_TOL + 4 * sr).all(), ctx
            worst = max(worst, np.abs(t - mt).max(), np.abs(r - mr).max())
    assert worst > 0.0  # the comparison ran on real numbers


# --------------------------------------------------------------------------------------
# Escape of trapped light
# --------------------------------------------------------------------------------------

def _mi_trapped(mi, dist: str, alpha: float, ior: float, n: int, seed: int):
    """Mitsuba's T, R for isotropic radiance inside: cosine-weighted incidence from inside
    (cos = sqrt(u), u jittered-stratified), one BSDF sample each. Returns T, R and the
    standard error of the escape T / (T + L) = T / (1 - R) (delta method, iid bound)."""
    rng = np.random.default_rng(seed)
    cos = np.sqrt((np.arange(n) + rng.random(n)) / n)
    # one sample per direction: the per-row "means" are the n single weights, pooled here
    t, r, _, _ = _mi_energies(mi, dist, alpha, ior, _wi(cos, True), 1, seed=seed + 1)
    T, R = t.mean(), r.mean()
    se_t, se_r = t.std() / math.sqrt(n), r.std() / math.sqrt(n)
    se = math.hypot(se_t / (1 - R), T * se_r / (1 - R) ** 2)
    return T, R, se


#: Allowance for escape_fraction's table lookups, 16-node Gauss-Legendre in cos theta and
#: 41-node interpolation in alpha. Measured against 2^21 Mitsuba samples per case (escape
#: standard error <= 0.0017): max |error| 0.0053 (beckmann, IOR 2.4, alpha 0.6), next
#: 0.0026 (beckmann, IOR 1.5, alpha 0.6); the rest <= 0.0013.
ESC_TOL = 0.01


def test_escape_fraction_matches_mitsuba(mi, table):
    # 2^20 samples per case: escape standard error 0.0003-0.0024 (largest at IOR 2.4,
    # alpha 0.3, where T is small and R close to 1), so 4 sigma <= 0.01
    n = 1 << 20
    cases = [(d, ior) for d in (0, 1) for ior in (1.5, 2.4)]  # one scene each
    alphas = (0.3, 0.6, 1.0)
    ior_t = torch.tensor([ior for _, ior in cases], dtype=F64)
    dist_t = torch.tensor([d for d, _ in cases])
    alpha_t = torch.tensor(alphas * len(cases), dtype=F64)
    batch = torch.arange(len(cases)).repeat_interleave(len(alphas))
    ours = escape_fraction(table, ior_t, dist_t, alpha_t, batch).numpy()
    for i, (alpha, b) in enumerate(zip(alpha_t.tolist(), batch.tolist())):
        d, ior = cases[b]
        T, R, se = _mi_trapped(mi, DISTS[d], alpha, ior, n, seed=i)
        L = 1 - T - R
        assert L > 0.03  # rough: the model loses light, escape well below 1
        ref = T / (T + L)
        assert abs(ours[i] - ref) < ESC_TOL + 4 * se, (DISTS[d], ior, alpha, ours[i], ref, se)


@pytest.mark.parametrize("ior", [1.1, 1.33, 1.5, 2.4, 3.0])
def test_escape_fraction_range_and_monotone(table, ior):
    grid = 41  # escape_fraction's default roughness nodes: k / 40
    alpha = torch.cat([torch.zeros(1, dtype=F64), torch.linspace(0, 1, 201, dtype=F64)])
    nodes = torch.arange(grid, dtype=F64) / (grid - 1)
    for d in (0, 1):
        esc = escape_fraction(table, torch.tensor([ior], dtype=F64), torch.tensor([d]),
                              alpha, torch.zeros(len(alpha), dtype=torch.long))
        assert esc[0].item() == 1.0 and esc[1].item() == 1.0  # exactly 1 when smooth
        assert ((esc > 0) & (esc <= 1)).all()
        assert (esc.diff() <= 0).all()  # non-increasing everywhere (piecewise linear)
        at_nodes = escape_fraction(table, torch.tensor([ior], dtype=F64), torch.tensor([d]),
                                   nodes, torch.zeros(grid, dtype=torch.long))
        assert (at_nodes.diff() < 0).all(), at_nodes  # strictly decreasing node to node
        assert esc[-1] < 0.9


def test_escape_grid_rows_kept_are_the_rows_computed(table):
    from torchrefract.shading import bounces

    ior = torch.tensor([1.5, 1.5, 1.33, 2.4, 1.5, 1.1, 1.33, 1.5])
    dist = torch.tensor([0, 0, 1, 0, 0, 1, 1, 0])
    for dtype in (torch.float32, torch.float64):
        fresh = torch.cat([bounces._escape_rows(table, ior[i:i + 1], dist[i:i + 1], dtype, 16,
                                                41) for i in range(len(ior))])
        for _ in range(2):  # computed, then taken from the kept rows
            assert torch.equal(bounces.escape_grid(table, ior, dist, dtype), fresh)
        # a scene's row does not depend on the batch around it
        assert torch.equal(bounces.escape_grid(table, ior[2:3], dist[2:3], dtype), fresh[2:3])
        assert torch.allclose(fresh, bounces._escape_rows(table, ior, dist, dtype, 16, 41),
                              rtol=1e-6, atol=1e-7)
    # with a gradient through the IOR the rows are computed, and carry it
    g = ior.clone().requires_grad_(True)
    bounces.escape_grid(table, g, dist, torch.float32).sum().backward()
    assert g.grad is not None and torch.isfinite(g.grad).all()

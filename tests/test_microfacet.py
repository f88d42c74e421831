"""Rough dielectric BSDF (torchrefract.optics.microfacet) against Mitsuba 3's ``roughdielectric``.

Mitsuba evaluates in float32; our reference values are float64 evaluations at the very same
float32 inputs. Agreement is ~1e-5 relative except where the float32 problem itself is
ill-conditioned: transmission through microfacets close to their critical angle (``|wo.m|``
small, ``F`` near 1), where ``1 - F`` and the half vector lose most float32 digits. Those
pairs are listed separately with a loose bound and their share is bounded.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from torchrefract.optics import microfacet as mf

ALPHAS = (0.01, 0.05, 0.3, 0.7, 1.0)
IORS = (1.5, 1 / 1.5, 1.33, 2.4)
DISTS = ("beckmann", "ggx")
F64 = torch.float64


@pytest.fixture(autouse=True, scope="module")
def _one_thread(one_thread):
    """One intra-op thread for this module (see conftest.one_thread)."""
    yield


def _rand_dirs(rng: np.random.Generator, n: int) -> np.ndarray:
    v = rng.normal(size=(n, 3))
    return v / np.linalg.norm(v, axis=1, keepdims=True)


# --------------------------------------------------------------------------------------
# Mitsuba wrapper (vectorized in the LLVM variant, a loop in scalar_rgb)
# --------------------------------------------------------------------------------------

class MiBSDF:
    def __init__(self, mi, dist: str, alpha: float, ior: float, visible: bool):
        self.mi = mi
        self.jit = not mi.variant().startswith("scalar")
        self.bsdf = mi.load_dict({"type": "roughdielectric", "distribution": dist,
                                  "alpha": alpha, "int_ior": ior, "ext_ior": 1.0,
                                  "sample_visible": visible})
        self.ctx = mi.BSDFContext()

    def _si(self, wi: np.ndarray):
        mi = self.mi
        import drjit as dr  # noqa: PLC0415

        si = dr.zeros(mi.SurfaceInteraction3f, len(wi)) if self.jit else mi.SurfaceInteraction3f()
        si.wi = mi.Vector3f(*(wi[:, i] for i in range(3)))
        si.sh_frame = mi.Frame3f(mi.Vector3f(0, 0, 1))  # identity shading frame
        return si

    def _loop(self, fn, *arrays):
        if self.jit:
            return fn(*arrays)
        outs = [fn(*(a[i:i + 1] for a in arrays)) for i in range(len(arrays[0]))]
        return tuple(np.concatenate([o[j] for o in outs]) for j in range(len(outs[0])))

    def eval_pdf(self, wi: np.ndarray, wo: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        mi = self.mi

        def fn(wi, wo):
            si, v = self._si(wi), mi.Vector3f(*(wo[:, i] for i in range(3)))
            f = np.array(self.bsdf.eval(self.ctx, si, v)).reshape(3, -1)[0]
            return f, np.array(self.bsdf.pdf(self.ctx, si, v)).reshape(-1)

        return self._loop(fn, wi, wo)

    def sample(self, wi: np.ndarray, u: np.ndarray):
        mi = self.mi

        def fn(wi, u):
            si = self._si(wi)
            bs, w = self.bsdf.sample(self.ctx, si, mi.Float(u[:, 0]),
                                     mi.Point2f(u[:, 1], u[:, 2]))
            return (np.array(bs.wo).reshape(3, -1).T, np.array(w).reshape(3, -1)[0],
                    np.array(bs.pdf).reshape(-1))

        return self._loop(fn, wi, u)


@pytest.fixture(scope="module")
def mi():
    pytest.importorskip("mitsuba")
    from torchrefract.truth.mitsuba import mitsuba  # noqa: PLC0415

    try:
        return mitsuba()
    except ImportError as exc:
        pytest.skip(f"Mitsuba unusable here: {exc}")


def _n_pairs(mi) -> int:
    return 1500 if not mi.variant().startswith("scalar") else 60


def _pairs(rng, n, alpha, ior, dist):
    """float32 (wi, wo): half uniform on the sphere, half sampled from the lobe (+ jitter)."""
    wi = _rand_dirs(rng, n).astype(np.float32)
    wo = _rand_dirs(rng, n)
    half = n // 2
    s, _, _ = mf.sample(torch.tensor(wi[:half], dtype=F64), alpha, ior, dist,
                        torch.tensor(rng.random((half, 3)), dtype=F64))
    s = s.numpy() + rng.normal(scale=0.2 * alpha, size=(half, 3))
    wo[:half] = s / np.linalg.norm(s, axis=1, keepdims=True)
    return wi, wo.astype(np.float32)


def _float32_tolerance(wi: np.ndarray, wo: np.ndarray, ior: float, alpha: float) -> np.ndarray:
    """Relative tolerance per pair for float32 (Mitsuba) vs float64 (ours) at equal inputs.

    1e-4, plus ``3e-6 / (wo.m)^2`` for transmission: near a microfacet's critical angle the
    float32 half vector and ``1 - F`` lose digits as ``1 / (wo.m)^2`` (measured: the
    largest errors all have ``|wo.m| < 0.04`` and ``F > 0.8``); plus ``3e-7 / cos(theta_m)``
    (a float32 ``m_z`` of a nearly vertical microfacet in the sampling density). At
    alpha = 0.01, ``exp(-tan^2 / alpha^2)`` of a float32 half vector adds ~1e-3.
    """
    twi, two = torch.tensor(wi, dtype=F64), torch.tensor(wo, dtype=F64)
    m, _, refl, _ = mf._half_vector(twi, two, torch.tensor(ior, dtype=F64).expand(len(wi)))
    wom = mf._dot(two, m).abs().numpy()
    cond = np.where(refl.numpy(), 0.0, 1.0 / np.maximum(wom, 1e-9) ** 2)
    return ((1e-4 if alpha > 0.01 else 1e-3) + 3e-6 * cond
            + 3e-7 / np.maximum(m[:, 2].numpy(), 1e-9))


def _well_conditioned(wi: np.ndarray, wo: np.ndarray, ior: float) -> np.ndarray:
    """Pairs whose float32 evaluation is far from a microfacet's critical angle."""
    return (_float32_tolerance(wi, wo, ior, 1.0) < 2e-4) & (np.abs(wi[:, 2]) > 1e-3)


# --------------------------------------------------------------------------------------
# Against Mitsuba
# --------------------------------------------------------------------------------------

@pytest.mark.parametrize("dist", DISTS)
def test_eval_and_pdf_match_mitsuba(mi, dist):
    rng = np.random.default_rng(1 if dist == "ggx" else 0)
    n = _n_pairs(mi)
    ill = []
    for alpha in ALPHAS:
        for ior in IORS:
            wi, wo = _pairs(rng, n, alpha, ior, dist)
            twi, two = torch.tensor(wi, dtype=F64), torch.tensor(wo, dtype=F64)
            ours = mf.eval(twi, two, alpha, ior, dist).numpy()
            tol = _float32_tolerance(wi, wo, ior, alpha)
            good = _well_conditioned(wi, wo, ior)
            ill.append(1 - good.mean())
            for visible in (False, True):
                b = MiBSDF(mi, dist, alpha, ior, visible)
                ref, ref_pdf = b.eval_pdf(wi, wo)
                pdf = mf.pdf(twi, two, alpha, ior, dist, sample_visible=visible).numpy()
                # zero exactly where Mitsuba is zero (masking, side tests, cut-off)
                assert ((ours > 0) == (ref > 0))[good].all(), (alpha, ior)
                assert ((ours > 0) != (ref > 0)).mean() < 2e-3, (alpha, ior)
                nz = (ref > 0) & (ours > 0)
                rel = np.abs(ours - ref) / np.maximum(ref, 1e-30)
                assert np.quantile(rel[good & nz], 0.99) < 5e-5, (alpha, ior, visible)
                assert (rel[nz] < tol[nz]).all(), (alpha, ior, visible, (rel / tol)[nz].max())
                pz = (ref_pdf > 0) & (pdf > 0)
                relp = np.abs(pdf - ref_pdf) / np.maximum(ref_pdf, 1e-30)
                assert (relp[pz] < tol[pz]).all(), (alpha, ior, visible)
    assert max(ill) < 0.06  # the widened tolerance covers only a small share of pairs


@pytest.mark.parametrize("dist", DISTS)
@pytest.mark.parametrize("visible", [False, True])
def test_sample_matches_mitsuba(mi, dist, visible):
    rng = np.random.default_rng(7)
    n = _n_pairs(mi)
    for alpha in ALPHAS:
        for ior in IORS:
            wi = _rand_dirs(rng, n).astype(np.float32)
            u = rng.random((n, 3)).astype(np.float32)
            b = MiBSDF(mi, dist, alpha, ior, visible)
            mwo, mw, mpdf = b.sample(wi, u)
            twi, tu = torch.tensor(wi, dtype=F64), torch.tensor(u, dtype=F64)
            wo, w, p = (t.numpy() for t in mf.sample(twi, alpha, ior, dist, tu,
                                                     sample_visible=visible))
            both = (mpdf > 0) & (p > 0)
            assert both.mean() > 0.9
            # same mapping from uniforms to directions (float32 vs float64 of one formula;
            # Mitsuba's sin(theta_m) = sqrt(1 - cos^2) in float32 dominates at small alpha)
            dwo = np.abs(wo - mwo).max(1)[both]
            assert np.quantile(dwo, 0.99) < 1e-3 and np.median(dwo) < 5e-5, (alpha, ior)
            rp = (np.abs(p - mpdf) / mpdf)[both]
            assert np.median(rp) < 1e-4 and np.quantile(rp, 0.95) < 1e-2, (alpha, ior)
            valid = both & (mw > 0) & (w > 0)
            if visible:
                # weight = G1(wo, m) (times 1/eta^2 for radiance): identical to Mitsuba's
                rw = np.abs(w - mw)[valid] / mw[valid]
                assert np.quantile(rw, 0.99) < 1e-4, (alpha, ior)
            else:
                # Mitsuba 3.9 omits D(m) / D_wide(m) from its weight when it widens alpha
                # (Walter's trick); ours is eval / pdf. Check exactly that difference.
                tm = torch.tensor(mwo, dtype=F64)
                m, _, refl, _ = mf._half_vector(twi, tm, torch.tensor(ior, dtype=F64).expand(n))
                a_w = alpha * (1.2 - 0.2 * np.sqrt(np.abs(wi[:, 2])))
                ratio = (mf.ndf(m[:, 2], alpha, dist, sin2_theta_h=m[:, 0] ** 2 + m[:, 1] ** 2)
                         / mf.ndf(m[:, 2], torch.tensor(a_w, dtype=F64), dist,
                                  sin2_theta_h=m[:, 0] ** 2 + m[:, 1] ** 2)).numpy()
                rw = np.abs(w - mw * ratio)[valid] / w[valid]
                assert np.median(rw) < 1e-3, (alpha, ior)
                assert np.median(np.abs(ratio[valid] - 1)) > 1e-3  # the difference is real


# --------------------------------------------------------------------------------------
# Internal consistency
# --------------------------------------------------------------------------------------

@pytest.mark.parametrize("visible", [False, True])
@pytest.mark.parametrize("dist", DISTS)
def test_weight_is_eval_over_pdf(dist, visible):
    g = torch.Generator().manual_seed(3)
    n = 4000
    wi = mf._normalize(torch.randn(n, 3, generator=g, dtype=F64))[0]
    alpha = torch.exp(torch.empty(n, dtype=F64).uniform_(math.log(1e-3), 0.0, generator=g))
    eta = torch.tensor(IORS, dtype=F64)[torch.randint(0, 4, (n,), generator=g)]
    u = torch.rand(n, 3, generator=g, dtype=F64)
    for radiance in (True, False):
        wo, w, p = mf.sample(wi, alpha, eta, dist, u, sample_visible=visible, radiance=radiance)
        f = mf.eval(wi, wo, alpha, eta, dist, radiance=radiance)
        p2 = mf.pdf(wi, wo, alpha, eta, dist, sample_visible=visible)
        ok = w > 0
        assert ok.float().mean() > 0.8
        assert torch.allclose(p2[ok], p[ok], rtol=1e-6)
        assert torch.allclose(f[ok] / p[ok], w[ok], rtol=1e-6)
        assert torch.isfinite(w).all() and torch.isfinite(p).all()


def _sphere_points(n_side: int) -> tuple[torch.Tensor, float]:
    """Stratified uniform directions on the sphere (midpoints in z and phi) and dw."""
    i = (torch.arange(n_side, dtype=F64) + 0.5) / n_side
    z = 1 - 2 * i
    phi = 2 * math.pi * (torch.arange(2 * n_side, dtype=F64) + 0.5) / (2 * n_side)
    r = torch.sqrt(1 - z * z)
    d = torch.stack([r[:, None] * torch.cos(phi), r[:, None] * torch.sin(phi),
                     z[:, None].expand(-1, 2 * n_side)], -1).reshape(-1, 3)
    return d, 4 * math.pi / d.shape[0]


@pytest.mark.parametrize("dist", DISTS)
def test_energy_sampler_equals_integral_of_eval(dist):
    """Mean sampling weight == integral of eval over the sphere (uniform quadrature)."""
    wo, dw = _sphere_points(140)  # 39k directions, spacing ~0.022 rad
    u = torch.quasirandom.SobolEngine(3, scramble=True, seed=5).draw(2 ** 14, dtype=F64)
    for alpha, eta, ct in ((0.3, 1.5, 0.9), (0.3, 1 / 1.5, -0.6), (0.7, 1 / 1.5, 0.4),
                           (1.0, 1.5, -0.6), (1.0, 2.4, 0.2), (0.5, 1.33, -0.95)):
        wi = torch.tensor([math.sqrt(1 - ct * ct), 0.0, ct], dtype=F64)
        f_imp = mf.eval(wi, wo, alpha, eta, dist, radiance=False)
        eta_e = eta if ct > 0 else 1 / eta
        # radiance mode = importance mode with transmission scaled by 1 / eta_e^2
        f_rad = torch.where(wo[:, 2] * ct > 0, f_imp, f_imp / eta_e ** 2)
        assert torch.allclose(f_rad, mf.eval(wi, wo, alpha, eta, dist))
        for radiance, f in ((False, f_imp), (True, f_rad)):
            integral = f.sum() * dw
            for visible in (False, True):
                _, w, _ = mf.sample(wi, alpha, eta, dist, u, sample_visible=visible,
                                    radiance=radiance)
                assert abs(w.mean() - integral) < 0.01 * integral + 1e-3, \
                    (alpha, eta, ct, radiance, visible, float(w.mean()), float(integral))
        # the density integrates to the share of valid samples (<= 1)
        _, w, _ = mf.sample(wi, alpha, eta, dist, u)
        ptot = mf.pdf(wi, wo, alpha, eta, dist).sum() * dw
        assert abs(ptot - (w > 0).double().mean()) < 0.01, (alpha, eta, ct)


@pytest.mark.parametrize("dist", DISTS)
def test_two_samplers_agree_at_small_alpha(dist):
    """Where uniform quadrature cannot resolve the lobe: NDF vs visible-normal sampling."""
    u = torch.quasirandom.SobolEngine(3, scramble=True, seed=9).draw(2 ** 12, dtype=F64)
    ct = torch.tensor([0.95, 0.3, -0.5], dtype=F64)
    wi = torch.stack([torch.sqrt(1 - ct * ct), torch.zeros_like(ct), ct], -1)[:, None]
    for alpha in (1e-4, 0.01, 0.05):
        for eta in IORS:
            e = [mf.sample(wi, alpha, eta, dist, u, sample_visible=v, radiance=False)[1]
                 .mean(-1) for v in (False, True)]
            assert (e[0] - e[1]).abs().max() < 5e-3, (alpha, eta, e)


@pytest.mark.parametrize("dist", DISTS)
def test_smooth_limit_is_fresnel(dist):
    """alpha -> 1e-4: reflected and transmitted fractions -> F and 1 - F of the macro normal."""
    u = torch.quasirandom.SobolEngine(3, scramble=True, seed=2).draw(4096, dtype=F64)
    for eta in IORS:
        for ct in (1.0, 0.7, 0.2, -0.9, -0.4):
            wi = torch.tensor([math.sqrt(1 - ct * ct), 0.0, ct], dtype=F64)
            wo, w, _ = mf.sample(wi, 1e-4, eta, dist, u, radiance=False)
            refl = wo[:, 2] * ct > 0
            f = mf.fresnel(torch.tensor(ct, dtype=F64), eta)[0]
            assert abs(w[refl].sum() / len(u) - f) < 0.02
            assert abs(w[~refl].sum() / len(u) - (1 - f)) < 0.02


@pytest.mark.parametrize("dist", DISTS)
def test_reciprocity(dist):
    """Adjoint relation and Walter's generalized reciprocity f(i, o) / n_o^2 = f(o, i) / n_i^2."""
    g = torch.Generator().manual_seed(11)
    n = 3000
    wi = mf._normalize(torch.randn(n, 3, generator=g, dtype=F64))[0]
    wo = mf._normalize(torch.randn(n, 3, generator=g, dtype=F64))[0]
    alpha = torch.empty(n, dtype=F64).uniform_(0.2, 1.0, generator=g)
    for eta in IORS:
        f_rad = mf.eval(wi, wo, alpha, eta, dist, radiance=True) / wo[:, 2].abs()
        f_imp = mf.eval(wi, wo, alpha, eta, dist, radiance=False) / wo[:, 2].abs()
        f_imp_rev = mf.eval(wo, wi, alpha, eta, dist, radiance=False) / wi[:, 2].abs()
        assert (f_rad > 0).float().mean() > 0.3
        # radiance-mode f(wi, wo) is the importance-mode f(wo, wi)
        assert torch.allclose(f_rad, f_imp_rev, rtol=1e-9, atol=0)
        one, e = torch.ones((), dtype=F64), torch.tensor(eta, dtype=F64)
        n_i = torch.where(wi[:, 2] > 0, one, e)
        n_o = torch.where(wo[:, 2] > 0, one, e)
        assert torch.allclose(f_imp / n_o ** 2, f_imp_rev / n_i ** 2, rtol=1e-9, atol=0)
        same = wi[:, 2] * wo[:, 2] > 0  # the BRDF is symmetric
        assert torch.allclose(f_imp[same], f_imp_rev[same], rtol=1e-9, atol=0)


# --------------------------------------------------------------------------------------
# Extremes, gradients, dtypes, helpers
# --------------------------------------------------------------------------------------

def _extreme_inputs(dtype):
    dirs = [[0, 0, 1], [0, 0, -1], [1, 0, 0], [0.6, 0, 0.8], [1, 0, 1e-7], [1, 0, -1e-7],
            [0.3, 0.4, -math.sqrt(0.75)], [1e-8, 0, 1], [-0.6, 0, -0.8], [0, 1, 1e-12]]
    d = mf._normalize(torch.tensor(dirs, dtype=torch.float64))[0].to(dtype)
    wi = d[:, None, :].expand(-1, len(dirs), -1).reshape(-1, 3)
    wo = d[None, :, :].expand(len(dirs), -1, -1).reshape(-1, 3)
    return wi, wo


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("dist", DISTS)
def test_extremes_finite_values_and_gradients(dist, dtype):
    wi0, wo0 = _extreme_inputs(dtype)
    u = torch.tensor([[0.0, 0.0, 0.0], [0.5, 0.5, 0.5], [1 - 1e-7, 1 - 1e-7, 1 - 1e-7],
                      [0.3, 1 - 1e-9, 0.999]], dtype=dtype)
    for alpha in (0.0, 1e-4, 1e-3, 0.5, 1.0):
        for eta in (1.0, 1.5, 1 / 1.5, 3.0):
            wi, wo = wi0.clone().requires_grad_(), wo0.clone().requires_grad_()
            a = torch.tensor(alpha, dtype=dtype, requires_grad=True)
            e = torch.tensor(eta, dtype=dtype, requires_grad=True)
            f = mf.eval(wi, wo, a, e, dist)
            p = mf.pdf(wi, wo, a, e, dist)
            for vis in (False, True):
                s_wo, s_w, s_p = mf.sample(wi[:, None], a, e, dist, u[None], sample_visible=vis)
                assert torch.isfinite(s_wo).all() and torch.isfinite(s_w).all() \
                    and torch.isfinite(s_p).all(), (alpha, eta, vis)
                assert (s_w >= 0).all() and (s_p >= 0).all()
                p = p + s_w.sum() + s_p.sum() * 0 + s_wo.sum()
            assert torch.isfinite(f).all() and (f >= 0).all(), (alpha, eta)
            (f.sum() + p.sum()).backward()
            for t in (wi, wo, a, e):
                assert torch.isfinite(t.grad).all(), (alpha, eta)
    # grazing wi: exactly zero (Mitsuba ignores perfectly grazing configurations)
    z = torch.tensor([[1.0, 0.0, 0.0]], dtype=dtype)
    assert mf.eval(z, torch.tensor([[0.0, 0.0, 1.0]], dtype=dtype), 0.3, 1.5, dist) == 0


@pytest.mark.parametrize("dist", DISTS)
def test_float32_matches_float64(dist):
    g = torch.Generator().manual_seed(5)
    n = 4000
    wi = mf._normalize(torch.randn(n, 3, generator=g, dtype=F64))[0]
    u = torch.rand(n, 3, generator=g, dtype=F64)
    alpha = torch.empty(n, dtype=F64).uniform_(0.01, 1.0, generator=g)
    wo, _, _ = mf.sample(wi, alpha, 1.5, dist, u)
    f64 = mf.eval(wi, wo, alpha, 1.5, dist)
    f32 = mf.eval(wi.float(), wo.float(), alpha.float(), 1.5, dist).double()
    good = torch.tensor(_well_conditioned(wi.float().numpy(), wo.float().numpy(), 1.5))
    f64 = mf.eval(wi.float().double(), wo.float().double(), alpha.float().double(), 1.5, dist)
    sel = good & (f64 > 0)
    rel = ((f32 - f64).abs() / f64)[sel]
    assert rel.quantile(0.99) < 1e-4 and rel.max() < 5e-3


@pytest.mark.parametrize("dist", DISTS)
def test_gradcheck_eval(dist):
    g = torch.Generator().manual_seed(2)
    wi = mf._normalize(torch.tensor([[0.3, 0.1, 0.9], [0.5, -0.2, -0.7]], dtype=F64))[0]
    u = torch.rand(2, 3, generator=g, dtype=F64)
    wo, _, _ = mf.sample(wi, 0.4, 1.5, dist, u)
    wo = wo.detach()
    alpha = torch.tensor([0.35, 0.5], dtype=F64, requires_grad=True)
    eta = torch.tensor([1.45, 1.6], dtype=F64, requires_grad=True)
    wi_, wo_ = wi.clone().requires_grad_(), wo.clone().requires_grad_()
    assert torch.autograd.gradcheck(lambda a, e, i, o: mf.eval(i, o, a, e, dist),
                                    (alpha, eta, wi_, wo_))
    assert torch.autograd.gradcheck(lambda a, e: mf.sample(wi, a, e, dist, u)[1], (alpha, eta))


@pytest.mark.parametrize("dist", DISTS)
def test_ndf_normalized_and_g1(dist):
    for alpha in (0.02, 0.3, 1.0):
        # integral D(m) cos(theta_m) dm = 1 (substitute t = tan theta, log-spaced)
        x = torch.linspace(-12, 9, 20001, dtype=F64)
        t = alpha * torch.exp(x)
        c = torch.rsqrt(1 + t * t)
        s = t * c
        d = mf.ndf(c, alpha, dist, sin2_theta_h=s * s, cutoff=False)
        integral = (d * c * s * s * c * 2 * math.pi).sum() * (x[1] - x[0])
        assert abs(integral - 1) < 1e-6
    m = torch.tensor([0.0, 0.0, 1.0], dtype=F64)
    v = mf._normalize(torch.tensor([[math.sin(th), 0, math.cos(th)]
                                    for th in np.linspace(0.01, 1.56, 200)], dtype=F64))[0]
    for alpha in (0.05, 0.5, 1.0):
        if dist == "beckmann":
            approx = mf.smith_g1(v, m, alpha, dist)
            exact = mf.smith_g1(v, m, alpha, dist, exact_beckmann_g1=True)
            assert ((approx - exact).abs() / exact.clamp(min=1e-3)).max() < 0.0035 + 1e-4
        g1 = mf.smith_g1(v, m, alpha, dist)
        # Walter's eq. 27 slightly exceeds 1 below a = 1.6 (by up to 6.1e-5), as in Mitsuba
        assert (g1 <= 1 + 7e-5).all() and (g1 >= 0).all()
        assert (g1[1:] <= g1[:-1] + 7e-5).all()  # non-increasing in theta_v (up to the bump)
    # back side of the microfacet is never visible
    v_up = torch.tensor([0.9, 0, 0.43589], dtype=F64)
    m_away = mf._normalize(torch.tensor([-1.0, 0, 0.2], dtype=F64))[0]
    assert mf.smith_g1(v_up, m_away, 0.3, dist) == 0
    v_down = torch.tensor([0.9, 0, -0.43589], dtype=F64)  # from inside, m's underside: seen
    assert mf.smith_g1(v_down, torch.tensor([0.0, 0, 1.0], dtype=F64), 0.3, dist) > 0


def test_blinn_phong_conversion():
    for kappa in (0.0, 1.0, 10.0, 100.0, 1e4):
        a = mf.alpha_from_blinn_phong(kappa)
        assert abs(a - math.sqrt(2 / (kappa + 2))) < 1e-15
        assert abs(mf.blinn_phong_from_alpha(a) - kappa) < 1e-8 * max(1.0, kappa)
    k = torch.tensor([0.5, 20.0, 300.0], dtype=F64)
    assert torch.allclose(mf.blinn_phong_from_alpha(mf.alpha_from_blinn_phong(k)), k)
    assert mf.blinn_phong_from_alpha(0.0) == 2 / 1e-8 - 2  # clamped to alpha = 1e-4


def test_fresnel_matches_optics_and_mitsuba_conventions():
    from torchrefract.optics.smooth import fresnel_dielectric

    c = torch.linspace(0, 1, 101, dtype=F64)
    for eta in (1.5, 1 / 1.5, 2.4):
        f, ct, eta_it, eta_ti = mf.fresnel(c, eta)
        # optics uses eta = n_incident / n_transmitted: for light from outside that is 1/eta
        assert torch.allclose(f, fresnel_dielectric(c, 1 / eta), atol=1e-12)
        assert (ct <= 0).all() and torch.allclose(eta_it, torch.full_like(c, eta))
        f_in, ct_in, _, _ = mf.fresnel(-c[1:], eta)  # inside (-0.0 counts as outside)
        assert torch.allclose(f_in, fresnel_dielectric(c[1:], eta), atol=1e-12)
        assert (ct_in >= 0).all()
    assert mf.fresnel(torch.tensor(0.3, dtype=F64), 1.0)[0] == 0
    assert mf.fresnel(torch.tensor(0.0, dtype=F64), 1.5)[0] == 1


def test_bad_distribution_raises():
    with pytest.raises(ValueError, match="distribution"):
        mf.ndf(torch.ones(1), 0.1, "phong")  # type: ignore[arg-type]

"""NDF and depth mips against slow loop references; the footprint lookup."""

from __future__ import annotations

import math

import pytest
import torch

from torchrefract.optics.ndf import (
    build_ndf_mips,
    combine_exponents,
    kappa_from_length,
    sample_mips,
)


def _random_layer(b=2, h=13, w=10, seed=0):
    g = torch.Generator().manual_seed(seed)
    n = torch.randn(b, h, w, 3, generator=g, dtype=torch.float64)
    n[..., 2] += 2.0
    n = n / n.norm(dim=-1, keepdim=True)
    mask = torch.rand(b, h, w, generator=g) > 0.3
    depth = torch.rand(b, h, w, generator=g, dtype=torch.float64) + 1.0
    return n, mask, depth


def test_mips_match_loop_reference():
    n, mask, depth = _random_layer()
    mips = build_ndf_mips(n, mask, depth)
    b, h, w, _ = n.shape
    assert mips.levels == 1 + math.ceil(math.log2(max(h, w)))
    for lvl in range(mips.levels):
        s = 2 ** lvl
        hl, wl = mips.direction[lvl].shape[1:3]
        assert (hl, wl) == (math.ceil(h / s), math.ceil(w / s))
        for bi in range(b):
            for y in range(hl):
                for x in range(wl):
                    blk = (bi, slice(y * s, (y + 1) * s), slice(x * s, (x + 1) * s))
                    m = mask[blk]
                    cnt = int(m.sum())
                    assert mips.coverage[lvl][bi, y, x, 0] == pytest.approx(cnt / s / s)
                    if cnt == 0:
                        assert mips.length[lvl][bi, y, x, 0] == 0
                        assert math.isinf(mips.depth_min[lvl][bi, y, x, 0])
                        continue
                    mean = n[blk][m].mean(0)
                    ln = mean.norm()
                    assert mips.length[lvl][bi, y, x, 0] == pytest.approx(float(ln), abs=1e-9)
                    assert torch.allclose(mips.direction[lvl][bi, y, x], mean / ln, atol=1e-9)
                    assert mips.depth_min[lvl][bi, y, x, 0] == depth[blk][m].min()
                    assert mips.depth_max[lvl][bi, y, x, 0] == depth[blk][m].max()


def test_flat_and_spread_footprints_give_expected_exponents():
    # All normals equal: length 1 -> a (clamped) huge exponent; spread normals: finite.
    n = torch.zeros(1, 8, 8, 3, dtype=torch.float64)
    n[..., 2] = 1.0
    mips = build_ndf_mips(n, torch.ones(1, 8, 8, dtype=torch.bool), torch.ones(1, 8, 8))
    assert kappa_from_length(mips.length[3]).item() >= 1e5
    ang = torch.linspace(-0.6, 0.6, 8, dtype=torch.float64)
    n2 = torch.stack([torch.sin(ang), torch.zeros(8, dtype=torch.float64), torch.cos(ang)], -1)
    n2 = n2[None, None].expand(1, 8, 8, 3)
    mips2 = build_ndf_mips(n2, torch.ones(1, 8, 8, dtype=torch.bool), torch.ones(1, 8, 8))
    k = kappa_from_length(mips2.length[3]).item()
    # Small-angle: 1 - |n| ~ var(angle) / 2, so kappa ~ 2 / var(angle) * ... bounded range.
    var = float((ang ** 2).mean())
    assert 0.5 * (4 / var) < k < 2.0 * (4 / var)
    # eq. 10 is symmetric and below both exponents
    kg, kd = torch.tensor(50.0), torch.tensor(200.0)
    kc = combine_exponents(kg, kd)
    assert kc < kg and kc == combine_exponents(kd, kg)
    assert kc == pytest.approx(40.0)


def test_sample_mips_levels_and_interpolation():
    n, mask, depth = _random_layer(b=2, h=16, w=16, seed=3)
    mask[:] = True
    mips = build_ndf_mips(n, mask, depth)
    # At a texel center of level l, the lookup returns that texel exactly.
    for lvl in (0, 1, 3):
        s = 2 ** lvl
        xy = torch.tensor([[s * 1.5, s * 0.5], [s * 0.5, s * 1.5]], dtype=torch.float64)
        batch = torch.tensor([1, 0])
        d, ln, cov = sample_mips(mips, batch, xy, torch.full((2,), float(lvl),
                                                              dtype=torch.float64))
        assert torch.allclose(d[0], mips.direction[lvl][1, 0, 1], atol=1e-9)
        assert torch.allclose(ln[1], mips.length[lvl][0, 1, 0, 0], atol=1e-9)
        assert torch.allclose(cov, torch.ones(2, dtype=torch.float64))
    # Between levels: the length varies monotonically between the two levels' values here.
    xy = torch.tensor([[4.0, 4.0]], dtype=torch.float64)
    vals = [sample_mips(mips, torch.tensor([0]), xy, torch.tensor([l], dtype=torch.float64))[1]
            for l in (3.0, 3.5, 4.0)]
    lo, hi = sorted([vals[0].item(), vals[2].item()])
    assert lo - 1e-12 <= vals[1].item() <= hi + 1e-12


@pytest.mark.parametrize("shape", [(1, 1, 1, 1), (2, 5, 7, 1), (2, 33, 17, 4), (1, 9, 1, 9),
                                   (3, 64, 48, 2)])
def test_box_mips_kernel_equals_the_tensor_code(monkeypatch, shape):
    """build_box_mips: csrc/box.c's one call gives avg_pool2d's sums' bits (ceil mode at odd
    sizes, the sign of zero) divided by 4^level, for every level count asked."""
    from torchrefract.kernels import native
    from torchrefract.optics.ndf import build_box_mips

    if not native.available():
        pytest.skip("no C compiler for the native kernels")
    g = torch.Generator().manual_seed(sum(shape))
    x = torch.randn(*shape, generator=g) * 3
    x[x.abs() < 0.3] = -0.0
    for levels in (1, 2, 3, 16):
        assert native.box_mips(x, levels) is not None
        fast = build_box_mips(x, levels)
        with monkeypatch.context() as m:
            m.setattr(native, "box_mips", lambda *a: None)
            slow = build_box_mips(x, levels)
        assert len(fast) == len(slow) and fast[0] is x
        for a, b in zip(fast, slow):
            assert a.shape == b.shape and torch.equal(a, b)
            assert torch.equal(torch.signbit(a), torch.signbit(b))

"""render._box / _masked_box: the supersampled pixels' box filter (n x n sub-pixels) is
avg_pool2d bit for bit, and the masks' averages shared between passes change nothing."""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F

from torchrefract.kernels import native
from torchrefract.result import box as _box, masked_box as _masked_box, plan_box as _plan_box


def _avg_pool(x: torch.Tensor, n: int) -> torch.Tensor:
    return F.avg_pool2d(x.permute(0, 3, 1, 2), n).permute(0, 2, 3, 1).contiguous()


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("n", [2, 3, 4])
@pytest.mark.parametrize("c", [1, 3, 4])
def test_box_is_avg_pool_bit_for_bit(dtype, n, c):
    g = torch.Generator().manual_seed(n * 10 + c)
    for b, h, w in ((1, n, n), (3, n * 17, n * 9), (8, n * 40, n * 33)):
        x = torch.randn(b, h, w, c, generator=g, dtype=dtype) * 7
        out = _box(x, n)
        assert out.shape == (b, h // n, w // n, c) and out.dtype == dtype
        assert torch.equal(out, _avg_pool(x, n))
    assert _box(x, 1) is x


@pytest.mark.parametrize("n", [1, 2, 3])
def test_masked_box_with_shared_masks_is_unchanged(n):
    g = torch.Generator().manual_seed(n)
    mask = torch.rand(2, n * 12, n * 10, generator=g) > 0.4
    xs = [torch.randn(2, n * 12, n * 10, c, generator=g, dtype=dt)
          for c, dt in ((1, torch.float32), (3, torch.float32), (1, torch.float64))]
    cache: dict = {}
    for x in xs:
        shared = _masked_box(x, mask, n, cache)
        alone = _masked_box(x, mask, n)
        assert torch.equal(shared, alone)
        if n > 1:  # the definition: covered sub-pixels' mean, 0 where none is covered
            m = mask[..., None].to(x.dtype)
            den = _avg_pool(m, n)
            ref = torch.where(den > 0, _avg_pool(x * m, n) / den.clamp(min=1e-12),
                              torch.zeros_like(den))
            assert torch.equal(shared, ref)
    # one entry per (mask, dtype) the tensor code averaged (the kernel needs none)
    tensor_dtypes = {torch.float64} | (set() if native.available() else {torch.float32})
    assert len(cache) == (len(tensor_dtypes) if n > 1 else 0)


@pytest.mark.parametrize("n", [1, 2, 3])
@pytest.mark.parametrize("c", [1, 3])
def test_box_kernel_equals_the_tensor_code(monkeypatch, n, c):
    """csrc/box.c gives the tensor code's bits for box, masked_box and plan_box (uniform
    pixels at their first sub-pixel), NaN and Inf at uncovered sub-pixels included (a
    value times a mask of 0 is NaN there, as torch's product; with one sample the masked
    value is 0 there, as torch's where)."""
    assert native.available()
    g = torch.Generator().manual_seed(10 * n + c)
    b, h, w = 3, 11, 13
    x = torch.randn(b, h * n, w * n, c, generator=g) * 3
    mask = torch.rand(b, h * n, w * n, generator=g) > 0.3
    x[~mask & (torch.rand(b, h * n, w * n, generator=g) > 0.9)] = float("inf")
    x[0, 0, 1] = float("nan")
    uniform = torch.rand(b, h, w, generator=g) > 0.5
    for i in range(n):  # a uniform pixel is covered throughout
        for j in range(n):
            mask[:, i::n, j::n] |= uniform
    calls = [lambda: _box(x, n), lambda: _masked_box(x, mask, n, {}),
             lambda: _plan_box(x, n, uniform), lambda: _plan_box(x, n, uniform, mask, {})]
    if n == 1:  # (no plan with one sample; box is x itself)
        calls = calls[1:2]
    fast = [f() for f in calls]
    monkeypatch.setattr(native, "box", lambda *a, **k: None)
    for f, out in zip(calls, fast):
        ref = f()
        assert out.shape == ref.shape and torch.equal(out.isnan(), ref.isnan())
        assert torch.equal(out.nan_to_num(), ref.nan_to_num())


@pytest.mark.parametrize("n", [1, 2, 3])
def test_material_passes_are_the_masked_mean_of_their_sub_pixels(n):
    """The ``roughness`` and ``ior`` passes of per-view materials (computed per pixel from
    the coverage) equal the masked box of the sub-pixels' values, which a roughness map
    still takes, and are exactly the view's value wherever a sub-pixel is covered."""
    import torchrefract as tr
    from conftest import ROOT

    s = tr.load_scene(str(ROOT / "configs" / "demo.yaml"))
    cam = tr.Camera(eye=(0.0, 0.3, 3.0), width=20, height=16, samples_per_pixel=n)
    scenes = [s.replace(camera=cam, method="specular",
                        material=tr.Material(ior=ior, roughness=a))
              for ior, a in ((1.5, 0.1), (1.33, 0.37))]
    out = tr.render(scenes)
    cov = out.coverage
    assert 0 < int((cov > 0).sum()) < cov.numel() and bool(((cov > 0) & (cov < 1)).any()) == (n > 1)
    for name, vals in (("roughness", (0.1, 0.37)), ("ior", (1.5, 1.33))):
        p = out.passes[name][..., 0]
        for i, v in enumerate(vals):
            assert torch.equal(p[i][cov[i] > 0], torch.full_like(p[i][cov[i] > 0], v))
            assert bool((p[i][cov[i] == 0] == 0).all())


@pytest.mark.parametrize("n", [1, 2, 3])
def test_filter_passes_at_once_equals_one_at_a_time(monkeypatch, n):
    """result.filter_passes: csrc/box.c's one pass over every request (2 x 2) gives each
    request the bits of its own filter (the tensor code, one at a time): masks front, back,
    both and none, the coverage, a plan's uniform pixels, 1 and 3 channels, odd sizes."""
    from types import SimpleNamespace

    from torchrefract.result import filter_passes

    if not native.available():
        pytest.skip("no C compiler for the native kernels")
    g = torch.Generator().manual_seed(7 + n)
    b, h, w = 3, n * 13, n * 9
    front = torch.rand(b, h, w, generator=g) > 0.3
    back = front & (torch.rand(b, h, w, generator=g) > 0.3)
    buf = SimpleNamespace(supersample=n, front=SimpleNamespace(mask=front),
                          back=SimpleNamespace(mask=back))
    uniform = torch.rand(b, h // n, w // n, generator=g) > 0.5 if n > 1 else None

    def x(c):
        return torch.randn(b, h, w, c, generator=g) * 5

    requests = {"a": (x(1), "front", False), "b": (x(3), "back", False),
                "c": (x(1), "both", False), "d": (x(3), None, True), "e": (x(1), "front", True),
                "f": (None, "front", False), "g": (None, "both", False), "h": (x(2), None, False)}
    if native.available() and n == 2:  # the kernel ran: it was not the fallback
        assert native.boxes([(v, i % 4, False) for i, (v, _, _) in enumerate(
            requests.values()) if v is not None], (front, back), None) is not None
    at_once = filter_passes(buf, requests, uniform)
    monkeypatch.setattr(native, "boxes", lambda *a: None)
    monkeypatch.setattr(native, "box", lambda *a: None)
    alone = filter_passes(buf, requests, uniform)
    assert at_once.keys() == alone.keys() == requests.keys()
    for k in requests:
        assert at_once[k].shape == alone[k].shape == (b, h // n, w // n, at_once[k].shape[3])
        assert torch.equal(at_once[k], alone[k]), k
    both = (front & back)[..., None].float()
    assert torch.equal(alone["g"], _box(both, n))  # the coverage of both layers


@pytest.mark.parametrize("per_pixel", [False, True])
def test_one_sample_passes_kernel_equals_the_tensor_code(monkeypatch, per_pixel):
    """result._one_sample: csrc/box.c's one sweep (coverage, thickness over both layers,
    roughness and IOR over the front) gives the tensor code's bits: per-view roughness or a
    map's per pixel, layers where one is empty, negative and NaN thickness, several views."""
    from types import SimpleNamespace

    from torchrefract import result

    if not native.available():
        pytest.skip("no C compiler for the native kernels")
    g = torch.Generator().manual_seed(3 + per_pixel)
    b, h, w = 3, 17, 11
    front = torch.rand(b, h, w, generator=g) > 0.3
    back = front & (torch.rand(b, h, w, generator=g) > 0.2)
    fd = torch.rand(b, h, w, generator=g) * 3 * front
    bd = (fd + torch.randn(b, h, w, generator=g)) * back  # some back before the front
    bd[0, 0, 0], front[0, 0, 0], back[0, 0, 0] = float("nan"), True, True
    layer = SimpleNamespace  # depth and normal pass through untouched
    buf = SimpleNamespace(
        front=layer(mask=front, dist=fd, depth=fd * 0.9, normal=torch.randn(b, h, w, 3, generator=g)),
        back=layer(mask=back, dist=bd, depth=bd * 0.9, normal=torch.randn(b, h, w, 3, generator=g)),
        supersample=1)
    rough = (torch.rand(b, h, w, 1, generator=g) if per_pixel
             else torch.tensor([0.1, 0.3, 0.05])[:, None, None, None])
    materials = SimpleNamespace(ior=torch.tensor([1.5, 1.33, 2.4]))
    assert native.one_sample_passes(front, back, fd, bd, rough, materials.ior) is not None
    fm, fast = result._one_sample(buf, rough, materials)
    monkeypatch.setattr(native, "one_sample_passes", lambda *a: None)
    fm_t, slow = result._one_sample(buf, rough.clone(), materials)
    assert torch.equal(fm, fm_t) and list(fast) == list(slow)
    for k in fast:
        assert fast[k].shape == slow[k].shape and torch.equal(fast[k], slow[k]) or (
            fast[k].isnan().equal(slow[k].isnan())
            and torch.equal(fast[k].nan_to_num(), slow[k].nan_to_num())), k
    assert fast["thickness"].isnan().any()  # the NaN case was exercised

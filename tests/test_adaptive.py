"""Adaptive sampling (``RenderSettings(adaptive=True)``, torchrefract.geometry.adaptive):
with n x n samples, one center sample where a pixel's G-buffer is smooth inside, every
sub-pixel elsewhere; with one, the 2x2 lattice shaded and the pixels between interpolated
where their G-buffer and the lattice's radiance are smooth."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest
import torch

import torchrefract as tr
from torchrefract.geometry import adaptive
from torchrefract.geometry.camera import pixel_rays
from torchrefract.geometry.gbuffer import build_gbuffer
from torchrefract.kernels import native
from torchrefract.geometry.mesh import load_mesh
from torchrefract.settings import RenderSettings
from torchrefract.truth.metrics import flip_map

SUITE = Path(__file__).resolve().parent.parent / "configs" / "suite"
UNIFORM, ADAPTIVE = RenderSettings(adaptive=False), RenderSettings(adaptive=True)


def _scene(name: str, size: int = 48, n: int = 2, **changes) -> tr.Scene:
    s = tr.load_scene(SUITE / f"{name}.yaml")
    return s.replace(camera=dataclasses.replace(s.camera, width=size, height=size,
                                                samples_per_pixel=n), **changes)


def _assert_same_render(a, b, *label) -> None:
    """Two renders' radiance and passes equal bit for bit (``label`` names the case)."""
    assert torch.equal(a.radiance, b.radiance), label
    assert set(a.passes) == set(b.passes), label
    for k in a.passes:
        assert torch.equal(a.passes[k], b.passes[k]), (*label, k)


def _plan(s: tr.Scene):
    g = build_gbuffer([load_mesh(s.mesh, s.transform)], [s.camera])
    alpha = torch.full(g.shape, s.material.roughness)
    return g, *adaptive.plan(g, pixel_rays(s.camera)[None], alpha)


def test_on_by_default(monkeypatch):
    assert RenderSettings().adaptive is True
    monkeypatch.delenv("TORCHREFRACT_ADAPTIVE", raising=False)
    assert RenderSettings.from_env().adaptive is True
    monkeypatch.setenv("TORCHREFRACT_ADAPTIVE", "0")
    assert RenderSettings.from_env().adaptive is False


def test_smooth_glass_is_sampled_uniformly():
    """Below SMOOTH_ALPHA every sub-pixel is shaded: the image is the uniform one (the n x n
    plan: ``cone_rays: plane`` reads the frame around a sample, so it is not sparse,
    tests/test_subsamples.py)."""
    s = _scene("sphere_a0", 32, method="rousiers",
               method_options={"internal_bounces": 2, "cone_rays": "plane"})
    a, b = tr.render(s, settings=UNIFORM), tr.render(s, settings=ADAPTIVE)
    assert torch.equal(a.radiance, b.radiance)


def test_edges_are_supersampled_and_the_smooth_interior_is_not():
    """The slab: silhouette pixels (partial coverage) are shaded at all four sub-pixels,
    most of its flat interior once; the center sample lies on the surface, on the ray
    through the pixel's center."""
    s = _scene("slab_a02", 48)
    g = build_gbuffer([load_mesh(s.mesh, s.transform)], [s.camera])  # as built
    _, g2, p = _plan(s)  # planned: its own G-buffer, center samples written in
    cov = g.front.mask.float().reshape(1, 48, 2, 48, 2).mean((2, 4))
    edge = (cov > 0) & (cov < 1)
    assert edge.any() and not (p.uniform & edge).any()
    assert p.uniform.sum() > 0.7 * (cov == 1).sum()
    shaded = g2.object_index().numel()
    assert shaded < 0.5 * int(g.front.mask.sum())
    # a center sample: on the ray through the pixel's center, on its triangle's plane
    first = g2.shade & ~torch.isclose(g2.ray_dir, g.ray_dir).all(-1)
    assert first.any()
    d, pos, eye = g2.ray_dir[first], g2.front.position[first], g2.eye[0]
    along = torch.linalg.cross(pos - eye, d, dim=-1).norm(dim=-1)
    assert float(along.max()) < 1e-4 * float((pos - eye).norm(dim=-1).max())


def test_close_to_uniform_and_fused_equals_tensor():
    """Rough glass: within a small FLIP of the uniform 2x2 image (measured against 1024-spp
    truth on the 12 suite scenes at 128 px, `internal_bounces: 2`: within 0.003 of uniform
    on every scene, mean 0.1432 against 0.1436); the fused kernels shade the planned
    sub-pixels as the tensor code does."""
    for name in ("torus_a01", "sphere_a03"):
        s = _scene(name, 48, method="rousiers", method_options={"internal_bounces": 2})
        u, a = tr.render(s, settings=UNIFORM), tr.render(s, settings=ADAPTIVE)
        t = tr.render(s, settings=RenderSettings(adaptive=True, fused=False))
        obj = (u.coverage[0] > 0).numpy()
        assert flip_map(a.radiance[0].numpy(), u.radiance[0].numpy())[obj].mean() < 0.02
        assert flip_map(a.radiance[0].numpy(), t.radiance[0].numpy())[obj].mean() < 0.002
        assert torch.equal(a.coverage, u.coverage)
        for k in ("exit_found", "bounces", "depth_front"):
            assert a.passes[k].shape == u.passes[k].shape


def test_plan_box_is_the_box_filter_of_the_first_sub_pixels_copied():
    """result.plan_box: the bits of the box filter (and the masked one) after each uniform
    pixel's first sub-pixel was copied to its others, without the copies, on a mesh with
    edges, folds and partly covered pixels."""
    from torchrefract.result import box, masked_box, plan_box  # noqa: PLC0415

    _, g, p = _plan(_scene("bunny_a01", 40))
    assert p.uniform.any() and (~p.uniform & g.front.mask[:, ::2, ::2]).any()
    x = torch.rand(*g.shape, 3, generator=torch.Generator().manual_seed(3)) * 5
    copied = x.clone()
    for i in range(2):
        for j in range(2):
            copied[:, i::2, j::2][p.uniform] = x[:, ::2, ::2][p.uniform]
    assert torch.equal(plan_box(x, 2, p.uniform), box(copied, 2))
    assert torch.equal(plan_box(x, 2, p.uniform, g.front.mask, {}),
                       masked_box(copied, g.front.mask, 2, {}))


def test_reference_is_sampled_uniformly():
    """Mitsuba renders every sub-pixel itself (``shades_object_index = False``): adaptive
    sampling leaves its image as it is."""
    s = _scene("slab_a02", 16, method="reference", method_options={"spp": 4})
    a, b = tr.render(s, settings=UNIFORM), tr.render(s, settings=ADAPTIVE)
    assert torch.equal(a.radiance, b.radiance)


# --- one sample per pixel: the lattice ---------------------------------------------------

def _lattice_inputs(s: tr.Scene):
    g = build_gbuffer([load_mesh(s.mesh, s.transform)], [s.camera])
    from torchrefract.optics.materials import MaterialBatch  # noqa: PLC0415
    from torchrefract.result import front_roughness as _front_roughness  # noqa: PLC0415
    alpha = _front_roughness(g, MaterialBatch.from_scenes([s]))
    return g, (g.front.mask, g.back.mask, g.front.normal, g.back.normal, g.back.depth, alpha)


def test_uniform_kernel_equals_tensor_code():
    """csrc/lattice.c's uniform pixels of a supersampled G-buffer and its sub-pixels to
    shade are adaptive's tensor code's, pixel for pixel: folds, a roughness map
    (per-sub-pixel alpha), per-view alpha, a region, n = 2 and 3, odd sizes."""
    assert native.available()
    tols = (adaptive.SMOOTH_ALPHA, adaptive.NORMAL_TOL, adaptive.DEPTH_TOL)
    seen = set()
    for name, size, n in (("sphere_a03", 41, 2), ("bunny_a01", 37, 2),
                          ("globe_gradient", 30, 3), ("wingnut_a01", 40, 2)):
        s = _scene(name, size, n=n)
        g, args = _lattice_inputs(s)
        region = torch.zeros_like(g.front.mask)
        region[:, : region.shape[1] // 2] = True  # the top half's sub-pixels
        for alpha in (args[-1], torch.full((1, 1, 1), s.material.roughness)):
            for reg in (None, region):
                made = native.uniform(*args[:5], alpha, n, *tols, region=reg)
                assert made is not None
                a, shade = made
                b = adaptive._uniform_torch(g, alpha, n, *tols)
                assert torch.equal(a, b), (name, n, alpha.shape)
                assert torch.equal(shade, adaptive._shade_torch(g.front.mask, b, reg)), name
                seen.update(a.unique().tolist())
    assert seen == {False, True}


def test_center_samples_kernel_equals_tensor_code():
    """csrc/gbuffer.c's center samples write the tensor code's values into the front layer
    and rays, bit for bit: pixels whose sub-pixels see one triangle and several (folds,
    edges), n = 2 and 3."""
    import copy

    for name, size, n in (("bunny_a01", 40, 2), ("sphere_a03", 33, 3), ("wingnut_a01", 36, 2)):
        s = _scene(name, size, n=n)
        g, args = _lattice_inputs(s)
        uniform = adaptive._uniform_torch(g, args[-1], n, adaptive.SMOOTH_ALPHA,
                                          adaptive.NORMAL_TOL, adaptive.DEPTH_TOL)
        center = pixel_rays(s.camera)[None].contiguous()
        a, b = copy.deepcopy(g), copy.deepcopy(g)
        assert native.center_samples(a, uniform, center)
        _, h, w = g.shape
        pb, py, px = uniform.nonzero(as_tuple=True)
        sel = (pb * h + py * n) * w + px * n
        tris = torch.stack([t[uniform] for t in adaptive._subs(b.front.tri, n)], 1)
        assert (tris != tris[:, :1]).any(), name  # some pixels with several triangles
        adaptive._center_samples(b, sel, tris, center[uniform])
        for f in ("tri", "position", "dist", "depth", "bary", "normal", "uv"):
            assert torch.equal(getattr(a.front, f), getattr(b.front, f)), (name, f)
        assert torch.equal(a.ray_dir, b.ray_dir)
        assert not torch.equal(a.front.position, g.front.position)  # it wrote


def test_lattice_plan_kernel_equals_tensor_code():
    """csrc/lattice.c's plan is adaptive._lattice_torch's, status for status, on meshes
    with folds, a roughness map and odd frame sizes (a last row and column without their
    second neighbour)."""
    assert native.available()
    blends = []  # whether some waiting pixels of a scene are near a tolerance (blended)
    coarse_waits = []  # whether some even pixels of a scene wait on those of stride 4
    fewer = []  # whether some pixels still wait among the uniform ones, fewer than among all
    for name, size in (("sphere_a03", 48), ("bunny_a01", 49), ("globe_gradient", 47),
                       ("wingnut_a01", 40)):
        _, args = _lattice_inputs(_scene(name, size, n=1))
        a = native.lattice_plan(*args, adaptive.SMOOTH_ALPHA, adaptive.NORMAL_TOL,
                                adaptive.DEPTH_TOL)
        b = adaptive._lattice_torch(*args, adaptive.SMOOTH_ALPHA, adaptive.NORMAL_TOL,
                                    adaptive.DEPTH_TOL)
        assert torch.equal(a[0], b[0]) and torch.equal(a[1], b[1]), name
        a, gap, counts = a
        assert torch.equal(counts, adaptive._counts(a)), name  # per view: objects, waiting
        assert (gap[a == 2] <= 1).all() and (gap[a == 2] >= 0).all() and (gap[a != 2] == 0).all()
        blends.append(bool((gap[a == 2] > adaptive.BLEND_FROM).any()))
        assert set(a.unique().tolist()) <= {0, 1, 2}
        lat = torch.zeros_like(a, dtype=torch.bool)
        lat[:, ::2, ::2] = True
        assert not ((a == 2) & lat).any()  # the lattice never waits
        assert torch.equal(a > 0, args[0])  # every object pixel has a status
        # the coarse level: the even pixels read in place equal the tensor code on copies
        even = (slice(None), slice(None, None, 2), slice(None, None, 2))
        sub = [x[even].contiguous() if x.dim() > 3 or x.shape[1:] == args[0].shape[1:]
               else x for x in args]
        tols = (adaptive.SMOOTH_ALPHA, adaptive.NORMAL_TOL, adaptive.DEPTH_TOL)
        a2, b2 = native.lattice_plan(*args, *tols, stride=2), adaptive._lattice_torch(*sub, *tols)
        assert torch.equal(a2[0], b2[0]) and torch.equal(a2[1], b2[1]), name
        assert torch.equal(a2[2], adaptive._counts(b2[0])), name
        coarse_waits.append(bool((a2[0] == 2).any()))
        # over a supersampled plan only its uniform pixels wait or are waited on
        uni = torch.rand(a.shape, generator=torch.Generator().manual_seed(size)) > 0.05
        for st, u, ins in ((1, uni, args), (2, uni[:, ::2, ::2], sub)):
            a3 = native.lattice_plan(*args, *tols, stride=st, uniform=u)
            b3 = adaptive._lattice_torch(*ins, *tols, uniform=u)
            assert torch.equal(a3[0], b3[0]) and torch.equal(a3[1], b3[1]), (name, st)
            assert torch.equal(a3[2], adaptive._counts(b3[0])), (name, st)
            assert not ((a3[0] == 2) & ~u).any(), (name, st)
            if st == 1:  # fewer wait (some still do: below)
                fewer.append(0 < int((a3[0] == 2).sum()) < int((a == 2).sum()))
    assert any(blends), blends
    assert any(coarse_waits), coarse_waits
    assert any(fewer), fewer


def test_lattice_plan_lanes_equal_tensor_code_on_adversarial_layers():
    """csrc/lattice.c's plan in AVX2 lanes (8 pixels of a row whose neighbours lie inside
    the frame) decides as the tensor code does where the layers are not a mesh's: random
    masks, normals with NaNs, back depths with NaNs, infinities and zeros, neighbours at
    the tolerances, roughness per view and per pixel (zeros and NaNs), rows of 8 to 71
    pixels (groups at every column parity, and the rest one by one)."""
    assert native.available()
    gen = torch.Generator().manual_seed(7)
    tols = (adaptive.SMOOTH_ALPHA, adaptive.NORMAL_TOL, adaptive.DEPTH_TOL)
    seen = set()
    for b, h, w in ((2, 37, 71), (1, 12, 8), (3, 9, 26), (1, 2, 40)):
        fm = torch.rand(b, h, w, generator=gen) > 0.15
        bm = fm & (torch.rand(b, h, w, generator=gen) > 0.1)

        def normals():
            # near one direction (many within the tolerance of a neighbour), a few NaN
            n = torch.tensor([0.0, 0.0, 1.0]) + 0.12 * torch.randn(b, h, w, 3, generator=gen)
            n = n / n.norm(dim=-1, keepdim=True)
            n[torch.rand(b, h, w, generator=gen) < 0.01] = float("nan")
            return n

        fn, bn = normals(), normals()
        bd = 2.0 + 0.1 * torch.randn(b, h, w, generator=gen)
        odd = torch.rand(b, h, w, generator=gen)
        bd[odd < 0.01] = float("nan")
        bd[(odd >= 0.01) & (odd < 0.02)] = float("inf")
        bd[(odd >= 0.02) & (odd < 0.03)] = 0.0
        for alpha in (torch.full((b, 1, 1), 0.3), torch.rand(b, h, w, generator=gen) * 0.4):
            if alpha.dim() == 3 and alpha.shape[1] > 1:
                alpha[torch.rand(b, h, w, generator=gen) < 0.02] = 0.0
                alpha[torch.rand(b, h, w, generator=gen) < 0.01] = float("nan")
            args = (fm, bm, fn, bn, bd, alpha)
            a = native.lattice_plan(*args, *tols)
            ref = adaptive._lattice_torch(*args, *tols)
            assert torch.equal(a[0], ref[0]), (b, h, w, alpha.shape)
            assert torch.equal(a[1], ref[1]), (b, h, w, alpha.shape)
            assert torch.equal(a[2], adaptive._counts(ref[0])), (b, h, w)
            seen.update(a[0].unique().tolist())
    assert seen == {0, 1, 2}


def test_first_pass_mask_and_index_kernels_equal_tensor_code():
    """csrc/index.c: the first pass's mask (a level's waiting pixels taken out at its stride)
    and the object pixels' flat indices and views are the tensor expressions', on real
    plans of odd-sized batches of two views and on masks whose views do not fill whole
    8-byte words, all clear or all set."""
    assert native.available()
    s = _scene("sphere_a03", 49, n=1)
    g, args = _lattice_inputs(s)
    g2, args2 = _lattice_inputs(s.replace(camera=dataclasses.replace(
        s.camera, eye=(0.4, 0.5, 2.9))))
    args = [torch.cat([a, b]) for a, b in zip(args, args2)]  # two views
    tols = (adaptive.SMOOTH_ALPHA, adaptive.NORMAL_TOL, adaptive.DEPTH_TOL)
    for stride in (1, 2):
        status = native.lattice_plan(*args, *tols, stride=stride)[0]
        assert (status == 2).any() and (status == 1).any()
        mine, ref = args[0].clone(), args[0].clone()
        assert native.clear_waiting(mine, status, stride)
        ref[:, ::stride, ::stride] &= status != 2
        assert torch.equal(mine, ref) and not torch.equal(mine, args[0]), stride
        masks = [mine, args[0], torch.zeros_like(mine), torch.ones(3, 7, 5, dtype=torch.bool),
                 torch.rand(2, 33, 65, generator=torch.Generator().manual_seed(stride)) > 0.6]
        for m in masks:
            hw = m.shape[1] * m.shape[2]
            idx, view = native.mask_index(m, hw)
            want = m.reshape(-1).nonzero(as_tuple=True)[0]
            assert torch.equal(idx, want) and torch.equal(view, want // hw)
    # the G-buffer's own: its object pixels' views, found with their indices
    both = build_gbuffer([load_mesh(s.mesh, s.transform)] * 2,
                         [s.camera, dataclasses.replace(s.camera, eye=(0.4, 0.5, 2.9))])
    idx, view = both.object_index(), both.object_views()
    assert view.unique().tolist() == [0, 1]
    assert torch.equal(view, idx // (49 * 49)) and both.object_index() is idx


def test_lattice_fill_kernel_equals_tensor_code():
    """The fill's decisions and means agree bit for bit, NaN and Inf neighbours included
    (never interpolated from), and huge and negative ones (spreads that overflow, negative
    luminances: the kernel divides once, the tensor code per channel)."""
    _, args = _lattice_inputs(_scene("sphere_a03", 41, n=1))
    st, gap = adaptive._lattice_torch(*args, adaptive.SMOOTH_ALPHA, adaptive.NORMAL_TOL,
                                      adaptive.DEPTH_TOL)
    gen = torch.Generator().manual_seed(3)
    rad = 1.0 + 0.08 * torch.rand(st.numel(), 3, generator=gen)  # spreads around the tol
    rad[::97] = float("nan")
    rad[5::131] = float("inf")
    rad[7::23] = -1e38  # negative luminances
    # spreads that overflow over a small luminance: lattice neighbours at +-1e38
    some = (st.view(-1) == 2).nonzero()[:, 0][3:60:7]
    nb, _, _ = adaptive._neighbours(some, *st.shape[1:])
    rad[nb[:, 0]], rad[nb[:, 1]] = 1e38, -1e38
    s1, s2, r1, r2 = st.clone(), st.clone(), rad.clone(), rad.clone()
    w1, w2 = torch.zeros(st.shape), torch.zeros(st.shape)
    assert native.lattice_fill(s1, gap, w1, r1, adaptive.LATTICE_RTOL, adaptive.BLEND_FROM)
    adaptive._fill_torch(s2, gap, w2, r2, adaptive.LATTICE_RTOL, adaptive.BLEND_FROM)
    assert torch.equal(s1, s2) and torch.equal(w1, w2)
    assert torch.equal(r1.nan_to_num(7.0, 8.0), r2.nan_to_num(7.0, 8.0))
    assert all((s1 == k).sum() > 0 for k in (3, 4, 5)) and not (s1 == 2).any()
    assert torch.isfinite(r1[(s1 >= 3).view(-1) & (s1 != 4).view(-1)]).all()
    assert ((w1[s1 == 5] > 0) & (w1[s1 == 5] < 1)).all() and (w1[s1 != 5] == 0).all()


def test_lattice_fill_lanes_equal_tensor_code_with_passes():
    """csrc/lattice.c's fill in AVX2 lanes (8 pixels of a row whose neighbours lie inside
    the frame) equals the tensor code with passes of 1 and 3 channels: radiance spreads
    around the tolerance, NaN, Inf, huge and negative neighbours, gaps on both sides of
    BLEND_FROM, rows of 8 to 71 pixels, several views."""
    assert native.available()
    gen = torch.Generator().manual_seed(11)
    seen = set()
    for b, h, w in ((2, 37, 71), (1, 12, 8), (3, 9, 26)):
        lat = torch.zeros(b, h, w, dtype=torch.bool)
        lat[:, ::2, ::2] = True
        obj = torch.rand(b, h, w, generator=gen) > 0.1
        st = torch.where(obj, torch.where(lat, 1, 2), 0).to(torch.uint8)
        st[:, -1, :] = torch.where(obj[:, -1, :] & (st[:, -1, :] == 2), 1, st[:, -1, :])
        if w % 2 == 0:  # a last odd column has no right neighbour: shaded, not waiting
            st[:, :, -1] = torch.where(st[:, :, -1] == 2, 1, st[:, :, -1])
        st[(st == 2) & (torch.rand(b, h, w, generator=gen) < 0.1)] = 1
        gap = torch.where(st == 2, torch.rand(b, h, w, generator=gen), torch.zeros(()))
        n = b * h * w
        rad = 1.0 + 0.08 * torch.rand(n, 3, generator=gen)
        rad[torch.rand(n, generator=gen) < 0.01] = float("nan")
        rad[torch.rand(n, generator=gen) < 0.01] = float("inf")
        rad[torch.rand(n, generator=gen) < 0.01] = -1e38
        rad[torch.rand(n, generator=gen) < 0.01] = 1e38
        passes = [torch.rand(n, 1, generator=gen), torch.rand(n, 3, generator=gen)]
        outs = []
        for run in ("kernel", "tensor"):
            s, g, r = st.clone(), gap.clone(), rad.clone()
            wt, ps = torch.zeros(b, h, w), [x.clone() for x in passes]
            if run == "kernel":
                assert native.lattice_fill(s, g, wt, r, adaptive.LATTICE_RTOL,
                                           adaptive.BLEND_FROM, ps)
            else:
                adaptive._fill_torch(s, g, wt, r, adaptive.LATTICE_RTOL, adaptive.BLEND_FROM,
                                     ps)
            outs.append((s, wt, r.nan_to_num(7.0, 8.0, -8.0), *ps))
        for x, y in zip(*outs):
            assert torch.equal(x, y), (b, h, w)
        seen.update(outs[0][0].unique().tolist())
    assert {3, 4, 5} <= seen and 2 not in seen
    # a lattice pixel set waiting (no plan does) is shaded, not filled, in lanes as one by one
    st = torch.ones(1, 6, 40, dtype=torch.uint8)
    st[0, 2, 10] = st[0, 2, 39] = 2  # an even row's even column: inside a lane group, last
    rad = torch.ones(6 * 40, 3)
    assert native.lattice_fill(st, torch.zeros(1, 6, 40), torch.zeros(1, 6, 40), rad,
                               adaptive.LATTICE_RTOL, adaptive.BLEND_FROM)
    assert st[0, 2, 10] == 4 and st[0, 2, 39] == 4 and torch.equal(rad, torch.ones(6 * 40, 3))


def test_fill_where_no_waiting_pixel_is_interpolated_keeps_the_passes():
    """A level whose waiting pixels all disagree with their neighbours (each is shaded)
    fills nothing, passes included: the tensor code and the kernel alike (the tensor code
    once failed on the empty set with passes to fill)."""
    _, args = _lattice_inputs(_scene("sphere_a03", 41, n=1))
    st, gap = adaptive._lattice_torch(*args, adaptive.SMOOTH_ALPHA, adaptive.NORMAL_TOL,
                                      adaptive.DEPTH_TOL)
    assert (st == 2).any()
    # lattice neighbours two apart always differ: 1 or 100 by row and column modulo 4
    ys, xs = torch.meshgrid(torch.arange(st.shape[1]), torch.arange(st.shape[2]),
                            indexing="ij")
    v = 1.0 + 99.0 * ((xs % 4 == 2) ^ (ys % 4 == 2)).float()
    rad = v.expand(st.shape).reshape(-1, 1).repeat(1, 3).contiguous()
    passes = [torch.arange(st.numel() * 2, dtype=torch.float32).view(-1, 2)]
    for run in ("kernel", "tensor"):
        s, r, w, p = st.clone(), rad.clone(), torch.zeros(st.shape), [passes[0].clone()]
        if run == "kernel":
            assert native.lattice_fill(s, gap, w, r, adaptive.LATTICE_RTOL,
                                       adaptive.BLEND_FROM, p)
        else:
            adaptive._fill_torch(s, gap, w, r, adaptive.LATTICE_RTOL, adaptive.BLEND_FROM, p)
        assert torch.equal(s[st == 2], torch.full_like(s[st == 2], 4)), run
        assert torch.equal(r, rad) and torch.equal(p[0], passes[0]) and not w.any(), run


def test_one_sample_shades_the_lattice_and_interpolates_the_smooth_rest():
    """The rough sphere: under half of its pixels are shaded; those are the full render's
    bit for bit, the others interpolated close to it (FLIP); the passes too."""
    s = _scene("sphere_a03", 64, n=1, method="rousiers")
    full, ad = tr.render(s, settings=UNIFORM), tr.render(s, settings=ADAPTIVE)
    g, args = _lattice_inputs(s)
    m = g.front.mask[0]
    same = (ad.radiance[0] == full.radiance[0]).all(-1)
    assert same[~m].all()  # the background is untouched
    exact = float(same[m].float().mean())
    assert 0.1 < exact < 0.5, exact  # the lattice (1/4, less with the coarse level) and more
    fl = float(flip_map(ad.radiance[0].numpy(), full.radiance[0].numpy())[m.numpy()].mean())
    # the interpolated pixels differ from the full render's (not from the truth: on the
    # validation set FLIP against the truth moves by < 0.003, docs/decisions.md); 64 px
    # is coarse for a lattice of stride 4, the largest here
    assert fl < 0.02, fl
    for k in ("exit_found", "normal_front", "thickness"):
        assert torch.isfinite(ad.passes[k]).all() and ad.passes[k].shape == full.passes[k].shape


def test_one_sample_with_bounces_a_light_and_a_roughness_map_stays_close():
    """Every shaded pixel is the full render's; the image stays within FLIP 0.02 of it
    with internal bounces, a sphere light in front (slab_light) and a roughness map."""
    for name, opts in (("slab_light", {}), ("globe_gradient", {"internal_bounces": 2}),
                       ("bunny_a01", {"internal_bounces": 2})):
        s = _scene(name, 48, n=1, method="rousiers", method_options=opts)
        full, ad = tr.render(s, settings=UNIFORM), tr.render(s, settings=ADAPTIVE)
        g, _ = _lattice_inputs(s)
        m = g.front.mask[0]
        fl = float(flip_map(ad.radiance[0].numpy(), full.radiance[0].numpy())[m.numpy()].mean())
        assert fl < 0.02, (name, fl)
        assert torch.isfinite(ad.radiance).all()


def test_one_sample_smooth_glass_and_fallback():
    """Smooth glass waits nowhere (the image is the full one); without the native kernels
    the tensor code plans and fills alike (the same pixels shaded)."""
    s = _scene("sphere_a0", 40, n=1, method="rousiers")
    assert torch.equal(tr.render(s, settings=UNIFORM).radiance,
                       tr.render(s, settings=ADAPTIVE).radiance)
    s = _scene("sphere_a03", 40, n=1, method="specular")
    a = tr.render(s, settings=ADAPTIVE)
    b = tr.render(s, settings=RenderSettings(adaptive=True, native=False, fused=False))
    close = torch.isclose(a.radiance, b.radiance, rtol=1e-3, atol=1e-5).all(-1)
    assert float(close.float().mean()) > 0.995


def test_two_levels_where_smooth_over_several_pixels_one_elsewhere(monkeypatch):
    """The rough sphere is smooth over several pixels: the even pixels get their own
    level (stride 4) first; with COARSE_SHARE at 0.5 the bunny keeps one level. With two
    levels every pixel that is shaded is still the full render's bit for bit, and the
    image stays close to it."""
    s = _scene("sphere_a03", 96, n=1, method="rousiers")
    g, args = _lattice_inputs(s)
    _, lat = adaptive.lattice(g, args[-1])
    assert [lv.stride for lv in lat.levels] == [2, 1]
    assert lat.levels[0].status.shape == (1, 48, 48)
    gb, argsb = _lattice_inputs(_scene("bunny_a01", 96, n=1))
    lat_b = adaptive.lattice(gb, argsb[-1], coarse_share=0.5)[1]
    assert lat_b is None or [lv.stride for lv in lat_b.levels] == [1]
    full, ad = tr.render(s, settings=UNIFORM), tr.render(s, settings=ADAPTIVE)
    m = g.front.mask[0]
    same = (ad.radiance[0] == full.radiance[0]).all(-1)[m]
    exact = float(same.float().mean())
    assert 0.05 < exact < 0.25, exact  # under the one-level lattice's quarter
    fl = float(flip_map(ad.radiance[0].numpy(), full.radiance[0].numpy())[m.numpy()].mean())
    assert fl < 0.02, fl
    # forced to one level: more pixels shaded, the image closer to the full one
    old = adaptive.COARSE_SHARE
    try:
        adaptive.COARSE_SHARE = 1.01
        one = tr.render(s, settings=ADAPTIVE)
    finally:
        adaptive.COARSE_SHARE = old
    assert float((one.radiance[0] == full.radiance[0]).all(-1)[m].float().mean()) > exact


def test_coarser_levels_up_to_the_coarsest_stride(monkeypatch):
    """Levels coarsen (strides 2, then 4) where COARSE_SHARE of a level's lattice pixels
    could wait, up to COARSEST: the rough sphere at 128 pixels takes three. csrc/lattice.c's
    driver gives the images of the levels run from Python bit for bit; every pixel shaded
    is the full render's, and the image stays close to it, but further than with two
    levels. With COARSEST raised (and COARSE_SHARE 0) the loop goes on at stride 8."""
    from torchrefract.shading import fused

    s = _scene("sphere_a03", 128, n=1, method="rousiers")
    made, lattice = [], adaptive.lattice
    monkeypatch.setattr(adaptive, "lattice", lambda *a, **k: made.append(lattice(*a, **k))
                        or made[-1])

    def rendered(**consts):
        for k, v in consts.items():
            monkeypatch.setattr(adaptive, k, v)
        out = tr.render(s, settings=ADAPTIVE)
        return out, made[-1][1]  # its levels' statuses as the fill left them

    a, lat = rendered()
    assert [lv.stride for lv in lat.levels] == [4, 2, 1]
    run = fused._run
    monkeypatch.setattr(fused, "_run", lambda n, job, *rest: run(n, job))
    b = tr.render(s, settings=ADAPTIVE)
    monkeypatch.setattr(fused, "_run", run)
    assert torch.equal(a.radiance, b.radiance)
    full = tr.render(s, settings=UNIFORM)
    m = full.coverage[0] > 0
    shaded = m.clone()  # no level interpolated it (status 3) nor blended it (5)
    for lv in lat.levels:
        st = lv.status[0]
        shaded[::lv.stride, ::lv.stride] &= (st != 3) & (st != 5)
    assert 0.03 < float(shaded[m].float().mean()) < 0.25
    assert torch.equal(a.radiance[0][shaded], full.radiance[0][shaded])

    def flip(r) -> float:
        return float(flip_map(r.radiance[0].numpy(), full.radiance[0].numpy())[m.numpy()].mean())

    two, lat2 = rendered(COARSEST=2)
    assert [lv.stride for lv in lat2.levels] == [2, 1]
    assert flip(two) < flip(a) < 0.03, (flip(two), flip(a))
    _, lat8 = rendered(COARSEST=8, COARSE_SHARE=0.0)
    assert [lv.stride for lv in lat8.levels] == [8, 4, 2, 1]


def test_coarser_levels_over_a_plan_refine_every_level(monkeypatch):
    """Over a 2x2 plan's center samples (a method that reads the frame around a sample)
    the levels coarsen too, and the refine pass shades again the center samples any level
    interpolated where the radiance spreads: the image stays close to the uniform 2x2."""
    monkeypatch.setattr(adaptive, "COARSE_SHARE", 0.0)
    s = _scene("sphere_a03", 64, n=2, method="lean")
    levels = []
    lattice = adaptive.lattice

    def seen(*a, **k):
        out = lattice(*a, **k)
        levels.append(None if out[1] is None else len(out[1].levels))
        return out

    monkeypatch.setattr(adaptive, "lattice", seen)
    a = tr.render(s, settings=ADAPTIVE)
    monkeypatch.undo()
    assert levels and levels[0] >= 3, levels
    u = tr.render(s, settings=UNIFORM)
    obj = a.coverage[0].numpy() > 0
    assert flip_map(a.radiance[0].numpy(), u.radiance[0].numpy())[obj].mean() < 0.02


def test_refine_reads_every_level():
    """refine() shades again a center sample that any level interpolated (status 3 or 5
    at that level's stride) where the radiance spreads, and none that no level did:
    each level alone marked, on a plan with four levels."""
    h = w = 16
    uniform = torch.ones(1, h, w, dtype=torch.bool)
    levels = tuple(adaptive.Level(s, torch.ones(1, h // s, w // s, dtype=torch.uint8),
                                  torch.zeros(1, h // s, w // s), sub=2) for s in (8, 4, 2, 1))
    plan = adaptive.Plan(uniform=uniform, n=2, lattice=adaptive.Lattice(levels))
    yy, xx = torch.meshgrid(torch.arange(2 * h), torch.arange(2 * w), indexing="ij")
    rad = (10.0 * ((yy // 2 + xx // 2) % 2))[None, ..., None].expand(1, 2 * h, 2 * w, 3)
    for k, lv in enumerate(levels):
        for other in levels:
            other.status.fill_(1)
        lv.status.view(-1)[::3] = 3 if k % 2 else 5  # some of its pixels interpolated
        more, rest = adaptive.refine(plan, rad)
        assert bool(more.all())  # (a checkerboard: every uniform pixel spreads)
        want = torch.zeros(1, h, w, dtype=torch.bool)
        want[:, ::lv.stride, ::lv.stride] = lv.status >= 3
        assert torch.equal(rest[:, ::2, ::2], want), lv.stride
        assert bool(rest[:, 1::2].all() and rest[:, :, 1::2].all())


@pytest.mark.parametrize("n", [1, 2])
def test_fused_levels_in_the_kernel_equal_the_levels_in_python(monkeypatch, n):
    """csrc/lattice.c's driver (the fused methods fill and shade every level after their
    first pass in one call) gives the images and passes of adaptive.fill and
    adaptive.merge bit for bit: two levels (the sphere), a light in front, a roughness map
    with bounces, the cone methods, at one sample per pixel and over a 2x2 plan's center
    samples; and it is the path taken."""
    from torchrefract.shading import fused

    cases = (("sphere_a03", "specular", {}), ("sphere_a03", "prefiltered", {}),
             ("sphere_a03", "rousiers", {}), ("slab_light", "rousiers", {}),
             ("globe_gradient", "rousiers", {"internal_bounces": 2}),
             ("globe_jump", "lean", {}), ("vgroove_a01", "gsr", {}))
    run, run_lattice, calls = fused._run, fused._run_lattice, []

    def counted(name, *rest):
        calls.append(name)
        return run_lattice(name, *rest)

    for name, method, opts in cases:
        s = _scene(name, 96 // n, n=n, method=method, method_options=opts)
        monkeypatch.setattr(fused, "_run_lattice", counted)
        a = tr.render(s, settings=ADAPTIVE)
        kernel = {"prefiltered": "specular", "gsr": "lean"}.get(method, method)
        assert calls and calls[-1] == kernel, (name, method, calls)
        # the same kernels, each level's fill and pass run from Python
        monkeypatch.setattr(fused, "_run", lambda n, job, *rest: run(n, job))
        b = tr.render(s, settings=ADAPTIVE)
        monkeypatch.undo()
        _assert_same_render(a, b, name, method)


def test_tensor_code_levels_in_the_kernels_driver_equal_the_levels_in_python(monkeypatch):
    """After a first pass by a method's tensor code (the fused kernels off here; ``sh``,
    ``lean``'s tensor code), csrc/lattice.c's driver fills every level and calls the
    method back for each level's pass (``fused.lattice_levels``): the images and passes of
    adaptive.fill and adaptive.merge bit for bit, three levels at one sample and over a
    2x2 plan; it is the path taken; an error in a level's pass reaches the caller as it
    was raised."""
    from torchrefract import result
    from torchrefract.shading import fused

    tensor = RenderSettings(adaptive=True, fused=False)
    levels, driven = fused.lattice_levels, []
    for name, method, n in (("sphere_a03", "rousiers", 1), ("sphere_a03", "specular", 1),
                            ("globe_jump", "lean", 2)):
        s = _scene(name, 128 // n, n=n, method=method)
        monkeypatch.setattr(fused, "lattice_levels", lambda lv, *rest: driven.append(
            len(lv)) or levels(lv, *rest))
        a = tr.render(s, settings=tensor)
        assert driven and driven[-1] >= 2, (name, method, driven)
        monkeypatch.setattr(fused, "lattice_levels", lambda *a: False)
        b = tr.render(s, settings=tensor)
        monkeypatch.undo()
        _assert_same_render(a, b, name, method)
    shade, passes = result.tiles.shade, []

    def failing(entry, g, *rest):
        passes.append(g.canvas is not None)
        if g.canvas is not None:  # a level's pass
            raise ArithmeticError("a level's pass failed")
        return shade(entry, g, *rest)

    monkeypatch.setattr(result.tiles, "shade", failing)
    with pytest.raises(ArithmeticError, match="a level's pass failed"):
        tr.render(_scene("sphere_a03", 128, n=1, method="rousiers"), settings=tensor)
    assert passes == [False, True]


def test_supersampled_plan_interpolates_only_uniform_center_samples():
    """Over a 2x2 plan the levels wait on the uniform pixels' center samples (their first
    sub-pixels): never a non-uniform pixel (shaded at every sub-pixel) nor on one; the
    first pass is the plan's sub-pixels less the waiting ones; the image stays within a
    small FLIP of the uniform 2x2 one."""
    s = _scene("slab_a02", 64, method="rousiers")
    _, g, p = _plan(s)
    alpha = torch.full(g.shape, s.material.roughness)
    with pytest.raises(ValueError, match="uniform"):
        adaptive.lattice(g, alpha)
    g2, lat = adaptive.lattice(g, alpha, uniform=p.uniform)
    assert lat is not None and all(lv.sub == 2 for lv in lat.levels)
    fine = lat.levels[-1]
    assert fine.status.shape == p.uniform.shape
    wait = fine.status == 2
    edge = (fine.status > 0) & ~p.uniform
    assert wait.any() and edge.any() and not (wait & edge).any()
    # nor on one: a waiting pixel's lattice neighbours (left/right in an even row, up/down
    # in an even column, the diagonals otherwise) are all uniform
    bi, y, x = wait.nonzero(as_tuple=True)
    for dy, dx, on in ((0, 1, (y % 2 == 0)), (1, 0, (x % 2 == 0)), (1, 1, (y % 2 == 1) & (x % 2 == 1)),
                       (1, -1, (y % 2 == 1) & (x % 2 == 1))):
        for sgn in (1, -1):
            assert bool(p.uniform[bi[on], y[on] + sgn * dy, x[on] + sgn * dx].all()), (dy, dx)
    first = g.shade.clone()
    for lv in lat.levels:
        first[:, ::lv.frame_stride, ::lv.frame_stride] &= lv.status != 2
    assert torch.equal(g2.shade, first) and int(g2.shade.sum()) < int(g.shade.sum())
    u, a = tr.render(s, settings=UNIFORM), tr.render(s, settings=ADAPTIVE)
    obj = (u.coverage[0] > 0).numpy()
    assert flip_map(a.radiance[0].numpy(), u.radiance[0].numpy())[obj].mean() < 0.02


def test_no_lattice_where_too_little_could_wait():
    """Under FINE_SHARE of the object pixels waiting, no lattice: the full render."""
    s = _scene("sphere_a03", 48, n=1, method="specular")
    g, args = _lattice_inputs(s)
    old = adaptive.FINE_SHARE
    try:
        adaptive.FINE_SHARE = 1.01
        g2, lat = adaptive.lattice(g, args[-1])
        assert g2 is g and lat is None
        ad = tr.render(s, settings=ADAPTIVE)
    finally:
        adaptive.FINE_SHARE = old
    assert torch.equal(ad.radiance, tr.render(s, settings=UNIFORM).radiance)


def test_camera_planes_are_kept_per_g_buffer_and_follow_its_inputs():
    """GBuffer.derived: a render's passes and tiles (dataclasses.replace of one G-buffer)
    share the march's planes; a G-buffer with another camera or layers changed in place
    gets its own."""
    from torchrefract.kernels.march import _camera_planes, camera_planes  # noqa: PLC0415

    g, _ = _lattice_inputs(_scene("sphere_a03", 32, n=1))
    a = camera_planes(g)
    assert camera_planes(dataclasses.replace(g, shade=g.front.mask)) is a  # shared
    moved = dataclasses.replace(g, eye=g.eye + 0.5)
    assert torch.equal(camera_planes(moved).table, _camera_planes(moved, False).table)
    assert not torch.equal(camera_planes(moved).table, a.table)
    assert g.back.tri[0, 16, 16] >= 0
    g.back.tri[0, 16, 16] = -1  # in place: the version moves
    again = camera_planes(g)
    assert again is not a and torch.equal(again.back, _camera_planes(g, False).back)
    assert again.back[16 * 32 + 16] == -1


def test_each_view_decides_alone_so_a_batch_is_its_views_rendered_alone(monkeypatch):
    """The lattice's levels are chosen per view: with shares that make a smooth view take
    two levels and a detailed one one level (or none), a batch of both gives each view's
    image alone, bit for bit (a large batch is rendered in chunks: its images must not
    depend on its neighbours)."""
    monkeypatch.setattr(adaptive, "FINE_SHARE", 0.4)
    monkeypatch.setattr(adaptive, "COARSE_SHARE", 0.5)
    a = _scene("sphere_a03", 96, n=1, method="rousiers")
    b = _scene("bunny_a01", 96, n=1, method="rousiers")
    ga, aa = _lattice_inputs(a)
    gb, ab = _lattice_inputs(b)
    lat_a, lat_b = adaptive.lattice(ga, aa[-1])[1], adaptive.lattice(gb, ab[-1])[1]
    levels = (len(lat_a.levels), 0 if lat_b is None else len(lat_b.levels))
    assert levels[0] == 2 and levels[1] < 2, levels  # the views decide differently
    both = tr.render([a, b], settings=ADAPTIVE)
    for i, s in enumerate((a, b)):
        alone = tr.render(s, settings=ADAPTIVE)
        assert torch.equal(both.radiance[i], alone.radiance[0]), i
        for k, v in alone.passes.items():
            assert torch.equal(both.passes[k][i], v[0]), (i, k)


def test_ior_one_stays_close_to_the_bare_environment():
    """At IOR 1 every method shows the environment itself (test_stability); adaptive
    shading interpolates some of it between lattice pixels where it is smooth, so the
    image stays close to it: the interpolation's error, bounded by the spread test
    (measured: FLIP 0.021 at 96x96, where the environment's detail is finest per pixel;
    against the full render on the held-out validation scenes 0.014 at 128x128)."""
    from torchrefract.geometry.camera import pixel_rays as rays  # noqa: PLC0415
    from torchrefract.lighting.envmap import load_envmap, lookup  # noqa: PLC0415

    s = _scene("sphere_a03", 96, n=1, method="rousiers")
    s = s.replace(material=dataclasses.replace(s.material, ior=1.0))
    out = tr.render(s, settings=ADAPTIVE)
    bare = lookup(load_envmap(s.envmap.path), rays(s.camera), s.envmap.rotate_deg)
    m = out.coverage[0] > 0.99
    fl = flip_map(out.radiance[0].numpy(), bare.numpy())[m.numpy()]
    assert m.sum() > 1000 and float(fl.mean()) < 0.03, float(fl.mean())
    full = tr.render(s, settings=UNIFORM)  # the method's own: the environment itself
    flf = flip_map(full.radiance[0].numpy(), bare.numpy())[m.numpy()]
    assert float(flf.mean()) < 1e-3, float(flf.mean())


def test_refine_takes_uniform_pixels_where_the_radiance_spreads():
    """adaptive.refine: around one bright pixel the uniform pixels of its 3x3 neighbourhood
    are shaded at their other sub-pixels (a non-uniform one is already), at the first sub-
    pixel too where the lattice interpolated the center sample; a flat image refines
    nothing."""
    n, h, w = 2, 6, 6
    uniform = torch.ones(1, h, w, dtype=torch.bool)
    uniform[0, 2, 3] = False
    plan = adaptive.Plan(uniform=uniform, n=n)
    flat = torch.ones(1, h * n, w * n, 3)
    assert adaptive.refine(plan, flat) is None
    bright = flat.clone()
    bright[0, 2 * n, 2 * n] = 10.0  # pixel (2, 2)'s first sub-pixel: the pixel's value
    more, rest = adaptive.refine(plan, bright)
    want = torch.zeros(1, h, w, dtype=torch.bool)
    want[0, 1:4, 1:4] = True
    want[0, 2, 3] = False
    assert torch.equal(more, want)
    assert torch.equal(rest[:, 1::n, 1::n], want) and torch.equal(rest[:, ::n, 1::n], want)
    assert not rest[:, ::n, ::n].any()  # no lattice: the center samples were shaded
    status = torch.ones(1, h, w, dtype=torch.uint8)
    status[0, 1, 1] = 3  # interpolated from its lattice neighbours
    lat = adaptive.Lattice(levels=(adaptive.Level(1, status, torch.zeros(1, h, w), sub=n),))
    _, rest = adaptive.refine(dataclasses.replace(plan, lattice=lat), bright)
    first = torch.zeros(1, h, w, dtype=torch.bool)
    first[0, 1, 1] = True
    assert torch.equal(rest[:, ::n, ::n], first)
    assert adaptive.refine(plan, bright, rtol=100.0) is None


def test_refined_render_is_closer_to_uniform(monkeypatch):
    """Where the G-buffer is smooth but the refraction is not (a lumpy blob of IOR 2.33 at
    alpha 0.03 with 2 bounces, a held-out validation scene), the pixels whose radiance
    spreads are shaded at every sub-pixel: the adaptive image moves towards the uniform
    2x2 one, and the fused kernels and the tensor code still agree (the n x n plan:
    ``cone_rays: plane``)."""
    s = tr.load_scene(SUITE.parent / "validation" / "v031_blob_lumpy_01a6.yaml")
    s = s.replace(camera=dataclasses.replace(s.camera, width=32, height=32),
                  method_options={"internal_bounces": 2, "cone_rays": "plane"})
    assert s.camera.samples_per_pixel == 2
    u = tr.render(s, settings=UNIFORM).radiance[0].numpy()
    refined = tr.render(s, settings=ADAPTIVE)
    obj = (refined.coverage[0] > 0).numpy()
    monkeypatch.setattr(adaptive, "REFINE_RTOL", float("inf"))
    plain = tr.render(s, settings=ADAPTIVE).radiance[0].numpy()
    monkeypatch.undo()
    near = flip_map(refined.radiance[0].numpy(), u)[obj].mean()
    assert near < 0.5 * flip_map(plain, u)[obj].mean()
    t = tr.render(s, settings=RenderSettings(adaptive=True, fused=False)).radiance[0].numpy()
    assert flip_map(refined.radiance[0].numpy(), t)[obj].mean() < 0.002


def test_refine_kernel_equals_tensor_code():
    """csrc/lattice.c's ``refine`` decides as adaptive._refine_torch: random radiances over
    partly uniform pixels, odd sizes (rows longer than the kernel's 64-pixel tiles too, and
    1 to 3 samples per side), a NaN and an infinity (whose neighbourhoods refine nothing),
    three tolerances."""
    if not native.available():
        pytest.skip("native kernels unavailable")
    g = torch.Generator().manual_seed(5)
    wide = [(9, 133, 2), (6, 70, 1), (4, 65, 3), (7, 256, 1), (5, 203, 1), (3, 9, 1)]
    for trial in range(12 + len(wide)):
        b, h, w, n = 2, 5 + trial % 3, 7 + trial % 2, 2
        if trial >= 12:
            h, w, n = wide[trial - 12]
        uniform = torch.rand(b, h, w, generator=g) > 0.3
        radiance = torch.rand(b, h * n, w * n, 3, generator=g) ** 4 * 3
        if trial >= 15:  # ties, zeros of both signs, a channel flat over a region
            radiance[..., 1] = (radiance[..., 1] * 4).round() / 4
            radiance[0, :, : w // 3] = -0.0
            radiance[1, : h // 2, :, 2] = 0.5
        radiance[0, n, n, 1] = float("nan")  # pixel (1, 1)'s first sub-pixel
        radiance[1, 2 * n, 0, 0] = float("inf")  # pixel (2, 0)'s
        for rtol in (0.2, 0.8, 1.6):
            made = native.refine(uniform, radiance, rtol)
            want = adaptive._refine_torch(uniform, radiance[:, ::n, ::n], rtol)
            assert torch.equal(made, want)
            assert not made[0, 1, 1] and not made[1, 2, 0]  # next to the NaN, the inf

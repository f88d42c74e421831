"""Relighting a matte with another map, rotation and scale against direct renders
(issue #27, part 2): FLIP <= 0.01 on object pixels."""

from __future__ import annotations

import pytest
import torch

import torchrefract as tr
from torchrefract.matte.matte import from_passes
from torchrefract.matte.relight import prepare, relight_reference
from torchrefract.truth.metrics import flip_map

from conftest import ASSETS, ROOT

OTHER = str(ASSETS / "envmaps" / "rooitou_park.exr")
TENSOR = tr.RenderSettings(fused=False, adaptive=False)  # the matte's own render


def _scene(name, method, opts, size=48):
    s = tr.load_scene(ROOT / "configs" / "suite" / name)
    cam = tr.Camera(**{**s.camera.__dict__, "width": size, "height": size,
                       "samples_per_pixel": 1})
    return s.replace(camera=cam, method=method, method_options=opts)


def _flip(img, ref, cov):
    fm = flip_map(img[0].numpy(), ref[0].numpy())
    return float(fm[(cov[0] > 0.999).numpy()].mean())


def _max_rel(img, ref):
    return float(((img - ref).abs().amax(-1) / ref.amax(-1).clamp(min=1e-4)).max())


@pytest.mark.parametrize("name,method,opts", [
    ("sphere_a03.yaml", "rousiers", {"internal_bounces": 2}),
    ("torus_a01.yaml", "prefiltered", {}),
    ("suzanne_a01.yaml", "specular", {"internal_bounces": 1}),
    ("slab_light.yaml", "rousiers", {}),
])
def test_other_map_rotation_scale(one_thread, name, method, opts):
    """A RenderResult knows its rotation (the scenes' 60 degrees): relit there, u is the
    renderer's op for op (<= 1e-4 relative to the render); at any other rotation it is the
    rotation-0 azimuth shifted: FLIP <= 0.01 against the direct render (measured 0.0000;
    max relative 1.6e-4 next to a sun, from u's last bits). The same matte without its
    rotation (a bare Matte) takes the renderer's u everywhere: <= 1e-4 there too."""
    s = _scene(name, method, opts)
    out = tr.render(s.replace(passes={"matte": {}}))
    p, bare = prepare(out), prepare(from_passes(out.passes))
    rendered = torch.tensor([s.envmap.rotate_deg])
    assert p.exact_views(rendered) == (True,) and bare.exact_views(rendered + 1) == (True,)
    img = tr.relight(out, s.envmap.path, s.envmap.rotate_deg, s.envmap.scale)
    assert _max_rel(img, out.radiance) <= 1e-4  # the render (recording changes nothing)
    for env in (tr.EnvMap(path=OTHER, rotate_deg=0.0, scale=1.0),
                tr.EnvMap(path=OTHER, rotate_deg=-75.0, scale=0.5),
                tr.EnvMap(path=s.envmap.path, rotate_deg=s.envmap.rotate_deg + 140.0,
                          scale=2.0)):
        assert p.exact_views(torch.tensor([env.rotate_deg])) == (False,)  # shifted u
        img = tr.relight(out, env.path, rotate_deg=env.rotate_deg, scale=env.scale)
        direct = tr.render(s.replace(envmap=env), settings=TENSOR)
        assert bool(torch.isfinite(img).all())
        assert _flip(img, direct.radiance, out.coverage) <= 0.01
        assert _max_rel(img, direct.radiance) <= 1e-3  # float32 rounding of u (above)
        # nothing folded at 1 spp: with the renderer's u, the render to float32 rounding
        img = tr.relight(bare, env.path, rotate_deg=env.rotate_deg, scale=env.scale)
        assert _max_rel(img, direct.radiance) <= 1e-4


def test_shifted_azimuth_sign(one_thread):
    """The shifted u (u0 + rotate_deg / 360, mod 1) is the renderer's (``rotate_y`` by
    -rotate_deg, then ``direction_to_uv``) to float32 rounding at any rotation, negative
    and beyond a turn included; the opposite sign (u0 - rotate_deg / 360) is off by
    2 rotate_deg around the circle. At the rendered rotation u is the renderer's bits."""
    from torchrefract.lighting.envmap import direction_to_uv, rotate_y

    s = _scene("torus_a01.yaml", "prefiltered", {}, size=32)
    p = prepare(tr.render(s.replace(passes={"matte": {}})))
    for deg in (0.0, 25.0, -75.0, 140.0, 200.0, -359.0, 725.5):
        rot = torch.tensor([deg])
        ref = direction_to_uv(rotate_y(p.d, -rot[0]))[:, 0]
        assert torch.equal(p.u(rot, (True,)), ref)  # the exact path: the renderer's own
        du = (p.u(rot, (False,)).double() - ref.double()).remainder(1.0)
        du = torch.minimum(du, 1.0 - du)  # the distance around the circle
        assert float(du.max()) <= 2.5e-7  # a few units in the last place of u
        wrong = ((p.u0 - deg / 360.0) - ref.double()).remainder(1.0)  # off by -2 rot
        off = (2.0 * deg / 360.0) % 1.0
        assert float(torch.minimum(wrong, 1.0 - wrong).min()) >= min(off, 1.0 - off) - 1e-6
    rendered = torch.tensor([s.envmap.rotate_deg])
    assert torch.equal(p.u(rendered), direction_to_uv(rotate_y(p.d, -rendered[0]))[:, 0])


def test_texels_and_batches(one_thread):
    """Texels in memory (their pyramid built here) and per-view rotations of a batch."""
    s = _scene("sphere_a03.yaml", "rousiers", {}, size=24)
    out = tr.render([s.replace(passes={"matte": {}}),
                     s.replace(passes={"matte": {}}, material=tr.Material(roughness=0.05))])
    tex = torch.ones(16, 32, 3) * torch.tensor([0.2, 0.5, 1.0])
    img = tr.relight(out, tex, rotate_deg=torch.tensor([0.0, 90.0]), scale=2.0)
    # a constant map: the image is 2 * color * (sum of the weights) everywhere
    m = from_passes(out.passes)
    expect = 2.0 * torch.tensor([0.2, 0.5, 1.0]) * m.weight.sum(-2)
    assert torch.allclose(img, expect, rtol=1e-4, atol=1e-5)
    with pytest.raises(tr.ConfigError, match="rotate_deg"):
        tr.relight(out, tex, rotate_deg=[1.0, 2.0, 3.0])
    # texels are checked and taken as a loaded map is: float64 as float32, no NaN, no
    # negative scale (a scene's envmap.scale may not be either)
    assert torch.equal(tr.relight(out, tex.double(), scale=2.0), tr.relight(out, tex, scale=2.0))
    from torchrefract.matte.relight import _checked_texels

    wide = tex.double()  # checked and cast once per tensor and version, not per relight
    assert _checked_texels(wide) is _checked_texels(wide)
    with pytest.raises(tr.ConfigError, match="NaN"):
        tr.relight(out, torch.full((16, 32, 3), float("nan")))
    with pytest.raises(tr.ConfigError, match="scale must be >= 0"):
        tr.relight(out, tex, scale=-1.0)


def test_prepared_equals_lookups(one_thread):
    """The prepared relight (gathers of precomputed texel indices) against the lookups one
    by one: per-view rotations and scales, a pyramid passed in, rotations seen before, a
    matte changed in place (prepared again); a batch whose views are at their rendered
    rotation and at another (the renderer's u, and the shifted one)."""
    from torchrefract.lighting.sg_pyramid import sg_pyramid_for

    s = _scene("suzanne_a01.yaml", "rousiers", {"internal_bounces": 1}, size=32)
    out = tr.render([s.replace(passes={"matte": {}}),
                     s.replace(passes={"matte": {}}, material=tr.Material(roughness=0.02))])
    pyr = sg_pyramid_for(OTHER)

    def close(a, b):
        rel = (a - b).abs().amax(-1) / b.amax(-1).clamp(min=1e-6)
        return float(rel.max()) <= 1e-6

    bare = from_passes(out.passes)  # its rotation unknown: the renderer's u at every one
    for env in (OTHER, pyr, s.envmap.path):
        for rot, sc in ((torch.tensor([10.0, -200.0]), torch.tensor([1.0, 0.3])),
                        (33.0, 2.0), (torch.tensor([10.0, -200.0]), 1.0)):
            assert close(tr.relight(bare, env, rot, sc), relight_reference(out, env, rot, sc))
    rot = torch.tensor([s.envmap.rotate_deg, 90.0])
    assert prepare(out).exact_views(rot) == (True, False)
    img, ref = tr.relight(out, OTHER, rot), relight_reference(out, OTHER, rot)
    assert close(img[:1], ref[:1])  # view 0 at its rendered rotation
    assert float(((img[1] - ref[1]).abs().amax(-1) / ref[1].amax(-1).clamp(min=1e-4)).max()
                 ) <= 1e-3  # view 1: u shifted (float32 rounding of u)
    m = from_passes(out.passes)
    before = tr.relight(m, OTHER, 5.0)
    assert prepare(m) is prepare(m)  # kept
    m.weight.mul_(2.0)  # in place: prepared again
    assert torch.allclose(tr.relight(m, OTHER, 5.0) - m.lights, 2 * (before - m.lights),
                          rtol=1e-5, atol=1e-6)


def test_native_reads_equal_tensor_code(one_thread):
    """The C kernel of a rotation's texel reads (csrc/relight.c, ``native.relight_reads``)
    against ``_Group.reads``' tensor code (its reference and fallback): indices and weights
    equal, for plain and SG groups, shifted u (one rotation, and one per view) and the
    renderer's u, rotations negative, beyond a turn and beyond 1e11 degrees (floor()
    itself), a NaN azimuth (carried as torch carries it). Its gather
    (``native.relight_values``) against ``embedding_bag`` over those reads: the same sum
    (measured: the same bits), and so the relit images (the same map's exactness at the
    rendered rotation: test_other_map_rotation_scale). A NaN azimuth (an index outside
    the image: embedding_bag raises) leaves the gather to the tensor code."""
    import copy

    import torch.nn.functional as F

    import torchrefract.matte.relight as relight_mod
    from torchrefract import settings
    from torchrefract.kernels import native
    from torchrefract.lighting.sg_pyramid import sg_pyramid_for

    if not native.available():
        pytest.skip(f"native kernels unavailable: {native.failure()}")
    off = tr.RenderSettings(native=False)
    tex = relight_mod._texels_last(sg_pyramid_for(OTHER), None)

    def close(a, b):  # float32 rounding of the sums (measured: the same bits)
        return torch.allclose(a, b, rtol=1e-6, atol=1e-30)

    s = _scene("suzanne_a01.yaml", "rousiers", {"internal_bounces": 1}, size=32)
    out = tr.render([s.replace(passes={"matte": {}}),
                     s.replace(passes={"matte": {}}, material=tr.Material(roughness=0.02))])
    for m in (out, from_passes(out.passes)):  # views at their rendered rotation; unknown
        p = prepare(m)
        img = tr.relight(p, OTHER, 0.0)
        taps = next(reversed(p._taps.values()))
        assert {g.plain for g in taps.groups} == {True, False}  # plain lobes, SG levels
        for rot in ([0.0, 0.0], [60.0, -75.0], [725.5, -359.0], [3e11, -1e12]):
            rot = torch.tensor(rot)
            for u in (None, p.u(rot)):
                for g in taps.groups:
                    n = g.lobe.numel()
                    got = (torch.empty(n, 4, dtype=torch.int32), torch.empty(n, 4))
                    assert native.relight_reads(
                        *got, g.row, g.sn, rot, u0=g.u0, view=g.view, u=u, lobe=g.lobe,
                        plain=g.plain, w_map=getattr(g, "w_map", 0), cols=g.cols,
                        last=g.last, x0p1=getattr(g, "x0p1", None), w=getattr(g, "w", None))
                    assert torch.equal(g.reads(None if u is None else u.clone(), rot)[0],
                                       got[0])
                    with settings.using(off):
                        ref = g.reads(None if u is None else u.clone(), rot)
                    assert torch.equal(ref[0], got[0]) and torch.equal(ref[1], got[1])
                    vals = torch.empty(n, 3)
                    assert g.values(u, rot, tex, vals)
                    bag = F.embedding_bag(ref[0].view(-1), tex, torch.arange(
                        0, 4 * n, 4, dtype=torch.int32), mode="sum",
                        per_sample_weights=ref[1].view(-1))
                    assert torch.allclose(vals, bag, rtol=1e-6, atol=1e-30)
            with settings.using(off):
                p.forget_rotations()
                ref = tr.relight(p, OTHER, rot)
            p.forget_rotations()
            assert close(tr.relight(p, OTHER, rot), ref)
        assert close(img, tr.relight(p, OTHER, 0.0))
    g = copy.copy(taps.groups[-1])  # a NaN azimuth: both write x86's index and NaN weights
    g.u0 = g.u0.clone()
    g.u0[::7] = float("nan")
    rot = torch.tensor([30.0, -40.0])
    got = g.reads(None, rot)
    with settings.using(off):
        ref = g.reads(None, rot)
    assert torch.equal(ref[0], got[0]) and bool(got[1][::7].isnan().all())
    assert torch.allclose(ref[1], got[1], rtol=0, atol=0, equal_nan=True)
    assert not g.values(None, rot, tex, torch.empty(g.lobe.numel(), 3))

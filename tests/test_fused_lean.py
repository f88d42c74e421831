"""The fused kernel of ``lean`` and ``gsr`` (torchrefract.shading.fused_lean, csrc/lean.c)
gives the tensor code's images (methods/lean/shade.py): on every suite scene, each ``tir``
rule and the options it covers, within 1e-4 relative on 99.9% of the object pixels and 0.002
of FLIP, with the same passes; with internal bounces within the tensor code's own float32
conditioning (as ``rousiers``' fused bounces, tests/test_fused.py). The LEAN moments of the
back layer by the kernel match ``moments.lean_mips``' level 0. Where the kernel does not
cover the options (``spread: paper``, ``env_lookup: mip``) or a gradient is wanted, the
tensor code runs."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

import torchrefract as tr
from torchrefract.kernels import native
from torchrefract.methods.lean import shade as lean_shade
from torchrefract.methods.lean.moments import lean_mips
from torchrefract.settings import RenderSettings
from torchrefract.shading import fused_lean
from test_fused import BOUNCES, _compare, _small, check_bounces_match

SUITE = sorted((Path(__file__).resolve().parent.parent / "configs" / "suite").glob("*.yaml"))
FUSED = RenderSettings(fused=True, adaptive=False)  # every pixel shaded: pixel by pixel
TENSOR = RenderSettings(fused=False, adaptive=False)

pytestmark = pytest.mark.skipif(not native.available(),
                                reason="the native kernels do not build here")


def _check_same(a: tr.RenderResult, b: tr.RenderResult, what, beyond: float = 1e-3) -> None:
    """The image within 1e-4 relative on 99.9% (1 - ``beyond``) of the object pixels (and
    1e-2 on all), FLIP within 0.002, the background within 1e-4; the passes alike (the
    lobe's on all object pixels but a share ``beyond`` - 1e-3)."""
    assert b.timings.get("fused", 0) > 0, what
    for m in _compare(a, b):
        assert m["beyond"] <= beyond and m["max_rel"] < 1e-2, (what, m)
        assert m["flip"] <= 0.002, (what, m)
        assert m["background"] <= 1e-4, (what, m)
    for k in ("exit_found", "tir"):
        assert torch.equal(a.passes[k], b.passes[k]), (what, k)
    # lobe_sigma: as rousiers' (test_fused), the bounding rays' nearly parallel chords
    # amplify their rounding
    obj = a.coverage > 0
    for k, rtol in (("lobe_sigma", 2e-3), ("footprint", 1e-4)):
        close = torch.isclose(a.passes[k], b.passes[k], rtol=rtol, atol=1e-6)[..., 0]
        assert torch.all(close[~obj]), (what, k)
        assert float((~close[obj]).float().mean()) <= beyond - 1e-3, (what, k)


@pytest.mark.parametrize("method", ["lean", "gsr"])
@pytest.mark.parametrize("path", SUITE, ids=[p.stem for p in SUITE])
def test_fused_lean_matches_the_tensor_code_on_the_suite(path, method):
    for tir in ("conserve", "clamp", "reflect"):
        s = _small(path, 48, method=method, method_options={"tir": tir})
        _check_same(tr.render(s, settings=TENSOR), tr.render(s, settings=FUSED),
                    (method, tir))


VARIANTS = {"taps1": {"ewa_taps": 1}, "taps8": {"ewa_taps": 8},
            "one_lobe": {"roughness_lobes": 1}, "k2": {"subdivisions": 2},
            "k8": {"subdivisions": 8}, "k1": {"subdivisions": 1},
            "plane": {"cone_rays": "plane"}}
SCENES = ("vgroove_back_a01", "sawtooth_back_a015", "globe_jump", "globe_gradient",
          "wingnut_a01", "sphere_a03", "slab_light")


@pytest.mark.parametrize("variant", sorted(VARIANTS))
@pytest.mark.parametrize("name", SCENES)
def test_fused_lean_options(name, variant):
    """The options the kernel covers besides the defaults (roughness maps on the globes,
    facets splitting ``gsr``'s lobes on the v-groove and sawtooth, a sphere light; the
    plane cone)."""
    opts = VARIANTS[variant]
    # the plane cone's exits are not marched but met on a plane, whose footprint sets the
    # level ``gsr``'s subdivisions are read at: their split (moments.separation) amplifies the
    # rounding there (globe_gradient: 2 of 1280 object pixels 2e-3 off, lobe_sigma 1%)
    beyond = 3e-3 if variant == "plane" else 1e-3
    for method in ("gsr",) if "subdivisions" in opts else ("lean", "gsr"):
        s = _small(SUITE[0].parent / f"{name}.yaml", 48, method=method, method_options=opts)
        _check_same(tr.render(s, settings=TENSOR), tr.render(s, settings=FUSED),
                    (method, opts), beyond)


def test_fused_lean_index_matched_and_absorbing():
    """IOR 1 (no interface: the object is invisible) and absorption."""
    base = _small(SUITE[0].parent / "sphere_a03.yaml", 48)
    for method in ("lean", "gsr"):
        for material in ({"ior": 1.0}, {"absorption": (0.8, 0.3, 0.0)}):
            mat = tr.Material(**{**base.material.__dict__, **material})
            s = base.replace(method=method, material=mat)
            _check_same(tr.render(s, settings=TENSOR), tr.render(s, settings=FUSED),
                        (method, material))


@pytest.mark.parametrize("method", ["lean", "gsr"])
@pytest.mark.parametrize("variant", sorted(BOUNCES))
@pytest.mark.parametrize("name", ["bunny_a01", "sphere_a0", "vgroove_back_a01", "globe_jump",
                                  "teapot_a01"])
def test_fused_lean_bounces_match_the_tensor_code(name, variant, method):
    """With internal bounces (bounces.h, rousiers.c's interfaces met from inside): as
    tests/test_fused.py's bounces, a path reflected inside a detailed mesh is chaotic, so
    where the fused image is beyond the bounds it must stay within what the tensor code
    itself does when the eye moves by 3 float32 roundings."""
    s = _small(SUITE[0].parent / f"{name}.yaml", 64, method=method,
               method_options=BOUNCES[variant])
    check_bounces_match(s)


def test_fused_lean_batch_of_views_with_and_without_a_map():
    """One batch mixing a roughness map (two roughness lobes for all) with uniform views,
    and two views: per-view frames, tables and pyramids."""
    a_s = _small(SUITE[0].parent / "globe_jump.yaml", 40, method="gsr")
    b_s = _small(SUITE[0].parent / "globe_2rough.yaml", 40, method="gsr")
    c_s = _small(SUITE[0].parent / "vgroove_back_a01.yaml", 40, method="gsr")
    d_s = c_s.replace(material=tr.Material(**{**c_s.material.__dict__, "roughness": 0.3}))
    for scenes in ([a_s, d_s], [c_s, d_s], [b_s, a_s]):
        _check_same(tr.render(scenes, settings=TENSOR), tr.render(scenes, settings=FUSED),
                    [s.name for s in scenes])


@pytest.mark.parametrize("name", ["globe_jump", "vgroove_back_a01", "bunny_a01"])
def test_lean_moments_kernel_is_lean_mips_level_0(name):
    """The back layer's moments (csrc/lean.c, moments_range) against moments.lean_mips: the
    same subdivision for every pixel, values within float32 rounding; ``lean``'s compact
    pyramid holds the same values of the channels it reads."""
    captured = {}
    original = fused_lean.lean

    def spy(g, lighting, materials, *args, **kw):
        captured["g"], captured["m"] = g, materials
        return original(g, lighting, materials, *args, **kw)

    s = _small(SUITE[0].parent / f"{name}.yaml", 48, method="gsr")
    lean_shade.fused_lean.lean = spy
    try:
        tr.render(s, settings=FUSED)
    finally:
        lean_shade.fused_lean.lean = original
    g, m = captured["g"], captured["m"]
    for k in (1, 4, 8):
        ref, got = lean_mips(g, m, k)[0], fused_lean.moments(g, m, k)
        assert got is not None and got.shape == ref.shape
        # a pixel in another subdivision would differ by its whole value
        assert torch.equal(ref != 0, got != 0), k
        assert torch.allclose(ref, got, rtol=1e-5, atol=1e-6), k
    # ``lean``'s own pyramid: the channels it reads (w, w u, w u^2, w u^3)
    ref = lean_mips(g, m, 1)[0][..., [0, 6, 7, 8]]
    for compact in (2, 4):
        got = fused_lean.moments(g, m, 1, compact)
        assert got.shape == ref[..., :compact].shape
        assert torch.allclose(ref[..., :compact], got, rtol=1e-5, atol=1e-6), compact


@pytest.mark.parametrize("options", [{"spread": "paper"}, {"env_lookup": "mip"}])
def test_uncovered_options_run_the_tensor_code(options):
    s = _small(SUITE[0].parent / "sphere_a03.yaml", 32, method="gsr", method_options=options)
    out = tr.render(s, settings=FUSED)
    assert out.timings.get("fused", 0) == 0
    ref = tr.render(s, settings=TENSOR)  # (its background by the tensor code too)
    obj = ref.coverage > 0
    assert torch.equal(out.radiance[obj], ref.radiance[obj])
    assert torch.allclose(out.radiance, ref.radiance, rtol=1e-4, atol=1e-6)


def test_a_gradient_runs_the_tensor_code():
    """A roughness that requires grad: the differentiable path (no fused stage), its
    gradient finite, its image the fused one's."""
    from torchrefract.geometry.gbuffer import build_gbuffer
    from torchrefract.geometry.mesh import load_mesh
    from torchrefract.lighting.lights import Lighting
    from torchrefract.methods.lean import GSR
    from torchrefract.optics.materials import MaterialBatch
    from torchrefract.stages import collect

    s = _small(SUITE[0].parent / "sphere_a03.yaml", 24, method="gsr")
    g = build_gbuffer([load_mesh(s.mesh, s.transform)], [s.camera])
    lighting = Lighting.from_scenes([s])

    def image(r):
        m = MaterialBatch(ior=torch.tensor([s.material.ior]), roughness=r,
                          absorption=torch.zeros(1, 3), distribution=("beckmann",))
        with collect() as times:
            out = GSR.shade(g, lighting, m, GSR.Options(), None).radiance
        return out, times

    r = torch.tensor([s.material.roughness], requires_grad=True)
    with_grad, stages = image(r)
    assert stages.get("fused", 0) == 0
    with_grad.mean().backward()
    assert torch.isfinite(r.grad).all()
    with torch.no_grad():
        fused_img, stages = image(r.detach())
    assert stages.get("fused", 0) > 0
    assert torch.allclose(with_grad.detach(), fused_img, rtol=1e-3, atol=1e-4)

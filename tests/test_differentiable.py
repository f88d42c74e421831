"""Gradients through ``rousiers``: roughness recovered from a target image; IOR gradients."""

from __future__ import annotations

import pytest
import torch
from conftest import ASSETS

import torchrefract as tr
from torchrefract.geometry.gbuffer import build_gbuffer
from torchrefract.geometry.mesh import load_mesh
from torchrefract.lighting.lights import Lighting
from torchrefract.methods import registry
from torchrefract.methods.rousiers import RousiersOptions, render_rousiers
from torchrefract.optics.materials import MaterialBatch


def _shade(method: str):
    """(g, lighting, materials) -> (radiance,) with the method's default options."""
    m = registry.get(method)
    return lambda g, lighting, mat: (m.shade(g, lighting, mat, m.Options(), None).radiance,)


@pytest.fixture(scope="module")
def setup():
    s = tr.Scene(mesh=str(ASSETS / "meshes" / "sphere.ply"),
                 envmap=tr.EnvMap(path=str(ASSETS / "envmaps" / "lebombo.exr")),
                 camera=tr.Camera(width=32, height=32))
    g = build_gbuffer([load_mesh(s.mesh, s.transform)], [s.camera])
    return g, Lighting.from_scenes([s])


def _image(setup, roughness, ior):
    g, lighting = setup
    m = MaterialBatch(ior=ior, roughness=roughness, absorption=torch.zeros(1, 3),
                      distribution=("beckmann",))
    return render_rousiers(g, lighting, m, RousiersOptions())[0]


def test_roughness_recovered_by_gradient_descent(setup):
    target = _image(setup, torch.tensor([0.25]), torch.tensor([1.5])).detach()
    r = torch.tensor([0.08], requires_grad=True)
    opt = torch.optim.Adam([r], lr=0.03)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, 45)
    for _ in range(45):
        opt.zero_grad()
        loss = ((_image(setup, r, torch.tensor([1.5])) - target) ** 2).mean()
        loss.backward()
        assert torch.isfinite(r.grad).all()
        opt.step()
        sched.step()
        with torch.no_grad():
            r.clamp_(0.01, 1.0)
    assert abs(r.item() - 0.25) < 0.03, r.item()


def test_roughness_gradient_matches_local_finite_differences(setup):
    """d(mean image)/d(roughness) against the median of eight one-sided differences
    (h = 1e-3 around the point): within 25%.

    The mean image is piecewise smooth in the roughness: where a bounding ray's exit moves
    to another triangle or misses the back layer, it steps (measured on this 32x32 sphere at
    IOR 1.5: steps of +1e-3 to +2e-3, 0.2-0.4% of the mean, every 0.02-0.03 in alpha). A
    central difference over such a step measures the step, not the slope (h = 1e-2 around
    0.2 gave -0.015 against a slope of -0.095); the median of the one-sided differences
    skips the intervals that hold a step.
    """
    for rough, ior in ((0.2, 1.5), (0.1, 1.33)):
        r = torch.tensor([rough], requires_grad=True)
        _image(setup, r, torch.tensor([ior])).mean().backward()
        assert torch.isfinite(r.grad).all()
        h = 1e-3
        vals = [_image(setup, torch.tensor([rough + k * h]), torch.tensor([ior])).double().mean()
                for k in range(-4, 5)]
        slopes = torch.stack([(vals[k + 1] - vals[k]) / h for k in range(8)])
        fd = slopes.median().item()
        assert abs(r.grad.item() - fd) < 0.25 * abs(fd), (r.grad.item(), fd, slopes.tolist())


@pytest.mark.parametrize("method", ["specular", "rousiers"])
def test_ior_gradient_matches_a_small_finite_difference(method, smooth_env_exr):
    """d(mean image)/d(IOR) against a central difference with h = 1e-4, on a smooth
    environment: within 2%.

    Larger steps do not measure the derivative: the image is only piecewise smooth in the
    IOR. Pixels crossing the critical angle switch to the TIR rule (``clamp``: the exit
    weight jumps from 1 - F2 -> 0 to 1), and march brackets / exit triangles change, so a
    difference over h = 1e-2 mixes in those steps (measured: on lebombo at IOR 1.33 it
    gives +0.096 against a derivative of -0.353, which h = 1e-4 reproduces to 0.1%). On a
    textured map even h = 1e-4 can straddle such an event, hence the smooth map here.
    """
    s = tr.Scene(mesh=str(ASSETS / "meshes" / "sphere.ply"),
                 envmap=tr.EnvMap(path=str(smooth_env_exr)),
                 camera=tr.Camera(width=32, height=32))
    g = build_gbuffer([load_mesh(s.mesh, s.transform)], [s.camera])
    lighting = Lighting.from_scenes([s])
    fn = _shade(method)

    def mean(rough, ior):
        m = MaterialBatch(ior=ior, roughness=torch.tensor([rough]),
                          absorption=torch.zeros(1, 3), distribution=("beckmann",))
        return fn(g, lighting, m)[0].double().mean()

    for rough, ior in ((0.2, 1.5), (0.1, 1.33)):
        i = torch.tensor([ior], requires_grad=True)
        mean(rough, i).backward()
        h = 1e-4
        fd = (mean(rough, torch.tensor([ior + h]))
              - mean(rough, torch.tensor([ior - h]))) / (2 * h)
        assert abs(i.grad.item() - fd.item()) < 0.02 * abs(fd.item()), (i.grad.item(), fd.item())


@pytest.mark.parametrize("method", ["specular", "prefiltered"])
def test_sharp_path_roughness_gradients(method, setup):
    """The roughness reaches ``specular``'s and ``prefiltered``'s images through the
    interfaces' energies (averaged over the arriving lobe at the exit) and the blur: the
    gradient of the mean image is finite and within 25% of the median of eight one-sided
    differences (h = 1e-3; measured within 11% at alpha 0.3 and 1% at 0.8; the table's
    trilinear interpolation makes the image piecewise smooth, see above)."""
    g, lighting = setup
    fn = _shade(method)

    def mean(r):
        m = MaterialBatch(ior=torch.tensor([1.5]), roughness=r, absorption=torch.zeros(1, 3),
                          distribution=("beckmann",))
        return fn(g, lighting, m)[0].double().mean()

    for rough in (0.3, 0.8):
        r = torch.tensor([rough], requires_grad=True)
        mean(r).backward()
        assert torch.isfinite(r.grad).all()
        h = 1e-3
        vals = [mean(torch.tensor([rough + k * h])) for k in range(-4, 5)]
        fd = torch.stack([(vals[k + 1] - vals[k]) / h for k in range(8)]).median().item()
        assert abs(r.grad.item() - fd) < 0.25 * abs(fd), (r.grad.item(), fd)


def test_gradients_flow_where_exits_need_a_second_try():
    """On suzanne some rays find no exit triangle at the pixel just beyond the crossing
    and take the last pixel still inside (the march's second try): the gradient must flow
    through both (the first try's mask was once overwritten in place, which broke the
    backward pass with an in-place modification error)."""
    s = tr.Scene(mesh=str(ASSETS / "meshes" / "suzanne.ply"),
                 envmap=tr.EnvMap(path=str(ASSETS / "envmaps" / "lebombo.exr")),
                 camera=tr.Camera(eye=(0.4, 0.3, 3.0), width=40, height=32))
    g = build_gbuffer([load_mesh(s.mesh, s.transform)], [s.camera])
    ior = torch.tensor([1.5], requires_grad=True)
    rough = torch.tensor([0.1], requires_grad=True)
    m = MaterialBatch(ior=ior, roughness=rough, absorption=torch.zeros(1, 3),
                      distribution=("beckmann",))
    img = render_rousiers(g, Lighting.from_scenes([s]), m, RousiersOptions())[0]
    gi, gr = torch.autograd.grad(img.double().mean(), (ior, rough))
    assert torch.isfinite(gi).all() and torch.isfinite(gr).all()
    assert gi.abs().item() > 0 and gr.abs().item() > 0


@pytest.mark.parametrize("method", ["prefiltered", "rousiers"])
def test_environment_gradients_reach_the_object(method, setup):
    """The SG methods read the map's pyramid: built from the lighting's own texels where
    they are not the file's (an edited map, or one a gradient is asked for), so the
    object's pixels follow the texels and differentiate in them (they read the file's
    pyramid before: a zero gradient, and an edited map ignored inside the object)."""
    import dataclasses

    g, lighting = setup
    mat = MaterialBatch(ior=torch.tensor([1.5]), roughness=torch.tensor([0.2]),
                        absorption=torch.zeros(1, 3), distribution=("beckmann",))
    gen = torch.Generator().manual_seed(0)
    tex = (0.5 + torch.rand(16, 32, 3, generator=gen)).requires_grad_(True)
    shade = _shade(method)
    obj = g.front.mask[0]
    img = shade(g, dataclasses.replace(lighting, texels=(tex,)), mat)[0]
    img[0][obj].mean().backward()
    assert tex.grad is not None and float(tex.grad.abs().sum()) > 0.1
    with torch.no_grad():
        twice = shade(g, dataclasses.replace(lighting, texels=(tex.detach() * 2,)), mat)[0]
    ratio = twice[0][obj].mean() / img.detach()[0][obj].mean()
    assert float(ratio) == pytest.approx(2.0, rel=1e-3)


def test_ior_gradient_is_finite_at_ior_one(setup):
    """At IOR 1 (index-matched) the critical angle's cosine is 0: its gradient is 0 there,
    not sqrt's infinite slope times the clamp's 0 (a NaN for every method with an exit
    rule)."""
    g, lighting = setup
    for method in ("rousiers", "specular"):
        ior = torch.tensor([1.0], requires_grad=True)
        mat = MaterialBatch(ior=ior, roughness=torch.tensor([0.3]),
                            absorption=torch.zeros(1, 3), distribution=("beckmann",))
        _shade(method)(g, lighting, mat)[0].mean().backward()
        assert torch.isfinite(ior.grad).all(), method

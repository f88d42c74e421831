"""Adaptive supersampling (``RenderSettings(adaptive=True)``, torchrefract.geometry.adaptive):
one center sample where a pixel's G-buffer is smooth inside, every sub-pixel elsewhere."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import torch

import torchrefract as tr
from torchrefract.geometry import adaptive
from torchrefract.geometry.camera import pixel_rays
from torchrefract.geometry.gbuffer import build_gbuffer
from torchrefract.geometry.mesh import load_mesh
from torchrefract.settings import RenderSettings
from torchrefract.truth.metrics import flip_map

SUITE = Path(__file__).resolve().parent.parent / "configs" / "suite"
UNIFORM, ADAPTIVE = RenderSettings(), RenderSettings(adaptive=True)


def _scene(name: str, size: int = 48, n: int = 2, **changes) -> tr.Scene:
    s = tr.load_scene(SUITE / f"{name}.yaml")
    return s.replace(camera=dataclasses.replace(s.camera, width=size, height=size,
                                                samples_per_pixel=n), **changes)


def _plan(s: tr.Scene):
    g = build_gbuffer([load_mesh(s.mesh, s.transform)], [s.camera])
    alpha = torch.full(g.shape, s.material.roughness)
    return g, *adaptive.plan(g, pixel_rays(s.camera)[None], alpha)


def test_off_by_default_and_a_no_op_at_one_sample():
    assert RenderSettings().adaptive is False
    s = _scene("sphere_a03", 32, n=1, method="rousiers")
    a, b = tr.render(s, settings=UNIFORM), tr.render(s, settings=ADAPTIVE)
    assert torch.equal(a.radiance, b.radiance)


def test_smooth_glass_is_sampled_uniformly():
    """Below SMOOTH_ALPHA every sub-pixel is shaded: the image is the uniform one."""
    s = _scene("sphere_a0", 32, method="rousiers", method_options={"internal_bounces": 2})
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


def test_reference_is_sampled_uniformly():
    """Mitsuba renders every sub-pixel itself (``shades_object_index = False``): adaptive
    sampling leaves its image as it is."""
    s = _scene("slab_a02", 16, method="reference", method_options={"spp": 4})
    a, b = tr.render(s, settings=UNIFORM), tr.render(s, settings=ADAPTIVE)
    assert torch.equal(a.radiance, b.radiance)

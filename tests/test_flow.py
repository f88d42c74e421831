"""Refractive flow (TOM-Net, Chen et al. 2018) through a parallel plate against the
analytic lateral shift d = t sin(theta) (1 - cos(theta) / sqrt(n^2 - sin^2 theta))
(issue #27, part 3)."""

from __future__ import annotations

import math

import pytest
import torch

import torchrefract as tr
from torchrefract.geometry.camera import pixel_rays, project, projection_params

from conftest import ASSETS

T, IOR, TILT, DIST = 0.4, 1.5, 30.0, 2.0


@pytest.fixture(scope="module")
def slab():
    """The suite's flat-shaded slab (1.6 x 1.6 x 0.16, exact face normals), scaled by 2.5."""
    return ASSETS / "meshes" / "slab.ply"


def _scene(slab, method="specular", alpha=0.0, size=40):
    return tr.Scene(mesh=str(slab), envmap=tr.EnvMap(path=str(ASSETS / "envmaps" /
                                                             "studio_small_03.exr")),
                    transform=tr.Transform(scale=T / 0.16, rotate_deg=(0.0, TILT, 0.0)),
                    material=tr.Material(ior=IOR, roughness=alpha),
                    camera=tr.Camera(eye=(0.0, 0.0, 5.0), yfov_deg=20.0, width=size,
                                     height=size),
                    method=method, passes={"flow": {"distance": DIST}})


def _analytic_flow(scene):
    """Per pixel: the camera ray, shifted sideways by the plate's lateral shift, met with
    the plane z = -DIST (target at the origin, view axis -Z) and projected."""
    cam = scene.camera
    d = pixel_rays(cam).double().reshape(-1, 3)  # (P, 3)
    a = math.radians(TILT)
    n = torch.tensor([math.sin(a), 0.0, math.cos(a)], dtype=torch.float64)  # front face
    cos = -(d @ n)
    sin = torch.sqrt(1 - cos ** 2)
    shift = T * sin * (1 - cos / torch.sqrt(IOR ** 2 - sin ** 2))  # the formula
    side = -n + (d @ n)[:, None] * d  # towards -n, across the ray
    side = side / side.norm(dim=-1, keepdim=True).clamp(min=1e-12)
    o = torch.tensor(cam.eye, dtype=torch.float64) + shift[:, None] * side
    s = (-DIST - o[:, 2]) / d[:, 2]
    hit = o + s[:, None] * d
    xy, _ = project(hit[None], projection_params(cam).double()[None])
    h, w = cam.height, cam.width
    yy, xx = torch.meshgrid(torch.arange(h), torch.arange(w), indexing="ij")
    center = torch.stack([xx + 0.5, yy + 0.5], -1).reshape(-1, 2).double()
    return (xy[0] - center).reshape(h, w, 2), shift.reshape(h, w)


def test_smooth_plate_matches_analytic_shift(one_thread, slab):
    s = _scene(slab)
    out = tr.render(s)
    flow = out.passes["flow"][0].double()
    expect, shift = _analytic_flow(s)
    valid = out.passes["flow_valid"][0, ..., 0] > 0.999
    assert bool(valid.all())
    err = (flow - expect).norm(dim=-1)
    print(f"flow error: max {float(err.max()):.2e} px, mean {float(err.mean()):.2e} px; "
          f"flow {float(flow.norm(dim=-1).min()):.2f}-{float(flow.norm(dim=-1).max()):.2f} px")
    assert float(err.max()) < 1e-3  # pixels (measured 4e-6); the flow itself is 0.8-1.9 px
    assert float(flow.norm(dim=-1).min()) > 0.5
    assert float(shift.min()) > 0.04  # world units: 0.05-0.11 across the view
    assert float(out.passes["flow_cov"].abs().max()) == 0.0  # smooth: no footprint


@pytest.mark.parametrize("method", ["rousiers", "prefiltered"])
def test_rough_plate_footprint(one_thread, slab, method):
    """Rough glass: the mean position stays near the smooth one (the lobe's axis tilts a
    little off the ray), the footprint is a positive covariance growing with roughness."""
    smooth, _ = _analytic_flow(_scene(slab))
    traces = []
    for alpha in (0.1, 0.3):
        out = tr.render(_scene(slab, method, alpha))
        flow, cov = out.passes["flow"][0], out.passes["flow_cov"][0]
        assert bool(torch.isfinite(flow).all()) and bool(torch.isfinite(cov).all())
        inner = (slice(4, -4), slice(4, -4))
        assert float((flow[inner] - smooth[inner].float()).norm(dim=-1).mean()) < 1.0
        xx, xy, yy = cov[inner].unbind(-1)
        assert bool((xx > 0).all()) and bool((xx * yy - xy ** 2 >= -1e-6).all())
        traces.append(float((xx + yy).mean()))
    assert traces[1] > 4 * traces[0]

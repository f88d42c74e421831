"""Spatially varying roughness (de Rousiers sec. 5.1): texture convention, front and exit."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import trimesh
from conftest import ASSETS
from PIL import Image

import torchrefract as tr
from torchrefract.optics.textures import load_roughness_map, sample_uv

ENV = str(ASSETS / "envmaps" / "lebombo.exr")


def test_texture_convention_and_wrap(tmp_path):
    img = np.zeros((2, 4, 3), np.uint8)
    img[0, 1] = (30, 60, 90)  # texel (c=1, r=0): u = 1.5/4, v = 1 - 0.5/2
    img[1, 3] = 255
    path = tmp_path / "m.png"
    Image.fromarray(img).save(path)
    tex = load_roughness_map(path)
    assert tex.shape == (2, 4) and tex[0, 1].item() == pytest.approx(60 / 255)
    uv = torch.tensor([[1.5 / 4, 0.75], [3.5 / 4, 0.25], [3.5 / 4 - 1.0, 0.25 + 2.0],
                       [0.0, 0.25]])
    v = sample_uv(tex, uv)
    assert v[0].item() == pytest.approx(60 / 255, abs=1e-6)
    assert v[1].item() == pytest.approx(1.0, abs=1e-6) and v[2].item() == pytest.approx(1.0)
    # u = 0 lies halfway between column 3 (wrapped) and column 0 of the bottom row
    assert v[3].item() == pytest.approx(0.5, abs=1e-6)
    with pytest.raises(tr.ConfigError, match="cannot be read"):
        bad = tmp_path / "bad.png"
        bad.write_bytes(b"not an image")
        load_roughness_map(bad)


@pytest.fixture(scope="module")
def uv_sphere(tmp_path_factory):
    """Icosphere with v = (y + 1) / 2 (and u constant, so no seam), as PLY with UVs."""
    m = trimesh.creation.icosphere(subdivisions=4)
    uv = np.stack([np.full(len(m.vertices), 0.5), (m.vertices[:, 1] + 1.0) / 2.0], -1)
    m.visual = trimesh.visual.TextureVisuals(uv=uv)
    path = tmp_path_factory.mktemp("uv") / "uvsphere.ply"
    m.export(path)
    return path


def _map(tmp_path, top, bottom, rows=64):
    img = np.zeros((rows, 4), np.uint8)
    img[: rows // 2] = top  # image top = high v = +y
    img[rows // 2:] = bottom
    path = tmp_path / f"map_{top}_{bottom}.png"
    Image.fromarray(img).save(path)
    return str(path)


def _scene(mesh, method, **material):
    return tr.Scene(mesh=str(mesh), envmap=tr.EnvMap(path=ENV),
                    material=tr.Material(**material), method=method,
                    camera=tr.Camera(eye=(0.0, 0.0, 3.5), width=40, height=40))


@pytest.mark.parametrize("method", ["rousiers", "prefiltered"])
def test_constant_map_equals_uniform_roughness(uv_sphere, tmp_path, method):
    path = _map(tmp_path, 255, 255)
    mapped = tr.render([_scene(uv_sphere, method, roughness_map=path,
                               roughness_range=(0.05, 0.4))])
    uniform = tr.render([_scene(uv_sphere, method, roughness=0.4)])
    assert torch.allclose(mapped.passes["roughness"], uniform.passes["roughness"], atol=1e-6)
    assert torch.allclose(mapped.radiance, uniform.radiance, rtol=1e-3, atol=1e-4)


def test_half_rough_map_mixes_the_two_roughnesses(uv_sphere, tmp_path):
    path = _map(tmp_path, 255, 0)  # top (+y) alpha 0.4, bottom alpha 0.05
    mixed = tr.render([_scene(uv_sphere, "rousiers", roughness_map=path,
                              roughness_range=(0.05, 0.4))]).radiance[0]
    rough = tr.render([_scene(uv_sphere, "rousiers", roughness=0.4)]).radiance[0]
    smooth = tr.render([_scene(uv_sphere, "rousiers", roughness=0.05)])
    cov = smooth.coverage[0] == 1
    smooth = smooth.radiance[0]
    top = cov.clone()
    top[20:] = False
    bottom = cov.clone()
    bottom[:20] = False
    d = lambda a, b, m: (a - b).abs()[m].mean().item()  # noqa: E731
    # Each half is closer to the uniform render of its own front roughness.
    assert d(mixed, rough, top) < d(mixed, smooth, top)
    assert d(mixed, smooth, bottom) < d(mixed, rough, bottom)
    # ...but the exit interface sees the other half too: not equal to either.
    assert d(mixed, rough, top) > 1e-4 and d(mixed, smooth, bottom) > 1e-4
    assert torch.isfinite(mixed).all()
    # The roughness pass shows the map on the front surface.
    rp = tr.render([_scene(uv_sphere, "rousiers", roughness_map=path,
                           roughness_range=(0.05, 0.4))]).passes["roughness"][0, ..., 0]
    assert rp[8, 20].item() == pytest.approx(0.4, abs=1e-5)
    assert rp[32, 20].item() == pytest.approx(0.05, abs=1e-5)

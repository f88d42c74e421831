"""The accuracy suite (configs/suite/*.yaml): every scene loads, renders with each of our
methods at a tiny size (finite radiance, the object in view) and converts to Mitsuba."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

import torchrefract as tr

SUITE = Path(__file__).resolve().parent.parent / "configs" / "suite"
EXPECTED = {"sphere_a005", "sphere_a03", "slab_a02", "bunny_a01", "suzanne_a01", "teapot_a01",
            "vgroove_a01", "torus_a01", "sphere_ior24_a01", "globe_2rough", "slab_light"}
METHODS = ("specular", "prefiltered", "rousiers")


def _tiny(scene: tr.Scene, size: int = 24) -> tr.Scene:
    c = scene.camera
    return scene.replace(camera=tr.Camera(eye=c.eye, target=c.target, up=c.up,
                                          yfov_deg=c.yfov_deg, width=size, height=size,
                                          samples_per_pixel=1))


@pytest.fixture(scope="module")
def suite() -> list[tr.Scene]:
    return [tr.load_scene(p) for p in sorted(SUITE.glob("*.yaml"))]


def test_suite_is_complete_and_full_size(suite):
    assert {s.name for s in suite} >= EXPECTED
    for s in suite:
        c = s.camera
        assert (c.width, c.height, c.samples_per_pixel) == (256, 256, 2), s.name
        assert s.method == "rousiers" and Path(s.envmap.path).name == "lebombo.exr", s.name
    globe = next(s for s in suite if s.name == "globe_2rough")
    assert globe.material.roughness_map is not None
    assert len(next(s for s in suite if s.name == "slab_light").lights) == 1


@pytest.mark.parametrize("method", METHODS)
def test_suite_renders_finite(suite, method, one_thread):
    scenes = [_tiny(s) for s in suite]
    out = tr.render(scenes, method=method)
    assert out.radiance.shape == (len(scenes), 24, 24, 3)
    for i, s in enumerate(scenes):
        rad, cov = out.radiance[i], out.coverage[i]
        assert torch.isfinite(rad).all(), f"{s.name} ({method}): non-finite radiance"
        assert (rad >= 0).all(), f"{s.name} ({method}): negative radiance"
        # The object fills a good part of the frame (measured 0.2-0.56 at 128x128).
        assert 0.1 < float(cov.mean()) < 0.9, f"{s.name}: coverage {float(cov.mean()):.2f}"
        assert float(rad[cov > 0.99].mean()) > 0.01, f"{s.name} ({method}): black object"


def test_suite_converts_to_mitsuba(suite):
    pytest.importorskip("mitsuba")
    reference = pytest.importorskip("torchrefract.truth.mitsuba")
    for s in suite:
        d = reference.to_mitsuba_dict(_tiny(s), spp=1)
        kind = "SmoothDielectric" if s.material.roughness == 0 and \
            s.material.roughness_map is None else "RoughDielectric"
        assert kind in str(d["glass"].bsdf()), s.name
        assert len([k for k in d if k.startswith("light_")]) == len(s.lights)
        if s.material.roughness_map is not None:
            assert d["glass"].has_vertex_texcoords(), s.name
            assert "BitmapTexture" in str(d["glass"].bsdf()), s.name

"""Sweep configs: loading, strict keys, expansion counts, order, determinism, geometry."""

from __future__ import annotations

import copy
import math

import numpy as np
import pytest
from conftest import ROOT
from sweep_fixtures import PARK, SPOT, STUDIO, SUZANNE, base_scene, small_sweep, write_config

from torchrefract.checks import ConfigError
from torchrefract.dataset.run import camera_metadata
from torchrefract.dataset.sweep import expand, load_sweep, sweep_from_dict
from torchrefract.geometry.camera import pixel_rays
from torchrefract.geometry.mesh import rotation_matrix
from torchrefract.scene.model import Camera


def _cfg(data, tmp_path=None):
    return sweep_from_dict(data, base_dir=tmp_path or ROOT, source="test.yaml")


# ---------------------------------------------------------------------------- counts

def test_grid_is_the_product_of_discrete_axes_last_axis_fastest():
    cfg = _cfg(small_sweep())
    samples = expand(cfg)
    assert len(samples) == cfg.num_samples == 8  # 2 IOR x 2 env maps x 2 azimuths
    got = [(p["material.ior"], p["envmap.path"], p["camera.orbit.azimuth_deg"])
           for _, _, p in samples]
    want = [(i, e, a) for i in (1.33, 1.6) for e in (STUDIO, PARK) for a in (-25.0, 25.0)]
    assert got == want
    # The scene carries the values.
    sid, scene, p = samples[5]
    assert sid == "000005" and scene.name == "000005"
    assert scene.material.ior == p["material.ior"]
    assert scene.envmap.path == p["envmap.path"] and scene.envmap.rotate_deg == p[
        "envmap.rotate_deg"]
    assert 0.0 <= scene.material.roughness <= 0.4


def test_grid_repeats_and_num_samples_check():
    d = small_sweep()
    d["sampling"]["repeats"] = 3
    cfg = _cfg(d)
    s = expand(cfg)
    assert len(s) == 24
    # Repeats share the grid point, with fresh random draws.
    assert s[0].params["material.ior"] == s[2].params["material.ior"]
    assert s[0].params["material.roughness"] != s[1].params["material.roughness"]
    d["sampling"]["num_samples"] = 23
    with pytest.raises(ConfigError, match=r"test.yaml: sampling.num_samples: grid sampling "
                                          r"gives 24 samples"):
        _cfg(d)


def test_list_zips_axes_and_checks_lengths():
    d = small_sweep()
    d["sampling"]["mode"] = "list"
    d["sweep"]["envmap"]["path"] = STUDIO  # a scalar broadcasts
    cfg = _cfg(d)
    s = expand(cfg)
    assert len(s) == 2
    assert [(x.params["material.ior"], x.params["camera.orbit.azimuth_deg"]) for x in s] == \
        [(1.33, -25.0), (1.6, 25.0)]
    d["sweep"]["material"]["ior"] = [1.2, 1.3, 1.4]
    with pytest.raises(ConfigError, match="equal lengths"):
        _cfg(d)


def test_random_count_choices_and_ranges():
    d = small_sweep()
    d["sampling"] = {"mode": "random", "seed": 11, "num_samples": 40}
    d["sweep"]["mesh"] = {"path": [SPOT, SUZANNE], "random_rotation": "so3",
                          "scale": {"log_uniform": [0.5, 1.0]}, "translate_jitter": 0.1}
    d["sweep"]["camera"]["resolution"] = [32, "24x16", [16, 24]]
    s = expand(_cfg(d))
    assert len(s) == 40
    assert {x.params["material.ior"] for x in s} == {1.33, 1.6}
    assert {x.scene.mesh for x in s} == {SPOT, SUZANNE}
    assert {(x.scene.camera.width, x.scene.camera.height) for x in s} == {(32, 32), (24, 16),
                                                                           (16, 24)}
    for x in s:
        assert 0.5 <= x.scene.transform.scale <= 1.0
        assert np.all(np.abs(x.scene.transform.translate) <= 0.1)
        assert np.all(np.abs(np.subtract(x.scene.camera.target, 0)) <= 0.05)
        assert 0.0 <= x.scene.envmap.rotate_deg <= 360.0
    with pytest.raises(ConfigError, match="num_samples: required"):
        _cfg(dict(d, sampling={"mode": "random"}))


def test_linspace_axis():
    d = small_sweep()
    d["sweep"]["material"]["roughness"] = {"linspace": [0.0, 0.5, 6]}
    cfg = _cfg(d)
    assert cfg.num_samples == 48
    assert sorted({x.params["material.roughness"] for x in expand(cfg)}) == pytest.approx(
        [0.0, 0.1, 0.2, 0.3, 0.4, 0.5])


# ---------------------------------------------------------------------------- determinism

def _key(samples):
    return [(sid, sc, p) for sid, sc, p in samples]


def test_expansion_is_deterministic_and_each_sample_stands_alone():
    d = small_sweep()
    d["sampling"] = {"mode": "random", "seed": 5, "num_samples": 12}
    a, b = expand(_cfg(d)), expand(_cfg(copy.deepcopy(d)))
    assert _key(a) == _key(b)
    # Sample i depends only on (seed, i): a longer sweep starts with the same samples, and
    # one sample drawn alone equals its place in the list.
    d2 = copy.deepcopy(d)
    d2["sampling"]["num_samples"] = 20
    longer = expand(_cfg(d2))
    assert _key(longer[:12]) == _key(a)
    assert _cfg(d).sample(7) == a[7]
    # Another seed gives other draws.
    d3 = copy.deepcopy(d)
    d3["sampling"]["seed"] = 6
    assert [x.params["material.roughness"] for x in expand(_cfg(d3))] != \
        [x.params["material.roughness"] for x in a]
    # Adding an axis leaves the other axes' draws unchanged (one stream per axis).
    d4 = copy.deepcopy(d)
    d4["sweep"]["camera"]["yfov_deg"] = {"uniform": [30, 50]}
    c = expand(_cfg(d4))
    assert [x.params["material.roughness"] for x in c] == \
        [x.params["material.roughness"] for x in a]
    assert [x.scene.camera.yfov_deg for x in c] != [x.scene.camera.yfov_deg for x in a]


def test_config_hash_tracks_content():
    h1 = _cfg(small_sweep()).config_hash
    assert h1 == _cfg(small_sweep()).config_hash and len(h1) == 64
    d = small_sweep()
    d["sampling"]["seed"] = 4
    assert _cfg(d).config_hash != h1


# ---------------------------------------------------------------------------- geometry

def test_orbit_places_the_eye_and_keeps_the_target():
    d = {"base": base_scene(), "sampling": {"mode": "grid"},
         "sweep": {"camera": {"orbit": {"azimuth_deg": [0, 90], "elevation_deg": 30,
                                        "distance": 2.0}}}}
    s = expand(_cfg(d))
    e = math.radians(30)
    assert s[0].scene.camera.eye == pytest.approx((0, 2 * math.sin(e), 2 * math.cos(e)))
    assert s[1].scene.camera.eye == pytest.approx((2 * math.cos(e), 2 * math.sin(e), 0),
                                                  abs=1e-12)
    assert s[0].scene.camera.target == (0.0, 0.0, 0.0)
    # Unset orbit axes keep the base camera's: its distance is |(0, 0.4, 3.2)|.
    d["sweep"]["camera"]["orbit"] = {"azimuth_deg": [45]}
    eye = np.array(expand(_cfg(d))[0].scene.camera.eye)
    assert np.linalg.norm(eye) == pytest.approx(math.hypot(0.4, 3.2))
    assert eye[1] == pytest.approx(0.4)


@pytest.mark.parametrize("mode", ["yaw", "so3"])
def test_random_rotation_composes_with_the_base_rotation(mode):
    d = {"base": dict(base_scene(), transform={"rotate_deg": [10, -35, 5]}),
         "sampling": {"mode": "random", "num_samples": 20, "seed": 2},
         "sweep": {"mesh": {"random_rotation": mode}}}
    r_base = rotation_matrix((10, -35, 5))
    ys = []
    for s in expand(_cfg(d)):
        extra = rotation_matrix(s.scene.transform.rotate_deg) @ r_base.T
        assert np.allclose(extra @ extra.T, np.eye(3), atol=1e-9)
        assert np.linalg.det(extra) == pytest.approx(1.0)
        if mode == "yaw":  # a rotation about +Y: Y is fixed
            assert np.allclose(extra[:, 1], [0, 1, 0], atol=1e-9)
        ys.append(extra[:, 1])
    if mode == "so3":  # the Y axis goes everywhere
        assert np.std(np.array(ys), axis=0).min() > 0.3


def test_camera_metadata_projects_pixel_centers_to_their_indices():
    cam = Camera(eye=(0.3, 0.8, 2.5), target=(0.1, -0.1, 0.0), yfov_deg=35, width=24,
                 height=16)
    m = camera_metadata(cam)
    k, w2c = np.array(m["K"]), np.array(m["world_to_camera"])
    assert m["intrinsics"]["cx"] == 11.5 and m["intrinsics"]["fx"] == m["intrinsics"]["fy"]
    rays = pixel_rays(cam).double().numpy()  # (H, W, 3), row 0 on top
    for j, i in [(0, 0), (5, 17), (15, 23)]:
        x = np.append(np.array(cam.eye) + 3.0 * rays[j, i], 1.0)
        xc = w2c @ x
        assert xc[2] > 0  # in front: +Z forward (OpenCV)
        uv = (k @ xc[:3])[:2] / xc[2]
        assert uv == pytest.approx([i, j], abs=1e-4)
    # The eye maps to the camera origin.
    assert (w2c @ np.append(cam.eye, 1.0))[:3] == pytest.approx([0, 0, 0], abs=1e-12)


# ---------------------------------------------------------------------------- errors

@pytest.mark.parametrize("change, message", [
    (lambda d: d.update(colour=1), r"test.yaml: <top level>: unknown key 'colour'"),
    (lambda d: d["sweep"]["material"].update(colour=1),
     r"test.yaml: sweep.material: unknown key 'colour'"),
    (lambda d: d["sweep"]["camera"]["orbit"].update(radius=1),
     r"test.yaml: sweep.camera.orbit: unknown key 'radius'"),
    (lambda d: d["sampling"].update(mode="sobol"), r"sampling.mode: expected one of"),
    (lambda d: d["sweep"]["material"].update(ior={"gauss": [1, 2]}),
     r"sweep.material.ior: unknown distribution 'gauss'"),
    (lambda d: d["sweep"]["material"].update(ior={"uniform": [1.6, 1.2]}),
     r"sweep.material.ior.uniform: expected lo <= hi"),
    (lambda d: d["sweep"]["material"].update(ior=[1.5, -1.0]),
     r"sweep.material.ior\[1\]: must be > 0.0, got -1.0"),
    (lambda d: d["sweep"]["envmap"].update(path=[STUDIO, "missing.exr"]),
     r"sweep.envmap.path\[1\]: file not found: 'missing.exr'"),
    (lambda d: d["sweep"]["camera"]["orbit"].update(elevation_deg=90),
     r"sweep.camera.orbit.elevation_deg: must be <= 89.0"),
    (lambda d: d["sweep"]["camera"].update(resolution=["64x"]),
     r"sweep.camera.resolution\[0\]: expected 'WIDTHxHEIGHT'"),
    (lambda d: d["sweep"].update(method=["magic"]), r"sweep.method\[0\]: expected one of"),
    (lambda d: d["base"]["material"].update(ior="glass"),
     r"base: material.ior: expected a number"),
    (lambda d: d.pop("base"), r"missing required key 'base'"),
    (lambda d: d["sweep"]["material"].update(roughness={"linspace": [0, 0.3, 10 ** 12]}),
     r"sweep.material.roughness.linspace\[2\]: must be <= 1e\+06"),
    (lambda d: d.update(sampling={"mode": "random", "seed": 1, "num_samples": 10 ** 15}),
     r"sampling.num_samples: must be <= 1e\+06"),
    (lambda d: d["sweep"]["material"].update(roughness={"linspace": [0, 0.3, 1000]},
                                             ior={"linspace": [1.1, 2.0, 1001]}),
     r"test.yaml: sweep: grid sampling gives [0-9,]+ samples, more than one sweep takes"),
])
def test_bad_configs_name_the_file_and_key(change, message):
    d = small_sweep()
    change(d)
    with pytest.raises(ConfigError, match=message):
        _cfg(d)


def test_load_sweep_from_files_with_relative_paths(tmp_path):
    # A base scene file next to the sweep, with its own relative paths.
    scene = dict(base_scene(), mesh="../../meshes/spot.ply")
    assets = tmp_path / "a" / "b"
    (tmp_path / "meshes").mkdir()
    (tmp_path / "meshes" / "spot.ply").write_bytes(open(SPOT, "rb").read())
    write_config(assets / "scene.yaml", scene)
    path = write_config(assets / "sweep.yaml", {"base": "scene.yaml",
                                                "sweep": {"material": {"ior": [1.2, 1.4]}}})
    cfg = load_sweep(path)
    assert cfg.name == "sweep" and cfg.num_samples == 2
    assert cfg.base.mesh == str((tmp_path / "meshes" / "spot.ply").resolve())
    (assets / "bad.yaml").write_text("base: scene.yaml\nsweep: {materal: {}}\n")
    with pytest.raises(ConfigError, match=r"bad.yaml: sweep: unknown key 'materal'"):
        load_sweep(assets / "bad.yaml")
    with pytest.raises(ConfigError, match="sweep file not found"):
        load_sweep(assets / "nope.yaml")


def test_shipped_demo_sweep_expands():
    cfg = load_sweep(ROOT / "configs" / "sweep_demo.yaml")
    s = expand(cfg)
    assert len(s) == 12
    assert {x.scene.camera.width for x in s} == {64}
    assert len({x.params["envmap.rotate_deg"] for x in s}) == 12


def test_the_throughput_config_is_what_docs_datasets_md_measures():
    """configs/sweep_throughput.yaml: 48 random samples at 256x256, two meshes in random
    poses, two maps, rousiers at 1 spp (docs/datasets.md, section 4)."""
    cfg = load_sweep(ROOT / "configs" / "sweep_throughput.yaml")
    samples = list(cfg.samples())
    assert len(samples) == 48
    scenes = [s.scene for s in samples]
    assert {(s.camera.width, s.camera.height, s.camera.samples_per_pixel, s.method)
            for s in scenes} == {(256, 256, 1, "rousiers")}
    assert len({s.mesh for s in scenes}) == 2 and len({s.envmap.path for s in scenes}) == 2
    assert len({s.transform.rotate_deg for s in scenes}) == 48  # a new pose per sample

"""Stability where methods fail (issue: speed/accuracy, part 5, first cases).

Every method must give finite, non-negative output bounded by the brightest environment
texel (times a small factor: the front reflection and the transmitted lobe can at most add
up), for extreme roughness and IOR, grazing views, objects leaving the frame, a camera very
close, tiny and huge scales, broken meshes, and an environment with a 1e5 sun.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
import trimesh

import torchrefract as tr
from torchrefract.envmap import load_envmap
from torchrefract.image_files import write_exr

from conftest import ASSETS

METHODS = ["specular", "prefiltered", "rousiers"]
ENV = str(ASSETS / "envmaps" / "lebombo.exr")
SPHERE = str(ASSETS / "meshes" / "sphere.ply")
SUZANNE = str(ASSETS / "meshes" / "suzanne.ply")


def _check(out, env_max):
    assert torch.isfinite(out.radiance).all()
    assert out.radiance.min() >= 0
    assert out.radiance.max() <= 2.0 * env_max
    for k, v in out.passes.items():
        assert torch.isfinite(v).all(), k


def _scene(mesh=SUZANNE, env=ENV, cam=None, transform=None, **material):
    return tr.Scene(mesh=mesh, envmap=tr.EnvMap(path=env),
                    material=tr.Material(**material),
                    transform=transform or tr.Transform(),
                    camera=cam or tr.Camera(eye=(0.4, 0.3, 3.0), width=24, height=24))


@pytest.mark.parametrize("method", METHODS)
def test_extreme_roughness_and_ior(method):
    env_max = float(load_envmap(ENV).max())
    scenes = [_scene(ior=ior, roughness=r) for r in (0.0, 1e-4, 0.5, 1.0)
              for ior in (1.0, 1.0001, 1.33, 2.4, 4.0)]
    _check(tr.render(scenes, method=method), env_max)


@pytest.mark.parametrize("method", METHODS)
def test_difficult_views(method):
    env_max = float(load_envmap(ENV).max())
    cams = [
        tr.Camera(eye=(0.0, 0.0, 1.05), yfov_deg=90, width=24, height=24),  # very close
        tr.Camera(eye=(2.5, 0.0, 0.0), target=(0.0, 0.9, 0.0), width=24, height=24),  # grazing
        tr.Camera(eye=(0.0, 0.0, 3.0), target=(1.2, 0.8, 0.0), width=24, height=24),  # edge
    ]
    for cam in cams:
        _check(tr.render([_scene(mesh=SPHERE, cam=cam, ior=1.5, roughness=0.2)],
                         method=method), env_max)
    for scale in (1e-3, 1e3):
        cam = tr.Camera(eye=(0.0, 0.0, 3.0 * scale), width=24, height=24)
        out = tr.render([_scene(mesh=SPHERE, cam=cam, transform=tr.Transform(scale=scale),
                                ior=1.5, roughness=0.2)], method=method)
        _check(out, env_max)
        assert out.coverage.mean() > 0.05


@pytest.mark.parametrize("method", METHODS)
def test_broken_meshes_and_a_bright_sun(method, tmp_path):
    ico = trimesh.creation.icosphere(subdivisions=2)
    open_mesh = trimesh.Trimesh(ico.vertices, ico.faces[:-10])
    open_path = tmp_path / "open.ply"
    open_mesh.export(open_path)
    tri_path = tmp_path / "tri.ply"
    trimesh.Trimesh([[-1.0, -1.0, 0.0], [1.0, -1.0, 0.0], [0.0, 1.0, 0.0]],
                    [[0, 1, 2]]).export(tri_path)
    sun = np.full((32, 64, 3), 0.5, np.float32)
    sun[8, 20] = 1e5
    sun_path = tmp_path / "sun.exr"
    write_exr(sun_path, {"R": sun[..., 0], "G": sun[..., 1], "B": sun[..., 2]})
    for mesh in (open_path, tri_path):
        with pytest.warns(UserWarning, match="not watertight"):
            out = tr.render([_scene(mesh=str(mesh), ior=1.5, roughness=0.3)], method=method)
        _check(out, float(load_envmap(ENV).max()))
    out = tr.render([_scene(mesh=SPHERE, env=str(sun_path), ior=1.5, roughness=0.3)],
                    method=method)
    _check(out, 1e5)


@pytest.mark.parametrize("method", METHODS)
def test_white_furnace(method, tmp_path):
    """Uniform environment of radiance 1: no pixel of any roughness exceeds 1.05 (a lossless
    interface cannot create light) and smooth glass keeps a mean >= 0.9 on object pixels.

    Not asserted yet (tracked in the issues): single pixels of smooth glass drop to ~0.64
    near the silhouette, because a two-interface method loses the light reflected inside at
    the exit (F2 (1 - F1), up to ~25% and more on tessellated normals) until internal
    bounces exist; and rough surfaces should match Mitsuba's furnace value within 0.05.
    """
    white = np.ones((16, 32, 3), np.float32)
    path = tmp_path / "white.exr"
    write_exr(path, {"R": white[..., 0], "G": white[..., 1], "B": white[..., 2]})
    for r in (0.0, 0.3, 1.0):
        out = tr.render([_scene(mesh=SPHERE, env=str(path), ior=1.5, roughness=r)],
                        method=method)
        obj = out.coverage[0] > 0.99
        vals = out.radiance[0][obj]
        assert vals.max() <= 1.05, (r, vals.max())
        if r == 0.0:
            assert vals.mean() >= 0.9, vals.mean()

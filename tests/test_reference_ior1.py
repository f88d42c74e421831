"""The Mitsuba reference of an index-matched object (IOR exactly 1): no interface at all.

Mitsuba's ``dielectric`` / ``roughdielectric`` reject equal indices, so the reference uses a
``null`` BSDF there; the object must vanish, as it does for every method of ours.
"""

from __future__ import annotations

import numpy as np
import pytest
from conftest import ASSETS

import torchrefract as tr

pytest.importorskip("mitsuba")


@pytest.mark.parametrize("roughness", [0.0, 0.5])
def test_index_matched_object_is_invisible(roughness):
    from torchrefract.truth.mitsuba import render_reference

    s = tr.Scene(mesh=str(ASSETS / "meshes" / "sphere.ply"),
                 envmap=tr.EnvMap(path=str(ASSETS / "envmaps" / "lebombo.exr")),
                 material=tr.Material(ior=1.0, roughness=roughness),
                 camera=tr.Camera(width=24, height=24))
    rgb, _ = render_reference(s, spp=2, seed=0)
    empty = s.replace(transform=tr.Transform(scale=1e-4))  # the same view, no object
    bg, _ = render_reference(empty, spp=2, seed=0)
    assert np.abs(rgb - bg).max() <= 1e-3 * bg.max()

"""Per-stage timings of a render (``RenderResult.timings``, :mod:`torchrefract.stages`)."""

from __future__ import annotations

import doctest
import time

from conftest import ASSETS

import torchrefract as tr
from torchrefract import stages
from torchrefract.stages import collect, stage, timed

SUZANNE = str(ASSETS / "meshes" / "suzanne.ply")
ENV = str(ASSETS / "envmaps" / "lebombo.exr")


def _scene(method, **options):
    return tr.Scene(method=method, mesh=SUZANNE, envmap=tr.EnvMap(path=ENV),
                    material=tr.Material(ior=1.5, roughness=0.2),
                    camera=tr.Camera(eye=(0.4, 0.3, 3.0), width=32, height=32),
                    method_options=options)


def test_stages_sum_counts_once_when_nested_and_isolate_collections():
    @timed("march")
    def inner():
        time.sleep(0.01)

    with collect() as outer:
        with stage("march"):
            inner()  # the same stage inside itself: counted once
            time.sleep(0.01)
        with collect() as own:
            inner()
        inner()
    assert set(outer) == {"march"} and set(own) == {"march"}
    assert 0.03 <= outer["march"] < 0.03 + 0.5 * 3, outer  # 0.02 + 0.01, not 0.04
    assert 0.01 <= own["march"] < outer["march"]
    with stage("march"):  # outside any collection: nothing recorded, nothing fails
        pass
    assert doctest.testmod(stages).failed == 0


def test_render_reports_march_and_mips_inside_shading():
    # The tensor code (the fused kernels march inside one call, reported as "fused"):
    # spread: paper reads the back layer's NDF mips; the default (rays) builds none.
    tensor = tr.RenderSettings(fused=False)
    for options, has_mips in (({"spread": "paper"}, True), ({}, False)):
        out = tr.render([_scene("rousiers", **options)], settings=tensor)
        t = out.timings
        assert t["march"] > 0.0
        assert (t["mips"] > 0.0) == has_mips, t
        assert t["march"] + t["mips"] <= t["shading"] <= t["total"]
    # specular with bounces marches inside as well
    t = tr.render([_scene("specular", internal_bounces=1)], settings=tensor).timings
    assert t["march"] > 0.0 and t["mips"] == 0.0
    t = tr.render([_scene("rousiers")]).timings  # the default: fused
    assert t["fused"] > 0.0 and t["march"] == 0.0 and t["fused"] <= t["shading"]

"""Method ``auto`` (issue #4, part 6): per-scene choice from the chart's measurements."""

from __future__ import annotations

import json

import pytest
import torch

import torchrefract as tr
from torchrefract.checks import ConfigError
from torchrefract.methods.auto import AutoOptions, choose, features, load_table

from conftest import ASSETS

SPHERE = str(ASSETS / "meshes" / "sphere.ply")
SLAB = str(ASSETS / "meshes" / "slab.ply")
ENV = str(ASSETS / "envmaps" / "lebombo.exr")


def _scene(mesh=SPHERE, roughness=0.1, **opts):
    return tr.Scene(mesh=mesh, envmap=tr.EnvMap(path=ENV),
                    material=tr.Material(ior=1.5, roughness=roughness),
                    camera=tr.Camera(eye=(0.4, 0.3, 3.0), width=24, height=24),
                    method="auto", method_options=opts)


def _table(tmp_path):
    """Two measured scenes: on the smooth sphere specular is as good as rousiers and faster;
    on the rough slab only rousiers is accurate."""
    sphere_f = features(_scene(roughness=0.0))
    slab_f = features(_scene(mesh=SLAB, roughness=0.3))
    t = {"version": 1, "scenes": [
        {"name": "smooth_sphere", "features": sphere_f, "variants": [
            {"method": "specular", "options": {}, "ms": 50, "flip": 0.10},
            {"method": "prefiltered", "options": {}, "ms": 60, "flip": 0.12},
            {"method": "rousiers", "options": {"internal_bounces": 1}, "ms": 120, "flip": 0.085},
            {"method": "rousiers", "options": {}, "ms": 100, "flip": 0.09}]},
        {"name": "rough_slab", "features": slab_f, "variants": [
            {"method": "specular", "options": {}, "ms": 40, "flip": 0.40},
            {"method": "prefiltered", "options": {}, "ms": 45, "flip": 0.25},
            {"method": "rousiers", "options": {"internal_bounces": 1}, "ms": 90, "flip": 0.08},
            {"method": "rousiers", "options": {}, "ms": 80, "flip": 0.15}]}]}
    path = tmp_path / "auto.json"
    path.write_text(json.dumps(t))
    return str(path)


def test_features_tell_a_slab_from_a_sphere():
    f_sphere, f_slab = features(_scene()), features(_scene(mesh=SLAB))
    assert f_sphere["thin"] > 0.9 and f_slab["thin"] < 0.2
    # a UV sphere (its vertices crowd at the poles: 0.69 from the vertex statistics) is as
    # round as an icosphere
    assert features(_scene(mesh=str(ASSETS / "meshes" / "globe.obj")))["thin"] > 0.95


def test_choice_follows_the_measurements_and_the_tolerance(tmp_path):
    table = _table(tmp_path)
    # Smooth sphere: specular is within 0.05 of the best and the cheapest.
    c = choose(_scene(roughness=0.0), AutoOptions(auto_table=table))
    assert (c.method, c.options) == ("specular", {})
    # Rough slab, tight tolerance: the most accurate (rousiers + 1 bounce).
    c = choose(_scene(mesh=SLAB, roughness=0.3), AutoOptions(auto_tolerance=0.0,
                                                             auto_table=table))
    assert (c.method, c.options) == ("rousiers", {"internal_bounces": 1})
    # Loose tolerance: the fastest variant measured on both neighbours.
    c = choose(_scene(mesh=SLAB, roughness=0.3), AutoOptions(auto_tolerance=1.0,
                                                             auto_table=table))
    assert c.method == "specular"


def test_a_smooth_surface_gets_no_cone(tmp_path):
    """Below SMOOTH_ALPHA only specular's variants are candidates, even where the nearest
    measured scenes are rough and favour the rough methods (the table has no smooth scene:
    the leave-one-out case of the shipped table's smooth sphere)."""
    rough_f = features(_scene(roughness=0.1))
    t = {"version": 1, "scenes": [
        {"name": f"rough_sphere_{i}", "features": {**rough_f, "ior": 1.5 + 0.1 * i},
         "variants": [
             {"method": "specular", "options": {}, "ms": 40, "flip": 0.30},
             {"method": "specular", "options": {"internal_bounces": 2}, "ms": 60,
              "flip": 0.20},
             {"method": "rousiers", "options": {"internal_bounces": 2}, "ms": 120,
              "flip": 0.10}]} for i in range(2)]}
    path = tmp_path / "rough_only.json"
    path.write_text(json.dumps(t))
    opts = AutoOptions(auto_tolerance=0.05, auto_table=str(path))
    assert choose(_scene(roughness=0.1), opts).method == "rousiers"  # rough: the measurements
    c = choose(_scene(roughness=0.0), opts)
    assert (c.method, c.options) == ("specular", {"internal_bounces": 2})  # specular's best
    c = choose(_scene(roughness=0.0), AutoOptions(auto_tolerance=0.2, auto_table=str(path)))
    assert (c.method, c.options) == ("specular", {})  # the fastest within the tolerance
    # no specular variant measured on the neighbours: the rule steps aside
    for row in t["scenes"]:
        row["variants"] = [v for v in row["variants"] if v["method"] != "specular"]
    path.write_text(json.dumps(t))
    load_table.cache_clear()
    assert choose(_scene(roughness=0.0), opts).method == "rousiers"


def test_render_auto_groups_and_records_the_choice(tmp_path):
    table = _table(tmp_path)
    scenes = [_scene(roughness=0.0, auto_table=table),
              _scene(mesh=SLAB, roughness=0.3, auto_table=table, auto_tolerance=0.0)]
    # one batch needs equal options: render the two apart, then a mixed batch of one kind
    a = tr.render([scenes[0], scenes[0]])
    assert [s.method for s in a.scenes] == ["specular", "specular"]
    direct = tr.render([scenes[0].replace(method="specular", method_options={})])
    assert torch.allclose(a.radiance[0], direct.radiance[0])
    b = tr.render([scenes[1]])
    assert b.scenes[0].method == "rousiers"
    assert b.scenes[0].method_options == {"internal_bounces": 1}
    assert "bounces" in b.passes


def test_mixed_choices_in_one_batch_keep_their_order(tmp_path):
    table = _table(tmp_path)
    smooth = _scene(roughness=0.0, auto_table=table)
    rough = smooth.replace(mesh=SLAB, material=tr.Material(ior=1.5, roughness=0.3))
    out = tr.render([rough, smooth, rough])
    assert [s.method for s in out.scenes] == ["rousiers", "specular", "rousiers"]
    alone = tr.render([smooth.replace(method="specular", method_options={})])
    assert torch.allclose(out.radiance[1], alone.radiance[0])
    assert out.passes["lobe_sigma"][1].abs().sum() == 0  # a rousiers-only pass: zeros


def test_bad_auto_options_are_named(tmp_path):
    with pytest.raises(ConfigError, match="auto_tolerance"):
        tr.render([_scene(auto_tolerance=-1)])
    with pytest.raises(ConfigError, match="auto_table"):
        tr.render([_scene(auto_table=str(tmp_path / "missing.json"))])
    bad = tmp_path / "bad.json"
    bad.write_text("[1, 2]")
    with pytest.raises(ConfigError, match="auto table"):
        tr.render([_scene(auto_table=str(bad))])


def test_shipped_table_covers_the_suite_and_its_picks_render():
    """The table shipped with the package (built from the chart's results.csv by
    scripts/build_auto_table.py) has every suite scene, only variants a scene file can ask
    for (the scene's own pixel sampling, batch 1, method options the methods accept), and
    auto renders with it."""
    from conftest import ROOT
    from torchrefract.methods.auto import DEFAULT_TABLE, load_table
    from torchrefract.render import METHODS

    table = load_table(str(DEFAULT_TABLE))
    suite = {p.stem for p in (ROOT / "configs" / "suite").glob("*.yaml")}
    assert {s["name"] for s in table["scenes"]} == suite
    for s in table["scenes"]:
        assert len(s["variants"]) >= 10, s["name"]
        for v in s["variants"]:
            assert v["method"] in ("specular", "prefiltered", "rousiers"), v
            METHODS[v["method"]][0](v["options"], None)  # raises on an unknown option
            assert v["ms"] > 0 and 0 <= v["flip"] <= 1
    # a rough slab and a smooth sphere, the default table: a choice from two neighbours
    rough = _scene(mesh=SLAB, roughness=0.25)
    c = choose(rough)
    assert len(c.neighbours) == 2 and c.predicted_flip is not None
    out = tr.render([rough])
    assert out.scenes[0].method == c.method and out.scenes[0].method_options == c.options
    assert torch.isfinite(out.radiance).all()

"""Method ``auto`` (issue #4, part 6): per-scene choice from the chart's measurements."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest
import torch
from conftest import ASSETS

import torchrefract as tr
from torchrefract.auto import (
    NEIGHBOURS,
    AutoOptions,
    choose,
    choose_by_pass,
    features,
    load_table,
    pass_variants,
    pass_weight,
)
from torchrefract.checks import ConfigError

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


def test_choice_follows_the_measurements_and_the_tolerance(tmp_path, monkeypatch):
    import torchrefract.auto as auto

    table = _table(tmp_path)
    # Both scenes are neighbours (a table smaller than NEIGHBOURS): a variant must be within
    # the tolerance on each. Smooth sphere: specular is within 0.02 of the best there, but
    # 0.32 behind on the rough slab: not risked; with 0.35 accepted it is the cheapest.
    opts = {"auto_table": table, "auto_blend": False}
    c = choose(_scene(roughness=0.0), AutoOptions(**opts))
    assert (c.method, c.options) == ("rousiers", {"internal_bounces": 1})
    c = choose(_scene(roughness=0.0), AutoOptions(auto_tolerance=0.35, **opts))
    assert (c.method, c.options) == ("specular", {})
    # One neighbour: the nearest scene's own measurements.
    monkeypatch.setattr(auto, "NEIGHBOURS", 1)
    c = choose(_scene(roughness=0.0), AutoOptions(**opts))
    assert (c.method, c.options) == ("specular", {})
    assert c.blend == (("specular", {}, 1.0),) and c.neighbours == ("smooth_sphere",)
    # Rough slab, tight tolerance: the most accurate (rousiers + 1 bounce).
    c = choose(_scene(mesh=SLAB, roughness=0.3), AutoOptions(auto_tolerance=0.0, **opts))
    assert (c.method, c.options) == ("rousiers", {"internal_bounces": 1})
    # Loose tolerance: the fastest variant measured on the neighbours.
    c = choose(_scene(mesh=SLAB, roughness=0.3), AutoOptions(auto_tolerance=1.0, **opts))
    assert c.method == "specular"
    # The blend, far from any threshold (the slab's neighbourhood is all rough, the two
    # measured scenes are far apart in thinness): one variant, all the weight.
    c = choose(_scene(mesh=SLAB, roughness=0.3), AutoOptions(auto_tolerance=0.0,
                                                             auto_table=table))
    assert c.blend == (("rousiers", {"internal_bounces": 1}, 1.0),)


def test_a_smooth_surface_gets_no_split_rays(tmp_path):
    """Below SPLIT_MIN_ALPHA no variant splits a lobe into rays (bounce_rays 4), even where
    the measurements favour it; otherwise smooth glass follows the measurements (no
    specular-only rule: the validation set measured rousiers' bounces ahead of it)."""
    from torchrefract.auto import SPLIT_MIN_ALPHA

    rough_f = features(_scene(roughness=0.1))
    rays4 = {"internal_bounces": "auto", "bounce_rays": 4}
    t = {"version": 1, "scenes": [
        {"name": f"sphere_{i}", "features": {**rough_f, "ior": 1.5 + 0.1 * i},
         "variants": [
             {"method": "specular", "options": {}, "ms": 40, "flip": 0.30},
             {"method": "rousiers", "options": {"internal_bounces": "auto"}, "ms": 100,
              "flip": 0.15},
             {"method": "rousiers", "options": rays4, "ms": 200, "flip": 0.10}]}
        for i in range(2)]}
    path = tmp_path / "rays.json"
    path.write_text(json.dumps(t))
    opts = AutoOptions(auto_tolerance=0.02, auto_table=str(path), auto_blend=False)
    assert choose(_scene(roughness=0.1), opts).options == rays4  # rough: the measurements
    for a in (0.0, 0.5 * SPLIT_MIN_ALPHA):
        c = choose(_scene(roughness=a), opts)
        assert (c.method, c.options) == ("rousiers", {"internal_bounces": "auto"}), a
    # blended: a mirror gets no split rays; the kernel ramps them in above the threshold
    w = {a: _weights(choose(_scene(roughness=a), AutoOptions(auto_table=str(path))))
         for a in (0.0, 0.06, 0.1, 0.2)}
    key = ("rousiers", json.dumps(rays4, sort_keys=True))
    ramp = [w[a].get(key, 0.0) for a in (0.0, 0.06, 0.1, 0.2)]
    assert ramp[0] == 0.0 and ramp[-1] == 1.0 and ramp == sorted(ramp), ramp
    # only split variants measured: the rule steps aside
    for row in t["scenes"]:
        row["variants"] = [v for v in row["variants"] if v["options"] == rays4]
    path.write_text(json.dumps(t))
    load_table.cache_clear()
    assert choose(_scene(roughness=0.0), opts).options == rays4


def test_render_auto_groups_and_records_the_choice(tmp_path, monkeypatch):
    import torchrefract.auto as auto

    monkeypatch.setattr(auto, "NEIGHBOURS", 1)  # each scene its measured twin's choice
    table = _table(tmp_path)
    scenes = [_scene(roughness=0.0, auto_table=table, auto_pass=False),
              _scene(mesh=SLAB, roughness=0.3, auto_table=table, auto_tolerance=0.0,
                     auto_pass=False)]
    # one batch needs equal options: render the two apart, then a mixed batch of one kind
    a = tr.render([scenes[0], scenes[0]])
    assert [s.method for s in a.scenes] == ["specular", "specular"]
    direct = tr.render([scenes[0].replace(method="specular", method_options={})])
    assert torch.allclose(a.radiance[0], direct.radiance[0])
    b = tr.render([scenes[1]])
    assert b.scenes[0].method == "rousiers"
    assert b.scenes[0].method_options == {"internal_bounces": 1}
    assert "bounces" in b.passes


def test_mixed_choices_in_one_batch_keep_their_order(tmp_path, monkeypatch):
    import torchrefract.auto as auto

    monkeypatch.setattr(auto, "NEIGHBOURS", 1)
    table = _table(tmp_path)
    smooth = _scene(roughness=0.0, auto_table=table, auto_pass=False)
    rough = smooth.replace(mesh=SLAB, material=tr.Material(ior=1.5, roughness=0.3))
    out = tr.render([rough, smooth, rough])
    assert [s.method for s in out.scenes] == ["rousiers", "specular", "rousiers"]
    alone = tr.render([smooth.replace(method="specular", method_options={})])
    assert torch.allclose(out.radiance[1], alone.radiance[0])
    assert out.passes["lobe_sigma"][1].abs().sum() == 0  # a rousiers-only pass: zeros


def _weights(c) -> dict:
    return {(m, json.dumps(o, sort_keys=True)): w for m, o, w in c.blend}


@pytest.mark.parametrize("mesh", ["sphere", "suzanne"])
def test_the_blend_changes_continuously_with_roughness_and_ior(mesh):
    """With the shipped table, a fine sweep of roughness (and of IOR) moves the blend's
    weights by little per step, while the single pick (auto_blend: false) switches outright
    somewhere along the same sweep (the jumps the blend removes).

    Bound: a step of alpha moves the box kernel by du <= d alpha / BLEND_A0 (0.1 for 0.01),
    so a share changes by at most du / (2 * half-width) plus one point; letting go of
    BLEND_MIN of each share and renormalizing scales that by 1 / (1 - n BLEND_MIN) for n
    variants in the blend (n = 3: 1.8): 0.24 per 0.01 of alpha. An IOR step of 0.01 moves
    the kernel by a twentieth of its width: (0.05 + 1 / 16) * 1.8 = 0.20 at most; a single
    pick's switch is 1."""
    from torchrefract.auto import BLEND_A0, BLEND_HALF_WIDTH, BLEND_MIN, BLEND_POINTS

    amp = 1 / (1 - 3 * BLEND_MIN)
    alpha_bound = (0.01 / BLEND_A0 / (2 * BLEND_HALF_WIDTH[0]) + 1 / BLEND_POINTS[0]) * amp
    ior_bound = (0.01 / (2 * BLEND_HALF_WIDTH[1]) + 1 / BLEND_POINTS[1]) * amp
    path = str(ASSETS / "meshes" / f"{mesh}.ply")

    def sweep(blend, **mats):
        out = []
        for m in [dict(zip(mats, v)) for v in zip(*mats.values())]:
            c = choose(_scene(mesh=path).replace(material=tr.Material(
                ior=m.get("ior", 1.5), roughness=m.get("roughness", 0.1))),
                AutoOptions(auto_blend=blend))
            w = _weights(c)
            assert abs(sum(w.values()) - 1) < 1e-9 and min(w.values()) > 0
            out.append(w)
        return out

    def largest_change(ws):
        return max(max(abs(a.get(k, 0) - b.get(k, 0)) for k in {*a, *b})
                   for a, b in zip(ws, ws[1:]))

    alphas = [round(0.01 * i, 2) for i in range(41)]
    assert largest_change(sweep(True, roughness=alphas)) <= alpha_bound
    assert largest_change(sweep(False, roughness=alphas)) == 1.0
    iors = [round(1.3 + 0.01 * i, 2) for i in range(111)]
    for a in (0.0, 0.1):
        assert largest_change(sweep(True, ior=iors, roughness=[a] * len(iors))) <= ior_bound


def test_a_blended_render_is_the_weighted_sum_of_its_variants(tmp_path):
    """The alpha-0.05 sphere sits near a switch of the shipped table's picks (one bounce
    budget to another): auto renders both and adds them with their weights; the result's scene
    stays auto, ``blends`` and the exported sidecar carry every share."""
    from torchrefract.output.export import save_render

    scene = _scene(roughness=0.05, auto_pass=False)
    c = choose(scene)
    assert len(c.blend) >= 2, c.blend
    out = tr.render([scene])
    parts = [tr.render([scene.replace(method=m, method_options=o)]) for m, o, _ in c.blend]
    expect = sum(w * p.radiance for (_, _, w), p in zip(c.blend, parts))
    assert torch.allclose(out.radiance, expect, rtol=1e-5, atol=1e-6)
    assert torch.equal(out.coverage, parts[0].coverage)
    assert out.scenes[0] == scene  # a blend is recorded as auto: it renders the same again
    assert torch.equal(tr.render([out.scenes[0]]).radiance, out.radiance)
    assert out.blends == (c.blend,)
    meta = json.loads(save_render(out, 0, tmp_path)["json"].read_text())
    assert [(b["method"], b["options"]) for b in meta["auto_blend"]] == [
        (m, o) for m, o, _ in c.blend]
    assert abs(sum(b["weight"] for b in meta["auto_blend"]) - 1) < 1e-9
    # what the table predicted goes with the image (issue #26): the choice's figures
    pred = meta["auto_prediction"]
    assert pred == out.predictions[0] == c.record()
    assert pred["predicted_flip"] == c.predicted_flip and pred["predicted_ms"] > 0
    assert pred["tolerance"] == AutoOptions().auto_tolerance and len(pred["neighbours"]) >= 2
    # auto_blend: false renders one variant, recorded as the scene's method; its predicted
    # FLIP is within the tolerance of the most accurate candidate's
    single = tr.render([scene.replace(method_options={"auto_blend": False,
                                                      "auto_pass": False})])
    assert len(single.blends[0]) == 1
    assert single.scenes[0].method == single.blends[0][0][0] != "auto"
    p1 = single.predictions[0]
    assert p1["best_predicted_flip"] <= p1["predicted_flip"] <= (p1["best_predicted_flip"]
                                                                + p1["tolerance"] + 1e-12)


def test_without_measurements_a_rule_stands_in_blended(tmp_path):
    """An empty table: specular below SMOOTH_ALPHA, rousiers above, the switch blended over
    alpha ~0-0.1 (a mirror is specular's alone, alpha 0.2 rousiers' alone)."""
    empty = tmp_path / "empty.json"
    empty.write_text(json.dumps({"version": 1, "scenes": []}))
    opts = AutoOptions(auto_table=str(empty))
    mix = {a: {m: w for m, _, w in choose(_scene(roughness=a), opts).blend}
           for a in (0.0, 0.02, 0.04, 0.06, 0.2)}
    assert mix[0.0] == {"specular": 1.0} and mix[0.2] == {"rousiers": 1.0}
    assert 0 < mix[0.04].get("rousiers", 0) < 1
    rough = [mix[a].get("rousiers", 0.0) for a in (0.0, 0.02, 0.04, 0.06, 0.2)]
    assert rough == sorted(rough) and max(b - a for a, b in zip(rough, rough[1:])) < 0.6
    crisp = AutoOptions(auto_table=str(empty), auto_blend=False)
    assert choose(_scene(roughness=0.03), crisp).blend == (("specular", {}, 1.0),)
    assert choose(_scene(roughness=0.05), crisp).blend == (("rousiers", {}, 1.0),)


def test_bad_auto_options_are_named(tmp_path):
    with pytest.raises(ConfigError, match="auto_tolerance"):
        tr.render([_scene(auto_tolerance=-1)])
    with pytest.raises(ConfigError, match="auto_blend.*'yes'"):
        tr.render([_scene(auto_blend="yes")])
    with pytest.raises(ConfigError, match="auto_table"):
        tr.render([_scene(auto_table=str(tmp_path / "missing.json"))])
    bad = tmp_path / "bad.json"
    bad.write_text("[1, 2]")
    with pytest.raises(ConfigError, match="auto table"):
        tr.render([_scene(auto_table=str(bad))])


def _validation(split: str) -> list[str]:
    from conftest import ROOT

    return json.loads((ROOT / "configs" / "validation" / "splits.json").read_text())[split]


def test_shipped_table_is_the_fit_half_and_its_picks_render():
    """The table shipped with the package (scripts/build_auto_table.py --split fit) holds the
    validation set's fit half and nothing of the held-out half, only variants a scene file
    can ask for (the scene's own pixel sampling, batch 1, options the methods accept); the
    suite's table (auto_v1.json) is still there for ``auto_table``; auto renders with it."""
    from conftest import ROOT

    from torchrefract.auto import DEFAULT_TABLE, load_table
    from torchrefract.methods import registry

    table = load_table(str(DEFAULT_TABLE))
    names = {s["name"] for s in table["scenes"]}
    assert names == set(_validation("fit")) and not names & set(_validation("heldout"))
    assert table["split"] == "fit" and table["configs"] == "configs/validation"
    for s in table["scenes"]:
        assert len(s["variants"]) >= 8, s["name"]
        for v in s["variants"]:
            assert v["method"] in ("specular", "prefiltered", "rousiers", "lean", "gsr"), v
            registry.get(v["method"]).parse(v["options"])  # raises on an unknown option
            assert v["ms"] > 0 and 0 <= v["flip"] <= 1
            assert "1x1" not in v["variant"]  # another pixel sampling: not auto's to pick
    suite = load_table(str(DEFAULT_TABLE.parent / "auto_v1.json"))
    assert {s["name"] for s in suite["scenes"]} == {
        p.stem for p in (ROOT / "configs" / "suite").glob("*.yaml")}
    rough = _scene(mesh=SLAB, roughness=0.25)
    c = choose(rough)
    assert len(c.neighbours) == NEIGHBOURS and c.predicted_flip is not None
    out = tr.render([rough])
    by_pass = choose_by_pass([rough])[0]  # the default: the first pass chooses
    assert out.blends == (by_pass.blend,) and torch.isfinite(out.radiance).all()
    drop = {"pass_ms"}  # timed: the same choice, another clock
    assert [{k: v for k, v in p.items() if k not in drop} for p in out.predictions] == [
        {k: v for k, v in by_pass.record().items() if k not in drop}]
    assert tr.render([rough.replace(method_options={"auto_pass": False})]).blends == (c.blend,)


def test_held_out_picks_predict_no_worse_than_plain_rousiers():
    """On every held-out scene (never in the table) auto's blend, in the table's own
    prediction, is within 0.01 FLIP of plain rousiers' and within the tolerance of the best
    predicted variant (issue #26's rule, as far as the table can tell)."""
    from conftest import ROOT

    import torchrefract.auto as auto

    t = auto._arrays(load_table(str(auto.DEFAULT_TABLE)))
    col = {k: j for j, k in enumerate(t.keys)}
    tol = AutoOptions().auto_tolerance
    for name in _validation("heldout"):
        scene = tr.load_scene(ROOT / "configs" / "validation" / f"{name}.yaml")
        c = choose(scene)
        assert name not in c.neighbours
        _, pf, _, _, _ = auto._crisp(t, np.array([auto._point(features(scene))]), tol)
        picked = sum(w * pf[0, col[(m, json.dumps(o, sort_keys=True))]] for m, o, w in c.blend)
        assert abs(picked - c.predicted_flip) < 1e-9
        assert picked <= pf[0, col[("rousiers", "{}")]] + 0.01, (name, c.blend)
        # within the tolerance of the best candidate (below SPLIT_MIN_ALPHA: no split rays)
        smooth = features(scene)["alpha"] < auto.SPLIT_MIN_ALPHA
        allowed = pf[0][~t.split] if smooth else pf[0]
        assert picked <= np.nanmin(allowed) + tol + 1e-9, (name, c.blend)


def test_table_builder_keeps_to_its_split(tmp_path):
    """scripts/build_auto_table.py --split fit reads only the fit half's rows (a held-out or
    suite scene in the same CSV is left out), without --split only the suite's; the 1x1
    rows (another pixel sampling) are never choices."""
    import importlib.util

    from conftest import ROOT

    spec = importlib.util.spec_from_file_location(
        "build_auto_table", ROOT / "scripts" / "build_auto_table.py")
    b = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(b)
    fit, held = _validation("fit")[0], _validation("heldout")[0]
    cols = ["scene", "method", "variant", "options", "batch", "samples_per_pixel",
            "ms_per_frame", "flip_object", "machine", "threads"]
    rows = [(s, "rousiers", "rousiers", "{}", 2) for s in (fit, held, "sphere_a03")]
    rows += [(fit, "rousiers", "rousiers ib2 1x1", '{"internal_bounces": 2}', 1),
             (fit, "auto", "auto", "{}", 2)]
    path = tmp_path / "results.csv"
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(cols)
        for scene, method, variant, opts, spp in rows:
            w.writerow([scene, method, variant, opts, 1, spp, 10.0, 0.2, "m", 2])
    t = b.build(path, split="fit")
    assert [s["name"] for s in t["scenes"]] == [fit] and t["split"] == "fit"
    assert [v["variant"] for v in t["scenes"][0]["variants"]] == ["rousiers"]
    assert [s["name"] for s in b.build(path, split="heldout")["scenes"]] == [held]
    assert [s["name"] for s in b.build(path)["scenes"]] == ["sphere_a03"]
    with pytest.raises(SystemExit, match="no split"):
        b.build(path, split="test")
    out = tmp_path / "table.json"
    b.main([str(path), "--split", "fit", "--out", str(out)])
    assert [s["name"] for s in json.loads(out.read_text())["scenes"]] == [fit]


# The first pass (auto_pass, the default; issue #26, part 2)

RAYS4 = ("rousiers", {"bounce_rays": 4, "internal_bounces": "auto"})
IB_AUTO = ("rousiers", {"internal_bounces": "auto"})


def _key(m):
    return m[0], json.dumps(m[1], sort_keys=True)


def test_the_pass_variants_follow_the_tables_means(tmp_path):
    """Accurate: the lowest mean FLIP over the table; cheap: the fastest within the tolerance
    of it on average (the same variant when none is)."""
    import torchrefract.auto as auto

    t = auto._arrays(load_table(_table(tmp_path)))
    cheap, acc = pass_variants(t, 0.02)  # means: ib1 0.0825, rousiers 0.12, ...
    assert cheap == acc and t.keys[acc] == ("rousiers", '{"internal_bounces": 1}')
    cheap, acc = pass_variants(t, 0.05)  # rousiers (0.12, 90 ms) within 0.05, faster
    assert t.keys[cheap] == ("rousiers", "{}") and t.keys[acc][1] == '{"internal_bounces": 1}'
    shipped = auto._arrays(load_table(str(auto.DEFAULT_TABLE)))
    cheap, acc = pass_variants(shipped, AutoOptions().auto_tolerance)
    assert (shipped.keys[cheap], shipped.keys[acc]) == (_key(IB_AUTO), _key(RAYS4))


def test_the_pass_weight_is_a_ramp_in_the_divergence():
    """1 below DIVERGENCE[0], 0 above DIVERGENCE[1], linear between (continuous); a single
    pick (auto_blend: false) switches at the middle."""
    from torchrefract.auto import DIVERGENCE

    lo, hi = DIVERGENCE
    ds = np.linspace(0, 2 * hi, 401)
    w = np.array([pass_weight(d) for d in ds])
    assert w[ds <= lo].min() == 1 and w[ds >= hi].max() == 0
    slope = (ds[1] - ds[0]) / (hi - lo)
    assert (np.diff(w) <= 0).all() and np.abs(np.diff(w)).max() <= slope + 1e-12
    assert pass_weight(0.5 * (lo + hi)) == pytest.approx(0.5)
    crisp = np.array([pass_weight(d, blend=False) for d in ds])
    assert set(crisp) == {0.0, 1.0} and crisp[ds < 0.5 * (lo + hi) - 1e-9].min() == 1


def test_divergence_of_two_pass_images():
    """The mean over object pixels of the largest channel difference of the sRGB previews:
    0 for equal images and without object pixels; a known difference is measured."""
    from torchrefract.auto_pass import divergence, srgb01

    rng = np.random.default_rng(0)
    a = rng.uniform(0, 1, (8, 8, 3)).astype(np.float32)
    cov = np.zeros((8, 8))
    cov[2:6, 2:6] = 1
    assert divergence(a, a, cov) == 0 and divergence(a, 2 * a, np.zeros((8, 8))) == 0
    b = a.copy()
    b[..., 1] = 0  # green off: the largest difference is the green preview's
    expect = (srgb01(a)[..., 1] - srgb01(b)[..., 1])[2:6, 2:6].mean()
    assert divergence(a, b, cov) == pytest.approx(expect, abs=1e-12) and expect > 0.2
    b[0, 0] = 0  # outside the object: not counted
    assert divergence(a, b, cov) == pytest.approx(expect, abs=1e-12)


def test_the_pass_renders_the_weighted_sum_and_records_its_evidence(tmp_path, monkeypatch):
    """With the shipped table the first pass compares one and four bounce rays on the scene
    itself: a divergence below the ramp renders the cheap variant alone, above it the
    accurate one, inside it both with the ramp's weights (``auto_regions: false``: over the
    whole object); the sidecar carries the divergence with the table's prediction."""
    import torchrefract.auto as auto
    from torchrefract.output.export import save_render

    scene = _scene(roughness=0.15, auto_regions=False)
    d = choose_by_pass([scene])[0].divergence
    assert d > 0
    parts = {_key(m): tr.render([scene.replace(method=m[0], method_options=m[1])]).radiance
             for m in (IB_AUTO, RAYS4)}
    for ramp, expect in [((d + 0.01, d + 0.02), {_key(IB_AUTO): 1.0}),
                         ((d - 0.02, d - 0.01), {_key(RAYS4): 1.0}),
                         ((d - 0.01, d + 0.03), {_key(IB_AUTO): 0.75, _key(RAYS4): 0.25})]:
        monkeypatch.setattr(auto, "DIVERGENCE", ramp)
        out = tr.render([scene])
        got = {_key(b[:2]): b[2] for b in out.blends[0]}
        assert got.keys() == expect.keys()
        assert all(got[k] == pytest.approx(w) for k, w in expect.items())
        img = sum(w * parts[_key((m, o))] for m, o, w in out.blends[0])
        assert torch.allclose(out.radiance, img, rtol=1e-5, atol=1e-6)
    pred = json.loads(save_render(out, 0, tmp_path)["json"].read_text())["auto_prediction"]
    assert pred["divergence"] == pytest.approx(d) and pred["divergence_ramp"] == [d - 0.01,
                                                                                  d + 0.03]
    assert pred["pass_ms"] > 0 and len(pred["neighbours"]) == NEIGHBOURS
    assert pred["best_predicted_flip"] <= pred["predicted_flip"] + 1e-12


def test_inside_the_ramp_each_variant_renders_where_it_weighs(monkeypatch):
    """``auto_regions`` (the default): inside the ramp each variant's weight is a map of
    the scene's pixels from the pass's local divergence, adding up to 1; a variant renders
    only where its map is above 0 (the region's pixels as its whole render's, every pixel
    shaded), and the image is the per-pixel weighted sum. The maps slide with the
    scene-level weight: at its ends a single variant weighs everywhere."""
    import torchrefract.auto as auto
    from torchrefract.auto_pass import local_ramp, region_weights

    scene = _scene(roughness=0.15)
    d = choose_by_pass([scene])[0].divergence
    monkeypatch.setattr(auto, "DIVERGENCE", (d - 0.01, d + 0.01))  # half and half
    c = choose_by_pass([scene])[0]
    assert c.maps is not None and len(c.maps) == len(c.blend) == 2
    total = c.maps[0] + c.maps[1]
    assert torch.allclose(total, torch.ones_like(total), atol=1e-6)
    shares = [float((m > 0).float().mean()) for m in c.maps]
    assert min(shares) < 1.0  # the split saves shading: a variant skips some pixels
    assert c.record()["region_shares"] == pytest.approx(shares)
    flat = tr.RenderSettings(adaptive=False)
    parts = {_key(m): tr.render([scene.replace(method=m[0], method_options=m[1])],
                                settings=flat).radiance[0] for m in (IB_AUTO, RAYS4)}
    out = tr.render([scene], settings=flat)
    img = sum(m[..., None] * parts[_key(b[:2])] for m, b in zip(c.maps, c.blend))
    assert torch.allclose(out.radiance[0], img, rtol=1e-5, atol=1e-6)
    # the weights at the scene-level weight's ends, and their continuity in it
    r = torch.linspace(0, 1, 11)
    assert torch.equal(region_weights(r, 0.0), torch.zeros(11))
    assert torch.equal(region_weights(r, 1.0), torch.ones(11))
    steps = [region_weights(r, w) for w in torch.linspace(0, 1, 101).tolist()]
    assert max(float((a - b).abs().max()) for a, b in zip(steps, steps[1:])) <= 0.021
    # the local ramp: a uniform divergence map gives the scene's own ramp value everywhere
    cov = np.zeros((8, 8))
    cov[2:6, 2:6] = 1
    lr = local_ramp(np.full((8, 8), 0.5 * (d - 0.01 + d + 0.01)), cov, (24, 24),
                    (d - 0.01, d + 0.01))
    assert lr.shape == (24, 24) and torch.allclose(lr, torch.full((24, 24), 0.5), atol=1e-5)


def test_a_region_render_shades_only_its_pixels():
    """render's regions (a policy's variants): the pixels inside equal the whole render's
    where every pixel is shaded; outside, the object's pixels keep the background's zero
    and the method's passes are 0; with adaptive shading the region's pixels stay within
    the interpolation's reach of the whole render's."""
    from torchrefract.methods import registry
    from torchrefract.render import _render_method
    from torchrefract.settings import using

    scene = _scene(roughness=0.2).replace(method="rousiers", method_options={})
    entry = registry.get("rousiers")
    options = entry.parse({}, None)
    region = torch.zeros(24, 24, dtype=torch.bool)
    region[:, :12] = True
    for adaptive, tol in ((False, 0.0), (True, 0.05)):
        with using(tr.RenderSettings(adaptive=adaptive)):
            whole = _render_method([scene], entry, options)
            part = _render_method([scene], entry, options, [region])
        obj = whole.coverage[0] > 0
        inside, outside = obj & region, obj & ~region
        assert int(inside.sum()) > 20 and int(outside.sum()) > 20
        diff = (part.radiance[0] - whole.radiance[0]).abs().amax(-1)
        scale = whole.radiance[0].amax(-1).clamp(min=1e-3)
        assert float((diff / scale)[inside].max()) <= tol + 1e-6
        if not adaptive:
            assert float(part.radiance[0][outside].abs().max()) == 0.0
            assert float(part.passes["exit_found"][0][outside].abs().max()) == 0.0
        assert torch.equal(part.coverage, whole.coverage)


def test_the_pass_is_per_scene_in_a_mixed_batch():
    """Scenes of other resolutions and materials in one batch each get their own pass: the
    same choice as alone, in batch order."""
    a = _scene(roughness=0.0)
    b = _scene(mesh=SLAB, roughness=0.3).replace(
        camera=tr.Camera(eye=(0.4, 0.3, 3.0), width=40, height=20))
    both = choose_by_pass([a, b, a])
    alone = [choose_by_pass([s])[0] for s in (a, b)]
    assert [c.blend for c in both] == [alone[0].blend, alone[1].blend, alone[0].blend]
    assert [c.divergence for c in both] == pytest.approx(
        [alone[0].divergence, alone[1].divergence, alone[0].divergence])


def test_the_ramp_fit_scores_blends_and_keeps_to_its_rules():
    """scripts/fit_auto_pass.py: a scene below the ramp costs the cheap variant and the pass,
    one above the accurate one, one inside both (its FLIP the weighted mean); the worst gap is
    against the accurate variant."""
    import importlib.util

    from conftest import ROOT

    spec = importlib.util.spec_from_file_location(
        "fit_auto_pass", ROOT / "scripts" / "fit_auto_pass.py")
    f = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(f)
    keys = (_key(IB_AUTO), _key(RAYS4))
    meas = {n: {keys[0]: (0.30, 100.0), keys[1]: (0.20, 200.0)} for n in "abc"}
    ev = {"a": (0.01, 5.0), "b": (0.03, 5.0), "c": (0.02, 5.0)}
    r = f.score(0.01, 0.03, list("abc"), ev, meas, keys)  # weights of one ray: 1, 0, 0.5
    assert r["flip"] == pytest.approx((0.30 + 0.20 + 0.25) / 3)
    assert r["ms"] == pytest.approx((100 + 200 + 300) / 3 + 5)
    assert r["worst"] == pytest.approx(0.10) and r["worst_scene"] == "a"
    assert r["accurate_flip"] == pytest.approx(0.20) and r["cheap_scenes"] == 2
    assert f.MIN_HI >= 0.03 and f.WORST == 0.03  # the suite's and the bounds

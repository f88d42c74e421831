"""The command line and the Python API end to end: real renders, real files."""

from __future__ import annotations

import importlib
import json
import subprocess
import sys

import numpy as np
import pytest
import torch
from conftest import ROOT, small_scene_yaml
from PIL import Image

import torchrefract as tr
from torchrefract.cli import main
from torchrefract.methods.base import Planned
from torchrefract.output.images import read_exr

_small_scene_yaml = small_scene_yaml


def test_cli_render_writes_exr_png_json(tmp_path):
    scene = _small_scene_yaml(tmp_path)
    out = tmp_path / "out"
    assert main(["render", str(scene), "--out", str(out), "--quiet"]) == 0
    ch = read_exr(out / "small.exr")
    for c in ("R", "G", "B", "A", "depth_front", "depth_back", "normal_front.X",
              "normal_back.Z", "thickness", "exit_found", "tir"):
        assert c in ch, c
        assert ch[c].shape == (32, 40) and np.isfinite(ch[c]).all()
    a = ch["A"]
    assert 0.05 < a.mean() < 0.9 and a.min() >= 0 and a.max() <= 1
    # Thickness and depths are positive on the object, zero off it.
    assert (ch["thickness"][a == 1] > 0).all() and (ch["depth_front"][a == 0] == 0).all()
    assert (ch["depth_back"][a == 1] > ch["depth_front"][a == 1]).all()
    png = np.asarray(Image.open(out / "small.png"))
    assert png.shape == (32, 40, 3) and png.dtype == np.uint8
    meta = json.loads((out / "small.json").read_text())
    assert meta["scene"]["camera"]["width"] == 40 and meta["torch_threads"] >= 1
    assert meta["torchrefract_version"] == tr.__version__
    # The EXR holds exactly what the API returns.
    api = tr.render([tr.load_scene(scene)])
    assert np.allclose(ch["R"], api.radiance[0, ..., 0].numpy(), atol=1e-6)


def test_cli_reports_bad_scene_and_renders_the_rest(tmp_path, capsys):
    good = _small_scene_yaml(tmp_path, "good")
    bad = _small_scene_yaml(tmp_path, "bad", material={"ior": -1.0})
    out = tmp_path / "out"
    assert main(["render", str(good), str(bad), "--out", str(out), "--quiet"]) == 1
    err = capsys.readouterr().err
    assert "bad.yaml" in err and "material.ior" in err and "-1.0" in err
    assert (out / "good.exr").is_file() and not (out / "bad.exr").exists()
    assert not list(out.glob(".*tmp*"))  # no temporary files left behind


def test_cli_survives_an_unexpected_failure_and_renders_the_rest(tmp_path, capsys,
                                                                  monkeypatch):
    """A render that fails other than by bad input (here one scene's render raises in a
    batch) fails that scene alone: the batch is tried scene by scene, the others are
    written, and the failure is named with its type. An output name that cannot be written
    fails its own scene too."""
    render_mod = importlib.import_module("torchrefract.render")  # the module, not tr.render
    good = _small_scene_yaml(tmp_path, "good")
    broken = _small_scene_yaml(tmp_path, "broken")
    real = render_mod.render

    def flaky(scenes, *a, **k):
        if any(s.name == "broken" for s in scenes):
            raise RuntimeError("kernel exploded")
        return real(scenes, *a, **k)

    monkeypatch.setattr(render_mod, "render", flaky)
    out = tmp_path / "out"
    assert main(["render", str(good), str(broken), "--out", str(out), "--quiet"]) == 1
    err = capsys.readouterr().err
    assert "FAILED broken: RuntimeError: kernel exploded" in err
    assert (out / "good.exr").is_file() and not (out / "broken.exr").exists()
    def interrupted(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(render_mod, "render", interrupted)
    assert main(["render", str(good), "--out", str(out), "--quiet"]) == 130  # no traceback
    assert "render interrupted" in capsys.readouterr().err
    monkeypatch.setattr(render_mod, "render", real)
    long = _small_scene_yaml(tmp_path, "x" * 240)  # its temporary names stay legal too
    assert main(["render", str(long), "--out", str(out), "--quiet"]) == 0
    assert (out / ("x" * 240 + ".exr")).is_file()
    assert not list(out.glob(".*tmp*"))


def test_cli_saves_a_batchs_frames_in_threads_and_a_failure_stays_its_own(
        tmp_path, capsys, monkeypatch):
    """A batch's frames are written in threads (their encoding took longer than the
    render); a frame whose files cannot be written fails alone, in the batch's order."""
    import threading

    import torch

    export = importlib.import_module("torchrefract.output.export")
    real, seen = export.save_render, []

    def save(result, i, *rest):
        seen.append(threading.current_thread().name)
        if result.scenes[i].name == "bad":
            raise OSError("disk said no")
        return real(result, i, *rest)

    monkeypatch.setattr(export, "save_render", save)
    paths = [str(_small_scene_yaml(tmp_path, n)) for n in ("a", "bad", "c")]
    out = tmp_path / "out"
    threads = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        assert main(["render", *paths, "--out", str(out), "--quiet"]) == 1
    finally:
        torch.set_num_threads(threads)
    assert "FAILED bad: OSError: disk said no" in capsys.readouterr().err
    assert (out / "a.exr").is_file() and (out / "c.exr").is_file()
    assert not (out / "bad.exr").exists()
    assert len(seen) == 3 and all(n.startswith("torchrefract-save") for n in seen)


def test_cli_render_writes_the_exr_compression_asked_for(tmp_path, capsys):
    """``--exr-compression`` sets the EXR's compression and its JSON records it; a name it
    does not offer is a usage error (exit 2) naming the option."""
    import OpenEXR

    path = _small_scene_yaml(tmp_path, "z")
    out = tmp_path / "out"
    assert main(["render", str(path), "--out", str(out), "--quiet",
                 "--exr-compression", "zstd"]) == 0
    with OpenEXR.File(str(out / "z.exr")) as f:
        assert str(f.header()["compression"]).endswith("ZSTD_COMPRESSION")
    assert json.loads((out / "z.json").read_text())["exr_compression"] == "zstd"
    with pytest.raises(SystemExit) as exc:
        main(["render", str(path), "--out", str(out), "--exr-compression", "b44"])
    assert exc.value.code == 2 and "--exr-compression" in capsys.readouterr().err


def test_a_camera_inside_the_object_is_warned_of(tmp_path):
    """From inside the glass the two layers see nothing: such a view says so instead of
    returning the environment silently; a camera outside does not."""
    s = tr.load_scene(ROOT / "configs" / "suite" / "sphere_a03.yaml")
    s = s.replace(camera=tr.Camera(eye=(0.0, 0.3, 3.4), width=12, height=10))
    inside = s.replace(camera=tr.Camera(eye=(0.0, 0.0, 0.1), width=12, height=10))
    with pytest.warns(UserWarning, match="inside the mesh's bounds and sees none of it"):
        out = tr.render(inside)
    assert float(out.coverage.max()) == 0.0
    import warnings as _w

    with _w.catch_warnings():
        _w.simplefilter("error")
        tr.render(s)


def test_cli_entry_point_runs_as_a_program(tmp_path):
    scene = _small_scene_yaml(tmp_path)
    r = subprocess.run([sys.executable, "-m", "torchrefract.cli", "render", str(scene),
                        "--out", str(tmp_path / "o")], capture_output=True, text=True,
                       timeout=120)
    assert r.returncode == 0, r.stderr
    assert "rendered 1 frame(s)" in r.stdout
    assert "frame" in r.stderr  # the tqdm progress bar


def test_api_batch_shapes_and_per_scene_materials(tmp_path):
    s = tr.load_scene(_small_scene_yaml(tmp_path))
    scenes = [s.replace(material=tr.Material(ior=i, roughness=0.0)) for i in (1.0, 1.5, 2.0)]
    out = tr.render(scenes, method="specular")
    assert out.radiance.shape == (3, 32, 40, 3) and out.radiance.dtype == torch.float32
    assert out.coverage.shape == (3, 32, 40)
    assert all(v.shape[:3] == (3, 32, 40) for v in out.passes.values())
    # Same geometry: coverage equal; different IOR: different object pixels.
    assert torch.equal(out.coverage[0], out.coverage[1])
    obj = out.coverage[0] == 1
    assert (out.radiance[1] - out.radiance[2]).abs()[obj].mean() > 1e-3
    # Each batch item equals its own single render.
    single = tr.render([scenes[1]], method="specular")
    assert torch.allclose(single.radiance[0], out.radiance[1], atol=1e-5)


def test_api_rejects_mixed_resolutions_and_unknown_method(tmp_path):
    s = tr.load_scene(_small_scene_yaml(tmp_path))
    other = s.replace(camera=tr.Camera(width=20, height=20))
    with pytest.raises(tr.ConfigError, match="same camera.width"):
        tr.render([s, other])
    with pytest.raises(tr.ConfigError, match="unknown method 'nope'"):
        tr.render([s], method="nope")
    tr.register_method("planned_x", Planned("planned_x", "issue #0"))
    with pytest.raises(NotImplementedError, match="'planned_x' is not implemented yet"):
        tr.render([s], method="planned_x")
    with pytest.raises(tr.ConfigError, match="march_stepz"):
        tr.render([s.replace(method_options={"march_stepz": 3})])


def test_api_method_override_checks_its_own_options(tmp_path):
    """``render(..., method=M)`` checks the options against M, not the scenes' own method."""
    s = tr.load_scene(_small_scene_yaml(tmp_path)).replace(
        method="specular", method_options={"cone_rays": "plane"})  # a rousiers option
    out = tr.render([s], method="rousiers")
    assert torch.isfinite(out.radiance).all()
    with pytest.raises(tr.ConfigError, match="'cone_rays' for method 'specular'"):
        tr.render([s])


def test_supersampling_box_filters_edges(tmp_path):
    s = tr.load_scene(_small_scene_yaml(tmp_path))
    one = tr.render([s])
    cam = s.camera
    four = tr.render([s.replace(camera=tr.Camera(**{**cam.__dict__, "samples_per_pixel": 4}))])
    c1, c4 = one.coverage[0], four.coverage[0]
    frac = ((c4 > 0) & (c4 < 1)).float().mean()
    assert frac > 0.01  # fractional coverage on the silhouette
    assert ((c1 == 0) | (c1 == 1)).all()
    # Interior pixels agree closely, the mean coverage agrees within the edge band.
    assert abs(c1.mean() - c4.mean()) < frac


def test_cli_compare_prints_metrics_and_writes_error_map(tmp_path, capsys):
    import json as _json

    scene = _small_scene_yaml(tmp_path)
    a, b = tmp_path / "a", tmp_path / "b"
    assert main(["render", str(scene), "--out", str(a), "--quiet"]) == 0
    assert main(["render", str(scene), "--out", str(b), "--quiet", "--method",
                 "prefiltered"]) == 0
    capsys.readouterr()
    assert main(["compare", str(a / "small.exr"), str(a / "small.exr")]) == 0
    same = capsys.readouterr().out
    assert "relmse_object  0\n" in same and "flip_object    0\n" in same and "inf" in same
    err = tmp_path / "err.png"
    js = tmp_path / "m.json"
    assert main(["compare", str(b / "small.exr"), str(a / "small.exr"), "--error-map",
                 str(err), "--json", str(js)]) == 0
    m = _json.loads(js.read_text())
    assert m["flip_object"] > 0 and m["relmse_object"] > 0 and m["flip"] <= m["flip_object"]
    assert np.asarray(Image.open(err)).shape == (32, 40, 3)
    assert main(["compare", str(tmp_path / "missing.exr"), str(a / "small.exr")]) == 2


def test_cli_compare_refuses_what_it_cannot_score(tmp_path, capsys):
    """``compare``: an alpha covering nothing falls back to the test's, then to every
    pixel (not a perfect object score); NaN pixels and a non-finite exposure are refused;
    outputs go into folders it makes; its JSON is strict (an infinite PSNR is null)."""
    import json as _json

    from torchrefract.output.images import write_exr

    scene = _small_scene_yaml(tmp_path)
    a = tmp_path / "a"
    assert main(["render", str(scene), "--out", str(a), "--quiet"]) == 0
    ch = read_exr(a / "small.exr")
    rgb = {c: ch[c] for c in "RGB"}
    ref, test = tmp_path / "ref.exr", tmp_path / "test.exr"
    write_exr(ref, {**rgb, "A": np.zeros_like(ch["A"])})
    write_exr(test, {**rgb, "R": rgb["R"] * 1.5, "A": ch["A"]})
    js = tmp_path / "new" / "m.json"
    assert main(["compare", str(test), str(ref), "--json", str(js),
                 "--error-map", str(tmp_path / "new" / "e.png")]) == 0
    m = _json.loads(js.read_text())
    assert m["flip_object"] > 0 and np.isfinite(m["relmse_object"])
    js2 = tmp_path / "same.json"
    assert main(["compare", str(ref), str(ref), "--json", str(js2)]) == 0
    assert _json.loads(js2.read_text())["psnr"] is None
    write_exr(test, {**rgb, "R": np.where(ch["A"] > 0, np.nan, rgb["R"]).astype(np.float32)})
    capsys.readouterr()
    assert main(["compare", str(test), str(ref)]) == 2
    assert "NaN or infinite" in capsys.readouterr().err
    assert main(["compare", str(ref), str(ref), "--exposure", "nan"]) == 2


def test_cli_refuses_bad_flags_and_folders_up_front(tmp_path, capsys):
    """Bad flags, an --out that is a file or another tool's folder, and a config that is
    not text end with a message and exit 2, not a traceback."""
    from sweep_fixtures import small_sweep, write_config

    cfg = write_config(tmp_path / "s.yaml", small_sweep())
    (tmp_path / "afile").write_text("x")
    foreign = tmp_path / "mine"
    foreign.mkdir()
    (foreign / "000000.exr").write_text("precious")
    (tmp_path / "bin.yaml").write_bytes(b"\xff\xfe garbage")
    cases = [(["sweep", str(cfg), "--out", str(tmp_path / "afile")], "--out"),
             (["sweep", str(cfg), "--out", str(foreign)], "holds no sweep"),
             (["sweep", str(tmp_path / "bin.yaml"), "--out", str(tmp_path / "o")],
              "not UTF-8"),
             (["sweep", str(cfg), "--out", str(tmp_path / "o"), "--threads", "-1"],
              "threads"),
             (["render", str(cfg), "--out", str(tmp_path / "o"), "--device", "bogus"],
              "device")]
    if not torch.cuda.is_available():
        cases.append((["sweep", str(cfg), "--out", str(tmp_path / "o"), "--device", "cuda"],
                      "CUDA device"))
    for argv, said in cases:
        capsys.readouterr()
        assert main(argv + ["--quiet"]) == 2, argv
        assert said in capsys.readouterr().err, argv
    assert (foreign / "000000.exr").read_text() == "precious"


def test_memory_budget_chunks_a_batch_and_refuses_a_view_up_front(tmp_path):
    """RenderSettings.memory_budget_mb (TORCHREFRACT_MEMORY_MB): a batch is shaded in
    chunks of the views that fit the budget (the same pixels), and a view that does not
    fit even in tiles fails before any work, naming its size and the budget (a sweep
    records such a sample as failed with that reason)."""
    import importlib

    from torchrefract import tiles
    from torchrefract.settings import RenderSettings, using

    render_mod = importlib.import_module("torchrefract.render")
    s = tr.load_scene(str(ROOT / "configs" / "demo.yaml"))
    scenes = [s.replace(camera=tr.Camera(eye=(0.1 * i, 0.3, 3.0), width=64, height=64))
              for i in range(5)]
    per_view = tiles.pass_bytes(64 * 64, 64 * 64) - tiles.PASS_BYTES_FIXED  # untiled
    budget_mb = (2 * per_view + tiles.PASS_BYTES_FIXED) // (1 << 20) + 1  # two views per pass
    with using(RenderSettings(memory_budget_mb=budget_mb)):
        assert [len(c) for c in render_mod._chunks(scenes)] == [2, 2, 1]
    a = tr.render(scenes, settings=RenderSettings(memory_budget_mb=budget_mb))
    assert torch.equal(a.radiance, tr.render(scenes, settings=RenderSettings()).radiance)
    # A view too large for one pass is shaded in tiles (tests/test_tiles.py); one whose
    # G-buffer alone is over the budget renders in strips with the fused kernels
    # (tests/test_large.py) and fails up front with the tensor code.
    big = s.replace(camera=tr.Camera(width=512, height=512, samples_per_pixel=2))
    need = tiles.size_text(tiles.pass_bytes(512 * 512 * 4, tiles.MIN_TILE), up=True)
    with pytest.raises(tr.ConfigError, match=rf"512x512 view at samples_per_pixel 2 .*{need} "
                                             r"as one G-buffer, over the memory budget of "
                                             r"100 MB"):
        tr.render(big, settings=RenderSettings(memory_budget_mb=100, fused=False))
    with pytest.raises(tr.ConfigError, match="memory_budget_mb"):
        RenderSettings(memory_budget_mb=0)


@pytest.mark.parametrize("method, options", [("rousiers", {"internal_bounces": 1}),
                                             ("specular", {})])
def test_a_large_batch_renders_in_chunks_with_the_same_pixels(monkeypatch, method, options):
    """Batches above render.MAX_PASS_SUBPIXELS are shaded in consecutive chunks of views:
    the result equals the one-pass render, passes included, also where a chunk sees no
    object at all (its passes are the same set)."""
    import importlib
    render_mod = importlib.import_module("torchrefract.render")  # the module, not tr.render
    s = tr.load_scene(str(ROOT / "configs" / "demo.yaml"))
    cam = tr.Camera(eye=(0.0, 0.3, 3.0), width=24, height=20)
    away = tr.Camera(eye=(0.0, 0.3, 3.0), target=(0.0, 0.3, 6.0), width=24, height=20)
    scenes = [s.replace(camera=c, method=method, method_options=options,
                        envmap=tr.EnvMap(path=s.envmap.path, rotate_deg=15.0 * i))
              for i, c in enumerate([cam, cam, away, away, cam])]
    whole = tr.render(scenes)
    monkeypatch.setattr(render_mod, "MAX_PASS_SUBPIXELS", 2 * 24 * 20)
    assert [len(c) for c in render_mod._chunks(scenes)] == [2, 2, 1]
    chunked = tr.render(scenes)
    assert whole.coverage[2:4].sum() == 0 and whole.coverage[0].sum() > 20
    assert torch.equal(whole.radiance, chunked.radiance)
    assert torch.equal(whole.coverage, chunked.coverage)
    assert whole.passes.keys() == chunked.passes.keys()
    for k in whole.passes:
        assert torch.equal(whole.passes[k], chunked.passes[k]), k
    assert chunked.scenes == whole.scenes

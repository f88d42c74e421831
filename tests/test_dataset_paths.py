"""Datasets that travel: paths stored relative to the dataset folder, a moved or copied
dataset loading the same (torchrefract, webdataset, Hugging Face datasets), old manifests
with absolute paths, and errors naming a missing file."""

from __future__ import annotations

import io
import json
import shutil
import tarfile
from pathlib import Path

import pytest
import torch
import yaml
from conftest import ASSETS
from test_data import _same as _same_tensors
from PIL import Image

from torchrefract.checks import ConfigError
from torchrefract.dataset.loaders import RefractDataset, decode_exr, decode_wds
from torchrefract.dataset.paths import resolve_record
from torchrefract.dataset.run import run_sweep
from torchrefract.dataset.sweep import load_sweep

# A project: assets beside the config, both outside the dataset folders out/folder, out/wds.
INPUTS = {"globe.obj": ASSETS / "meshes" / "globe.obj",
          "globe_roughness.png": ASSETS / "textures" / "globe_roughness.png",
          "studio.exr": ASSETS / "envmaps" / "studio_small_03.exr",
          "park.exr": ASSETS / "envmaps" / "rooitou_park.exr"}
CONFIG = {
    "name": "travel",
    "base": {"mesh": "../assets/globe.obj", "envmap": {"path": "../assets/studio.exr"},
             "material": {"ior": 1.5, "roughness_map": "../assets/globe_roughness.png"},
             "camera": {"eye": [0, 0.3, 3.4], "width": 16, "height": 16},
             "method": "specular"},
    "sampling": {"mode": "grid", "seed": 5},
    "sweep": {"mesh": {"path": ["../assets/globe.obj"], "random_rotation": "yaw"},
              "material": {"ior": [1.33, 1.6]},
              "envmap": {"path": ["../assets/studio.exr", "../assets/park.exr"]}},
}  # 4 samples of 16x16


def _render_project(proj: Path) -> Path:
    (proj / "assets").mkdir(parents=True)
    for name, src in INPUTS.items():
        shutil.copy(src, proj / "assets" / name)
    (proj / "configs").mkdir()
    cfg = proj / "configs" / "travel.yaml"
    cfg.write_text(yaml.safe_dump(CONFIG, sort_keys=False))
    assert run_sweep(cfg, proj / "out" / "folder", batch_size=4, quiet=True).ok == 4
    assert run_sweep(cfg, proj / "out" / "wds", fmt="webdataset", shard_size=2, batch_size=4,
                     quiet=True).ok == 4
    return proj


@pytest.fixture(scope="module")
def project(tmp_path_factory) -> Path:
    return _render_project(tmp_path_factory.mktemp("project") / "proj")


def _items(root: Path) -> list[dict]:
    ds = RefractDataset(root)
    return [ds[i] for i in range(len(ds))]


def _same(a: dict, b: dict, meta: bool = True) -> None:
    _same_tensors(a, b, meta=meta)


def _shard_json(shard: Path) -> list[dict]:
    with tarfile.open(shard) as t:
        return [json.loads(t.extractfile(n).read()) for n in t.getnames()
                if n.endswith(".json")]


# ----------------------------------------------------------------------- what is written

def test_metadata_paths_are_relative_to_the_dataset_folder(project):
    texts = {}
    for fmt in ("folder", "wds"):
        out = project / "out" / fmt
        texts[f"{fmt}/manifest"] = (out / "manifest.jsonl").read_text()
        texts[f"{fmt}/sweep.json"] = (out / "sweep.json").read_text()
        lines = [json.loads(ln) for ln in texts[f"{fmt}/manifest"].splitlines()]
        assert len(lines) == 4
        for e in lines:
            s = e["scene"]
            assert s["mesh"] == e["params"]["mesh"] == "../../assets/globe.obj"
            assert s["material"]["roughness_map"] == "../../assets/globe_roughness.png"
            assert s["envmap"]["path"] == e["params"]["envmap.path"]
            assert s["envmap"]["path"] in ("../../assets/studio.exr", "../../assets/park.exr")
        if fmt == "folder":
            assert {e["files"]["exr"] for e in lines} == {f"{i:06d}.exr" for i in range(4)}
        else:
            assert {e["shard"] for e in lines} == {"shard-000000.tar", "shard-000001.tar"}
            for shard in sorted(out.glob("shard-*.tar")):
                for j in _shard_json(shard):
                    texts[f"{shard.name}/{j['sample_id']}.json"] = json.dumps(j)
                    assert j["scene"]["mesh"] == "../../assets/globe.obj"
        rec = json.loads(texts[f"{fmt}/sweep.json"])
        assert rec["source"] == "../../configs/travel.yaml"
        assert rec["base_scene"]["envmap"]["path"] == "../../assets/studio.exr"
        assert rec["config"] == CONFIG  # the config as written (paths relative to it)
    # No path of this machine anywhere in the metadata a loader reads.
    where = str(project.resolve())
    for name, text in texts.items():
        assert where not in text, name


# ----------------------------------------------------------------------- moved or copied

def test_a_moved_project_loads_resumes_and_rerenders(project, tmp_path):
    here = tmp_path / "a" / "proj"
    shutil.copytree(project, here)
    before = {fmt: _items(here / "out" / fmt) for fmt in ("folder", "wds")}
    moved = tmp_path / "b" / "deeper" / "proj"
    moved.parent.mkdir(parents=True)
    shutil.move(here, moved)
    assert not here.exists()
    cfg = load_sweep(moved / "configs" / "travel.yaml")
    for fmt in ("folder", "wds"):
        out = moved / "out" / fmt
        after = _items(out)
        assert len(after) == 4
        for a, b in zip(before[fmt], after):
            _same(a, b)
        # Its inputs resolve at the new place, to the very scenes the config gives there.
        ds = RefractDataset(out)
        for i in range(4):
            scene = ds.scene(i)
            assert scene.mesh == str((moved / "assets" / "globe.obj").resolve())
            assert scene == cfg.sample(i).scene
        # The run resumes there: every sample is complete.
        s = run_sweep(moved / "configs" / "travel.yaml", out,
                      fmt="webdataset" if fmt == "wds" else "folder", shard_size=2,
                      quiet=True)
        assert (s.skipped, s.ok, s.failed) == (4, 0, 0)
    for a, b in zip(before["folder"], before["wds"]):  # both formats hold the same samples
        _same(a, b, meta=False)


def test_a_dataset_copied_alone_loads_and_names_what_is_missing(project, tmp_path):
    for fmt in ("folder", "wds"):
        alone = tmp_path / fmt
        shutil.copytree(project / "out" / fmt, alone)
        ds = RefractDataset(alone)
        for a, b in zip(_items(project / "out" / fmt), _items(alone)):
            _same(a, b)
        with pytest.raises(ConfigError, match=r"sample 000000: input file\(s\) not found: "
                                              r"'\.\./\.\./assets/globe\.obj'"):
            ds.scene(0)
    (tmp_path / "folder" / "000002.exr").unlink()
    with pytest.raises(ConfigError, match=r"sample 000002: file '000002\.exr' is missing"):
        RefractDataset(tmp_path / "folder")[2]
    (tmp_path / "wds" / "shard-000001.tar").unlink()
    ds = RefractDataset(tmp_path / "wds")
    ds[1]  # shard 0 is there
    with pytest.raises(ConfigError, match=r"file 'shard-000001\.tar' is missing"):
        ds[3]


def test_an_old_manifest_with_absolute_paths_loads_and_resumes(project, tmp_path):
    """What the code before relative paths wrote: absolute input paths, absolute source."""
    proj = tmp_path / "proj"
    shutil.copytree(project, proj)
    out = proj / "out" / "folder"
    lines = [json.loads(ln) for ln in (out / "manifest.jsonl").read_text().splitlines()]
    old = [resolve_record(e, out) for e in lines]
    assert old[0]["scene"]["mesh"] == str((proj / "assets" / "globe.obj").resolve())
    assert old[0]["params"]["envmap.path"].startswith(str(proj.resolve()))
    rec = json.loads((out / "sweep.json").read_text())
    rec["source"] = str(proj / "configs" / "travel.yaml")
    (out / "sweep.json").write_text(json.dumps(rec))
    # The run was cut short: sample 3 has no line and no files.
    (out / "manifest.jsonl").write_text("".join(json.dumps(e) + "\n" for e in old[:3]))
    (out / "000003.exr").unlink()
    (out / "000003.png").unlink()
    s = run_sweep(proj / "configs" / "travel.yaml", out, quiet=True)
    assert (s.skipped, s.ok) == (3, 1)
    got = [json.loads(ln) for ln in (out / "manifest.jsonl").read_text().splitlines()]
    assert [e["scene"]["mesh"] for e in got] == [old[0]["scene"]["mesh"]] * 3 + [
        "../../assets/globe.obj"]  # old lines kept, the new one relative
    ds = RefractDataset(out)
    for i, (a, b) in enumerate(zip(_items(project / "out" / "folder"), _items(out))):
        _same(a, b, meta=False)
        assert resolve_record(a["meta"], out)["scene"] == resolve_record(b["meta"], out)["scene"]
        assert ds.scene(i) == load_sweep(proj / "configs" / "travel.yaml").sample(i).scene
    shutil.rmtree(proj / "assets")  # the inputs are gone: each kind of record says so
    with pytest.raises(ConfigError, match="globe.obj.*holds absolute paths"):
        ds.scene(0)
    with pytest.raises(ConfigError, match="globe.obj.*relative to its folder"):
        ds.scene(3)


# ----------------------------------------------------------------------- other loaders

def test_webdataset_reads_a_copied_shard(project, tmp_path):
    wds = pytest.importorskip("webdataset")
    shutil.copytree(project / "out" / "wds", tmp_path / "wds")
    shard = tmp_path / "wds" / "shard-000000.tar"
    raw = list(wds.WebDataset(str(shard), shardshuffle=False))
    assert [x["__key__"] for x in raw] == ["000000", "000001"]
    ref = _items(project / "out" / "folder")
    for i, x in enumerate(raw):
        meta = json.loads(x["json"])
        assert meta["sample_id"] == f"{i:06d}"
        assert meta["scene"]["mesh"] == "../../assets/globe.obj"
        assert x["exr"][:4] == b"\x76\x2f\x31\x01"  # OpenEXR magic
        assert x["png"] == (project / "out" / "folder" / f"{i:06d}.png").read_bytes()
        _same(ref[i], decode_wds(x), meta=False)
        assert decode_wds(x)["meta"]["params"] == ref[i]["meta"]["params"]


def test_hugging_face_datasets_reads_a_shard(project, tmp_path, monkeypatch):
    for k, v in (("HF_HOME", tmp_path / "hf_home"), ("HF_HUB_OFFLINE", "1"),
                 ("HF_DATASETS_OFFLINE", "1")):
        monkeypatch.setenv(k, str(v))
    datasets = pytest.importorskip("datasets")
    shard = project / "out" / "wds" / "shard-000001.tar"
    ds = datasets.load_dataset("webdataset", data_files={"train": [str(shard)]},
                               split="train", cache_dir=str(tmp_path / "hf_cache"))
    ds = ds.cast_column("png", datasets.Image(decode=False))
    assert len(ds) == 2 and ds["__key__"] == ["000002", "000003"]
    with tarfile.open(shard) as t:
        members = {n: t.extractfile(n).read() for n in t.getnames()}
    ref = RefractDataset(project / "out" / "folder")
    for row in ds:
        sid = row["__key__"]
        meta = row["json"]  # decoded by datasets
        stored = json.loads(members[f"{sid}.json"])
        assert meta["sample_id"] == sid and meta["params"] == stored["params"]
        assert meta["scene"]["mesh"] == "../../assets/globe.obj"
        assert meta["camera"]["K"] == stored["camera"]["K"]
        assert row["exr"] == members[f"{sid}.exr"]
        assert row["png"]["bytes"] == members[f"{sid}.png"]
        assert Image.open(io.BytesIO(row["png"]["bytes"])).size == (16, 16)
        x = ref[int(sid)]
        got = decode_exr(row["exr"], meta["channels"])
        assert torch.equal(got["radiance"], x["radiance"])
        assert torch.equal(got["passes"]["depth_front"], x["passes"]["depth_front"])

"""Training-side API: RefractDataset over folders and shards, RenderStream in a DataLoader."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap

import numpy as np
import pytest
import torch
from conftest import ROOT
from sweep_fixtures import small_sweep, write_config
from torch.utils.data import DataLoader

from torchrefract.checks import ConfigError
from torchrefract.dataset.loaders import RefractDataset, RenderStream, collate, decode_wds
from torchrefract.dataset.paths import resolve_record
from torchrefract.dataset.run import run_sweep
from torchrefract.output.images import read_exr


@pytest.fixture(scope="module")
def cfg_path(tmp_path_factory):
    return write_config(tmp_path_factory.mktemp("cfg") / "small.yaml", small_sweep())


@pytest.fixture(scope="module")
def folder(cfg_path, tmp_path_factory):
    out = tmp_path_factory.mktemp("folder")
    assert run_sweep(cfg_path, out, batch_size=4, quiet=True).ok == 8
    return out


@pytest.fixture(scope="module")
def shards(cfg_path, tmp_path_factory):
    out = tmp_path_factory.mktemp("shards")
    assert run_sweep(cfg_path, out, fmt="webdataset", shard_size=3, batch_size=4,
                     quiet=True).ok == 8
    return out


def _same(a: dict, b: dict, meta: bool = False) -> None:
    """Two loaded samples hold the same tensors (and with ``meta`` the same record)."""
    assert a["sample_id"] == b["sample_id"]
    for k in ("radiance", "coverage", "K", "world_to_camera"):
        assert torch.equal(a[k], b[k]), k
    assert a["passes"].keys() == b["passes"].keys()
    for n in a["passes"]:
        assert torch.equal(a["passes"][n], b["passes"][n]), n
    if meta:
        assert a["meta"] == b["meta"]


def test_refract_dataset_over_a_folder(folder):
    ds = RefractDataset(folder)
    assert len(ds) == 8 and ds.failed == []
    x = ds[5]
    assert x["sample_id"] == "000005"
    assert x["radiance"].shape == (3, 32, 32) and x["radiance"].dtype == torch.float32
    assert x["coverage"].shape == (1, 32, 32)
    assert x["passes"]["normal_front"].shape == (3, 32, 32)
    assert x["passes"]["depth_back"].shape == (1, 32, 32)
    assert {"depth_front", "thickness", "roughness", "ior"} <= set(x["passes"])
    assert x["K"].shape == (3, 3) and x["world_to_camera"].shape == (4, 4)
    assert x["meta"]["params"]["index"] == 5
    # Values are the EXR's channels, untouched.
    ch = read_exr(folder / "000005.exr")
    assert np.array_equal(x["radiance"][1].numpy(), ch["G"])
    assert np.array_equal(x["passes"]["normal_front"][2].numpy(), ch["normal_front.Z"])
    # Channels-last layout and a subset of passes.
    y = RefractDataset(folder, layout="hwc", passes=["depth_front"])[5]
    assert torch.equal(y["radiance"], x["radiance"].permute(1, 2, 0))
    assert list(y["passes"]) == ["depth_front"] and y["passes"]["depth_front"].shape == (
        32, 32, 1)
    with pytest.raises(IndexError):
        ds[8]
    with pytest.raises(ConfigError, match="layout"):
        RefractDataset(folder, layout="nchw")
    with pytest.raises(ConfigError, match=r"no pass 'nope' \(it has \[.*'depth_front'"):
        RefractDataset(folder, passes=["depth_front", "nope"])  # at once, not in a worker
    with pytest.raises(ConfigError, match="no manifest.jsonl"):
        RefractDataset(ROOT / "configs")


def test_webdataset_round_trip(folder, shards):
    assert len(list(shards.glob("shard-*.tar"))) == 3
    a, b = RefractDataset(folder), RefractDataset(shards)
    assert len(b) == 8
    for i in range(8):
        _same(a[i], b[i])
    # The shards also stream with the webdataset package itself.
    wds = pytest.importorskip("webdataset")
    urls = [str(p) for p in sorted(shards.glob("shard-*.tar"))]
    stream = wds.WebDataset(urls, shardshuffle=False).map(decode_wds)
    got = list(stream)
    assert [x["sample_id"] for x in got] == [f"{i:06d}" for i in range(8)]
    for i, x in enumerate(got):
        _same(a[i], x)
        assert x["meta"]["params"] == a[i]["meta"]["params"]


def test_collate_keeps_metadata_as_a_list(folder):
    ds = RefractDataset(folder)
    batch = next(iter(DataLoader(ds, batch_size=4, collate_fn=collate)))
    assert batch["radiance"].shape == (4, 3, 32, 32)
    assert batch["passes"]["normal_back"].shape == (4, 3, 32, 32)
    assert batch["sample_id"] == ["000000", "000001", "000002", "000003"]
    assert [m["index"] for m in batch["meta"]] == [0, 1, 2, 3]
    a, b = ds[0], ds[1]
    b["passes"] = dict(b["passes"], blur_sigma=b["passes"]["ior"])  # another method's pass
    with pytest.raises(ConfigError, match="different passes"):
        collate([a, b])
    b = dict(ds[1], radiance=torch.zeros(3, 16, 16))
    with pytest.raises(ConfigError, match="different sizes"):
        collate([a, b])


def test_render_stream_equals_the_written_dataset(cfg_path, folder):
    stream = RenderStream(cfg_path, batch_size=3)
    assert len(stream) == 8
    got = list(stream)
    ds = RefractDataset(folder)
    assert len(got) == 8
    for i, x in enumerate(got):
        _same(ds[i], x)
        # The stream's paths are absolute, the dataset's relative to its folder.
        assert x["meta"]["params"] == resolve_record(ds[i]["meta"], folder)["params"]
        stream_scene = json.loads(json.dumps(x["meta"]["scene"]))  # tuples -> lists
        assert stream_scene == resolve_record(ds[i]["meta"], folder)["scene"]


def test_render_stream_in_a_dataloader_with_two_workers(tmp_path):
    d = small_sweep()
    d["sampling"] = {"mode": "random", "seed": 1, "num_samples": 6}
    cfg = write_config(tmp_path / "r.yaml", d)

    # Spawned workers (each creates its own EGL context), kept for the second epoch.
    loader = DataLoader(RenderStream(cfg, batch_size=2, threads=1), batch_size=2,
                        num_workers=2, collate_fn=collate, multiprocessing_context="spawn",
                        persistent_workers=True)

    def epoch():
        return [_unbatch(batch) for batch in loader]

    batches = epoch()
    first = [x for b in batches for x in b]
    ids = [x["sample_id"] for x in first]
    assert sorted(ids) == [f"{i:06d}" for i in range(6)]  # distinct, none missing
    # Worker w of 2 takes indices w, w + 2, ...; the loader alternates between workers.
    assert [[x["meta"]["index"] for x in b] for b in batches] == [[0, 2], [1, 3], [4], [5]]
    second = {x["sample_id"]: x for b in epoch() for x in b}
    here = {x["sample_id"]: x for x in RenderStream(cfg, batch_size=6)}
    for x in first:  # reproducible from the seed, in any process and batch size
        _same(x, second[x["sample_id"]])
        _same(x, here[x["sample_id"]])
        assert x["meta"]["params"] == here[x["sample_id"]]["meta"]["params"]
    # More samples of a random sweep than the config's count: the first ones are the same.
    longer = RenderStream(cfg, num_samples=7, batch_size=4)
    assert len(longer) == 7
    assert [x["sample_id"] for x in longer][-1] == "000006"


def _unbatch(batch: dict) -> list[dict]:
    n = len(batch["sample_id"])
    return [{"sample_id": batch["sample_id"][i], "meta": batch["meta"][i],
             "radiance": batch["radiance"][i], "coverage": batch["coverage"][i],
             "K": batch["K"][i], "world_to_camera": batch["world_to_camera"][i],
             "passes": {k: v[i] for k, v in batch["passes"].items()}} for i in range(n)]


def test_render_stream_skips_broken_samples_with_a_warning(tmp_path):
    broken = tmp_path / "broken.ply"
    broken.write_bytes(b"garbage")
    d = small_sweep()
    d["sweep"]["mesh"]["path"] = [str(ROOT / "assets" / "meshes" / "spot.ply"), str(broken)]
    d["sweep"]["material"]["ior"] = [1.5]
    d["sweep"]["envmap"]["path"] = d["sweep"]["envmap"]["path"][:1]
    cfg = write_config(tmp_path / "b.yaml", d)  # 2 meshes x 2 azimuths
    with pytest.warns(RuntimeWarning, match="broken.ply"):
        got = list(RenderStream(cfg, batch_size=4))
    assert [x["sample_id"] for x in got] == ["000000", "000001"]
    with pytest.raises(RuntimeError, match="sample 000002 failed"):
        list(RenderStream(cfg, batch_size=4, on_error="raise"))


@pytest.mark.parametrize("rasterizer", ["native", "opengl"])
def test_forked_worker_after_rendering(cfg_path, rasterizer):
    """A fork-started DataLoader after the main process rendered: with the native
    rasterizer (no EGL context) the worker renders; after the OpenGL passes (an EGL
    context, which hangs in a forked child) a clear error, no hang."""
    code = textwrap.dedent(f"""
        import torch, torchrefract as tr
        from torch.utils.data import DataLoader
        from torchrefract.dataset.loaders import RenderStream
        s = RenderStream({str(cfg_path)!r}, batch_size=2)
        next(iter(s))
        try:
            got = list(DataLoader(s, num_workers=1, multiprocessing_context="fork",
                                  collate_fn=lambda b: b))
            print("RENDERED", sum(len(b) for b in got) == len(s))
        except RuntimeError as e:
            print("RAISED", "multiprocessing_context='spawn'" in str(e))
    """)
    env = dict(os.environ, TORCHREFRACT_RASTERIZER=rasterizer)
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                       timeout=120, env=env)
    want = "RENDERED True" if rasterizer == "native" else "RAISED True"
    assert want in r.stdout, r.stdout[-500:] + r.stderr[-2000:]

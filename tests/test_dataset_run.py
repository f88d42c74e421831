"""The dataset runner: files, manifest, determinism, resume after kill -9, failures, shards,
local worker processes and Ray."""

from __future__ import annotations

import hashlib
import json
import os
import signal
import subprocess
import sys
import tarfile
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import ROOT
from sweep_fixtures import SPOT, STUDIO, small_sweep, write_config

import torchrefract as tr
from torchrefract.checks import ConfigError
from torchrefract.cli import main
from torchrefract.dataset.run import _Lock, read_manifest, run_sweep
from torchrefract.dataset.sweep import load_sweep
from torchrefract.output.export import exr_channels
from torchrefract.output.images import read_exr, write_exr

CHANNELS = ("R", "G", "B", "A", "depth_front", "depth_back", "normal_front.X",
            "normal_front.Y", "normal_front.Z", "normal_back.X", "normal_back.Z", "thickness",
            "roughness", "ior")


def _files(out: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(out.iterdir())
            if p.suffix in (".exr", ".png", ".tar")}


def _manifest(out: Path) -> list[dict]:
    return [json.loads(ln) for ln in (out / "manifest.jsonl").read_text().splitlines()]


def _no_temporaries(out: Path) -> bool:
    return not [p for p in out.iterdir() if ".tmp" in p.name]


@pytest.fixture(scope="module")
def cfg_path(tmp_path_factory) -> Path:
    return write_config(tmp_path_factory.mktemp("cfg") / "small.yaml", small_sweep())


@pytest.fixture(scope="module")
def reference(cfg_path, tmp_path_factory) -> Path:
    """The small sweep rendered serially, batch size 3."""
    out = tmp_path_factory.mktemp("ref")
    s = run_sweep(cfg_path, out, batch_size=3, quiet=True)
    assert (s.ok, s.failed, s.skipped) == (8, 0, 0)
    return out


# ---------------------------------------------------------------------------- folder output

def test_folder_run_writes_all_passes_and_a_complete_manifest(reference, cfg_path):
    cfg = load_sweep(cfg_path)
    lines = _manifest(reference)
    assert [e["sample_id"] for e in lines] == [f"{i:06d}" for i in range(8)]
    assert _no_temporaries(reference)
    for e in lines:
        assert e["status"] == "ok" and e["reason"] is None
        assert e["config_hash"] == cfg.config_hash and e["seed"] == 3
        assert e["torchrefract_version"] == tr.__version__
        assert e["sample_seed"] == [3, e["index"]] and e["method"] == "specular"
        assert set(e["params"]) >= {"material.ior", "material.roughness", "envmap.path",
                                    "envmap.rotate_deg", "camera.orbit.azimuth_deg",
                                    "camera.eye", "camera.target", "transform.rotate_deg"}
        cam = e["camera"]
        assert cam["convention"].startswith("opencv")
        assert set(cam["intrinsics"]) == {"fx", "fy", "cx", "cy"}
        assert np.array(cam["world_to_camera"]).shape == (4, 4)
        assert e["timings"]["render_s"] > 0 and e["timings"]["encode_s"] > 0
        for kind in ("exr", "png"):
            data = (reference / e["files"][kind]).read_bytes()
            assert hashlib.sha256(data).hexdigest() == e["sha256"][kind]
            assert len(data) == e["bytes"][kind]
        ch = read_exr(reference / e["files"]["exr"])
        for c in CHANNELS:
            assert ch[c].shape == (32, 32) and np.isfinite(ch[c]).all(), c
        assert 0.05 < ch["A"].mean() < 0.95
        assert np.allclose(ch["ior"][ch["A"] == 1], e["scene"]["material"]["ior"])
    # The EXR is exactly what the API renders for the recorded scene, written as
    # `torchrefract render` writes it.
    e = lines[5]
    # Its input paths are relative to the dataset folder.
    assert e["scene"]["mesh"] == os.path.relpath(Path(SPOT).resolve(), reference.resolve())
    scene = tr.scene_from_dict(e["scene"], base_dir=reference, name=e["sample_id"])
    assert scene == cfg.sample(5).scene
    direct = reference / "direct.exr.out"
    write_exr(direct, exr_channels(tr.render([scene]), 0))
    assert direct.read_bytes() == (reference / "000005.exr").read_bytes()
    direct.unlink()
    assert json.loads((reference / "sweep.json").read_text())["config_hash"] == cfg.config_hash


def test_same_config_and_seed_give_byte_identical_files(reference, cfg_path, tmp_path):
    # Another batch size (and one-by-one rendering) must not change a single byte.
    s = run_sweep(cfg_path, tmp_path, batch_size=1, quiet=True)
    assert s.ok == 8
    assert _files(tmp_path) == _files(reference) and len(_files(reference)) == 16


def test_second_run_skips_complete_samples_and_redoes_missing_ones(reference, cfg_path,
                                                                    tmp_path):
    out = tmp_path / "o"
    run_sweep(cfg_path, out, batch_size=4, quiet=True, limit=5)
    assert len(_manifest(out)) == 5
    (out / "000002.png").unlink()  # a lost file: that sample is rendered again
    s = run_sweep(cfg_path, out, batch_size=4, quiet=True)
    assert (s.skipped, s.ok) == (4, 4)
    assert [e["sample_id"] for e in _manifest(out)] == [f"{i:06d}" for i in range(8)]
    assert _files(out) == _files(reference)
    s = run_sweep(cfg_path, out, quiet=True)
    assert (s.skipped, s.ok, s.failed) == (8, 0, 0)


def test_truncated_manifest_line_is_repaired(reference, cfg_path, tmp_path):
    out = tmp_path / "o"
    run_sweep(cfg_path, out, quiet=True, limit=3)
    raw = (out / "manifest.jsonl").read_bytes()
    (out / "manifest.jsonl").write_bytes(raw[:-40])  # the third line cut short
    (out / ".000007.exr.abc123.tmp").write_bytes(b"half a file")  # a killed write
    with pytest.warns(UserWarning, match="dropped 1 incomplete"):
        s = run_sweep(cfg_path, out, quiet=True)
    assert (s.skipped, s.ok) == (2, 6)
    assert len(_manifest(out)) == 8 and _no_temporaries(out)
    assert _files(out) == _files(reference)


def test_another_sweep_or_a_running_run_is_refused(reference, cfg_path, tmp_path):
    d = small_sweep()
    d["sampling"]["seed"] = 99
    other = write_config(tmp_path / "other.yaml", d)
    with pytest.raises(ConfigError, match="holds a different sweep"):
        run_sweep(other, reference, quiet=True)
    with pytest.raises(ConfigError, match="was written with --format folder"):
        run_sweep(cfg_path, reference, fmt="webdataset", quiet=True)
    lock = _Lock(tmp_path)
    try:
        with pytest.raises(ConfigError, match="another run is writing"):
            run_sweep(cfg_path, tmp_path, quiet=True)
    finally:
        lock.release()


# ---------------------------------------------------------------------------- kill -9

def _kill_mid_run(cmd: list[str], out: Path, after_lines: int) -> None:
    """Start ``cmd``, kill -9 it once the manifest has ``after_lines`` lines."""
    proc = subprocess.Popen(cmd, start_new_session=True, stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE)
    manifest = out / "manifest.jsonl"
    deadline = time.monotonic() + 120
    try:
        while time.monotonic() < deadline and proc.poll() is None:
            if manifest.exists() and manifest.read_bytes().count(b"\n") >= after_lines:
                break
            time.sleep(0.005)
        os.killpg(proc.pid, signal.SIGKILL)
    finally:
        proc.wait(timeout=30)
    assert proc.returncode == -signal.SIGKILL, ("the run ended before it was killed",
                                                proc.stderr.read().decode()[-2000:])


def _sweep_cmd(cfg: Path, out: Path, *extra: str) -> list[str]:
    return [sys.executable, "-m", "torchrefract.cli", "sweep", str(cfg), "--out", str(out),
            "--batch-size", "1", "--quiet", *extra]


def test_resume_after_kill_9_completes_without_duplicates(tmp_path):
    d = small_sweep()
    d["sampling"]["repeats"] = 3  # 24 samples, so the kill lands mid-run
    cfg = write_config(tmp_path / "c.yaml", d)
    out = tmp_path / "out"
    _kill_mid_run(_sweep_cmd(cfg, out), out, after_lines=3)
    # Whatever is there now is whole: every EXR under its final name reads.
    entries = read_manifest(out / "manifest.jsonl", repair=False)
    assert 3 <= len(entries) < 24
    for p in out.glob("*.exr"):
        read_exr(p)
    # The resumed run is killed too.
    _kill_mid_run(_sweep_cmd(cfg, out), out, after_lines=len(entries) + 3)
    r = subprocess.run(_sweep_cmd(cfg, out), capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    lines = _manifest(out)
    assert [e["sample_id"] for e in lines] == [f"{i:06d}" for i in range(24)]
    assert all(e["status"] == "ok" for e in lines)
    assert _no_temporaries(out)
    files = _files(out)
    assert len(files) == 48
    for e in lines:  # every file is whole: it is what the manifest recorded
        for kind in ("exr", "png"):
            assert hashlib.sha256(files[e["files"][kind]]).hexdigest() == e["sha256"][kind]
    # ... and what an uninterrupted render of the sample gives, byte for byte.
    sweep = load_sweep(cfg)
    for i in (0, 23):
        direct = tmp_path / f"direct{i}.exr"
        write_exr(direct, exr_channels(tr.render([sweep.sample(i).scene]), 0))
        assert direct.read_bytes() == files[f"{i:06d}.exr"]


@pytest.mark.slow
@pytest.mark.parametrize("fmt", ["folder", "webdataset"])
def test_killed_at_five_random_points_resumes_to_identical_files(tmp_path, fmt):
    """kill -9 at five random points of one dataset (seeded), a resume after each: what
    the manifest records is whole every time, and the finished folder holds the bytes of
    an uninterrupted run."""
    import random

    d = small_sweep()
    d["sampling"]["repeats"] = 4  # 32 samples
    cfg = write_config(tmp_path / "c.yaml", d)
    out, full = tmp_path / "out", tmp_path / "full"
    extra = ("--format", fmt, "--shard-size", "3") if fmt == "webdataset" else ()
    points = sorted(random.Random(5).sample(range(2, 30), 5))
    for after in points:
        have = _lines(out / "manifest.jsonl")
        _kill_mid_run(_sweep_cmd(cfg, out, *extra), out, after_lines=max(after, have + 1))
        for e in read_manifest(out / "manifest.jsonl", repair=False):
            if fmt == "folder":
                for kind in ("exr", "png"):
                    data = (out / e["files"][kind]).read_bytes()
                    assert hashlib.sha256(data).hexdigest() == e["sha256"][kind]
            else:
                assert (out / e["shard"]).exists()
    for target in (out, full):
        r = subprocess.run(_sweep_cmd(cfg, target, *extra), capture_output=True, text=True,
                           timeout=300)
        assert r.returncode == 0, r.stderr
    lines = _manifest(out)
    assert [e["sample_id"] for e in lines] == [f"{i:06d}" for i in range(32)]
    assert all(e["status"] == "ok" for e in lines) and _no_temporaries(out)
    if fmt == "folder":
        assert _files(out) == _files(full)
    else:  # a resumed run packs its shards from where it stopped: the members are equal
        assert _members(out) == _members(full)


def _lines(path: Path) -> int:
    return path.read_bytes().count(b"\n") if path.exists() else 0


def _members(out: Path) -> dict[str, bytes]:
    got = {}
    for p in sorted(out.glob("shard-*.tar")):
        with tarfile.open(p) as t:
            for m in t.getmembers():
                got[m.name] = t.extractfile(m).read()
    return got


@pytest.fixture
def small_disk(tmp_path):
    """A 64 KiB tmpfs (root only: skipped where mounting is not allowed); ``resize(kib)``
    gives it more space."""
    mnt = tmp_path / "disk"
    mnt.mkdir()
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=64k", "tmpfs", str(mnt)],
                       capture_output=True, text=True)
    if r.returncode:
        pytest.skip(f"a size-limited folder needs a tmpfs mount: {r.stderr.strip()}")

    def resize(kib: int) -> None:
        subprocess.run(["mount", "-o", f"remount,size={kib}k", str(mnt)], check=True)

    yield mnt, resize
    subprocess.run(["umount", "-l", str(mnt)], capture_output=True)


@pytest.mark.parametrize("fmt", ["folder", "webdataset"])
def test_full_disk_stops_with_a_clear_error_and_resumes(small_disk, reference, cfg_path,
                                                        tmp_path, capsys, fmt):
    """A full file system stops the run with an error naming the folder (exit 3, no
    traceback), leaves no partial file and only whole recorded samples; with space back,
    the same command completes the dataset, byte for byte the uninterrupted run's."""
    mnt, resize = small_disk
    need = sum(p.stat().st_size for p in reference.iterdir()) // 1024
    resize(max(64, need // 3))  # room for part of the samples
    out = mnt / "out"
    args = ["sweep", str(cfg_path), "--out", str(out), "--quiet", "--format", fmt,
            "--batch-size", "1"]
    assert main(args) == 3
    err = capsys.readouterr().err
    assert str(out) in err and "no space left" in err and "Traceback" not in err
    assert _no_temporaries(out)
    done = [e for e in read_manifest(out / "manifest.jsonl") if e["status"] == "ok"]
    assert len(done) < 8
    if fmt == "folder":
        for e in done:  # what is recorded is whole
            for kind in ("exr", "png"):
                data = (out / e["files"][kind]).read_bytes()
                assert hashlib.sha256(data).hexdigest() == e["sha256"][kind]
    resize(4 * need + 1024)
    assert main(args) == 0
    lines = _manifest(out)
    assert len(lines) == 8 and all(e["status"] == "ok" for e in lines)
    assert _no_temporaries(out)
    if fmt == "folder":
        assert _files(out) == _files(reference)
    else:
        full = tmp_path / "full" / "out"  # beside the disk: the same relative input paths
        assert main(args[:3] + [str(full)] + args[4:]) == 0
        assert _files(out) == _files(full)


def test_resume_after_kill_9_with_shards(tmp_path, reference):
    cfg = write_config(tmp_path / "c.yaml", small_sweep())
    out = tmp_path / "out"
    _kill_mid_run(_sweep_cmd(cfg, out, "--format", "webdataset", "--shard-size", "2"), out,
                  after_lines=2)
    r = subprocess.run(_sweep_cmd(cfg, out, "--format", "webdataset", "--shard-size", "2"),
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert _no_temporaries(out)
    keys = []
    for shard in sorted(out.glob("shard-*.tar")):
        with tarfile.open(shard) as t:
            names = t.getnames()
            keys += [n[:-4] for n in names if n.endswith(".exr")]
            for n in names:  # every sample's EXR equals the serial folder run's
                if n.endswith(".exr"):
                    assert t.extractfile(n).read() == (reference / n).read_bytes()
    assert sorted(keys) == [f"{i:06d}" for i in range(8)]  # each sample exactly once


def test_orphan_shard_is_replaced_not_duplicated(tmp_path, reference, cfg_path):
    """A kill after a shard's rename but before its manifest lines: the shard is dropped."""
    out = tmp_path / "o"
    run_sweep(cfg_path, out, fmt="webdataset", shard_size=3, quiet=True, limit=6)
    assert sorted(p.name for p in out.glob("shard-*.tar")) == ["shard-000000.tar",
                                                              "shard-000001.tar"]
    lines = (out / "manifest.jsonl").read_text().splitlines()
    (out / "manifest.jsonl").write_text("\n".join(lines[:4]) + "\n")  # shard 1 half-recorded
    s = run_sweep(cfg_path, out, fmt="webdataset", shard_size=3, quiet=True)
    assert (s.skipped, s.ok) == (3, 5)
    assert not (out / "shard-000001.tar").exists()
    members = []
    for shard in sorted(out.glob("shard-*.tar")):
        with tarfile.open(shard) as t:
            members += t.getnames()
    assert sorted(members) == sorted(f"{i:06d}.{x}" for i in range(8)
                                     for x in ("exr", "png", "json"))


# ---------------------------------------------------------------------------- failures

def test_broken_mesh_and_envmap_fail_only_their_samples(tmp_path, capsys):
    broken_mesh = tmp_path / "broken.ply"
    broken_mesh.write_bytes(b"ply\nformat ascii 1.0\nelement vertex 3\nend_header\n1 2\n")
    broken_env = tmp_path / "broken.exr"
    broken_env.write_bytes(b"not an exr at all")
    d = small_sweep()
    d["sweep"]["mesh"]["path"] = [SPOT, str(broken_mesh)]
    d["sweep"]["envmap"]["path"] = [d["sweep"]["envmap"]["path"][0], str(broken_env)]
    d["sweep"]["camera"]["orbit"]["azimuth_deg"] = [0]
    cfg = write_config(tmp_path / "c.yaml", d)  # 2 meshes x 2 IOR x 2 env maps = 8
    out = tmp_path / "out"
    assert main(["sweep", str(cfg), "--out", str(out), "--batch-size", "8", "--quiet"]) == 1
    err = capsys.readouterr().err
    assert "6 sample(s) FAILED" in err
    lines = {e["sample_id"]: e for e in _manifest(out)}
    assert len(lines) == 8
    for e in lines.values():
        bad_mesh = e["scene"]["mesh"] == "../broken.ply"  # relative to the dataset folder
        bad_env = e["scene"]["envmap"]["path"] == "../broken.exr"
        if not (bad_mesh or bad_env):  # batch-mates of broken samples still render
            assert e["status"] == "ok" and (out / f"{e['sample_id']}.exr").is_file()
            continue
        assert e["status"] == "failed" and not (out / f"{e['sample_id']}.exr").exists()
        assert ("broken.ply" if bad_mesh else "broken.exr") in e["reason"]
    # Running again retries the failed samples only; the manifest keeps one line each.
    s = run_sweep(cfg, out, batch_size=8, quiet=True)
    assert (s.skipped, s.ok, s.failed) == (2, 0, 6)
    assert len(_manifest(out)) == 8


# ---------------------------------------------------------------------------- executors

def test_shards_are_deterministic(reference, cfg_path, tmp_path):
    a, b = tmp_path / "a", tmp_path / "b"
    run_sweep(cfg_path, a, fmt="webdataset", shard_size=3, batch_size=2, quiet=True)
    run_sweep(cfg_path, b, fmt="webdataset", shard_size=3, batch_size=8, quiet=True)
    assert _files(a) == _files(b) and len(_files(a)) == 3


def test_a_batch_is_encoded_in_threads_in_order_and_a_failure_stays_its_own():
    """A batch's samples are encoded in threads: each sample's bytes are the ones it
    encodes alone, in the batch's order, and a sample that cannot be encoded is recorded
    as failed without its neighbours."""
    import dataclasses
    import types

    import torch

    from torchrefract.dataset.encode import _encode
    from torchrefract.dataset.run import _encode_batch

    base = tr.Scene(mesh=SPOT, envmap=STUDIO, camera=tr.Camera(width=24, height=24),
                    method="specular")
    scenes = [base.replace(camera=dataclasses.replace(base.camera, eye=(0.3 * i, 0.2, 3.0)))
              for i in range(4)]
    res = tr.render(scenes)
    results = [{"ok": True, "result": res, "result_index": i, "timings": {}} for i in range(4)]
    results[2]["result_index"] = 7  # no such view: its encoding raises
    batch = [types.SimpleNamespace(scene=s) for s in scenes]
    threads = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        total = _encode_batch(batch, results)
    finally:
        torch.set_num_threads(threads)
    assert [r["ok"] for r in results] == [True, True, False, True]
    assert "index" in results[2]["reason"].lower() and "exr" not in results[2]
    for i in (0, 1, 3):
        alone = _encode(res, i, scenes[i])
        assert results[i]["exr"] == alone["exr"] and results[i]["png"] == alone["png"]
        assert results[i]["sha256"] == alone["sha256"]
    assert total == pytest.approx(sum(r["timings"]["encode_s"] for r in results))


def test_a_serial_run_encodes_between_renders_and_writes_beside_them(cfg_path, reference,
                                                                   tmp_path, monkeypatch):
    """Serially, no sample is encoded while a batch renders (their threads would take each
    other's cores: docs/datasets.md, section 4) nor in the writer thread, which only
    writes; the files are the reference run's."""
    import threading

    import torchrefract.dataset.executors as executors
    import torchrefract.dataset.run as run

    events: list[tuple[str, float, float, str]] = []
    render_batch, encode = executors.render_batch, run._encode

    def timed(kind, fn):
        def call(*args, **kwargs):
            t0 = time.perf_counter()
            out = fn(*args, **kwargs)
            events.append((kind, t0, time.perf_counter(), threading.current_thread().name))
            return out
        return call

    monkeypatch.setattr(executors, "render_batch", timed("render", render_batch))
    monkeypatch.setattr(run, "_encode", timed("encode", encode))
    s = run_sweep(cfg_path, tmp_path, batch_size=3, quiet=True)
    assert (s.ok, s.failed) == (8, 0)
    renders = [e for e in events if e[0] == "render"]
    encodes = [e for e in events if e[0] == "encode"]
    assert len(renders) == 3 and len(encodes) == 8
    assert not [e for e in encodes if e[3] == "torchrefract-writer"]
    for _, a0, a1, _ in encodes:
        assert not [r for r in renders if r[1] < a1 and a0 < r[2]], "encoded during a render"
    # the encoding is the run's work, not its overhead
    assert s.encode_wall_s >= max(a1 - a0 for _, a0, a1, _ in encodes)
    assert s.overhead_fraction == pytest.approx((s.wall_s - s.wait_s - s.encode_wall_s)
                                                / s.wall_s)
    for p in reference.glob("*.exr"):
        assert (tmp_path / p.name).read_bytes() == p.read_bytes()


_ORPHAN = """
import multiprocessing as mp, os, sys, time
from torchrefract.dataset.executors import exit_with_parent

def child(parent):
    exit_with_parent(parent)
    time.sleep(120)

if __name__ == "__main__":
    p = mp.get_context("spawn").Process(target=child, args=(os.getpid(),))
    p.start()
    print(p.pid, flush=True)
    time.sleep(120)
"""


def test_a_worker_ends_when_its_driver_is_killed(tmp_path):
    """The sweep's worker processes watch their driver: killed with SIGKILL (the OOM
    killer, a scheduler), it leaves no worker behind, where they used to wait on their
    queue forever. The pool's workers get the watch as their initializer."""
    from torchrefract.dataset.executors import _ProcessExecutor, exit_with_parent
    from torchrefract.settings import RenderSettings

    script = tmp_path / "driver.py"
    script.write_text(_ORPHAN)
    drv = subprocess.Popen([sys.executable, str(script)], stdout=subprocess.PIPE, text=True)
    child = int(drv.stdout.readline())
    os.kill(drv.pid, signal.SIGKILL)
    drv.wait()
    deadline = time.time() + 10
    while time.time() < deadline:
        try:
            os.kill(child, 0)
        except ProcessLookupError:
            break
        try:  # reap it if it is ours (it is init's once reparented)
            os.waitpid(child, os.WNOHANG)
        except ChildProcessError:
            pass
        time.sleep(0.1)
    else:
        os.kill(child, signal.SIGKILL)
        pytest.fail("the worker outlived its driver by 10 s")
    ex = _ProcessExecutor(2, RenderSettings())
    try:
        assert ex.pool._initializer is exit_with_parent
    finally:
        ex.pool.shutdown()


def test_local_worker_processes_give_the_serial_files(reference, cfg_path, tmp_path):
    s = run_sweep(cfg_path, tmp_path, workers=2, batch_size=2, quiet=True)
    assert s.ok == 8
    pids = {e["worker"]["pid"] for e in _manifest(tmp_path)}
    assert os.getpid() not in pids and len(pids) >= 1
    assert _files(tmp_path) == _files(reference)


def test_an_exr_compression_reaches_the_workers_and_keeps_the_pixels(reference, cfg_path,
                                                                     tmp_path):
    """``exr_compression`` is each file's (the workers' too), recorded per sample and in
    the run's line; the pixels are the default's bit for bit; an unknown one is refused."""
    import OpenEXR

    s = run_sweep(cfg_path, tmp_path, workers=1, batch_size=4, quiet=True,
                  exr_compression="rle")
    assert s.ok == 8 and s.exr_compression == "rle"
    recs = _manifest(tmp_path)
    assert {r["exr_compression"] for r in recs} == {"rle"}
    for p in sorted(reference.glob("0*.exr")):
        with OpenEXR.File(str(tmp_path / p.name)) as f:
            assert str(f.header()["compression"]).endswith("RLE_COMPRESSION")
        mine, ref = read_exr(tmp_path / p.name), read_exr(p)
        assert all(mine[k].tobytes() == ref[k].tobytes() for k in ref)
    run_line = json.loads((tmp_path / "runs.jsonl").read_text().splitlines()[-1])
    assert run_line["exr_compression"] == "rle"
    with pytest.raises(ConfigError, match="exr_compression: 'lzw'"):
        run_sweep(cfg_path, tmp_path / "x", exr_compression="lzw")


@pytest.mark.slow
def test_ray_local_cluster_gives_the_serial_files(reference, cfg_path, tmp_path):
    pytest.importorskip("ray", reason="ray is not installed (pip install 'torchrefract[data]')")
    s = run_sweep(cfg_path, tmp_path, executor="ray", workers=2, batch_size=2, quiet=True)
    assert (s.ok, s.failed) == (8, 0)
    assert os.getpid() not in {e["worker"]["pid"] for e in _manifest(tmp_path)}
    assert _files(tmp_path) == _files(reference)


def test_an_invalid_sample_fails_alone_at_planning(tmp_path):
    """A camera whose up vector is parallel to the view at one orbit position."""
    d = small_sweep()
    d["base"]["camera"].update(eye=[4, 0, 0], up=[0, 0, 1])
    d["sweep"] = {"camera": {"orbit": {"azimuth_deg": [0, 90], "elevation_deg": 0}}}
    cfg = write_config(tmp_path / "c.yaml", d)
    s = run_sweep(cfg, tmp_path / "o", quiet=True)
    assert (s.ok, s.failed, s.failed_ids) == (1, 1, ["000000"])
    bad = _manifest(tmp_path / "o")[0]
    assert bad["status"] == "failed" and "sample 000000: camera.up" in bad["reason"]


def test_shipped_demo_sweep_renders(tmp_path):
    """configs/sweep_demo.yaml (method rousiers) renders; two samples keep the test short."""
    s = run_sweep(ROOT / "configs" / "sweep_demo.yaml", tmp_path, quiet=True, limit=2)
    assert (s.ok, s.failed) == (2, 0)
    e = _manifest(tmp_path)[0]
    assert e["method"] == "rousiers" and e["camera"]["width"] == 64
    ch = read_exr(tmp_path / "000000.exr")
    assert np.allclose(ch["roughness"][ch["A"] == 1], 0.05)


def test_auto_records_what_it_rendered(tmp_path):
    """method auto in a sweep: each sample's manifest line (and its record in a shard)
    names the variants whose images it is, with their weights."""
    d = small_sweep()
    d["base"]["method"] = "auto"
    d["sweep"] = {"material": {"roughness": [0.0, 0.05, 0.3]}}
    cfg = write_config(tmp_path / "c.yaml", d)
    assert run_sweep(cfg, tmp_path / "o", quiet=True).ok == 3
    lines = _manifest(tmp_path / "o")
    assert all(e["method"] == "auto" for e in lines)
    for e in lines:
        assert abs(sum(b["weight"] for b in e["auto_blend"]) - 1) < 1e-9
        assert e["auto_prediction"]["predicted_flip"] > 0  # what the table predicted
    # smooth: no lobe split into rays (auto.SPLIT_MIN_ALPHA); rough: the cone method
    assert all(b["options"].get("bounce_rays", 1) == 1 for b in lines[0]["auto_blend"])
    assert lines[2]["auto_blend"][0]["method"] == "rousiers"
    run_sweep(cfg, tmp_path / "w", fmt="webdataset", quiet=True)
    with tarfile.open(next((tmp_path / "w").glob("*.tar"))) as tar:
        meta = [json.loads(tar.extractfile(m).read()) for m in tar.getmembers()
                if m.name.endswith(".json")]
    assert [m["auto_blend"] for m in meta] == [e["auto_blend"] for e in lines]


def test_batches_keep_the_samples_of_one_view_together():
    """_plan_batches puts the samples of one view (mesh, transform, camera) side by side
    (views in first-seen order, samples in index order within a view), so a batch's
    repeated views share one G-buffer; each sample is planned exactly once."""
    import torchrefract as tr
    from torchrefract.dataset.run import _plan_batches
    from torchrefract.dataset.sweep import Sample
    base = tr.Scene(mesh="m.ply", envmap=tr.EnvMap(path="e.exr"))
    cams = [tr.Camera(eye=(0.0, 0.0, 4.0 + k)) for k in range(3)]
    # a grid whose camera axis varies fastest: views interleaved
    todo = [Sample(f"{i:06d}", base.replace(camera=cams[i % 3],
                                            material=tr.Material(roughness=0.1 * (i // 3))),
                   {"index": i}) for i in range(12)]
    batches = _plan_batches(todo, 4)
    assert [[int(s.sample_id) for s in b] for b in batches] == [
        [0, 3, 6, 9], [1, 4, 7, 10], [2, 5, 8, 11]]
    assert all(len({s.scene.camera for s in b}) == 1 for b in batches)


def test_a_folder_keeps_the_adaptive_sampling_it_was_started_with(cfg_path, tmp_path,
                                                                  monkeypatch, capsys):
    """sweep.json records whether the samples are rendered with adaptive sampling; a
    resumed run renders the rest alike whatever the settings in force say (a record
    from before the setting existed: without it), and says so."""
    import torchrefract.dataset.run as run_mod
    from torchrefract.settings import RenderSettings

    seen = []
    make = run_mod._make_executor

    def spy(executor, workers, settings, *args):
        seen.append(settings.adaptive)
        return make(executor, workers, settings, *args)

    monkeypatch.setattr(run_mod, "_make_executor", spy)
    out = tmp_path / "o"
    run_sweep(cfg_path, out, quiet=True, limit=2, settings=RenderSettings())
    rec = json.loads((out / "sweep.json").read_text())
    assert rec["adaptive"] is True and seen == [True]
    run_sweep(cfg_path, out, quiet=False, limit=4, settings=RenderSettings(adaptive=False))
    assert seen == [True, True] and "adaptive sampling on" in capsys.readouterr().err
    del rec["adaptive"]  # a folder started before the setting existed
    (out / "sweep.json").write_text(json.dumps(rec))
    s = run_sweep(cfg_path, out, quiet=True, settings=RenderSettings())
    assert seen == [True, True, False] and (s.skipped, s.ok) == (6, 2)


def test_a_resume_across_image_revisions_warns_and_records_each_samples(cfg_path, tmp_path,
                                                                        monkeypatch):
    """A folder begun at another IMAGE_REVISION (or before revisions were recorded) is
    resumed with a warning naming both revisions; every record carries its own revision,
    and a folder resumed at its own revision says nothing."""
    import warnings

    import torchrefract
    from torchrefract.dataset.manifest import latest_entries, read_manifest

    out = tmp_path / "o"
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a fresh folder and a same-revision resume: silent
        run_sweep(cfg_path, out, quiet=True, limit=2)
        run_sweep(cfg_path, out, quiet=True, limit=3)
    rec = json.loads((out / "sweep.json").read_text())
    assert rec["image_revision"] == torchrefract.IMAGE_REVISION
    monkeypatch.setattr(torchrefract, "IMAGE_REVISION", torchrefract.IMAGE_REVISION + 1)
    with pytest.warns(UserWarning, match=r"5 finished samples were rendered at image "
                                         rf"revision {rec['image_revision']}"):
        run_sweep(cfg_path, out, quiet=True, limit=2)
    entries = latest_entries(read_manifest(out / "manifest.jsonl"))
    revs = sorted(e.get("image_revision") for e in entries.values())
    assert revs == [rec["image_revision"]] * 5 + [rec["image_revision"] + 1] * 2
    del rec["image_revision"]  # a folder begun before revisions were recorded
    (out / "sweep.json").write_text(json.dumps(rec))
    with pytest.warns(UserWarning, match="unrecorded revision"):
        run_sweep(cfg_path, out, quiet=True, limit=1)

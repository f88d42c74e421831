"""Dataset runner: render a sweep into a folder of files or WebDataset shards, resumably.

What a run does (``torchrefract sweep CONFIG --out DIR``, or :func:`run_sweep`):

1. Plans: expands the sweep (:mod:`torchrefract.dataset.sweep`), reads ``DIR/manifest.jsonl``
   (repairing a truncated last line) and skips every sample already complete.
2. Groups the rest into batches of one resolution, supersampling, method and options, in
   index order, and renders them with :func:`torchrefract.render` in this process, in
   ``--workers N`` spawned processes (each with its own EGL context), or as Ray tasks.
   A batch that fails is rendered again one sample at a time, so one broken mesh or env
   map fails only its own samples.
3. Writes, in plan order (so the output does not depend on which worker finished first):

   - folder format: ``DIR/<id>.exr`` (R, G, B linear radiance with background, A coverage,
     every pass as extra channels, as ``torchrefract render`` writes them) and
     ``DIR/<id>.png`` (sRGB preview);
   - webdataset format: ``DIR/shard-NNNNNN.tar`` with members ``<id>.exr``, ``<id>.png``,
     ``<id>.json`` (the sample's metadata), ``--shard-size`` samples per shard;

   then appends one JSON line per sample to ``DIR/manifest.jsonl``: status ``ok`` or
   ``failed`` with the reason, every resolved parameter, the full scene, camera intrinsics
   and extrinsics, method, seeds, timings, package version and config hash.

Crash safety: every file is written to a temporary name, fsynced and renamed; manifest lines
are appended (flush + fsync) only after the files they describe are durable; a shard is
accepted on resume only when the manifest holds all of its samples (otherwise it is deleted
and its samples rendered again). So a ``kill -9`` at any moment loses at most the batches in
flight, and running the same command again completes the dataset with no duplicate or
corrupt files. At the end of a run the manifest is rewritten (atomically) with one line per
sample in index order. A lock file keeps two runs from writing into one folder.

Determinism: the same config and seed give byte-identical EXR and PNG files (and shards),
whatever the executor, worker count or batch size.
"""

from __future__ import annotations

import fcntl
import hashlib
import io
import json
import math
import os
import platform
import re
import socket
import sys
import tarfile
import tempfile
import time
import warnings
from collections import deque
from dataclasses import asdict, dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Callable

import numpy as np

from torchrefract.checks import ConfigError
from torchrefract.dataset.sweep import Sample, SweepConfig, load_sweep
from torchrefract.scene.model import Camera, Scene

MANIFEST = "manifest.jsonl"
SWEEP_RECORD = "sweep.json"
RUN_LOG = "runs.jsonl"
LOCK = ".lock"
FORMATS = ("folder", "webdataset")
EXECUTORS = ("local", "ray")
_SHARD_RE = re.compile(r"^shard-(\d{6,})\.tar$")
# Temporary files of our atomic writers (and of image_files): ".<name>.<random>.tmp[...]".
_TMP_RE = re.compile(r"^\..+\.tmp(\.[A-Za-z0-9]+)?$")
# tar members get fixed owners and times so that shards are byte-identical across runs.
_TAR_MTIME = 0


# --------------------------------------------------------------------------------------
# Camera metadata
# --------------------------------------------------------------------------------------

def camera_metadata(cam: Camera) -> dict:
    """Intrinsics and extrinsics of a scene camera, OpenCV convention.

    - ``world_to_camera``: 4x4, camera x right, y down, z forward (the viewing direction);
      ``X_cam = R X_world + t``.
    - ``intrinsics``: ``fx, fy, cx, cy`` in pixels for ``u = fx X/Z + cx``,
      ``v = fy Y/Z + cy`` where pixel (column i, row j) is centered at (u, v) = (i, j)
      (OpenCV); SCENE_SPEC.md's continuous coordinates (centers at i + 0.5) are u + 0.5.
    """
    from torchrefract.geometry.camera import camera_frame  # noqa: PLC0415

    eye, r, u, f = camera_frame(cam)
    rot = np.stack([r, -u, f])  # rows: camera axes in world coordinates
    w2c = np.eye(4)
    w2c[:3, :3] = rot
    w2c[:3, 3] = -rot @ eye
    fy = cam.height / (2.0 * math.tan(math.radians(cam.yfov_deg) / 2.0))
    # Square pixels: the spec's horizontal half-angle is t * (W / H), so fx = fy.
    return {
        "convention": "opencv (x right, y down, z forward; pixel (i, j) centered at (i, j))",
        "width": cam.width, "height": cam.height,
        "intrinsics": {"fx": fy, "fy": fy, "cx": cam.width / 2.0 - 0.5,
                       "cy": cam.height / 2.0 - 0.5},
        "K": [[fy, 0.0, cam.width / 2.0 - 0.5], [0.0, fy, cam.height / 2.0 - 0.5],
              [0.0, 0.0, 1.0]],
        "world_to_camera": w2c.tolist(),
    }


# --------------------------------------------------------------------------------------
# Worker side: render a batch, fall back to one by one, encode files
# --------------------------------------------------------------------------------------

def encode_exr(channels: dict[str, np.ndarray]) -> bytes:
    """The bytes :func:`torchrefract.output.images.write_exr` writes for these channels."""
    import OpenEXR  # noqa: PLC0415

    data = {k: np.ascontiguousarray(v, dtype=np.float32) for k, v in channels.items()}
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    buf = io.BytesIO()
    with OpenEXR.File(header, data) as f:
        f.write(buf)
    return buf.getvalue()


def encode_png(rgb: np.ndarray, exposure: float = 0.0) -> bytes:
    """sRGB PNG preview bytes of linear radiance (H, W, 3)."""
    from PIL import Image  # noqa: PLC0415

    from torchrefract.output.images import linear_to_srgb8  # noqa: PLC0415

    buf = io.BytesIO()
    Image.fromarray(linear_to_srgb8(rgb, exposure)).save(buf, format="PNG")
    return buf.getvalue()


def channel_layout(result, i: int = 0) -> dict:
    """Which EXR channels hold what: radiance, coverage and each pass."""
    passes = {}
    for name, p in result.passes.items():
        c = int(p.shape[-1])
        passes[name] = [name] if c == 1 else [f"{name}.{'XYZW'[k]}" for k in range(c)]
    return {"radiance": ["R", "G", "B"], "coverage": ["A"], "passes": passes}


def _failure(exc: BaseException) -> str:
    msg = str(exc).strip().splitlines()
    return f"{type(exc).__name__}: {msg[0] if msg else ''}"[:2000]


def _render_one_group(scenes: list[Scene], settings):
    from torchrefract.render import render  # noqa: PLC0415

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        result = render(scenes, settings=settings)
    return result, sorted({str(w.message) for w in caught})


def render_items(items: list[tuple[int, str, Scene]], settings=None,
                 encode: bool = True) -> list[dict]:
    """Render one batch (the worker's task). Never raises for a bad sample.

    Args:
        items: ``(index, sample_id, scene)`` of one resolution, method and options.
        settings: the :class:`~torchrefract.settings.RenderSettings` of the renders (None:
            those in force; ``threads`` sets torch's thread count for each render).
        encode: encode the EXR and PNG bytes (else return the tensors in ``result``).

    Returns:
        One dict per item: ``index``, ``sample_id``, ``ok``, ``reason``, ``exr``, ``png``
        (bytes), ``sha256``, ``channels``, ``timings`` (seconds: this sample's share of
        the batch render, its encoding), ``batch_size``, ``warnings``, ``host``, ``pid``.
    """
    import torch  # noqa: PLC0415

    scenes = [s for _, _, s in items]
    groups: list[tuple[list[int], Any, list[str], str | None]] = []
    try:
        res, warn = _render_one_group(scenes, settings)
        groups.append((list(range(len(items))), res, warn, None))
    except Exception as exc:  # noqa: BLE001 - any failure: retry alone, then report
        if len(items) == 1:
            groups.append(([0], None, [], _failure(exc)))
        else:
            for k, s in enumerate(scenes):
                try:
                    res, warn = _render_one_group([s], settings)
                    groups.append(([k], res, warn, None))
                except Exception as exc1:  # noqa: BLE001
                    groups.append(([k], None, [], _failure(exc1)))
    out: list[dict | None] = [None] * len(items)
    host, pid = socket.gethostname(), os.getpid()
    for ks, res, warn, reason in groups:
        for j, k in enumerate(ks):
            index, sid, scene = items[k]
            rec = {"index": index, "sample_id": sid, "ok": res is not None, "reason": reason,
                   "batch_size": len(ks), "warnings": warn, "host": host, "pid": pid,
                   "torch_threads": (settings.threads if settings is not None
                                     and settings.threads else torch.get_num_threads()),
                   "timings": {}}
            if res is not None:
                rec["timings"]["render_s"] = res.timings["total"] / len(ks)
                rec["timings"]["batch"] = dict(res.timings)
                rec["channels"] = channel_layout(res)
                if res.blends is not None:  # auto: the variants in the image, weighted
                    from torchrefract.output.export import blend_records  # noqa: PLC0415
                    rec["auto_blend"] = blend_records(res, j)
                if encode:
                    t0 = time.perf_counter()
                    try:
                        rec.update(_encode(res, j, scene))
                    except Exception as exc:  # noqa: BLE001
                        rec.update(ok=False, reason=_failure(exc))
                    rec["timings"]["encode_s"] = time.perf_counter() - t0
                else:
                    rec["result"], rec["result_index"] = res, j
            out[k] = rec
    return out  # type: ignore[return-value]


def _encode(res, j: int, scene: Scene) -> dict:
    from torchrefract.output.export import exr_channels  # noqa: PLC0415

    exr = encode_exr(exr_channels(res, j))
    png = encode_png(res.radiance[j].detach().cpu().numpy(), scene.exposure)
    return {"exr": exr, "png": png,
            "sha256": {"exr": hashlib.sha256(exr).hexdigest(),
                       "png": hashlib.sha256(png).hexdigest()}}


# --------------------------------------------------------------------------------------
# Files: atomic writes, manifest, shards
# --------------------------------------------------------------------------------------

def _fsync_dir(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def write_bytes_atomic(path: Path, data: bytes, fsync: bool = True) -> None:
    """Write ``data`` to ``path`` via a temporary file in the same folder and a rename."""
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            if fsync:
                os.fsync(f.fileno())
        os.chmod(tmp, 0o644)
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


def _json_line(rec: dict) -> str:
    return json.dumps(rec, sort_keys=False, separators=(",", ":"), allow_nan=False) + "\n"


def read_manifest(path: str | Path, repair: bool = True) -> list[dict]:
    """Every valid line of a manifest, in file order.

    A truncated last line (a run killed while appending) or any line that is not a JSON
    object is dropped, with a warning; with ``repair`` the file is rewritten atomically
    without it.
    """
    path = Path(path)
    if not path.exists():
        return []
    raw = path.read_bytes()
    lines = raw.split(b"\n")
    tail = lines.pop()  # b"" when the file ends with a newline
    entries, bad = [], 0
    for ln in lines:
        if not ln.strip():
            continue
        try:
            rec = json.loads(ln)
            if not isinstance(rec, dict) or "sample_id" not in rec:
                raise ValueError("not a sample record")
            entries.append(rec)
        except ValueError:
            bad += 1
    if tail.strip() or bad:
        warnings.warn(f"{path}: dropped {bad + bool(tail.strip())} incomplete or corrupt "
                      f"line(s) (an interrupted run); those samples are rendered again",
                      stacklevel=2)
        if repair:
            write_bytes_atomic(path, "".join(_json_line(e) for e in entries).encode())
    return entries


def latest_entries(entries: list[dict]) -> dict[str, dict]:
    """The last record of every sample (later lines supersede earlier ones)."""
    out: dict[str, dict] = {}
    for e in entries:
        out[e["sample_id"]] = e
    return out


class _Manifest:
    """Append-only JSON Lines file; each append is flushed and fsynced."""

    def __init__(self, path: Path):
        self.path = path
        self.f = open(path, "ab")  # noqa: SIM115

    def append(self, records: list[dict]) -> None:
        if not records:
            return
        # One write call per batch: a kill leaves whole lines or one truncated last line.
        self.f.write("".join(_json_line(r) for r in records).encode())
        self.f.flush()
        os.fsync(self.f.fileno())

    def close(self) -> None:
        self.f.close()

    def compact(self) -> None:
        """Rewrite with one line per sample (the latest), in index order, atomically."""
        entries = sorted(latest_entries(read_manifest(self.path)).values(),
                         key=lambda e: (e.get("index", 0), e["sample_id"]))
        write_bytes_atomic(self.path, "".join(_json_line(e) for e in entries).encode())


class _TarShards:
    """WebDataset shards written atomically: ``.shard-NNNNNN.tar.<rand>.tmp`` -> rename."""

    def __init__(self, out: Path, shard_size: int, first: int):
        self.out, self.size, self.next = out, shard_size, first
        self.tar: tarfile.TarFile | None = None
        self.tmp: str | None = None
        self.pending: list[dict] = []

    def add(self, key: str, members: list[tuple[str, bytes]], record: dict) -> list[dict]:
        """Add one sample; returns the records of a shard that just became durable."""
        if self.tar is None:
            name = f"shard-{self.next:06d}.tar"
            fd, self.tmp = tempfile.mkstemp(prefix=f".{name}.", suffix=".tmp", dir=self.out)
            self.file = os.fdopen(fd, "wb")
            self.tar = tarfile.open(fileobj=self.file, mode="w", format=tarfile.USTAR_FORMAT)
            self.name = name
        for ext, data in members:
            info = tarfile.TarInfo(f"{key}.{ext}")
            info.size, info.mtime, info.mode = len(data), _TAR_MTIME, 0o644
            info.uid = info.gid = 0
            info.uname = info.gname = ""
            self.tar.addfile(info, io.BytesIO(data))
        record = dict(record, shard=self.name,
                      members={ext: f"{key}.{ext}" for ext, _ in members})
        self.pending.append(record)
        return self.close() if len(self.pending) >= self.size else []

    def close(self) -> list[dict]:
        if self.tar is None:
            return []
        self.tar.close()
        self.file.flush()
        os.fsync(self.file.fileno())
        self.file.close()
        os.chmod(self.tmp, 0o644)
        final = self.out / self.name
        os.replace(self.tmp, final)
        _fsync_dir(self.out)
        size = final.stat().st_size
        done = [dict(r, shard_samples=len(self.pending), shard_bytes=size)
                for r in self.pending]
        self.tar, self.tmp, self.pending = None, None, []
        self.next += 1
        return done

    def abort(self) -> None:
        if self.tar is not None:
            try:
                self.file.close()
            finally:
                if self.tmp and os.path.exists(self.tmp):
                    os.unlink(self.tmp)
            self.tar = None


# --------------------------------------------------------------------------------------
# Executors: all return futures with .result(); results come back in submission order
# --------------------------------------------------------------------------------------

class _Lazy:
    def __init__(self, fn: Callable[[], Any]):
        self.fn = fn

    def result(self) -> Any:
        return self.fn()


class _SerialExecutor:
    """Renders in this process, when the result is asked for."""

    window = 1

    def __init__(self, settings):
        self.settings = settings

    def submit(self, items):
        # Encoding happens in the writer thread, overlapping the next render.
        return _Lazy(lambda: render_items(items, self.settings, encode=False))

    def close(self) -> None:
        pass


class _ProcessExecutor:
    """``workers`` spawned processes; each creates its own EGL context on first use."""

    def __init__(self, workers: int, settings):
        import multiprocessing as mp  # noqa: PLC0415
        from concurrent.futures import ProcessPoolExecutor  # noqa: PLC0415

        # 'spawn', not 'fork': an EGL context does not survive a fork, and a forked child of
        # a process that holds one hangs. (The parent never renders in this mode.)
        if settings.threads is None:
            settings = settings.replace(threads=max(1, (os.cpu_count() or 1) // workers))
        self.settings = settings
        self._new = lambda: ProcessPoolExecutor(
            max_workers=workers, mp_context=mp.get_context("spawn"))
        self.pool = self._new()
        self.window = 2 * workers

    def submit(self, items):
        from concurrent.futures.process import BrokenProcessPool  # noqa: PLC0415

        try:
            return self.pool.submit(render_items, items, self.settings)
        except BrokenProcessPool:
            # A worker died (its batches in flight are reported failed and are retried by
            # the next run); carry on with fresh processes.
            self.pool.shutdown(wait=False, cancel_futures=True)
            self.pool = self._new()
            return self.pool.submit(render_items, items, self.settings)

    def close(self) -> None:
        self.pool.shutdown(wait=True, cancel_futures=True)


class _RayRef:
    def __init__(self, ref):
        self.ref = ref

    def result(self):
        import ray  # noqa: PLC0415

        return ray.get(self.ref)


class _RayExecutor:
    """Ray tasks (one CPU each) on the cluster at ``address``, or on a local cluster."""

    def __init__(self, address: str | None, workers: int, settings, quiet: bool):
        try:
            import ray  # noqa: PLC0415
        except ImportError as exc:
            raise ConfigError("--executor ray needs the 'ray' package: pip install "
                              "'torchrefract[data]' (or pip install ray)") from exc
        self.started = False
        if not ray.is_initialized():
            kwargs: dict[str, Any] = {"include_dashboard": False, "log_to_driver": not quiet,
                                      "configure_logging": not quiet}
            if address:
                ray.init(address=address, **kwargs)
            else:
                # A local cluster; workers start in this venv (same interpreter and path).
                ray.init(num_cpus=workers or None, **kwargs)
            self.started = True
        self.task = ray.remote(num_cpus=1)(render_items)
        cpus = int(ray.cluster_resources().get("CPU", 1))
        self.window = 2 * max(1, cpus)
        self.settings = settings if settings.threads else settings.replace(threads=1)

    def submit(self, items):
        return _RayRef(self.task.remote(items, self.settings))

    def close(self) -> None:
        import ray  # noqa: PLC0415

        if self.started:
            ray.shutdown()


# --------------------------------------------------------------------------------------
# The run
# --------------------------------------------------------------------------------------

@dataclass
class RunSummary:
    """What a run did, and where its wall time went (seconds)."""

    out: str
    format: str
    executor: str
    workers: int
    num_samples: int
    skipped: int = 0
    """Samples already complete from an earlier run."""
    ok: int = 0
    failed: int = 0
    failed_ids: list[str] = field(default_factory=list)
    wall_s: float = 0.0
    plan_s: float = 0.0
    """Config, expansion, manifest reading and resume checks."""
    write_s: float = 0.0
    """Writing and fsyncing files and shards (in this process)."""
    manifest_s: float = 0.0
    """Appending, fsyncing and compacting the manifest."""
    encode_s: float = 0.0
    """EXR/PNG encoding done in this process (serial runs; workers encode their own)."""
    render_s: float = 0.0
    """Sum of the render time of all batches (in whichever process rendered them)."""
    wait_s: float = 0.0
    """Time the main thread spent getting results (rendering them, when serial)."""
    startup_s: float = 0.0
    """Starting the executor (Ray cluster / connection; worker processes start lazily)
    until the first result arrived, minus that batch's render time."""
    shutdown_s: float = 0.0
    """Stopping the executor (worker processes, a local Ray cluster)."""

    @property
    def samples_per_s(self) -> float:
        return (self.ok + self.failed) / self.wall_s if self.wall_s > 0 else 0.0

    @property
    def steady_samples_per_s(self) -> float:
        """Samples per second without planning, start-up and shut-down: the rate a long run
        approaches."""
        t = self.wall_s - self.plan_s - self.startup_s - self.shutdown_s
        return (self.ok + self.failed) / t if t > 0 else 0.0

    @property
    def own_work_fraction(self) -> float:
        """(planning + encoding here + writing + manifest) / wall time: the run's own work,
        most of it done by the writer thread while the next batch renders."""
        own = self.plan_s + self.write_s + self.manifest_s + self.encode_s
        return own / self.wall_s if self.wall_s > 0 else 0.0

    @property
    def overhead_fraction(self) -> float:
        """Share of the wall time the main thread was not waiting for rendered results:
        planning, start-up of workers and the writes that did not overlap rendering."""
        return max(0.0, self.wall_s - self.wait_s) / self.wall_s if self.wall_s > 0 else 0.0

    def to_dict(self) -> dict:
        d = asdict(self)
        d.update(samples_per_s=self.samples_per_s, overhead_fraction=self.overhead_fraction,
                 own_work_fraction=self.own_work_fraction,
                 steady_samples_per_s=self.steady_samples_per_s)
        return d


class _Lock:
    def __init__(self, out: Path):
        self.f = open(out / LOCK, "a")  # noqa: SIM115
        try:
            fcntl.flock(self.f, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            self.f.close()
            raise ConfigError(f"{out}: another run is writing into this folder (it holds "
                              f"{out / LOCK}); wait for it or use another --out") from None

    def release(self) -> None:
        fcntl.flock(self.f, fcntl.LOCK_UN)
        self.f.close()


def _remove_temporaries(out: Path) -> int:
    n = 0
    for p in out.iterdir():
        if p.is_file() and _TMP_RE.match(p.name):
            p.unlink()
            n += 1
    return n


def _sample_meta(cfg: SweepConfig, sample: Sample) -> dict:
    """Everything that decides a sample (deterministic: no times or hosts in it)."""
    from torchrefract import __version__  # noqa: PLC0415

    scene = sample.scene
    return {
        "sample_id": sample.sample_id,
        "index": sample.params["index"],
        "sweep": cfg.name,
        "config_hash": cfg.config_hash,
        "seed": cfg.sampling.seed,
        "sample_seed": [cfg.sampling.seed, sample.params["index"]],
        "method": scene.method,
        "params": sample.params,
        "scene": scene.to_dict(),
        "camera": camera_metadata(scene.camera),
        "torchrefract_version": __version__,
    }


def _check_sweep_record(out: Path, cfg: SweepConfig, fmt: str) -> None:
    from torchrefract import __version__  # noqa: PLC0415

    path = out / SWEEP_RECORD
    if path.exists():
        try:
            rec = json.loads(path.read_text())
        except ValueError:
            rec = None
        if rec is not None:
            if rec.get("config_hash") != cfg.config_hash:
                raise ConfigError(
                    f"{out} holds a different sweep (config hash {rec.get('config_hash')!r:.20}"
                    f"..., this config {cfg.config_hash[:16]}...): the samples would not "
                    f"match their records; use a new --out folder")
            if rec.get("format") != fmt:
                raise ConfigError(f"{out} was written with --format {rec.get('format')}; "
                                  f"resume it with the same format (or use a new --out)")
            return
    record = {"name": cfg.name, "config_hash": cfg.config_hash, "format": fmt,
              "num_samples": cfg.num_samples, "source": cfg.source,
              "sampling": asdict(cfg.sampling), "config": cfg.raw,
              "base_scene": cfg.base.to_dict(), "torchrefract_version": __version__,
              "created": datetime.now(timezone.utc).isoformat(timespec="seconds")}
    write_bytes_atomic(path, (json.dumps(record, indent=2, default=str) + "\n").encode())


def _completed(out: Path, fmt: str, latest: dict[str, dict], verify: bool
               ) -> tuple[set[str], int]:
    """Sample ids whose files are complete; deletes shards no complete record covers."""
    done: set[str] = set()
    if fmt == "folder":
        for sid, e in latest.items():
            if e.get("status") != "ok":
                continue
            good = True
            for kind, rel in e.get("files", {}).items():
                p = out / rel
                if not p.is_file() or p.stat().st_size != e.get("bytes", {}).get(kind, -1):
                    good = False
                    break
                if verify and hashlib.sha256(p.read_bytes()).hexdigest() != e["sha256"][kind]:
                    good = False
                    break
            if good and e.get("files"):
                done.add(sid)
        return done, -1
    by_shard: dict[str, list[dict]] = {}
    for e in latest.values():
        if e.get("status") == "ok" and e.get("shard"):
            by_shard.setdefault(e["shard"], []).append(e)
    good_shards = set()
    for shard, es in by_shard.items():
        p = out / shard
        ok = (p.is_file() and all(e.get("shard_samples") == len(es) for e in es)
              and all(e.get("shard_bytes") == p.stat().st_size for e in es))
        if ok and verify:
            try:
                with tarfile.open(p) as t:
                    names = set(t.getnames())
                ok = all(set(e["members"].values()) <= names for e in es)
            except tarfile.TarError:
                ok = False
        if ok:
            good_shards.add(shard)
            done.update(e["sample_id"] for e in es)
    last = -1
    for p in out.iterdir():
        m = _SHARD_RE.match(p.name)
        if not m:
            continue
        last = max(last, int(m.group(1)))
        if p.name not in good_shards:
            # Renamed into place but its manifest lines never all made it: its samples are
            # rendered again, so keeping it would duplicate them.
            p.unlink()
    return done, last


def _plan_batches(todo: list[Sample], batch_size: int) -> list[list[Sample]]:
    groups: dict[tuple, list[Sample]] = {}
    for s in todo:
        c = s.scene.camera
        key = (c.width, c.height, c.samples_per_pixel, s.scene.method,
               json.dumps(s.scene.method_options, sort_keys=True, default=str))
        groups.setdefault(key, []).append(s)
    batches = []
    for g in groups.values():  # dicts keep first-seen order: deterministic
        # Samples of one view (mesh, transform, camera) side by side, views in first-seen
        # order (a stable sort): a batch's repeated views share one G-buffer
        # (gbuffer.build_gbuffer), e.g. a grid sweep whose camera axis is not the last.
        first: dict[tuple, int] = {}
        for smp in g:
            first.setdefault(_view_key(smp), len(first))
        g = sorted(g, key=lambda smp: first[_view_key(smp)])
        batches.extend(g[k:k + batch_size] for k in range(0, len(g), batch_size))
    return batches


def _view_key(s: Sample) -> tuple:
    return (s.scene.mesh, s.scene.transform, s.scene.camera)


def run_sweep(config: SweepConfig | str | Path, out: str | Path, *, fmt: str = "folder",
              shard_size: int = 1000, workers: int = 0, executor: str = "local",
              ray_address: str | None = None, batch_size: int = 8, threads: int | None = None,
              quiet: bool = False, verify: bool = False,
              limit: int | None = None, settings=None) -> RunSummary:
    """Render a sweep into ``out`` (resuming whatever an earlier run left).

    Args:
        config: a :class:`SweepConfig` or the path of a sweep YAML file.
        out: output folder (created if missing).
        fmt: ``folder`` (files per sample) or ``webdataset`` (tar shards).
        shard_size: samples per shard (webdataset).
        workers: local: 0 renders in this process, N > 0 in N spawned processes. ray: the
            CPUs of a local cluster (default: all); ignored with ``ray_address``.
        executor: ``local`` or ``ray``.
        ray_address: a Ray cluster's address (``ray.init(address=...)``); none starts a
            local cluster.
        batch_size: samples of one resolution/method rendered in one tensor pass.
        threads: torch CPU threads per rendering process (default: torch's own when
            serial, cores / workers for local workers, 1 for Ray tasks).
        quiet: no progress bar.
        verify: on resume, check the sha256 of existing files (else their sizes).
        limit: render at most this many of the remaining samples (then stop cleanly).
        settings: how every render runs (:class:`~torchrefract.settings.RenderSettings`,
            default: the settings in force); ``threads`` above overrides its own.

    Returns:
        A :class:`RunSummary`; failed samples are listed in it and in the manifest.

    Raises:
        ConfigError: bad arguments, an invalid config, or ``out`` holding another sweep.
    """
    t_start = time.perf_counter()
    if fmt not in FORMATS:
        raise ConfigError(f"format: expected one of {list(FORMATS)}, got {fmt!r}")
    if executor not in EXECUTORS:
        raise ConfigError(f"executor: expected one of {list(EXECUTORS)}, got {executor!r}")
    for name, v, lo in (("batch_size", batch_size, 1), ("shard_size", shard_size, 1),
                        ("workers", workers, 0)):
        if not isinstance(v, int) or v < lo:
            raise ConfigError(f"{name}: expected an integer >= {lo}, got {v!r}")
    from torchrefract.settings import current  # noqa: PLC0415

    settings = settings if settings is not None else current()
    if threads:
        settings = settings.replace(threads=threads)
    cfg = config if isinstance(config, SweepConfig) else load_sweep(config)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    lock = _Lock(out)
    summary = RunSummary(out=str(out), format=fmt, executor=executor, workers=workers,
                         num_samples=cfg.num_samples)
    ex = None
    shards: _TarShards | None = None
    manifest: _Manifest | None = None
    try:
        _remove_temporaries(out)
        _check_sweep_record(out, cfg, fmt)
        latest = latest_entries(read_manifest(out / MANIFEST))
        done, last_shard = _completed(out, fmt, latest, verify)
        summary.skipped = len(done)
        todo: list[Sample] = []
        planned_failures: list[dict] = []
        for i in range(cfg.num_samples):
            sid = cfg.sample_id(i)
            if sid in done:
                continue
            try:
                todo.append(cfg.sample(i))
            except ConfigError as exc:  # an invalid combination: that sample fails alone
                planned_failures.append({"sample_id": sid, "index": i, "status": "failed",
                                         "reason": _failure(exc),
                                         "config_hash": cfg.config_hash})
        if limit is not None:
            todo = todo[:limit]
        batches = _plan_batches(todo, batch_size)
        manifest = _Manifest(out / MANIFEST)
        if fmt == "webdataset":
            shards = _TarShards(out, shard_size, last_shard + 1)
        summary.plan_s = time.perf_counter() - t_start

        t = time.perf_counter()
        manifest.append([dict(r, run=_run_info()) for r in planned_failures])
        summary.manifest_s += time.perf_counter() - t
        summary.failed += len(planned_failures)
        summary.failed_ids += [r["sample_id"] for r in planned_failures]

        t_ex = time.perf_counter()
        if batches:
            ex = _make_executor(executor, workers, settings, ray_address, quiet)
        _drive(cfg, out, fmt, ex, batches, manifest, shards, summary, quiet, t_ex)
        if shards is not None:
            t = time.perf_counter()
            recs = shards.close()
            summary.write_s += time.perf_counter() - t
            t = time.perf_counter()
            manifest.append(recs)
            summary.manifest_s += time.perf_counter() - t
        t = time.perf_counter()
        manifest.close()
        manifest.compact()
        summary.manifest_s += time.perf_counter() - t
    finally:
        if shards is not None:
            shards.abort()
        if manifest is not None and not manifest.f.closed:
            manifest.close()
        if ex is not None:
            t = time.perf_counter()
            ex.close()
            summary.shutdown_s = time.perf_counter() - t
        summary.wall_s = time.perf_counter() - t_start
        try:
            with open(out / RUN_LOG, "a") as f:
                f.write(json.dumps(dict(summary.to_dict(), run=_run_info())) + "\n")
        finally:
            lock.release()
    return summary


def _run_info() -> dict:
    import torch  # noqa: PLC0415

    return {"finished_at": datetime.now(timezone.utc).isoformat(timespec="milliseconds"),
            "driver_host": socket.gethostname(), "driver_pid": os.getpid(),
            "python": sys.version.split()[0], "torch_version": torch.__version__,
            "machine": platform.platform()}


def _make_executor(executor: str, workers: int, settings, ray_address: str | None,
                   quiet: bool):
    if executor == "ray":
        return _RayExecutor(ray_address, workers, settings, quiet)
    if workers == 0:
        return _SerialExecutor(settings)
    return _ProcessExecutor(workers, settings)


class _WriterThread:
    """Writes finished batches in order in a background thread, so that this process can
    render the next batch meanwhile (serial runs) or collect the next result. Rendering
    stays in the calling thread: the EGL context belongs to it."""

    def __init__(self, write: Callable[..., None], depth: int = 2):
        import queue  # noqa: PLC0415
        import threading  # noqa: PLC0415

        self.write, self.error = write, None
        self.q: queue.Queue = queue.Queue(maxsize=depth)
        self.thread = threading.Thread(target=self._run, name="torchrefract-writer",
                                       daemon=True)
        self.thread.start()

    def _run(self) -> None:
        while True:
            job = self.q.get()
            if job is None:
                return
            if self.error is None:
                try:
                    self.write(*job)
                except BaseException as exc:  # noqa: BLE001 - re-raised in the caller
                    self.error = exc

    def put(self, *job) -> None:
        if self.error is not None:
            raise self.error
        self.q.put(job)

    def close(self) -> None:
        self.q.put(None)
        self.thread.join()
        if self.error is not None:
            raise self.error


def _drive(cfg: SweepConfig, out: Path, fmt: str, ex, batches: list[list[Sample]],
           manifest: _Manifest, shards: _TarShards | None, summary: RunSummary,
           quiet: bool, t_executor: float) -> None:
    """Keep the executor busy with a window of batches; write results in plan order."""
    from tqdm import tqdm  # noqa: PLC0415

    total = sum(len(b) for b in batches)
    if not total:
        return
    bar = tqdm(total=total, unit="frame", disable=quiet, dynamic_ncols=True,
               desc=cfg.name, smoothing=0.05, file=sys.stderr)
    if summary.skipped and not quiet:
        bar.write(f"{cfg.name}: {summary.skipped} sample(s) already complete in {out}, "
                  f"{total} to render")
    pending: deque = deque()
    it = iter(batches)

    def fill() -> None:
        while len(pending) < ex.window:
            b = next(it, None)
            if b is None:
                return
            items = [(s.params["index"], s.sample_id, s.scene) for s in b]
            pending.append((b, ex.submit(items)))

    def write(batch: list[Sample], results: list[dict]) -> None:
        _write_batch(cfg, out, fmt, batch, results, manifest, shards, summary)
        bar.update(len(batch))
        if summary.failed:
            bar.set_postfix(failed=summary.failed, refresh=False)

    writer = _WriterThread(write)
    first = None
    try:
        fill()
        while pending:
            batch, fut = pending.popleft()
            fill()
            t = time.perf_counter()
            try:
                results = fut.result()
            except Exception as exc:  # noqa: BLE001 - a worker died: fail this batch only
                results = [{"index": s.params["index"], "sample_id": s.sample_id, "ok": False,
                            "reason": f"worker failed: {_failure(exc)}", "timings": {},
                            "batch_size": len(batch)} for s in batch]
            now = time.perf_counter()
            summary.wait_s += now - t
            if first is None:  # start-up: the first result's wait beyond its render
                first = now
                render = max((r.get("timings", {}).get("batch", {}).get("total", 0.0)
                              for r in results), default=0.0)
                summary.startup_s = max(0.0, now - t_executor - render)
            writer.put(batch, results)
    finally:
        try:
            writer.close()
        finally:
            bar.close()


def _write_batch(cfg: SweepConfig, out: Path, fmt: str, batch: list[Sample],
                 results: list[dict], manifest: _Manifest, shards: _TarShards | None,
                 summary: RunSummary) -> None:
    t0 = time.perf_counter()
    records = []
    batch_render = batch_encode = 0.0
    for sample, res in zip(batch, results):
        meta = _sample_meta(cfg, sample)
        if res["ok"] and "result" in res:  # rendered in this process, not yet encoded
            te = time.perf_counter()
            try:
                res.update(_encode(res.pop("result"), res.pop("result_index"), sample.scene))
            except Exception as exc:  # noqa: BLE001
                res.update(ok=False, reason=_failure(exc))
            res["timings"]["encode_s"] = time.perf_counter() - te
            batch_encode += res["timings"]["encode_s"]
        timings = dict(res.get("timings", {}))
        if "batch" in timings:
            batch_render = max(batch_render, timings["batch"]["total"])
        run = {k: res.get(k) for k in ("batch_size", "host", "pid", "torch_threads",
                                       "warnings") if k in res}
        if not res["ok"]:
            summary.failed += 1
            summary.failed_ids.append(sample.sample_id)
            records.append(dict(meta, status="failed", reason=res["reason"],
                                timings=timings, worker=run))
            continue
        if "auto_blend" in res:
            meta["auto_blend"] = res["auto_blend"]
        rec = dict(meta, channels=res["channels"], status="ok", reason=None,
                   sha256=res["sha256"],
                   bytes={"exr": len(res["exr"]), "png": len(res["png"])},
                   timings=timings, worker=run)
        if fmt == "folder":
            tw = time.perf_counter()
            files = {"exr": f"{sample.sample_id}.exr", "png": f"{sample.sample_id}.png"}
            write_bytes_atomic(out / files["exr"], res["exr"])
            write_bytes_atomic(out / files["png"], res["png"])
            rec["files"] = files
            timings["write_s"] = time.perf_counter() - tw
            records.append(rec)
        else:
            sample_json = json.dumps(dict(meta, channels=res["channels"]), indent=1,
                                     allow_nan=False).encode()
            records.extend(shards.add(sample.sample_id, [("exr", res["exr"]),
                                                          ("png", res["png"]),
                                                          ("json", sample_json)], rec))
        summary.ok += 1
    # Count each batch's render once (every sample of it carries the batch's timing).
    summary.render_s += batch_render
    if fmt == "folder" and records:
        _fsync_dir(out)  # the renames are durable before the manifest names the files
    t1 = time.perf_counter()
    summary.encode_s += batch_encode
    summary.write_s += t1 - t0 - batch_encode
    run = _run_info()
    manifest.append([dict(r, run=run) for r in records])
    summary.manifest_s += time.perf_counter() - t1

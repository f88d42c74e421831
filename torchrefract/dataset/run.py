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
   and extrinsics, method, seeds, timings, package version and config hash. Its file and
   input paths are relative to ``DIR`` (:mod:`~torchrefract.dataset.paths`), so the folder
   can be copied elsewhere and still loads (and resumes, its inputs' relative layout kept).

Crash safety: every file is written to a temporary name, fsynced and renamed; manifest lines
are appended (flush + fsync) only after the files they describe are durable; a shard is
accepted on resume only when the manifest holds all of its samples (otherwise it is deleted
and its samples rendered again). So a ``kill -9`` at any moment loses at most the batches in
flight, and running the same command again completes the dataset with no duplicate or
corrupt files. At the end of a run the manifest is rewritten (atomically) with one line per
sample in index order. A lock file keeps two runs from writing into one folder.

Determinism: the same config and seed give byte-identical EXR and PNG files (and shards),
whatever the executor, worker count or batch size.
Modules: :mod:`~torchrefract.dataset.manifest` (the manifest file),
:mod:`~torchrefract.dataset.shards` (tar shards), :mod:`~torchrefract.dataset.executors`
(rendering a batch, in this process, worker processes or Ray),
:mod:`~torchrefract.dataset.encode` (a sample's file bytes) and
:mod:`~torchrefract.dataset.records` (a sample's metadata); this one plans and drives a run.
"""

from __future__ import annotations

import errno
import fcntl
import hashlib
import json
import os
import platform
import re
import socket
import sys
import time
import warnings
from collections import deque
from dataclasses import asdict, dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Callable

from torchrefract.checks import ConfigError
from torchrefract.dataset.encode import _encode, channel_layout, encode_exr, encode_png
from torchrefract.dataset.attempt import failure_reason
from torchrefract.dataset.executors import _make_executor, render_items
from torchrefract.dataset.manifest import MANIFEST, _Manifest, latest_entries, read_manifest
from torchrefract.dataset.paths import map_scene_paths, relative_path
from torchrefract.dataset.records import _sample_meta, camera_metadata
from torchrefract.dataset.relight import sources as relight_sources
from torchrefract.dataset.shards import _completed_shards, _TarShards
from torchrefract.dataset.sweep import Sample, SweepConfig, load_sweep
from torchrefract.output.atomic import write_bytes
from torchrefract.output.images import check_exr_compression

# Names other modules imported from here before the split (kept importable).
__all__ = ["EXECUTORS", "FORMATS", "MANIFEST", "DiskFullError", "RunSummary", "camera_metadata",
           "channel_layout", "encode_exr", "encode_png", "latest_entries", "read_manifest",
           "render_items", "run_sweep"]

SWEEP_RECORD = "sweep.json"
RUN_LOG = "runs.jsonl"
LOCK = ".lock"
FORMATS = ("folder", "webdataset")
EXECUTORS = ("local", "ray")
# Temporary files of torchrefract.output.atomic (every writer's): ".<name>.<random>.tmp[...]".
_TMP_RE = re.compile(r"^\..+\.tmp(\.[A-Za-z0-9]+)?$")


class DiskFullError(RuntimeError):
    """The dataset folder's file system is full (or its quota spent): the run stopped
    there. Every sample the manifest records is whole (no partial file is left: the writes
    are atomic, an unfinished shard is deleted); the same command resumes once there is
    space again."""


def _log_run(out: Path, line: bytes) -> None:
    """Append the run's line to ``RUN_LOG``, whole or not at all (a full disk leaves it
    out rather than cut: the error the run stops with is the one reported)."""
    try:
        fd = os.open(out / RUN_LOG, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o666)
    except OSError:
        return
    try:
        start = os.lseek(fd, 0, os.SEEK_END)
        try:
            written = os.write(fd, line)
        except OSError:
            written = -1
        if written != len(line):
            os.ftruncate(fd, start)
    except OSError:
        pass
    finally:
        os.close(fd)


def _disk_full(out: Path, exc: OSError) -> DiskFullError:
    where = f" (writing {exc.filename})" if exc.filename else ""
    return DiskFullError(
        f"{out}: no space left on its file system{where}: {exc.strerror}. The run stopped; "
        f"the samples written so far are complete and recorded. Free space (or move the "
        f"folder) and run the same command again to resume.")


@dataclass
class RunSummary:
    """What a run did, and where its wall time went (seconds)."""

    out: str
    format: str
    executor: str
    workers: int
    num_samples: int
    exr_compression: str = "zip"
    """The EXR files' compression (:data:`torchrefract.output.images.EXR_COMPRESSIONS`)."""
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
    """EXR/PNG encoding done in this process (serial runs; workers encode their own),
    summed over the samples (encoded several at a time)."""
    encode_wall_s: float = 0.0
    """The wall time this process spent encoding, between renders (serial runs)."""
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
        """(planning + encoding here + writing + manifest) / wall time: the run's own work
        (the writing by the writer thread while the next batch renders)."""
        own = self.plan_s + self.write_s + self.manifest_s + self.encode_s
        return own / self.wall_s if self.wall_s > 0 else 0.0

    @property
    def overhead_fraction(self) -> float:
        """Share of the wall time the main thread was neither waiting for rendered results
        nor encoding them: planning, start-up of workers and the writes that did not
        overlap rendering."""
        busy = self.wait_s + self.encode_wall_s
        return max(0.0, self.wall_s - busy) / self.wall_s if self.wall_s > 0 else 0.0

    def to_dict(self) -> dict:
        d = asdict(self)
        d.update(samples_per_s=self.samples_per_s, overhead_fraction=self.overhead_fraction,
                 own_work_fraction=self.own_work_fraction,
                 steady_samples_per_s=self.steady_samples_per_s)
        return d



class _Lock:
    """An exclusive lock on ``out``: one run writes into a folder at a time."""

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
    """Delete the temporary files an interrupted run left; returns how many."""
    n = 0
    for p in out.iterdir():
        if p.is_file() and _TMP_RE.match(p.name):
            p.unlink()
            n += 1
    return n


def _check_sweep_record(out: Path, cfg: SweepConfig, fmt: str, adaptive: bool
                        ) -> tuple[bool, int | None]:
    """Refuse a folder holding another sweep or format; record this sweep in a new one.
    Returns whether its samples are rendered with adaptive sampling: as the record says
    (a record without it is from before adaptive sampling was the default: False), so
    that a resumed folder's images are all made alike; else ``adaptive``. And the image
    revision the folder was begun at (``torchrefract.IMAGE_REVISION``; None: a record from
    before revisions were recorded)."""
    from torchrefract import IMAGE_REVISION, __version__  # noqa: PLC0415

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
            return bool(rec.get("adaptive", False)), rec.get("image_revision")
    if not (out / MANIFEST).exists():  # (a manifest without its record is resumed)
        others = sorted(p.name for p in out.iterdir() if not p.name.startswith("."))
        if others:
            raise ConfigError(
                f"{out} is not empty and holds no sweep (no {SWEEP_RECORD} or {MANIFEST}): "
                f"its files ({', '.join(others[:3])}{', ...' if len(others) > 3 else ''}) "
                f"could be overwritten; use an empty or new --out folder")
    # Paths relative to the folder (a moved dataset keeps them valid); the config as written.
    source = cfg.source
    if source and os.path.isfile(source):
        source = relative_path(os.path.abspath(source), out)
    base = map_scene_paths(cfg.base.to_dict(), lambda p: relative_path(p, out))
    record = {"name": cfg.name, "config_hash": cfg.config_hash, "format": fmt,
              "num_samples": cfg.num_samples, "source": source,
              "sampling": asdict(cfg.sampling), "config": cfg.raw,
              "base_scene": base, "adaptive": adaptive, "torchrefract_version": __version__,
              "image_revision": IMAGE_REVISION,
              "created": datetime.now(timezone.utc).isoformat(timespec="seconds")}
    write_bytes(path, (json.dumps(record, indent=2, default=str) + "\n").encode(), fsync=True)
    return adaptive, IMAGE_REVISION

def _completed(out: Path, fmt: str, latest: dict[str, dict], verify: bool
               ) -> tuple[set[str], int]:
    """Sample ids whose files are complete and the last shard number (-1: none, or the
    folder format); deletes shards no complete record covers."""
    if fmt != "folder":
        return _completed_shards(out, latest, verify)
    done: set[str] = set()
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


def _plan_batches(todo: list[Sample], batch_size: int,
                  sources: dict[str, Sample] | None = None) -> list[list[Sample]]:
    """Group samples into batches of one resolution, supersampling, method and options.
    In relight mode (``sources``: each sample's relight source) a relight group's samples
    are kept side by side and in one batch where it fits (:func:`_pack`)."""
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
        if sources is not None:
            batches.extend(_pack(g, batch_size, sources))
        else:
            batches.extend(g[k:k + batch_size] for k in range(0, len(g), batch_size))
    return batches


def _pack(g: list[Sample], batch_size: int, sources: dict[str, Sample]) -> list[list[Sample]]:
    """Batches of whole relight groups (first-seen order; a group larger than
    ``batch_size`` split into chunks of it): a batch renders each group's source once."""
    groups: dict[str, list[Sample]] = {}
    for smp in g:
        groups.setdefault(sources[smp.sample_id].sample_id, []).append(smp)
    batches: list[list[Sample]] = []
    cur: list[Sample] = []
    for members in groups.values():
        if cur and len(cur) + len(members) > batch_size:
            batches.append(cur)
            cur = []
        for k in range(0, len(members), batch_size):
            part = members[k:k + batch_size]
            if len(part) == batch_size:
                batches.append(part)
            else:
                cur.extend(part)
    if cur:
        batches.append(cur)
    return batches


def _view_key(s: Sample) -> tuple:
    """What a sample's G-buffer depends on."""
    return (s.scene.mesh, s.scene.transform, s.scene.camera)



def _check_args(fmt: str, executor: str, batch_size, shard_size, workers) -> None:
    """Raise ConfigError for an unknown format or executor, or a bad size or count."""
    if fmt not in FORMATS:
        raise ConfigError(f"format: expected one of {list(FORMATS)}, got {fmt!r}")
    if executor not in EXECUTORS:
        raise ConfigError(f"executor: expected one of {list(EXECUTORS)}, got {executor!r}")
    for name, v, lo in (("batch_size", batch_size, 1), ("shard_size", shard_size, 1),
                        ("workers", workers, 0)):
        if not isinstance(v, int) or v < lo:
            raise ConfigError(f"{name}: expected an integer >= {lo}, got {v!r}")


def _warn_revision(out: Path, revision: int | None, done: int) -> None:
    """Warn where ``done`` samples of ``out`` were rendered at another image revision than
    this code's: the resumed folder would hold images of both (nothing is deleted; each
    sample's record carries its revision, so the two sets can be told apart)."""
    from torchrefract import IMAGE_REVISION  # noqa: PLC0415

    if done and revision != IMAGE_REVISION:
        begun = "an unrecorded revision (before 1)" if revision is None else \
            f"image revision {revision}"
        warnings.warn(f"{out}: its {done} finished samples were rendered at {begun}; this "
                      f"torchrefract renders revision {IMAGE_REVISION}, whose default images "
                      f"differ. The new samples are rendered at {IMAGE_REVISION} (each "
                      f"record's image_revision tells them apart); use a new --out folder "
                      f"for a dataset made alike.", stacklevel=3)


PLAN_BAR_FROM = 10_000
"""Samples from which the plan shows a progress bar of its own (``quiet`` hides it)."""


def _plan(cfg: SweepConfig, out: Path, fmt: str, verify: bool, limit: int | None,
          summary: RunSummary, settings, quiet: bool = True
          ) -> tuple[list[Sample], list[dict], int, object]:
    """Resume what an earlier run left in ``out`` and list what remains.

    Returns the samples to render (at most ``limit``), the records of samples that fail
    already when expanded (an invalid combination fails alone), the last shard's number
    (-1: none), and ``settings`` with the folder's adaptive sampling
    (:func:`_check_sweep_record`). Sets ``summary.skipped``.
    """
    _remove_temporaries(out)
    adaptive, revision = _check_sweep_record(out, cfg, fmt, settings.adaptive)
    if adaptive != settings.adaptive:
        if not quiet:
            print(f"{out}: resumed with adaptive sampling {'on' if adaptive else 'off'}, as "
                  "its first samples were rendered", file=sys.stderr)
        settings = settings.replace(adaptive=adaptive)
    latest = latest_entries(read_manifest(out / MANIFEST))
    done, last_shard = _completed(out, fmt, latest, verify)
    summary.skipped = len(done)
    _warn_revision(out, revision, len(done))
    todo: list[Sample] = []
    planned_failures: list[dict] = []
    from tqdm import tqdm  # noqa: PLC0415

    # a large sweep's plan takes a while: shown as it is made
    for i in tqdm(range(cfg.num_samples), desc="planning", unit="sample", leave=False,
                  disable=quiet or cfg.num_samples < PLAN_BAR_FROM, dynamic_ncols=True):
        sid = cfg.sample_id(i)
        if sid in done:
            continue
        try:
            todo.append(cfg.sample(i))
        except ConfigError as exc:  # an invalid combination: that sample fails alone
            planned_failures.append({"sample_id": sid, "index": i, "status": "failed",
                                     "reason": failure_reason(exc),
                                     "config_hash": cfg.config_hash})
    if limit is not None:
        todo = todo[:limit]
    return todo, planned_failures, last_shard, settings


def run_sweep(config: SweepConfig | str | Path, out: str | Path, *, fmt: str = "folder",
              shard_size: int = 1000, workers: int = 0, executor: str = "local",
              ray_address: str | None = None, batch_size: int = 8, threads: int | None = None,
              quiet: bool = False, verify: bool = False,
              limit: int | None = None, settings=None,
              exr_compression: str = "zip") -> RunSummary:
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
        exr_compression: the EXR files' (lossless: ``images.EXR_COMPRESSIONS``); each
            sample's record names its own.

    Returns:
        A :class:`RunSummary`; failed samples are listed in it and in the manifest.

    Raises:
        ConfigError: bad arguments, an invalid config, or ``out`` holding another sweep.
    """
    t_start = time.perf_counter()
    _check_args(fmt, executor, batch_size, shard_size, workers)
    check_exr_compression(exr_compression)
    from torchrefract.settings import current  # noqa: PLC0415

    settings = settings if settings is not None else current()
    if threads:
        settings = settings.replace(threads=threads)
    cfg = config if isinstance(config, SweepConfig) else load_sweep(config)
    if cfg.relight:  # relit from mattes, which shade every pixel: the rendered samples alike
        settings = settings.replace(adaptive=False)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    lock = _Lock(out)
    summary = RunSummary(out=str(out), format=fmt, executor=executor, workers=workers,
                         num_samples=cfg.num_samples, exr_compression=exr_compression)
    ex = None
    shards: _TarShards | None = None
    manifest: _Manifest | None = None
    try:
        todo, planned_failures, last_shard, settings = _plan(cfg, out, fmt, verify, limit,
                                                             summary, settings, quiet)
        sources = relight_sources(cfg, todo) if cfg.relight else None
        batches = _plan_batches(todo, batch_size, sources)
        manifest = _Manifest(out / MANIFEST)
        if fmt == "webdataset":
            shards = _TarShards(out, shard_size, last_shard + 1)
        summary.plan_s = time.perf_counter() - t_start

        _record_failures(manifest, planned_failures, summary)
        t_ex = time.perf_counter()
        if batches:
            ex = _make_executor(executor, workers, settings, ray_address, quiet,
                                exr_compression)
        _drive(cfg, out, fmt, ex, batches, manifest, shards, summary, quiet, t_ex, sources)
        _finish(manifest, shards, summary)
    except OSError as exc:
        if exc.errno in (errno.ENOSPC, errno.EDQUOT):
            raise _disk_full(out, exc) from exc
        raise
    finally:
        _close_run(out, lock, ex, manifest, shards, summary, t_start)
    return summary


def _record_failures(manifest: _Manifest, records: list[dict], summary: RunSummary) -> None:
    """Append the records of samples that failed at planning, and count them."""
    t = time.perf_counter()
    manifest.append([dict(r, run=_run_info()) for r in records])
    summary.manifest_s += time.perf_counter() - t
    summary.failed += len(records)
    summary.failed_ids += [r["sample_id"] for r in records]


def _close_run(out: Path, lock: "_Lock", ex, manifest: _Manifest | None,
               shards: _TarShards | None, summary: RunSummary, t_start: float) -> None:
    """The end of a run, finished or not: an unfinished shard deleted, the manifest and the
    executor closed, the run's line logged and the folder's lock released."""
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
        _log_run(out, (json.dumps(dict(summary.to_dict(), run=_run_info())) + "\n").encode())
    finally:
        lock.release()


def _finish(manifest: _Manifest, shards: _TarShards | None, summary: RunSummary) -> None:
    """Close the last shard and record its samples, then close and compact the manifest."""
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


def _run_info() -> dict:
    """Where and when records were written (the ``run`` entry of a manifest line)."""
    import torch  # noqa: PLC0415

    return {"finished_at": datetime.now(timezone.utc).isoformat(timespec="milliseconds"),
            "driver_host": socket.gethostname(), "driver_pid": os.getpid(),
            "python": sys.version.split()[0], "torch_version": torch.__version__,
            "machine": platform.platform()}


class _WriterThread:
    """Writes finished, encoded batches in order in a background thread: their files'
    writes and fsyncs wait on the disk while this process renders the next batch (serial
    runs) or collects the next result. Rendering stays in the calling thread: the EGL
    context belongs to it."""

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
           quiet: bool, t_executor: float, sources: dict[str, Sample] | None = None) -> None:
    """Keep the executor busy with a window of batches; write results in plan order. In
    relight mode each item carries its relight group's source (``sources``)."""
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
            if sources is not None:
                items = [it + ((src.params["index"], src.sample_id, src.scene),)
                         for it in items for src in (sources[it[1]],)]
            pending.append((b, ex.submit(items)))

    def write(batch: list[Sample], results: list[dict], encode_s: float) -> None:
        _write_batch(cfg, out, fmt, batch, results, manifest, shards, summary, encode_s)
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
                            "reason": f"worker failed: {failure_reason(exc)}", "timings": {},
                            "batch_size": len(batch)} for s in batch]
            now = time.perf_counter()
            summary.wait_s += now - t
            if first is None:  # start-up: the first result's wait beyond its render
                first = now
                render = max((r.get("timings", {}).get("batch", {}).get("total", 0.0)
                              for r in results), default=0.0)
                summary.startup_s = max(0.0, now - t_executor - render)
            t = time.perf_counter()  # encoded between renders
            encode_s = _encode_batch(batch, results, summary.exr_compression)
            summary.encode_wall_s += time.perf_counter() - t
            writer.put(batch, results, encode_s)
    finally:
        try:
            writer.close()
        finally:
            bar.close()


def _encode_batch(batch: list[Sample], results: list[dict], exr_compression: str = "zip"
                  ) -> float:
    """Encode, in place, the samples of a batch rendered in this process (not yet encoded:
    the EXR and PNG bytes and their hashes), as many at once as the run has torch threads
    (zlib, OpenEXR and hashlib let go of the GIL), between two renders: encoded beside the
    next render, its threads and these took each other's cores (docs/datasets.md, section
    4). A sample whose encoding fails is recorded as failed. Returns the samples' encoding
    times, summed."""
    todo = [(s, r) for s, r in zip(batch, results) if r["ok"] and "result" in r]

    def one(item: tuple[Sample, dict]) -> float:
        sample, res = item
        te = time.perf_counter()
        try:
            res.update(_encode(res.pop("result"), res.pop("result_index"), sample.scene,
                               exr_compression))
        except Exception as exc:  # noqa: BLE001
            res.update(ok=False, reason=failure_reason(exc))
        res["timings"]["encode_s"] = time.perf_counter() - te
        return res["timings"]["encode_s"]

    from torchrefract.output.export import in_threads  # noqa: PLC0415

    return sum(in_threads(one, todo, "torchrefract-encode"))


def _write_batch(cfg: SweepConfig, out: Path, fmt: str, batch: list[Sample],
                 results: list[dict], manifest: _Manifest, shards: _TarShards | None,
                 summary: RunSummary, batch_encode: float) -> None:
    """Write one batch's files (or shard members), then append its manifest lines."""
    records = []
    batch_render = 0.0
    t_encoded = time.perf_counter()
    for sample, res in zip(batch, results):
        meta = _sample_meta(cfg, sample, out)
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
        for key in ("auto_blend", "auto_prediction"):  # auto: what it rendered and predicted
            if key in res:
                meta[key] = res[key]
        if res.get("relit_from"):  # relight mode: relit from that sample's matte
            meta["relit_from"] = res["relit_from"]
        rec = dict(meta, channels=res["channels"], exr_compression=summary.exr_compression,
                   status="ok", reason=None,
                   sha256=res["sha256"],
                   bytes={"exr": len(res["exr"]), "png": len(res["png"])},
                   timings=timings, worker=run)
        if fmt == "folder":
            tw = time.perf_counter()
            files = {"exr": f"{sample.sample_id}.exr", "png": f"{sample.sample_id}.png"}
            # Durable renames: the manifest names only files that survive a crash.
            write_bytes(out / files["exr"], res["exr"], fsync=True)
            write_bytes(out / files["png"], res["png"], fsync=True)
            rec["files"] = files
            timings["write_s"] = time.perf_counter() - tw
            records.append(rec)
        else:
            sample_json = json.dumps(dict(meta, channels=res["channels"],
                                          exr_compression=summary.exr_compression),
                                     indent=1, allow_nan=False).encode()
            records.extend(shards.add(sample.sample_id, [("exr", res["exr"]),
                                                          ("png", res["png"]),
                                                          ("json", sample_json)], rec))
        summary.ok += 1
    # Count each batch's render once (every sample of it carries the batch's timing).
    summary.render_s += batch_render
    t1 = time.perf_counter()
    summary.encode_s += batch_encode
    summary.write_s += t1 - t_encoded
    run = _run_info()
    manifest.append([dict(r, run=run) for r in records])
    summary.manifest_s += time.perf_counter() - t1

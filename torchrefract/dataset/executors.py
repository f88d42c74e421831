"""Executors of a sweep: render batches in this process, in spawned worker processes or as
Ray tasks. Each returns futures (``.result()``) of :func:`render_items`, the worker's task:
render a batch, fall back to one sample at a time when it fails, encode the files."""

from __future__ import annotations

import os
import socket
import time
from typing import Any, Callable

from torchrefract.checks import ConfigError
from torchrefract.dataset.attempt import failure_reason, render_batch
from torchrefract.dataset.encode import _encode, channel_layout
from torchrefract.scene.model import Scene


def render_items(items: list[tuple[int, str, Scene]], settings=None,
                 encode: bool = True, exr_compression: str = "zip") -> list[dict]:
    """Render one batch (the worker's task). Never raises for a bad sample.

    Args:
        items: ``(index, sample_id, scene)`` of one resolution, method and options; in a
            sweep's relight mode ``(index, sample_id, scene, source)``, ``source`` the
            ``(index, sample_id, scene)`` of the item's relight group's source
            (:mod:`torchrefract.dataset.relight`: those items are rendered once per group
            and relit; where that fails, rendered directly).
        settings: the :class:`~torchrefract.settings.RenderSettings` of the renders (None:
            those in force; ``threads`` sets torch's thread count for each render).
        encode: encode the EXR and PNG bytes (else return the tensors in ``result``).
        exr_compression: the EXR's (:data:`torchrefract.output.images.EXR_COMPRESSIONS`).

    Returns:
        One dict per item: ``index``, ``sample_id``, ``ok``, ``reason``, ``exr``, ``png``
        (bytes), ``sha256``, ``channels``, ``timings`` (seconds: this sample's share of
        the batch render, its encoding), ``batch_size``, ``warnings``, ``host``, ``pid``;
        a relit sample's ``relit_from`` (its source's sample id).
    """
    import torch  # noqa: PLC0415

    groups: list[tuple[list[int], Any, list[str], str | None, dict]] = []
    if items and len(items[0]) == 4:
        from torchrefract.dataset.relight import render_relit  # noqa: PLC0415

        try:
            groups = render_relit(items, settings)
        except Exception:  # noqa: BLE001 - no matte for this method, a source fails: direct
            groups = []
        items = [it[:3] for it in items]
    scenes = [s for _, _, s in items]
    if not groups:
        try:
            res, warn = render_batch(scenes, settings)
            groups.append((list(range(len(items))), res, warn, None, {}))
        except Exception as exc:  # noqa: BLE001 - any failure: retry alone, then report
            if len(items) == 1:
                groups.append(([0], None, [], failure_reason(exc), {}))
            else:
                for k, s in enumerate(scenes):
                    try:
                        res, warn = render_batch([s], settings)
                        groups.append(([k], res, warn, None, {}))
                    except Exception as exc1:  # noqa: BLE001
                        groups.append(([k], None, [], failure_reason(exc1), {}))
    out: list[dict | None] = [None] * len(items)
    host, pid = socket.gethostname(), os.getpid()
    for ks, res, warn, reason, extra in groups:
        for j, k in enumerate(ks):
            index, sid, scene = items[k]
            rec = {"index": index, "sample_id": sid, "ok": res is not None, "reason": reason,
                   "batch_size": len(ks), "warnings": warn, "host": host, "pid": pid,
                   "torch_threads": (settings.threads if settings is not None
                                     and settings.threads else torch.get_num_threads()),
                   "timings": {}}
            if "relit_from" in extra:
                rec["relit_from"] = extra["relit_from"]
            if res is not None:
                rec["timings"]["render_s"] = extra.get("render_s",
                                                       res.timings["total"] / len(ks))
                rec["timings"]["batch"] = dict(res.timings)
                rec["channels"] = channel_layout(res)
                if res.blends is not None:  # auto: the variants in the image, weighted
                    from torchrefract.output.export import blend_records  # noqa: PLC0415
                    rec["auto_blend"] = blend_records(res, j)
                if res.predictions is not None and res.predictions[j] is not None:
                    rec["auto_prediction"] = res.predictions[j]  # what auto's table said
                if encode:
                    t0 = time.perf_counter()
                    try:
                        rec.update(_encode(res, j, scene, exr_compression))
                    except Exception as exc:  # noqa: BLE001
                        rec.update(ok=False, reason=failure_reason(exc))
                    rec["timings"]["encode_s"] = time.perf_counter() - t0
                else:
                    rec["result"], rec["result_index"] = res, j
            out[k] = rec
    return out  # type: ignore[return-value]


class _Lazy:
    """A future computed when its result is asked for (the serial executor's)."""

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
        # Encoded by the driver between renders (dataset.run._encode_batch).
        return _Lazy(lambda: render_items(items, self.settings, encode=False))

    def close(self) -> None:
        pass


PARENT_POLL_S = 1.0
"""How often a worker process checks that its driver is still there."""


def exit_with_parent(parent: int) -> None:
    """A worker's initializer: a daemon thread ends the worker once its driver is gone (a
    driver killed by the OOM killer, a scheduler or ``kill -9`` cannot stop its workers,
    which would otherwise wait on their queue forever, reparented). Python's own exit of
    the driver shuts the pool down as before."""
    import threading  # noqa: PLC0415

    def watch() -> None:
        while True:
            time.sleep(PARENT_POLL_S)
            if os.getppid() != parent:
                os._exit(1)

    threading.Thread(target=watch, name="torchrefract-parent-watch", daemon=True).start()


class _ProcessExecutor:
    """``workers`` spawned processes; each creates its own EGL context on first use."""

    def __init__(self, workers: int, settings, exr_compression: str = "zip"):
        import multiprocessing as mp  # noqa: PLC0415
        from concurrent.futures import ProcessPoolExecutor  # noqa: PLC0415

        # 'spawn', not 'fork': an EGL context does not survive a fork, and a forked child of
        # a process that holds one hangs. (The parent never renders in this mode.)
        if settings.threads is None:
            settings = settings.replace(threads=max(1, (os.cpu_count() or 1) // workers))
        self.settings, self.exr_compression = settings, exr_compression
        self._new = lambda: ProcessPoolExecutor(
            max_workers=workers, mp_context=mp.get_context("spawn"),
            initializer=exit_with_parent, initargs=(os.getpid(),))
        self.pool = self._new()
        self.window = 2 * workers

    def submit(self, items):
        from concurrent.futures.process import BrokenProcessPool  # noqa: PLC0415

        try:
            return self.pool.submit(render_items, items, self.settings, True,
                                    self.exr_compression)
        except BrokenProcessPool:
            # A worker died (its batches in flight are reported failed and are retried by
            # the next run); carry on with fresh processes.
            self.pool.shutdown(wait=False, cancel_futures=True)
            self.pool = self._new()
            return self.pool.submit(render_items, items, self.settings, True,
                                    self.exr_compression)

    def close(self) -> None:
        self.pool.shutdown(wait=True, cancel_futures=True)


class _RayRef:
    """A future of a Ray task."""

    def __init__(self, ref):
        self.ref = ref

    def result(self):
        import ray  # noqa: PLC0415

        return ray.get(self.ref)


class _RayExecutor:
    """Ray tasks (one CPU each) on the cluster at ``address``, or on a local cluster."""

    def __init__(self, address: str | None, workers: int, settings, quiet: bool,
                 exr_compression: str = "zip"):
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
        self.exr_compression = exr_compression

    def submit(self, items):
        return _RayRef(self.task.remote(items, self.settings, True, self.exr_compression))

    def close(self) -> None:
        import ray  # noqa: PLC0415

        if self.started:
            ray.shutdown()


def _make_executor(executor: str, workers: int, settings, ray_address: str | None,
                   quiet: bool, exr_compression: str = "zip"):
    """The executor a run asked for (``local`` with 0 workers: this process, which encodes
    the files itself: ``exr_compression`` is the others')."""
    if executor == "ray":
        return _RayExecutor(ray_address, workers, settings, quiet, exr_compression)
    if workers == 0:
        return _SerialExecutor(settings)
    return _ProcessExecutor(workers, settings, exr_compression)


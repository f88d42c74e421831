"""Training-side datasets: read a rendered sweep, or render one on the fly.

Both return samples of the same form (a dict; ``C`` = channels, images channels-first by
default, ``layout="hwc"`` gives channels-last ``(H, W, C)`` instead)::

    {
      "radiance":  (3, H, W) float32 linear RGB, background included,
      "coverage":  (1, H, W) float32 object coverage in [0, 1],
      "passes":    {"depth_front": (1, H, W), "depth_back": (1, H, W),
                    "normal_front": (3, H, W), "normal_back": (3, H, W),
                    "thickness": (1, H, W), "roughness": (1, H, W), "ior": (1, H, W),
                    ... the method's own buffers},
      "K":               (3, 3) float32 intrinsics (OpenCV: pixel (i, j) centered at (i, j)),
      "world_to_camera": (4, 4) float32 extrinsics (OpenCV: x right, y down, z forward),
      "sample_id": str,
      "meta":      dict: the manifest record (params, scene, seeds, method, version, ...),
    }

:func:`collate` batches such samples, keeping ``meta`` a list of dicts (torch's default
collate would transpose the lists inside it).

A rendered dataset's paths are relative to its folder (:mod:`~torchrefract.dataset.paths`):
``meta`` holds them as stored (as the shards' ``.json`` members do), and
:meth:`RefractDataset.scene` resolves them. The folder can be copied or moved elsewhere.

Example:
    >>> from torch.utils.data import DataLoader
    >>> from torchrefract.dataset.loaders import RefractDataset, RenderStream, collate
    >>> ds = RefractDataset("out/sweep_demo")                                # doctest: +SKIP
    >>> batch = next(iter(DataLoader(ds, batch_size=4, collate_fn=collate)))  # doctest: +SKIP
    >>> batch["radiance"].shape                                              # doctest: +SKIP
    torch.Size([4, 3, 64, 64])
    >>> stream = RenderStream("configs/sweep_demo.yaml", batch_size=4)        # doctest: +SKIP
    >>> loader = DataLoader(stream, batch_size=4, num_workers=2, collate_fn=collate,
    ...                     multiprocessing_context="spawn")                 # doctest: +SKIP
"""

from __future__ import annotations

import io
import json
import os
import sys
import tarfile
import warnings
from pathlib import Path
from typing import Any, Iterator

import numpy as np
import torch
from torch.utils.data import Dataset, IterableDataset, get_worker_info

from torchrefract.checks import ConfigError
from torchrefract.dataset.encode import channel_layout
from torchrefract.dataset.manifest import MANIFEST, latest_entries, read_manifest
from torchrefract.dataset.paths import dataset_file, sample_scene
from torchrefract.dataset.records import _sample_meta, camera_metadata
from torchrefract.dataset.sweep import SweepConfig, load_sweep

LAYOUTS = ("chw", "hwc")


def _check_layout(layout: str) -> str:
    if layout not in LAYOUTS:
        raise ConfigError(f"layout: expected one of {list(LAYOUTS)}, got {layout!r}")
    return layout


def _image(a: np.ndarray, layout: str) -> torch.Tensor:
    """(H, W, C) array -> tensor in the chosen layout."""
    t = torch.from_numpy(np.ascontiguousarray(a, dtype=np.float32))
    return t.permute(2, 0, 1).contiguous() if layout == "chw" else t


def _camera_tensors(cam: dict) -> dict[str, torch.Tensor]:
    return {"K": torch.tensor(cam["K"], dtype=torch.float32),
            "world_to_camera": torch.tensor(cam["world_to_camera"], dtype=torch.float32)}


def decode_exr(data: bytes | str | Path, channels: dict | None = None, layout: str = "chw"
               ) -> dict[str, Any]:
    """Decode a sample EXR (bytes or path) into ``radiance``, ``coverage`` and ``passes``.

    Args:
        data: the file's bytes, or its path.
        channels: the record's channel layout (``{"radiance": [...], "coverage": [...],
            "passes": {name: [channel, ...]}}``); default: inferred from the names (``R, G,
            B``, ``A``, ``<pass>.X/Y/Z`` grouped, others one channel each).
        layout: ``chw`` or ``hwc``.
    """
    import OpenEXR  # noqa: PLC0415

    src = io.BytesIO(data) if isinstance(data, (bytes, bytearray)) else str(data)
    try:
        with OpenEXR.File(src, separate_channels=True) as f:
            ch = {k: np.asarray(v.pixels, dtype=np.float32) for k, v in f.channels().items()}
    except Exception as exc:  # noqa: BLE001
        raise ConfigError(f"cannot decode EXR ({exc})") from None
    if channels is None:
        passes: dict[str, list[str]] = {}
        for name in sorted(ch):
            if name in ("R", "G", "B", "A"):
                continue
            base = name.rsplit(".", 1)[0] if name[-2:] in (".X", ".Y", ".Z", ".W") else name
            passes.setdefault(base, []).append(name)
        channels = {"radiance": ["R", "G", "B"], "coverage": ["A"], "passes": passes}
    out: dict[str, Any] = {
        "radiance": _image(np.stack([ch[c] for c in channels["radiance"]], -1), layout),
        "coverage": _image(np.stack([ch[c] for c in channels["coverage"]], -1), layout),
        "passes": {name: _image(np.stack([ch[c] for c in cs], -1), layout)
                   for name, cs in channels["passes"].items()},
    }
    return out


def decode_wds(sample: dict, layout: str = "chw") -> dict[str, Any]:
    """Decode one raw sample of a ``webdataset.WebDataset`` pipeline over our shards.

    Example:
        >>> import webdataset as wds                                          # doctest: +SKIP
        >>> ds = wds.WebDataset("out/shard-{000000..000003}.tar").map(decode_wds)  # doctest: +SKIP
    """
    meta = json.loads(sample["json"])
    out = decode_exr(sample["exr"], meta.get("channels"), layout)
    out.update(_camera_tensors(meta["camera"]))
    out["sample_id"] = meta["sample_id"]
    out["meta"] = meta
    return out


def collate(samples: list[dict]) -> dict[str, Any]:
    """Batch samples: tensors stacked, ``passes`` per name, ``sample_id`` and ``meta`` lists.

    All samples of a batch must share one resolution and the same passes.
    """
    if not samples:
        raise ConfigError("collate: no samples")
    shapes = {tuple(x["radiance"].shape) for x in samples}
    if len(shapes) > 1:
        raise ConfigError(f"collate: samples of different sizes {sorted(shapes)} cannot share "
                          "a batch (sweep one resolution, or batch by resolution)")
    names = [sorted(x.get("passes", {})) for x in samples]
    if any(n != names[0] for n in names):
        raise ConfigError(f"collate: samples have different passes ({names[0]} vs "
                          f"{next(n for n in names if n != names[0])}; methods differ): "
                          "choose common ones, e.g. RefractDataset(..., passes=[...])")
    out: dict[str, Any] = {}
    for k, v in samples[0].items():
        if isinstance(v, torch.Tensor):
            out[k] = torch.stack([s[k] for s in samples])
        elif k == "passes":
            out[k] = {n: torch.stack([s[k][n] for s in samples]) for n in v}
        else:
            out[k] = [s[k] for s in samples]
    return out


class RefractDataset(Dataset):
    """Map-style dataset over a rendered sweep (folder of files or WebDataset shards).

    Reads ``DIR/manifest.jsonl`` and serves the samples whose status is ``ok``, in index
    order. Files are opened per item (safe with DataLoader workers, fork or spawn). The
    records' paths are relative to ``DIR`` (older ones absolute), so ``DIR`` may have been
    copied or moved since it was rendered; a file it lacks raises a ConfigError naming it.

    Args:
        root: the ``--out`` folder of ``torchrefract sweep``.
        layout: ``chw`` (default) or ``hwc`` for the images.
        passes: names of the passes to return (default: all).

    Raises:
        ConfigError: no manifest, or no complete sample in it.
    """

    def __init__(self, root: str | Path, layout: str = "chw", passes: list[str] | None = None):
        self.root = Path(root)
        self.layout = _check_layout(layout)
        self.pass_names = None if passes is None else list(passes)
        mpath = self.root / MANIFEST
        if not mpath.is_file():
            raise ConfigError(f"{self.root}: no {MANIFEST} (not the output of "
                              "`torchrefract sweep`, or the run has not finished a sample)")
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # a run in progress may be appending a line
            entries = latest_entries(read_manifest(mpath, repair=False))
        self.records = sorted((e for e in entries.values() if e.get("status") == "ok"),
                              key=lambda e: e["index"])
        self.failed = sorted(sid for sid, e in entries.items() if e.get("status") != "ok")
        if not self.records:
            raise ConfigError(f"{self.root}: the manifest lists no complete sample")
        self._offsets: dict[str, dict[str, tuple[int, int]]] = {}
        if self.pass_names is not None:  # a typo fails here, not in a DataLoader's worker
            self._passes(self.records[0], self._decode(self.records[0]))

    def _decode(self, rec: dict) -> dict[str, Any]:
        return decode_exr(self._read(rec, "exr"), rec.get("channels"), self.layout)

    def _passes(self, rec: dict, out: dict[str, Any]) -> dict[str, Any]:
        """The asked-for passes of a decoded sample (ConfigError naming a missing one)."""
        missing = [n for n in self.pass_names if n not in out["passes"]]
        if missing:
            raise ConfigError(f"{self.root}: sample {rec['sample_id']} has no pass "
                              f"{', '.join(map(repr, missing))} (it has "
                              f"{sorted(out['passes'])})")
        return {n: out["passes"][n] for n in self.pass_names}

    def __len__(self) -> int:
        return len(self.records)

    def _shard_index(self, rec: dict) -> dict[str, tuple[int, int]]:
        shard = rec["shard"]
        idx = self._offsets.get(shard)
        if idx is None:
            with tarfile.open(dataset_file(self.root, shard, rec["sample_id"])) as t:
                idx = {m.name: (m.offset_data, m.size) for m in t.getmembers() if m.isfile()}
            self._offsets[shard] = idx
        return idx

    def _read(self, rec: dict, ext: str) -> bytes:
        if "shard" in rec:
            member = rec["members"][ext]
            idx = self._shard_index(rec)
            if member not in idx:
                raise ConfigError(f"{self.root / rec['shard']}: no member {member!r} (sample "
                                  f"{rec['sample_id']}; the shard was replaced?)")
            off, size = idx[member]
            with open(self.root / rec["shard"], "rb") as f:
                f.seek(off)
                return f.read(size)
        return dataset_file(self.root, rec["files"][ext], rec["sample_id"]).read_bytes()

    def scene(self, i: int):
        """The :class:`~torchrefract.scene.Scene` of item ``i``, its mesh and maps resolved
        against the dataset folder (to render it again, or look at its inputs).

        Raises:
            ConfigError: an input file is missing (the dataset was copied without it),
                naming it and where it was looked for.
        """
        return sample_scene(self.records[i], self.root)

    def __getitem__(self, i: int) -> dict[str, Any]:
        if not -len(self) <= i < len(self):
            raise IndexError(f"index {i} out of range for {len(self)} samples")
        rec = self.records[i]
        out = self._decode(rec)
        if self.pass_names is not None:
            out["passes"] = self._passes(rec, out)
        out.update(_camera_tensors(rec["camera"]))
        out["sample_id"] = rec["sample_id"]
        out["meta"] = rec
        return out


class RenderStream(IterableDataset):
    """Render a sweep on the fly, in batches, as an IterableDataset.

    Sample ``i`` of the sweep depends only on the seed and ``i``
    (:mod:`torchrefract.dataset.sweep`), so the stream is reproducible, and DataLoader
    workers split the indices among themselves (worker ``w`` of ``n`` takes ``i = w, w + n,
    ...``): every sample comes exactly once per epoch, each from one worker. The native
    rasterizer (the default) holds no EGL context, so fork-started workers render too; after
    the OpenGL passes (``RenderSettings.rasterizer``) the main process holds one, which
    hangs in a forked child: then use ``multiprocessing_context="spawn"`` in the DataLoader
    (this class raises a clear error instead of hanging).

    Args:
        config: a sweep YAML path or a :class:`SweepConfig`.
        batch_size: samples rendered together (grouped by resolution); the DataLoader's own
            ``batch_size`` is independent.
        num_samples: for random sweeps, how many samples to stream (default: the config's;
            sample ``i`` is the same whatever this is).
        seed: replaces the config's seed (e.g. a new seed per epoch for fresh draws).
        start: first sample index (e.g. to resume a stream).
        layout: ``chw`` (default) or ``hwc``.
        on_error: ``skip`` (warn and leave a sample that cannot be rendered out) or ``raise``.
        threads: torch threads in each worker (default: the settings').
        settings: how the renders run (:class:`~torchrefract.settings.RenderSettings`;
            default: the environment's defaults, as for :func:`torchrefract.render`).
    """

    def __init__(self, config: str | Path | SweepConfig, batch_size: int = 4,
                 num_samples: int | None = None, start: int = 0, layout: str = "chw",
                 on_error: str = "skip", threads: int | None = None, seed: int | None = None,
                 settings=None):
        super().__init__()
        self.config = config if isinstance(config, SweepConfig) else load_sweep(config)
        if seed is not None:
            from dataclasses import replace  # noqa: PLC0415

            from torchrefract.checks import check_number  # noqa: PLC0415

            seed = check_number(seed, "seed", minimum=0, integer=True)
            self.config = replace(self.config,
                                  sampling=replace(self.config.sampling, seed=seed))
        if batch_size < 1:
            raise ConfigError(f"batch_size: expected >= 1, got {batch_size}")
        n = self.config.num_samples
        if num_samples is not None:
            if self.config.sampling.mode != "random" and num_samples > n:
                raise ConfigError(f"num_samples: a {self.config.sampling.mode} sweep has {n} "
                                  f"samples, got {num_samples}")
            n = num_samples
        if on_error not in ("skip", "raise"):
            raise ConfigError(f"on_error: expected 'skip' or 'raise', got {on_error!r}")
        if not isinstance(start, int) or not 0 <= start <= n:
            raise ConfigError(f"start: expected an integer in [0, {n}], got {start!r}")
        self.stop, self.start = n, start
        self.batch_size, self.layout, self.on_error = batch_size, _check_layout(layout), on_error
        if threads:
            from torchrefract.settings import RenderSettings  # noqa: PLC0415

            settings = (settings or RenderSettings.from_env()).replace(threads=threads)
        self.settings = settings

    def __len__(self) -> int:
        return max(0, self.stop - self.start)

    def _config_with(self, n: int) -> SweepConfig:
        if n == self.config.num_samples or self.config.sampling.mode != "random":
            return self.config
        from dataclasses import replace  # noqa: PLC0415

        return replace(self.config, sampling=replace(self.config.sampling, num_samples=n))

    def indices(self) -> range:
        """The sample indices this process yields (its DataLoader worker's share)."""
        info = get_worker_info()
        if info is None:
            return range(self.start, self.stop)
        return range(self.start + info.id, self.stop, info.num_workers)

    def __iter__(self) -> Iterator[dict[str, Any]]:
        from torchrefract.dataset.executors import render_items  # noqa: PLC0415

        if _INHERITED_CONTEXT and get_worker_info() is not None:
            raise RuntimeError(
                "RenderStream: this DataLoader worker was forked from a process that already "
                "holds an OpenGL (EGL) context, which cannot be used after a fork (it hangs). "
                "Pass multiprocessing_context='spawn' to the DataLoader, or do not render in "
                "the main process before starting the workers.")
        cfg = self._config_with(self.stop)
        idx = list(self.indices())
        for k in range(0, len(idx), self.batch_size):
            chunk = []
            for i in idx[k:k + self.batch_size]:
                try:
                    chunk.append(cfg.sample(i))
                except ConfigError as exc:
                    self._fail(cfg.sample_id(i), str(exc))
            groups: dict[tuple, list] = {}
            for s in chunk:
                c = s.scene.camera
                key = (c.width, c.height, c.samples_per_pixel, s.scene.method,
                       json.dumps(s.scene.method_options, sort_keys=True, default=str))
                groups.setdefault(key, []).append(s)
            done: dict[int, dict] = {}
            for g in groups.values():
                items = [(s.params["index"], s.sample_id, s.scene) for s in g]
                for s, r in zip(g, render_items(items, self.settings, encode=False)):
                    if not r["ok"]:
                        self._fail(s.sample_id, r["reason"])
                        continue
                    done[s.params["index"]] = self._sample(cfg, s, r)
            for i in sorted(done):  # index order within the chunk
                yield done[i]

    def _fail(self, sid: str, reason: str) -> None:
        if self.on_error == "raise":
            raise RuntimeError(f"RenderStream: sample {sid} failed: {reason}")
        warnings.warn(f"RenderStream: sample {sid} skipped: {reason}", RuntimeWarning,
                      stacklevel=3)

    def _sample(self, cfg: SweepConfig, s, r: dict) -> dict[str, Any]:
        res, j = r["result"], r["result_index"]
        layout = self.layout

        def img(t: torch.Tensor) -> torch.Tensor:  # (H, W, C) -> layout
            t = t.detach().to("cpu", torch.float32)
            return t.permute(2, 0, 1).contiguous() if layout == "chw" else t.contiguous()

        meta = dict(_sample_meta(cfg, s), channels=channel_layout(res), status="ok",
                    timings=r["timings"], warnings=r["warnings"])
        out = {"radiance": img(res.radiance[j]), "coverage": img(res.coverage[j][..., None]),
               "passes": {n: img(p[j]) for n, p in res.passes.items()}}
        out.update(_camera_tensors(camera_metadata(s.scene.camera)))
        out["sample_id"] = s.sample_id
        out["meta"] = meta
        return out


# A process forked after its parent created an EGL context cannot render (it hangs); note
# it so RenderStream can say so instead.
_INHERITED_CONTEXT = False


def _after_fork_in_child() -> None:
    global _INHERITED_CONTEXT
    raster = sys.modules.get("torchrefract.geometry.raster")  # no imports inside a fork hook
    _INHERITED_CONTEXT = raster is not None and raster._renderer is not None


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_after_fork_in_child)

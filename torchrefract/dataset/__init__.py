"""Datasets: sweeps of scenes (:mod:`~torchrefract.dataset.sweep`), resumable runs that
render them to files or shards (:mod:`~torchrefract.dataset.run`), and torch datasets that
read them back or render on the fly (:mod:`~torchrefract.dataset.loaders`). The names below
are imported when first used (the loaders import torch.utils.data, a run may import Ray)."""

from __future__ import annotations

import importlib

_NAMES = {
    "RefractDataset": "loaders", "RenderStream": "loaders", "collate": "loaders",
    "decode_exr": "loaders", "decode_wds": "loaders",
    "run_sweep": "run", "RunSummary": "run", "read_manifest": "manifest",
    "load_sweep": "sweep", "sweep_from_dict": "sweep", "expand": "sweep",
    "SweepConfig": "sweep", "Sample": "sweep",
    "sample_scene": "paths", "resolve_record": "paths",
}


def __getattr__(name: str):
    if name in _NAMES:
        return getattr(importlib.import_module(f"{__name__}.{_NAMES[name]}"), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = sorted(_NAMES)

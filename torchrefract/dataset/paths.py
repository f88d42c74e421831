"""Paths in a dataset's metadata: stored relative to the dataset folder, so a dataset that is
copied or moved elsewhere still loads.

Every path a run writes into ``manifest.jsonl``, a shard's ``<id>.json`` or ``sweep.json``
is relative to the dataset folder (``DIR``, the run's ``--out``), with forward slashes:

- the sample's own files (``000004.exr``, ``shard-000000.tar``), inside ``DIR``;
- its inputs: ``scene.mesh``, ``scene.envmap.path``, ``scene.material.roughness_map``,
  ``params["mesh"]``, ``params["envmap.path"]`` (e.g. ``../../assets/meshes/spot.ply``),
  and ``sweep.json``'s ``source`` (the sweep config) and ``base_scene``.

So a record's ``scene`` is a scene in SCENE_SPEC.md form whose paths are relative to a
YAML file in ``DIR``; :func:`sample_scene` rebuilds it. A dataset copied alone loads (its
images and metadata live inside it); copied together with its inputs, keeping their
relative layout, it re-renders and resumes too. Records written before paths were relative
hold absolute paths: they read the same way (an absolute path joined to ``DIR`` stays
itself).
"""

from __future__ import annotations

import os
from pathlib import Path

from torchrefract.checks import ConfigError

SCENE_PATHS = (("mesh",), ("envmap", "path"), ("material", "roughness_map"))
"""Where a scene dict (``Scene.to_dict()``) holds file paths."""
PARAM_PATHS = ("mesh", "envmap.path")
"""The swept parameters that are file paths."""


def relative_path(path: str | None, root: str | Path) -> str | None:
    """``path`` relative to ``root`` (posix separators); a relative or empty path as it is,
    an absolute one that has no relative form (another Windows drive) too."""
    if not path or not os.path.isabs(path):
        return path
    try:
        return Path(os.path.relpath(path, Path(root).resolve())).as_posix()
    except ValueError:
        return path


def absolute_path(path: str | None, root: str | Path) -> str | None:
    """A stored path as an absolute one: relative ones against ``root``."""
    if not path:
        return path
    return str((Path(root) / path).resolve())


def _map_paths(rec: dict, fn) -> dict:
    """A copy of a record (or a scene dict, under ``scene``) with ``fn`` applied to every
    input path in its scene and params."""
    out = dict(rec)
    if isinstance(rec.get("scene"), dict):
        out["scene"] = map_scene_paths(rec["scene"], fn)
    if isinstance(rec.get("params"), dict):
        out["params"] = {k: fn(v) if k in PARAM_PATHS and isinstance(v, str) else v
                         for k, v in rec["params"].items()}
    return out


def map_scene_paths(scene: dict, fn) -> dict:
    """A copy of a scene dict with ``fn`` applied to its mesh, env map and roughness map."""
    scene = dict(scene)
    for keys in SCENE_PATHS:
        d = scene
        for k in keys[:-1]:
            if not isinstance(d.get(k), dict):
                break
            d[k] = d = dict(d[k])
        else:
            if isinstance(d.get(keys[-1]), str):
                d[keys[-1]] = fn(d[keys[-1]])
    return scene


def portable_record(rec: dict, root: str | Path) -> dict:
    """A record with its input paths relative to the dataset folder ``root`` (for writing)."""
    return _map_paths(rec, lambda p: relative_path(p, root))


def resolve_record(rec: dict, root: str | Path) -> dict:
    """A record as read from the dataset folder ``root``, with absolute input paths (what
    :class:`~torchrefract.dataset.loaders.RenderStream` reports for the same sample)."""
    return _map_paths(rec, lambda p: absolute_path(p, root))


def dataset_file(root: str | Path, path: str, sample_id: str) -> Path:
    """A file of the dataset (EXR, PNG or shard) that a record names.

    Raises:
        ConfigError: it is missing, naming it, the sample and where it was looked for.
    """
    p = Path(root) / path
    if not p.is_file():
        raise ConfigError(f"{Path(root) / 'manifest.jsonl'}: sample {sample_id}: file "
                          f"{path!r} is missing (looked at {p}); was the dataset folder "
                          f"copied only in part?")
    return p


def sample_scene(rec: dict, root: str | Path):
    """The :class:`~torchrefract.scene.Scene` a record describes, its input paths resolved
    against the dataset folder ``root``.

    Raises:
        ConfigError: an input file (mesh, env map, roughness map) is missing, naming it,
            the sample and where it was looked for.
    """
    from torchrefract.scene import scene_from_dict  # noqa: PLC0415

    sid = rec.get("sample_id", "?")
    if not isinstance(rec.get("scene"), dict):
        raise ConfigError(f"{Path(root) / 'manifest.jsonl'}: sample {sid}: no scene recorded")
    missing: list[str] = []

    def check(p: str) -> str:
        a = absolute_path(p, root)
        if not os.path.isfile(a):
            missing.append(p)
        return a

    scene = map_scene_paths(rec["scene"], check)
    if missing:
        what = ", ".join(f"{p!r} (looked at {absolute_path(p, root)})" for p in missing)
        hint = ("this record holds absolute paths (written before paths were stored relative "
                "to the dataset folder): put the inputs back there, or render the dataset "
                "again" if any(os.path.isabs(p) for p in missing) else
                "paths in a dataset are relative to its folder: copy the inputs along with "
                "it, keeping their relative layout")
        raise ConfigError(f"{Path(root) / 'manifest.jsonl'}: sample {sid}: input file(s) not "
                          f"found: {what}; {hint}")
    return scene_from_dict(scene, source=f"{Path(root) / 'manifest.jsonl'}: sample {sid}",
                           name=scene.get("name", sid))

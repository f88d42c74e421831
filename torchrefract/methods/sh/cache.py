"""The precomputed tables on disk and in memory, keyed by the mesh's content.

Key: the SHA-256 of the *object-space* mesh (vertices, faces, shading normals as the
renderer loads them, before the scene's transform) and the settings the paths depend on
(IOR, direction rings, sample target, interface limit, branch rule, branches stored; not
the SH order or window, applied when shading). A scene's rigid transform and uniform scale
are a remapping at shading time (sec. 5.4), so every pose of a mesh file shares one table;
a mesh whose content changes (a deformed or re-exported file) gets a new key and a new
precomputation, never a stale table.

Files: ``<cache folder>/sh/sh_<mesh>_<settings>.npz`` (the user cache folder of
:func:`torchrefract.settings.cache_folder`), written atomically
(:mod:`torchrefract.output.atomic`: an interrupted run leaves no half file), with the key's
full text inside, checked on load; an unreadable or mismatching file is recomputed. Loaded
tables stay in memory (the last :data:`MEMORY_TABLES`).
"""

from __future__ import annotations

import hashlib
import json
import logging
import sys
import zipfile
from collections import OrderedDict
from dataclasses import asdict
from pathlib import Path

import numpy as np
import torch

from torchrefract.geometry.mesh import MeshData
from torchrefract.methods.sh.layout import Layout
from torchrefract.methods.sh.precompute import SHTable, Settings, channels, precompute
from torchrefract.output.atomic import atomic_path

log = logging.getLogger(__name__)

FORMAT = 2
"""Version of the file layout and of the path rules (bumped when either changes; 2: the
rough-interface gain channel)."""

MEMORY_TABLES = 4
"""Tables kept loaded in memory (LRU)."""

_memory: "OrderedDict[tuple, SHTable]" = OrderedDict()


def mesh_hash(mesh: MeshData) -> str:
    """SHA-256 (hex) of an object-space mesh's vertices, faces and shading normals
    (:attr:`MeshData.content_hash`, computed once per mesh)."""
    return mesh.content_hash


def settings_key(settings: Settings) -> str:
    """Canonical text of the settings (and the format version)."""
    d = asdict(settings)
    d["ior"] = float(np.float32(d["ior"]))  # the renderer's IOR is float32
    if d["branches"] == 1:  # the key (and file) of the tables made before the option
        del d["branches"]
    d["format"] = FORMAT
    return json.dumps(d, sort_keys=True)


def cache_path(cache_dir: Path, mesh_key: str, settings: Settings) -> Path:
    """Where the table of a mesh and settings lives."""
    s = hashlib.sha256(settings_key(settings).encode()).hexdigest()
    return Path(cache_dir) / "sh" / f"sh_{mesh_key[:20]}_{s[:12]}.npz"


def save_table(table: SHTable, path: Path) -> None:
    """Write a table atomically (uncompressed npz: float16 weights hardly compress)."""
    lay = table.layout
    meta = {"mesh_hash": table.mesh_hash, "settings": settings_key(table.settings),
            "radius": table.radius, "rate": lay.rate, "channels": list(channels(table.settings)),
            "stats": table.stats}
    with atomic_path(path, suffix=".npz") as tmp:
        np.savez(tmp, coeffs=table.coeffs.numpy(), lattice=lay.lattice.numpy().astype(np.int32),
                 position=lay.position.numpy(), frame=lay.frame.numpy(),
                 meta=np.array(json.dumps(meta)))


def load_table(path: Path, mesh_key: str, settings: Settings) -> SHTable:
    """Read a table written by :func:`save_table`.

    Raises:
        ValueError: the file is for another mesh or settings, or is malformed.
        OSError, zipfile.BadZipFile: unreadable or truncated.
    """
    with np.load(path, allow_pickle=False) as z:
        meta = json.loads(str(z["meta"]))
        if meta.get("mesh_hash") != mesh_key or meta.get("settings") != settings_key(settings):
            raise ValueError(f"{path} holds another mesh or settings")
        if meta.get("channels") != list(channels(settings)):
            raise ValueError(f"{path} has channels {meta.get('channels')}")
        layout = Layout(rate=int(meta["rate"]),
                        lattice=torch.from_numpy(z["lattice"].astype(np.int64)),
                        position=torch.from_numpy(np.array(z["position"])),
                        frame=torch.from_numpy(np.array(z["frame"])))
        coeffs = torch.from_numpy(np.array(z["coeffs"]))
    if coeffs.shape[0] != layout.num_samples or coeffs.shape[2] != len(channels(settings)):
        raise ValueError(f"{path}: coefficient shape {tuple(coeffs.shape)} does not match "
                         f"{layout.num_samples} samples")
    return SHTable(layout=layout, coeffs=coeffs, radius=float(meta["radius"]),
                   settings=settings, mesh_hash=mesh_key, stats=dict(meta.get("stats", {})))


def get_table(mesh: MeshData, settings: Settings, cache_dir: Path, tracer: str = "auto",
              name: str = "mesh") -> tuple[SHTable, str]:
    """The table of an object-space mesh: from memory, else from the cache folder, else
    precomputed now (with a progress bar on a terminal) and written there.

    Returns:
        the table and where it came from: ``memory``, ``disk`` or ``computed``.
    """
    key = mesh_hash(mesh)
    mem_key = (key, settings_key(settings), str(cache_dir))
    hit = _memory.get(mem_key)
    if hit is not None:
        _memory.move_to_end(mem_key)
        return hit, "memory"
    path = cache_path(cache_dir, key, settings)
    table, source = None, "disk"
    if path.is_file():
        try:
            table = load_table(path, key, settings)
        except (OSError, ValueError, KeyError, zipfile.BadZipFile) as exc:
            log.warning("sh: ignoring unreadable cache %s (%s)", path, exc)
    if table is None:
        source = "computed"
        table = precompute(mesh, settings, key, tracer, progress=f"sh precompute {name}")
        save_table(table, path)
        st = table.stats
        msg = (f"torchrefract: sh precomputation of {name} (IOR {settings.ior:g}): "
               f"{st['samples']} surface samples x {2 * settings.rings ** 2} directions = "
               f"{st['paths']} paths ({st['rays']} rays, {st['tracer']}) in "
               f"{st['seconds']:.1f} s; cache {path.stat().st_size / 2 ** 20:.1f} MB at {path}")
        log.info(msg)
        print(msg, file=sys.stderr, flush=True)
    _memory[mem_key] = table
    while len(_memory) > MEMORY_TABLES:
        _memory.popitem(last=False)
    return table, source


def clear_memory() -> None:
    """Forget the loaded tables (the files stay)."""
    _memory.clear()


__all__ = ["FORMAT", "MEMORY_TABLES", "cache_path", "clear_memory", "get_table", "load_table",
           "mesh_hash", "save_table", "settings_key"]

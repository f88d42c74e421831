"""Atomic file writes: the one helper every writer uses (images, sidecars, manifests,
shards' index, the SG pyramids' and table's caches, the native library).

The data goes to a temporary file in the target's folder (``.<name>.<random>.tmp[.ext]``,
the name cut to its first 64 characters so that any target's temporary name is a legal
file name; the pattern a resumed sweep clears) and is renamed over the target, so an interrupted
process never leaves a half-written file under the real name. The temporary file is made
with mode 0o666 less the process's umask, as ``open()`` makes files (the umask is never
read or changed).
"""

from __future__ import annotations

import os
import secrets
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator


def _fsync_dir(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


@contextmanager
def atomic_path(path: str | Path, suffix: str = "", fsync: bool = False) -> Iterator[Path]:
    """Yield a temporary path beside ``path`` for the caller to write; on success it is
    renamed to ``path`` (after an fsync of the file and its folder with ``fsync``), on any
    error removed.

    Args:
        path: the target file (its folder is created if missing).
        suffix: appended to the temporary name (``.exr``: for writers that infer the
            format from it).
        fsync: make the rename durable (manifests).
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    while True:
        tmp = path.with_name(f".{path.name[:64]}.{secrets.token_hex(4)}.tmp{suffix}")
        try:
            os.close(os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666))
            break
        except FileExistsError:
            continue
    try:
        yield tmp
        if fsync:
            fd = os.open(tmp, os.O_RDONLY)
            try:
                os.fsync(fd)
            finally:
                os.close(fd)
        os.replace(tmp, path)
        if fsync:
            _fsync_dir(path.parent)
    finally:
        if tmp.exists():
            tmp.unlink()


def write_bytes(path: str | Path, data: bytes, fsync: bool = False) -> None:
    """Write ``data`` to ``path`` atomically."""
    with atomic_path(path, fsync=fsync) as tmp:
        tmp.write_bytes(data)


def write_text(path: str | Path, text: str, fsync: bool = False) -> None:
    """Write ``text`` (UTF-8) to ``path`` atomically."""
    write_bytes(path, text.encode("utf-8"), fsync=fsync)


__all__ = ["atomic_path", "write_bytes", "write_text"]

"""WebDataset shards of a sweep: ``DIR/shard-NNNNNN.tar``, ``--shard-size`` samples each.

A shard is written to a temporary file and renamed into place, durably, once full (or at
the end of the run); only then are its samples' manifest lines appended. On resume a shard
counts only when the manifest holds all of its samples; any other is deleted and its
samples rendered again. Members get fixed owners, modes and times, so shards are
byte-identical across runs. A sample's ``<id>.json`` member names its inputs relative to
``DIR`` (:mod:`~torchrefract.dataset.paths`); any webdataset reader can stream the shards
(``webdataset.WebDataset``, Hugging Face ``datasets.load_dataset("webdataset", ...)``).
"""

from __future__ import annotations

import io
import re
import tarfile
from contextlib import ExitStack
from pathlib import Path

from torchrefract.output.atomic import atomic_path

_SHARD_RE = re.compile(r"^shard-(\d{6,})\.tar$")
# tar members get fixed owners and times so that shards are byte-identical across runs.
_TAR_MTIME = 0


class _ShardAborted(Exception):
    """Passed to the atomic write of an unfinished shard: remove it, rename nothing."""


class _TarShards:
    """WebDataset shards written atomically: ``.shard-NNNNNN.tar.<rand>.tmp`` -> rename."""

    def __init__(self, out: Path, shard_size: int, first: int):
        self.out, self.size, self.next = out, shard_size, first
        self.tar: tarfile.TarFile | None = None
        self.tmp: Path | None = None
        self.pending: list[dict] = []

    def _open(self) -> None:
        """Start the next shard: its temporary file (renamed by :meth:`close`) and tar."""
        self.name = f"shard-{self.next:06d}.tar"
        self._files = ExitStack()
        self.tmp = self._files.enter_context(atomic_path(self.out / self.name, fsync=True))
        self.file = self._files.enter_context(open(self.tmp, "wb"))
        self.tar = tarfile.open(fileobj=self.file, mode="w", format=tarfile.USTAR_FORMAT)

    def add(self, key: str, members: list[tuple[str, bytes]], record: dict) -> list[dict]:
        """Add one sample; returns the records of a shard that just became durable."""
        if self.tar is None:
            self._open()
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
        """Finish the open shard: fsync, rename into place, fsync the folder; returns its
        samples' records (with the shard's size), for the manifest."""
        if self.tar is None:
            return []
        self.tar.close()
        self._files.close()  # closes the file, then fsyncs and renames it
        size = (self.out / self.name).stat().st_size
        done = [dict(r, shard_samples=len(self.pending), shard_bytes=size)
                for r in self.pending]
        self.tar, self.tmp, self.pending = None, None, []
        self.next += 1
        return done

    def abort(self) -> None:
        """Delete the unfinished shard (a failed run: its samples are rendered again). A
        flush that fails on the way (a full disk) changes nothing: the temporary file is
        removed all the same, and the error the run stopped with is the one reported."""
        if self.tar is not None:
            self.tar = None
            try:
                self._files.__exit__(_ShardAborted, _ShardAborted(), None)
            except OSError:
                pass


def _completed_shards(out: Path, latest: dict[str, dict], verify: bool
                      ) -> tuple[set[str], int]:
    """Sample ids of complete shards and the last shard number; deletes shards that no
    complete set of records covers."""
    done: set[str] = set()
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

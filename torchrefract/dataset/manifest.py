"""A sweep's manifest: ``DIR/manifest.jsonl``, one JSON line per sample record.

Lines are appended (one write, flushed and fsynced, per batch) only after the files they
describe are durable, so a killed run leaves whole lines or one truncated last line, which
:func:`read_manifest` drops. At the end of a run the file is compacted to one line per
sample, in index order. Every rewrite is atomic and fsynced. Paths in the records are
relative to ``DIR`` (:mod:`~torchrefract.dataset.paths`; older records: absolute).
"""

from __future__ import annotations

import json
import os
import warnings
from pathlib import Path

from torchrefract.output.atomic import write_bytes

MANIFEST = "manifest.jsonl"


def _json_line(rec: dict) -> str:
    return json.dumps(rec, sort_keys=False, separators=(",", ":"), allow_nan=False) + "\n"


def _rewrite(path: Path, entries: list[dict]) -> None:
    """Replace the manifest by ``entries``, atomically and durably."""
    write_bytes(path, "".join(_json_line(e) for e in entries).encode(), fsync=True)


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
            _rewrite(path, entries)
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
        _rewrite(self.path, entries)

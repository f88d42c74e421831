"""Heap reuse: keep the memory of freed tensors for the next ones instead of returning it
to the operating system.

Every torch op on the CPU allocates its output. glibc serves a block above its mmap
threshold (128 KiB, raised as blocks are freed, up to 32 MiB) with fresh pages from the
kernel and unmaps them when the tensor is freed, so the next op's output faults its pages
in again: a render of the demo batch (256x256, 8 views) took 10,000-19,000 page faults
and 4-8 ms of system time per frame, single-thread. With glibc's mmap and trim thresholds
at 1 GiB (``mallopt``) those blocks come from the heap, and the heap is not cut back after
each free: the blocks are reused, no faults, 0.3 ms of system time per frame
(``scripts/bench.py`` records the setting). It also keeps every thread's blocks in one
arena, so the kept heap reaches its working set once, not once per thread.

Process-wide, and the process keeps the memory near its peak between renders instead of
giving it back (the peak itself does not change). So it is never switched on by importing
or by default: a render asks for it with ``RenderSettings(heap_reuse=True)`` (the
``torchrefract`` command, its worker processes and the scripts do), or a caller calls
:func:`set_heap_reuse`. ``TORCHREFRACT_HEAP_REUSE=1`` makes it the settings' default,
``TORCHREFRACT_HEAP_REUSE=0`` forbids it everywhere.

glibc only (Linux); elsewhere it does nothing and says so by returning ``False``.
"""

from __future__ import annotations

import ctypes
import functools
import ctypes.util
import os

_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD, _M_ARENA_MAX = -1, -3, -8  # glibc's malloc.h
_REUSE = 1 << 30  # both thresholds while reusing
_DEFAULT = 128 * 1024  # glibc's initial values of both

_ENV = "TORCHREFRACT_HEAP_REUSE"
_enabled = False


def _forbidden() -> bool:
    """``TORCHREFRACT_HEAP_REUSE=0``: the user keeps glibc's default everywhere."""
    return os.environ.get(_ENV, "").strip() == "0"


@functools.lru_cache(maxsize=1)
def _mallopt():
    """glibc's ``mallopt`` (looked up once: ``find_library`` runs ``ldconfig -p``, a fork
    of the whole process, which cost a few ms of every render)."""
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        fn = libc.mallopt
    except (OSError, AttributeError):
        return None
    fn.argtypes = [ctypes.c_int, ctypes.c_int]
    fn.restype = ctypes.c_int
    return fn


def set_heap_reuse(enabled: bool = True) -> bool:
    """Serve large blocks from the reused heap (``True``) or from fresh pages again (glibc's
    initial threshold, ``False``). Returns whether the allocator took the setting (``False``
    where it is not glibc's, or where ``TORCHREFRACT_HEAP_REUSE=0`` forbids it)."""
    global _enabled
    if enabled and _forbidden():
        return False
    fn = _mallopt()
    if fn is None:
        return False
    value = _REUSE if enabled else _DEFAULT
    ok = fn(_M_MMAP_THRESHOLD, value) == 1 and fn(_M_TRIM_THRESHOLD, value) == 1
    if ok and enabled:
        # One arena: with the heap never cut back, each thread's arena (up to 8 per core)
        # grows to its own high-water mark over thousands of renders (scripts/long_run.py,
        # docs/datasets.md). Arenas made before stay, so the command sets this first thing.
        fn(_M_ARENA_MAX, 1)
    if ok:
        _enabled = bool(enabled)
    return ok


def heap_reuse() -> bool:
    """Whether this process set heap reuse on (:func:`set_heap_reuse`)."""
    return _enabled


__all__ = ["heap_reuse", "set_heap_reuse"]

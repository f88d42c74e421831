"""How many cores other processes keep busy right now: for a render's thread count under
load (``RenderSettings.adapt_threads``, issue #28).

With one of two cores busy (a training job's DataLoader worker, another render), torch's
default of one thread per core is slower than one thread: every tensor op waits at its
barrier for the thread that lost its core, and libgomp's spinning workers fight the busy
process (measured: docs/benchmarks.md, "Threads under load"). Linux reports the runnable
tasks of the whole machine (``/proc/loadavg``, fourth field) and each of our threads'
state (``/proc/self/task/*/stat``); the difference is what other processes run. A few
samples a fraction of a millisecond apart, the least kept: a task that runs for an instant
is not load.
"""

from __future__ import annotations

import functools
import os
import time

from torchrefract.kept import Recent


def _running_here() -> int:
    """This process's threads in state R (running or ready to run)."""
    n = 0
    for t in os.scandir("/proc/self/task"):
        try:
            with open(os.path.join(t.path, "stat"), "rb") as f:
                stat = f.read()
        except OSError:  # the thread ended
            continue
        if stat[stat.rfind(b")") + 2:][:1] == b"R":
            n += 1
    return n


def busy_cores(samples: int = 3, gap_s: float = 0.0005) -> int:
    """Cores other processes keep busy now (0 where /proc is not readable): the machine's
    runnable tasks less this process's, the least of ``samples`` reads ``gap_s`` apart."""
    best = None
    try:
        for i in range(samples):
            if i:
                time.sleep(gap_s)
            with open("/proc/loadavg") as f:
                running = int(f.read().split()[3].split("/")[0])
            other = max(0, running - _running_here())
            best = other if best is None else min(best, other)
            if best == 0:
                break
    except (OSError, ValueError, IndexError):
        return 0
    return best or 0


MAX_AGE_S = 1.0
"""How long a reading of :func:`busy_cores` serves the renders that follow it: renders in
quick succession (a training loop's batches) read /proc once a second, not every call
(under load a reading waits between its samples: docs/benchmarks.md)."""

_busy = Recent(lambda: busy_cores(), MAX_AGE_S)  # (looked up per reading: patchable)


def recent_busy_cores(max_age_s: float = MAX_AGE_S) -> int:
    """:func:`busy_cores`, read anew only where the last reading is older than
    ``max_age_s`` seconds."""
    return _busy.get(max_age_s)


@functools.lru_cache(maxsize=1)
def _cores() -> int:
    """The machine's cores (``os.cpu_count`` reads /sys on every call: ~0.1 ms a render)."""
    return os.cpu_count() or 1


def threads_for(requested: int, cores: int | None = None, busy: int | None = None) -> int:
    """The threads a render takes when it asked for ``requested``: at most the cores other
    processes leave free (:func:`recent_busy_cores` unless ``busy`` is given), at least 1."""
    cores = cores if cores is not None else _cores()
    busy = busy if busy is not None else recent_busy_cores()
    return max(1, min(requested, cores - busy))


__all__ = ["MAX_AGE_S", "busy_cores", "recent_busy_cores", "threads_for"]

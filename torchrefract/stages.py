"""Wall time per stage inside a render (the benchmark's stage columns).

:func:`torchrefract.render` collects, around the method's shading, the time spent in
named stages that the pipeline's functions mark with :func:`stage` or :func:`timed`:
``march`` (the ray
marches through the depth layers, :mod:`torchrefract.kernels.march`), ``mips`` (the NDF and
coverage mip pyramids of the back layer, :mod:`torchrefract.optics.ndf`) and ``fused`` (a
method's fused shading kernel, its marches included, :mod:`torchrefract.shading.fused`). Outside a collection
:func:`stage` costs one context-variable read. Stages are summed when entered several
times; a stage entered inside another of the same name counts once.

Example:
    >>> from torchrefract.stages import collect, stage
    >>> with collect() as times:
    ...     with stage("march"):
    ...         pass
    >>> sorted(times)
    ['march']
"""

from __future__ import annotations

import contextvars
import functools
import time
from contextlib import contextmanager
from typing import Callable, Iterator

_CURRENT: contextvars.ContextVar[dict[str, float] | None] = contextvars.ContextVar(
    "torchrefract_stages", default=None)
_OPEN: contextvars.ContextVar[frozenset[str]] = contextvars.ContextVar(
    "torchrefract_open_stages", default=frozenset())


@contextmanager
def collect() -> Iterator[dict[str, float]]:
    """Collect the seconds of every :func:`stage` run inside into the yielded dict (a
    nested collection gets its own dict; the outer one does not see its stages)."""
    times: dict[str, float] = {}
    token = _CURRENT.set(times)
    open_token = _OPEN.set(frozenset())
    try:
        yield times
    finally:
        _OPEN.reset(open_token)
        _CURRENT.reset(token)


@contextmanager
def stage(name: str) -> Iterator[None]:
    """Add the wall time of the block to stage ``name`` of the current collection."""
    times = _CURRENT.get()
    if times is None or name in _OPEN.get():
        yield
        return
    token = _OPEN.set(_OPEN.get() | {name})
    t0 = time.perf_counter()
    try:
        yield
    finally:
        times[name] = times.get(name, 0.0) + time.perf_counter() - t0
        _OPEN.reset(token)


def timed(name: str) -> Callable[[Callable], Callable]:
    """Decorator: every call of the function counts to stage ``name``."""
    def deco(fn: Callable) -> Callable:
        @functools.wraps(fn)
        def run(*args, **kwargs):
            with stage(name):
                return fn(*args, **kwargs)
        return run
    return deco


__all__ = ["collect", "stage", "timed"]

"""Optional ``torch.compile`` of the hot tensor kernels, with an eager fallback.

The ray march (``march.py``) spends most of its time in chains of small elementwise ops
around one gather (project a point, pick its pixel, test it against that pixel's plane),
which are memory-bound in eager torch. Compiled (inductor, dynamic shapes) they fuse into
one loop each. Measured on the project's 2-core CPU (docs/benchmarks.md, "Compiled march").

Off by default: the first compiled call of a process costs seconds (tracing, or a full
C++ compile when the on-disk cache is cold), which a single small render never earns back.
Turn it on for long runs with ``RenderSettings(compile=True)`` (``--compile`` on the CLI,
``TORCHREFRACT_COMPILE=1`` as the environment's default).

Where compiling fails (no C++ compiler, an unsupported platform) a warning names the
error once and the kernels stay eager: the images are the same either way (the kernels
return comparisons and interval ends; tests/test_accel.py checks equality).
"""

from __future__ import annotations

import functools
import warnings
from typing import Callable

import torch

from torchrefract import settings


def set_compile(enabled: bool) -> None:
    """Deprecated: pass ``RenderSettings(compile=...)`` to the render instead."""
    settings.deprecated_switch("set_compile", "compile", "TORCHREFRACT_COMPILE", enabled)


def compile_enabled() -> bool:
    """Whether the current settings run :func:`kernel` functions compiled."""
    return settings.current().compile


def kernel(fn: Callable) -> Callable:
    """Decorator: ``fn`` runs through ``torch.compile(fn, dynamic=True)`` while compiling
    is enabled, eagerly otherwise. ``fn`` must take no tensor that requires grad (callers
    pass detached tensors: these kernels only decide where a ray crosses a layer)."""
    compiled: Callable | None = None
    failed = False

    @functools.wraps(fn)
    def run(*args, **kwargs):
        nonlocal compiled, failed
        if failed or not settings.current().compile:
            return fn(*args, **kwargs)
        if compiled is None:
            compiled = torch.compile(fn, dynamic=True)
        try:
            return compiled(*args, **kwargs)
        except Exception as exc:  # noqa: BLE001  (any compiler failure: fall back)
            failed = True
            warnings.warn(f"torchrefract: torch.compile of {fn.__name__} failed, running it "
                          f"eagerly from now on ({type(exc).__name__}: "
                          f"{str(exc).splitlines()[0] if str(exc) else ''})",
                          RuntimeWarning, stacklevel=2)
            return fn(*args, **kwargs)

    return run


__all__ = ["compile_enabled", "kernel", "set_compile"]

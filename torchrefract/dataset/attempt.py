"""One attempt at rendering a batch of a sweep: the result with the warnings it raised, or
a failed sample's reason (the executors' and the relight mode's shared steps)."""

from __future__ import annotations

import warnings

from torchrefract.scene.model import Scene


def failure_reason(exc: BaseException) -> str:
    """A failed sample's reason: the exception's type and first line (at most 2000 chars)."""
    msg = str(exc).strip().splitlines()
    return f"{type(exc).__name__}: {msg[0] if msg else ''}"[:2000]


def render_batch(scenes: list[Scene], settings):
    """Render one batch; returns the result and the distinct warnings it raised."""
    from torchrefract.render import render  # noqa: PLC0415

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        result = render(scenes, settings=settings)
    return result, sorted({str(w.message) for w in caught})


__all__ = ["failure_reason", "render_batch"]

"""Values kept per object identity: the last few results computed from objects that are
not hashable or too costly to hash (a tensor, a scene with dict fields, the SG table),
each checked against the object itself (a weak reference: a dead object's reused id never
matches) and a key the caller derives from its mutable state or other arguments. And
readings of the machine kept for a while (:class:`Recent`)."""

from __future__ import annotations

import time
import weakref
from collections import OrderedDict
from typing import Any, Callable, Hashable


class KeptByIdentity:
    """At most ``size`` values, keyed by (an object, a key); the least recently used goes
    first."""

    def __init__(self, size: int):
        self.size = size
        self._kept: OrderedDict[tuple[int, Hashable], tuple[weakref.ref, Any]] = OrderedDict()

    def get(self, obj: Any, key: Hashable = None) -> Any | None:
        """The value kept for ``obj`` and ``key``, or None."""
        hit = self._kept.get((id(obj), key))
        if hit is None or hit[0]() is not obj:
            return None
        self._kept.move_to_end((id(obj), key))
        return hit[1]

    def put(self, obj: Any, key: Hashable, value: Any) -> Any:
        """Keep ``value`` (not None) for ``obj`` and ``key``; returns it."""
        self._kept[(id(obj), key)] = (weakref.ref(obj), value)
        self._kept.move_to_end((id(obj), key))
        while len(self._kept) > self.size:
            self._kept.popitem(last=False)
        return value


class Recent:
    """A reading of the machine (its load, its free memory: /proc) kept for ``max_age_s``
    seconds: renders in quick succession read it once a second, not every call."""

    def __init__(self, read: Callable[[], Any], max_age_s: float):
        self.read, self.max_age_s = read, max_age_s
        self.last: tuple[float, Any] | None = None  # (time.monotonic(), value)

    def get(self, max_age_s: float | None = None) -> Any:
        """The last reading, read anew where it is older than ``max_age_s`` (None: the
        kept age) or there is none."""
        now = time.monotonic()
        age = self.max_age_s if max_age_s is None else max_age_s
        if self.last is None or now - self.last[0] > age:
            self.last = (now, self.read())
        return self.last[1]

"""Values kept per object identity: the last few results computed from objects that are
not hashable or too costly to hash (a tensor, a scene with dict fields, the SG table),
each checked against the object itself (a weak reference: a dead object's reused id never
matches) and a key the caller derives from its mutable state or other arguments."""

from __future__ import annotations

import weakref
from collections import OrderedDict
from typing import Any, Hashable


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

"""torchrefract.kept: values kept per object identity and key, least recently used first."""

from __future__ import annotations

import torch

from torchrefract.kept import KeptByIdentity


def test_kept_by_identity_and_key_evicting_the_least_recent():
    kept = KeptByIdentity(2)
    a, b, c = torch.zeros(1), torch.zeros(1), torch.zeros(1)
    kept.put(a, 1, "a1")
    kept.put(b, 1, "b1")
    assert kept.get(a, 1) == "a1" and kept.get(a, 2) is None
    assert kept.get(torch.zeros(1), 1) is None  # an equal object is not the same one
    kept.put(c, 1, "c1")  # b was used least recently: it goes
    assert kept.get(b, 1) is None and kept.get(a, 1) == "a1" and kept.get(c, 1) == "c1"
    del a  # a dead object's entry never matches an object that reuses its id
    d = torch.zeros(1)
    assert kept.get(d, 1) is None

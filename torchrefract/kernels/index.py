"""Row gathers and scatters along the first axis, by ``index_select`` / ``index_copy_``.

``take(x, idx)`` has the values of ``x[idx]`` and ``put_(x, idx, v)`` the effect of
``x[idx] = v`` (``idx`` a 1-D int64 tensor, distinct indices for ``put_``), gradients
included. On CPU torch's advanced indexing runs a generic strided kernel that is several
times slower than these (measured on this project's 2-core CPU, 300k rows, 2 threads:
(524k, 4) float rows 10.8 ms against 1.4 ms; 1-D 1.5 against 0.33 ms; scatters of 120k
(N, 3) rows 1.26 against 0.76 ms). The ray march, the G-buffer and the lookups gather per
ray and per sample, so they use these. ``broadcast_shape`` is ``torch.broadcast_shapes``
without its first call's cost.
"""

from __future__ import annotations

import numpy as np
import torch


def take(x: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
    """``x[idx]`` for a 1-D int64 ``idx``: rows of ``x`` along its first axis."""
    return x.index_select(0, idx)


def put_(x: torch.Tensor, idx: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """``x[idx] = v`` in place for a 1-D int64 ``idx`` of distinct rows; returns ``x``."""
    return x.index_copy_(0, idx, v.to(x.dtype))


def where_true(mask: torch.Tensor) -> torch.Tensor:
    """(K,) int64 positions of the True entries of a 1-D bool ``mask``."""
    return mask.nonzero().squeeze(1)


def where_in(ids: torch.Tensor, members: list[int], size: int) -> torch.Tensor:
    """(K,) int64 positions of the entries of ``ids`` (1-D int64 in [0, ``size``)) that are
    among ``members`` (e.g. the points whose view is one of a group of views)."""
    on = torch.zeros(size, dtype=torch.bool, device=ids.device)
    on[members] = True
    return where_true(take(on, ids))


def broadcast_shape(*shapes) -> tuple[int, ...]:
    """The shape ``shapes`` broadcast to (torch's rule, numpy's implementation:
    ``torch.broadcast_shapes`` imports ``torch._refs`` on its first call, which slowed every
    process's first render; docs/benchmarks.md)."""
    return tuple(np.broadcast_shapes(*(tuple(s) for s in shapes)))

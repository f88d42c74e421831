"""torchrefract.kernels.index: take / put_ / where_true give the values (and gradients) of advanced
indexing, which they replace on the hot paths."""

from __future__ import annotations

import torch

from torchrefract.kernels.index import put_, take, where_true


def test_take_and_put_match_advanced_indexing():
    g = torch.Generator().manual_seed(0)
    x = torch.randn(50, 4, 3, generator=g)
    idx = torch.randint(0, 50, (80,), generator=g)  # repeats allowed for take
    assert torch.equal(take(x, idx), x[idx])
    rows = torch.randperm(50, generator=g)[:20]  # distinct rows for put_
    v = torch.randn(20, 4, 3, generator=g)
    a, b = x.clone(), x.clone()
    a[rows] = v
    assert put_(b, rows, v) is b and torch.equal(a, b)
    # put_ casts like an indexed assignment does
    m = torch.zeros(5, dtype=torch.bool)
    put_(m, torch.tensor([1, 3]), torch.ones(2))
    assert m.tolist() == [False, True, False, True, False]


def test_where_true_is_the_nonzero_positions():
    mask = torch.tensor([False, True, True, False, True])
    assert where_true(mask).tolist() == [1, 2, 4]
    assert where_true(torch.zeros(3, dtype=torch.bool)).numel() == 0


def test_gradients_flow_through_take_and_put():
    x = torch.randn(6, 3, dtype=torch.float64, requires_grad=True)
    idx = torch.tensor([0, 2, 2, 5])
    (take(x, idx) ** 2).sum().backward()
    ref = torch.zeros(6, 3, dtype=torch.float64)
    ref.index_add_(0, idx, 2 * x.detach()[idx])
    assert torch.allclose(x.grad, ref)
    v = torch.randn(2, 3, dtype=torch.float64, requires_grad=True)
    out = put_(torch.zeros(6, 3, dtype=torch.float64), torch.tensor([1, 4]), v)
    (out * torch.arange(18.0, dtype=torch.float64).view(6, 3)).sum().backward()
    assert torch.equal(v.grad, torch.arange(18.0, dtype=torch.float64).view(6, 3)[[1, 4]])

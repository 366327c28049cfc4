"""The sampled product ``(G X^T)|_A`` (the gradient of ``loss(A X)`` for A's values) against the
dense ``G X^T`` read at the pattern's positions, on random patterns of every shape and width."""

from __future__ import annotations

import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from torch_polylap.sparse.autograd import _sampled_cpu, sampled_op
from torch_polylap.sparse.pattern import SparsityPattern


@st.composite
def _problem(draw: st.DrawFn) -> tuple[SparsityPattern, torch.Tensor, torch.Tensor]:
    n, m = draw(st.integers(1, 9)), draw(st.integers(1, 9))
    c = draw(st.integers(0, 5))
    mask = torch.tensor(draw(st.lists(st.booleans(), min_size=n * m, max_size=n * m)))
    row, col = torch.nonzero(mask.view(n, m), as_tuple=True)
    gen = torch.Generator().manual_seed(draw(st.integers(0, 2**31 - 1)))
    G = torch.randn(n, c, generator=gen, dtype=torch.float64)
    X = torch.randn(m, c, generator=gen, dtype=torch.float64)
    return SparsityPattern.from_rows(row, col, (n, m)), G, X


@settings(max_examples=80, deadline=None)
@given(problem=_problem(), block=st.sampled_from([1, 3, 7, 1 << 16]))
def test_sampled_product_equals_dense_product_at_the_pattern(problem, block):
    """Every block size (entries split across blocks) and width (no column: zeros)."""
    pattern, G, X = problem
    want = (G @ X.t())[pattern.row, pattern.col]
    got = _sampled_cpu(G, X, pattern.row, pattern.col, block)
    assert got.shape == (pattern.nnz,)
    torch.testing.assert_close(got, want, rtol=1e-14, atol=1e-14)
    torch.testing.assert_close(sampled_op(G, X, pattern.crow, pattern.col, pattern.row), want)


def test_sampled_product_of_transposed_inputs(device, dtype):
    """Non-contiguous operands (transposed views) in either dtype give the same entries (the
    CPU's blocked gathers, ``sampled_addmm`` elsewhere)."""
    pattern = SparsityPattern.from_rows(
        torch.tensor([0, 0, 1, 2]), torch.tensor([0, 2, 1, 0]), (3, 3)
    )
    crow, col, row = (t.to(device) for t in (pattern.crow, pattern.col, pattern.row))
    G = torch.randn(4, 3, dtype=dtype, device=device).t()
    X = torch.randn(4, 3, dtype=dtype, device=device).t()
    got = sampled_op(G, X, crow, col, row)
    assert got.device.type == device.type and got.dtype == dtype
    torch.testing.assert_close(got, (G @ X.t())[row, col])

"""The vmap rules of the sparse products against a loop of dense products, for every batch
position of the dense operand and batched or shared values."""

from __future__ import annotations

import pytest
import torch

from torch_polylap.sparse.autograd import spmm_op, spmm_t_op
from torch_polylap.sparse.pattern import SparsityPattern

_N, _M, _C, _B = 5, 4, 3, 2


def _problem() -> tuple[SparsityPattern, torch.Tensor]:
    gen = torch.Generator().manual_seed(0)
    mask = torch.rand(_N, _M, generator=gen) < 0.6
    mask[0, 0] = True
    row, col = torch.nonzero(mask, as_tuple=True)
    values = torch.randn(_B, row.numel(), generator=gen, dtype=torch.float64)
    return SparsityPattern.from_rows(row, col, (_N, _M)), values


def _dense(pattern: SparsityPattern, values: torch.Tensor) -> torch.Tensor:
    out = torch.zeros(_N, _M, dtype=values.dtype)
    out[pattern.row, pattern.col] = values
    return out


@pytest.mark.parametrize("values_batched", [True, False])
@pytest.mark.parametrize("dim", [0, 1, 2])
@pytest.mark.parametrize("transpose", [False, True])
def test_vmap_of_a_product_equals_the_loop(values_batched, dim, transpose):
    """``A X`` and ``A^T G`` with the operand's batch dimension anywhere (the result of an
    earlier vmapped product has it in the middle)."""
    pattern, values = _problem()
    parts = (pattern.crow, pattern.col, pattern.row)
    rows = _N if transpose else _M
    D = torch.randn(_B, rows, _C, dtype=torch.float64).movedim(0, dim)
    v_dim = 0 if values_batched else None
    v = values if values_batched else values[0]
    if transpose:
        got = torch.func.vmap(spmm_t_op, in_dims=(v_dim, None, None, None, dim, None))(
            v, *parts, D, _M
        )
    else:
        got = torch.func.vmap(spmm_op, in_dims=(v_dim, None, None, None, dim, None))(
            v, *parts, D, False
        )
    want = []
    for b in range(_B):
        A = _dense(pattern, values[b] if values_batched else values[0])
        want.append((A.t() if transpose else A) @ D.movedim(dim, 0)[b])
    torch.testing.assert_close(got, torch.stack(want), rtol=1e-14, atol=1e-14)

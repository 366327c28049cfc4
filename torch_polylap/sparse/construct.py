"""Building sparse operators, converting them, and the structural operations consumers need.

Every function that creates or takes apart a :class:`SparseOperator` lives here or in its
sibling modules: no other module of the package touches CSR indices or value arrays directly.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable, Sequence
from typing import Any, TypeVar

import numpy as np
import scipy.sparse as sp
import torch

from .._torch_compat import version_counter
from ..tracing import run_eagerly
from .autograd import sampled_product
from .dispatch import apply
from .operator import SparseOperator, operator_on
from .pattern import SparsityPattern

__all__ = [
    "as_operator",
    "block_diag",
    "diag",
    "eliminate",
    "from_coo",
    "identity",
    "mark_symmetric",
    "operator_from_parts",
    "pattern_of",
    "sampled_gradient",
    "solver_cache",
    "sparse_values",
    "spmm",
    "submatrix",
    "from_scipy",
    "to_scipy",
    "to_torch_sparse",
]

T = TypeVar("T")


def operator_from_parts(
    crow: torch.Tensor,
    col: torch.Tensor,
    values: torch.Tensor,
    shape: tuple[int, int],
    *,
    symmetric: bool = False,
) -> SparseOperator:
    """A :class:`SparseOperator` from CSR arrays with sorted, unique columns in every row.

    ``values`` ``(nnz,)`` may require grad; ``symmetric`` declares ``A = A^T`` (not checked).
    For repeated use on one pattern, build the operator once and take ``A.with_values(v)``,
    which shares the pattern and its cached transposes and unions.
    """
    pattern = SparsityPattern(crow, col, shape)
    return operator_on(pattern, values, symmetric=symmetric)


def from_coo(
    row: torch.Tensor,
    col: torch.Tensor,
    values: torch.Tensor,
    shape: tuple[int, int],
    *,
    symmetric: bool = False,
) -> SparseOperator:
    """The operator with entries ``values`` ``(N,)`` at ``(row, col)`` in any order, duplicates
    summed (differentiable in ``values``)."""
    n, m = int(shape[0]), int(shape[1])
    keys = row.to(torch.int64) * m + col.to(torch.int64)
    unique, inverse = torch.unique(keys, sorted=True, return_inverse=True)
    summed = values.new_zeros(unique.numel()).index_add(0, inverse, values)
    urow = torch.div(unique, m, rounding_mode="floor")
    pattern = SparsityPattern.from_rows(urow, unique - urow * m, (n, m))
    return operator_on(pattern, summed, symmetric=symmetric)


def pattern_of(A: SparseOperator) -> SparsityPattern:
    """The :class:`SparsityPattern` of a sparse matrix."""
    return as_operator(A).pattern


def mark_symmetric(A: Any) -> SparseOperator:
    """``A`` declared symmetric (not checked), so products' backward reuse ``A`` for ``A^T``."""
    A = as_operator(A)
    return A if A.symmetric else A.with_values(A._vals, symmetric=True)


def as_operator(A: Any) -> SparseOperator:
    """``A`` as a :class:`SparseOperator`: returned as is, or converted from a torch sparse CSR/COO
    tensor or a scipy sparse matrix.

    A torch sparse tensor's values are taken with ``values()``; for a CSR tensor whose values
    require grad that would route gradients through torch's dense sparse-tensor autograd, so it is
    refused: build the operator from its value array with :func:`operator_from_parts` instead.
    """
    if isinstance(A, SparseOperator):
        return A
    if sp.issparse(A):
        return from_scipy(A)
    if isinstance(A, torch.Tensor):
        if A.layout == torch.sparse_csr:
            values = A.values()
            if values.requires_grad:
                raise TypeError(_native_grad_message())
            return operator_from_parts(A.crow_indices(), A.col_indices(), values, _shape2(A))
        if A.layout == torch.sparse_coo:
            A = A if A.is_coalesced() else A.coalesce()
            values = A.values()
            if values.requires_grad:
                raise TypeError(_native_grad_message())
            row, col = A.indices()
            pattern = SparsityPattern.from_rows(row, col, _shape2(A))
            return operator_on(pattern, values)
        raise TypeError(
            "torch_polylap: expected a sparse matrix (an operator from torch_polylap, a torch "
            f"sparse CSR/COO tensor or a scipy sparse matrix), got a dense tensor of shape "
            f"{tuple(A.shape)}; convert it with A.to_sparse_csr() (no gradient) or build it from a "
            "value array with torch_polylap.sparse.operator_from_parts."
        )
    raise TypeError(f"torch_polylap: expected a sparse matrix, got {type(A).__name__}.")


def _shape2(A: torch.Tensor) -> tuple[int, int]:
    if A.dim() != 2:
        raise ValueError(
            f"torch_polylap: expected a 2-D sparse matrix, got shape {tuple(A.shape)}."
        )
    return int(A.shape[0]), int(A.shape[1])


def _native_grad_message() -> str:
    return (
        "torch_polylap: a torch sparse tensor whose values require grad would send gradients "
        "through torch's sparse autograd, which builds a dense n x m matrix. Keep the operators "
        "that torch_polylap returns (they stay sparse under +, *, @, .T, .to), or build one from "
        "a differentiable value array with torch_polylap.sparse.operator_from_parts."
    )


def csr_indices(A: Any) -> tuple[torch.Tensor, torch.Tensor]:
    """``(crow, col)`` of an operator, as tensors (what an operator built in traced code has)."""
    A = as_operator(A)
    return A._crow, A._col


def sparse_values(A: Any) -> torch.Tensor:
    """The ``(nnz,)`` value array of a sparse matrix, differentiable in O(nnz) (``A.values()``)."""
    return as_operator(A)._vals


def spmm(A: Any, X: torch.Tensor) -> torch.Tensor:
    """``A @ X`` for a sparse ``A`` ``(n, m)``, dense ``X`` ``(m,)``, ``(m, c)`` or ``(..., m, c)``.

    The same as ``A @ X`` on an operator from this package; also accepts torch sparse tensors
    without grad and scipy matrices.  Backward costs O(nnz * c) time and memory in ``A``'s
    values and ``X``, to any order (see :mod:`torch_polylap.sparse.autograd`).
    """
    A = as_operator(A)
    if not isinstance(X, torch.Tensor):
        raise TypeError(f"spmm: X must be a torch.Tensor, got {type(X).__name__}.")
    if X.dtype != A.dtype:
        raise ValueError(f"spmm: A has dtype {A.dtype} but X has {X.dtype}; convert one of them.")
    if X.dim() == 0 or X.shape[-2 if X.dim() > 1 else 0] != A.shape[1]:
        raise ValueError(
            f"spmm: cannot multiply A of shape {tuple(A.shape)} with X of shape {tuple(X.shape)}."
        )
    return apply(A, X)


def sampled_gradient(A: Any, G: torch.Tensor, X: torch.Tensor) -> torch.Tensor:
    """``(nnz,)`` entries of ``G X^T`` on ``A``'s pattern (the value gradient of ``loss(A X)``)."""
    return sampled_product(as_operator(A).pattern, G, X)


def solver_cache(A: Any, key: str, build: Callable[[], T]) -> T:
    """A derived object (a factorization) of ``A``'s current values, built once and reused.

    The cache is shared with ``A.detach()`` and with the operator a solve's backward rebuilds,
    and is checked against the values' storage and version counter, so an in-place change of
    the values rebuilds it.
    The entry keeps the values alive, so their address cannot be reused by other values.
    """
    A = as_operator(A)
    values = A._vals
    stamp = (
        values.data_ptr(),
        version_counter(values),
        values.numel(),
        values.dtype,
        values.device,
    )
    cached = A._solver_cache.get(key)
    if cached is not None and cached[0] == stamp:
        return cached[1]
    value = build()
    A._solver_cache[key] = (stamp, value, values.detach())
    return value


def diag(d: torch.Tensor) -> SparseOperator:
    """The ``n x n`` diagonal operator with diagonal ``d`` ``(n,)`` (differentiable)."""
    if d.dim() != 1:
        raise ValueError(f"diag: expected a 1-D tensor, got shape {tuple(d.shape)}.")
    # int(): under torch.compile with dynamic shapes the size is specialized (the pattern is
    # one per size anyway)
    pattern = run_eagerly(diagonal_pattern, int(d.shape[0]), d.device)
    return operator_on(pattern, d, symmetric=True)


_DIAGONALS: dict[tuple[int, torch.device], SparsityPattern] = {}


def diagonal_pattern(n: int, device: torch.device) -> SparsityPattern:
    """The shared pattern of ``n x n`` diagonal operators on ``device``."""
    # one pattern per size and device, so that M0 + t L finds its cached union every step;
    # under torch.compile it is looked up at trace time and enters the graph as a constant
    key = (n, torch.device(device))
    pattern = _DIAGONALS.get(key)
    if pattern is None:
        if len(_DIAGONALS) >= 16:
            _DIAGONALS.clear()
        pattern = SparsityPattern.diagonal_of(n, device)
        _DIAGONALS[key] = pattern
    return pattern


def identity(
    n: int, *, dtype: torch.dtype | None = None, device: torch.device | str | None = None
) -> SparseOperator:
    """The ``n x n`` identity as a sparse operator."""
    return diag(torch.ones(n, dtype=dtype or torch.get_default_dtype(), device=device))


def block_diag(operators: Sequence[Any]) -> SparseOperator:
    """The block-diagonal operator of ``operators`` (differentiable in each one's values)."""
    ops = [as_operator(A) for A in operators]
    if not ops:
        raise ValueError("block_diag: needs at least one operator.")
    crows, cols, vals = [], [], []
    rows = cols_off = nnz = 0
    for A in ops:
        p = A.pattern.to(ops[0].device)
        crows.append(p.crow[:-1] + nnz)
        cols.append(p.col + cols_off)
        vals.append(A._vals)
        rows, cols_off, nnz = rows + p.shape[0], cols_off + p.shape[1], nnz + p.nnz
    crows.append(torch.tensor([nnz], device=ops[0].device))
    pattern = SparsityPattern(torch.cat(crows), torch.cat(cols), (rows, cols_off))
    return operator_on(pattern, torch.cat(vals), symmetric=all(A.symmetric for A in ops))


def submatrix(A: Any, rows: torch.Tensor, cols: torch.Tensor) -> SparseOperator:
    """``A[rows][:, cols]`` for increasing index tensors; values gathered (differentiable)."""
    A = as_operator(A)
    pattern, keep = A.pattern.select(rows.to(A.device), cols.to(A.device))
    same = rows.shape == cols.shape and bool((rows == cols).all())
    return operator_on(pattern, A._vals[keep], symmetric=A.symmetric and same)


def eliminate(
    A: Any, fixed: torch.Tensor, diagonal: torch.Tensor
) -> tuple[SparseOperator, SparseOperator]:
    """Split ``A`` for prescribed values at the ``fixed`` rows (a ``(n,)`` bool mask).

    Returns ``(A_D, C)`` on one pattern (``A``'s plus its diagonal): ``A_D`` is ``A`` with the
    row and column of every fixed ``p`` replaced by ``diagonal[p] e_p`` (symmetric and definite
    when ``A`` is, for a positive ``diagonal``), and ``C`` keeps only the coupling entries
    ``A[free, fixed]``, so that ``A_D X = B - C X_fixed`` on the free rows solves ``A X = B``
    with ``X[fixed]`` given.  Differentiable in ``A``'s values and ``diagonal``.
    """
    A = as_operator(A)
    A = A + diag(A._vals.new_zeros(A.shape[0]))  # store every diagonal entry
    row, col = A.pattern.row, A.pattern.col
    fixed = fixed.to(A.device)
    touches = fixed[row] | fixed[col]
    kept_diagonal = torch.where(row == col, diagonal.to(A._vals)[row], torch.zeros_like(A._vals))
    reduced = A.with_values(torch.where(touches, kept_diagonal, A._vals))
    coupling = torch.where(~fixed[row] & fixed[col], A._vals, torch.zeros_like(A._vals))
    return reduced, A.with_values(coupling, symmetric=False)


def to_scipy(A: Any) -> sp.csr_matrix:
    """A sparse (operator, CSR/COO) or dense 2-D tensor as a ``scipy.sparse.csr_matrix``
    (detached, on the CPU)."""
    if isinstance(A, torch.Tensor) and not isinstance(A, SparseOperator):
        if A.layout == torch.strided:
            return sp.csr_matrix(A.detach().cpu().numpy())
    A = as_operator(A)
    p = A.pattern
    return sp.csr_matrix(
        (A._vals.detach().cpu().numpy(), p.col.cpu().numpy(), p.crow.cpu().numpy()),
        shape=p.shape,
    )


def from_scipy(
    S: Any,
    dtype: torch.dtype | None = None,
    device: torch.device | str | None = None,
    *,
    symmetric: bool = False,
) -> SparseOperator:
    """A scipy sparse matrix as a :class:`SparseOperator` (indices sorted, duplicates summed).

    Examples:
        >>> import scipy.sparse as sp
        >>> import torch
        >>> from torch_polylap.sparse import from_scipy, to_scipy
        >>> A = from_scipy(sp.diags([1.0, 2.0, 3.0]).tocsr())
        >>> A @ torch.ones(3, dtype=torch.float64)
        tensor([1., 2., 3.], dtype=torch.float64)
        >>> (to_scipy(2 * A) - 2 * sp.diags([1.0, 2.0, 3.0])).nnz
        0
    """
    S = sp.csr_matrix(S)
    S.sum_duplicates()
    S.sort_indices()
    values = torch.from_numpy(S.data).to(device=device, dtype=dtype)
    pattern = SparsityPattern(
        torch.from_numpy(S.indptr.astype(np.int64)).to(values.device),
        torch.from_numpy(S.indices.astype(np.int64)).to(values.device),
        S.shape,
    )
    return operator_on(pattern, values, symmetric=symmetric)


def to_torch_sparse(A: Any, layout: torch.layout = torch.sparse_csr) -> torch.Tensor:
    """A plain torch sparse CSR or COO tensor with ``A``'s (detached) values, for libraries that
    need torch's own sparse type.  Detached because torch's sparse autograd is dense."""
    A = as_operator(A)
    p, values = A.pattern, A._vals.detach()
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*[Ss]parse.*")
        if layout == torch.sparse_csr:
            return torch.sparse_csr_tensor(p.crow, p.col, values, p.shape)
        if layout == torch.sparse_coo:
            return torch.sparse_coo_tensor(
                torch.stack((p.row, p.col)), values, p.shape, is_coalesced=True
            )
    raise ValueError(f"layout must be torch.sparse_csr or torch.sparse_coo, got {layout}.")

"""The package's one sparse seam: the :class:`SparseOperator` type and everything done with it.

``L``, ``M0`` and every operator the package builds are :class:`SparseOperator` tensors: torch
tensors whose algebra (``@``, ``+``, ``*``, ``.T``, ``.to``) keeps O(nnz) gradients.  CSR
plumbing -- patterns, unions, transposes, sampled products, block diagonals, submatrices, the
per-operator solver cache, scipy conversion -- lives in this package and nowhere else.
"""

from . import construct, operator, pattern
from .construct import (
    as_operator,
    block_diag,
    diag,
    eliminate,
    from_coo,
    from_scipy,
    identity,
    mark_symmetric,
    operator_from_parts,
    pattern_of,
    sampled_gradient,
    solver_cache,
    sparse_values,
    spmm,
    submatrix,
    to_scipy,
    to_torch_sparse,
)
from .operator import SparseOperator, UnsupportedOperation, is_operator
from .pattern import SparsityPattern

__all__ = [*construct.__all__, *operator.__all__, *pattern.__all__]

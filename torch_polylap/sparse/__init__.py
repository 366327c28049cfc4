"""The package's one sparse seam: the :class:`SparseOperator` type and everything done with it.

``L``, ``M0`` and every operator the package builds are :class:`SparseOperator` tensors: torch
tensors whose algebra (``@``, ``+``, ``*``, ``.T``, ``.to``) keeps O(nnz) gradients.  CSR
plumbing -- patterns, unions, transposes, sampled products, block diagonals, submatrices, the
per-operator solver cache, scipy conversion -- lives in this package and nowhere else.

What is exported here is what users build, combine and convert operators with.  The plumbing
the rest of the package shares (the solver cache, sampled gradients, patterns, symmetry marks,
eliminating fixed rows) is imported from the modules :mod:`.construct`, :mod:`.operator` and
:mod:`.pattern` by the package itself and is not part of the public API. :mod:`.dispatch` holds
the operator's torch dispatch table (what each torch function does with an operator).
"""

from .construct import (
    as_operator,
    block_diag,
    diag,
    from_coo,
    from_scipy,
    identity,
    operator_from_parts,
    sparse_values,
    spmm,
    submatrix,
    to_scipy,
    to_torch_sparse,
)
from .operator import SparseOperator, UnsupportedOperation, is_operator

__all__ = [
    "SparseOperator",
    "UnsupportedOperation",
    "is_operator",
    "as_operator",
    "operator_from_parts",
    "from_coo",
    "from_scipy",
    "to_scipy",
    "to_torch_sparse",
    "sparse_values",
    "block_diag",
    "diag",
    "identity",
    "spmm",
    "submatrix",
]

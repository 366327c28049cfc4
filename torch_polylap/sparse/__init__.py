"""The package's one sparse seam: the :class:`SparseOperator` type and everything done with it.

``L``, ``M0`` and every operator the package builds are :class:`SparseOperator` tensors: torch
tensors whose algebra (``@``, ``+``, ``*``, ``.T``, ``.to``) keeps O(nnz) gradients.  CSR
plumbing -- patterns, unions, transposes, sampled products, block diagonals, submatrices, the
per-operator solver cache, scipy conversion -- lives in this package and nowhere else.
"""

from . import construct, operator, pattern
from .construct import *  # noqa: F403  (the names are listed once, in each module's __all__)
from .operator import *  # noqa: F403
from .pattern import *  # noqa: F403

__all__ = [*construct.__all__, *operator.__all__, *pattern.__all__]

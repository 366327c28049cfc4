"""Differentiable sparse products whose gradients stay on the sparsity pattern (O(nnz) memory).

torch's own autograd for ``sparse @ dense`` returns a *dense* ``n x m`` gradient for the sparse
operand: at 62k vertices that is 31 GB.  Here a matrix is its pattern plus a value array, and
the two products below are each other's backward:

    product:  Y = A X,                 dvalues = sampled(G, X),  dX = A^T G
    sampled:  s_k = (G X^T)_{r_k c_k}, dG = A(w) X,              dX = A(w)^T G

(``A(w)`` is the matrix on the same pattern with values ``w``.)  The backward passes are written
with the same two functions, so gradients of gradients (Hessian-vector products, gradient
penalties, ``create_graph=True``) are exact to any order, each at O(nnz * columns).
"""

from __future__ import annotations

import warnings
from typing import Any

import torch

from .pattern import SparsityPattern

__all__ = ["csr_product", "sampled_product", "torch_csr"]


def torch_csr(pattern: SparsityPattern, values: torch.Tensor) -> torch.Tensor:
    """A plain torch sparse CSR tensor on ``pattern`` (for torch's kernels; no autograd meaning).

    Skips torch's invariant checks and its one-time "CSR support is in beta" warning: the
    package builds its patterns itself and knows them valid.
    """
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*[Ss]parse.*")
        return torch.sparse_csr_tensor(
            pattern.crow, pattern.col, values, pattern.shape, check_invariants=False
        )


def csr_product(
    pattern: SparsityPattern, values: torch.Tensor, X: torch.Tensor, symmetric: bool
) -> torch.Tensor:
    """``A X`` for ``A`` = (``pattern``, ``values``) ``(n, m)`` and dense ``X`` ``(m, c)``.

    Differentiable in ``values`` and ``X`` to any order; ``symmetric`` (``A = A^T``) lets the
    backward multiply by ``A`` itself instead of transposing the pattern.
    """
    if not (torch.is_grad_enabled() and (values.requires_grad or X.requires_grad)):
        # nothing to differentiate: the autograd.Function's fixed cost dominates small products
        return torch_csr(pattern, values.detach()) @ X
    return _Product.apply(values, X, pattern, symmetric)


def sampled_product(pattern: SparsityPattern, G: torch.Tensor, X: torch.Tensor) -> torch.Tensor:
    """``(nnz,)`` entries of ``G X^T`` on ``pattern``: ``s_k = sum_c G[row_k, c] X[col_k, c]``.

    The gradient of ``loss(A X)`` with respect to ``A``'s values, for ``G = dloss / d(A X)``.
    ``G`` ``(n, c)``, ``X`` ``(m, c)``.  Differentiable in both to any order.
    """
    if not (torch.is_grad_enabled() and (G.requires_grad or X.requires_grad)):
        return _sampled(pattern, G.detach(), X.detach())
    return _Sampled.apply(G, X, pattern)


def _sampled(pattern: SparsityPattern, G: torch.Tensor, X: torch.Tensor) -> torch.Tensor:
    zeros = G.new_zeros(pattern.nnz)
    return torch.sparse.sampled_addmm(
        torch_csr(pattern, zeros), G.contiguous(), X.t().contiguous(), beta=0.0
    ).values()


def _transposed_product(
    pattern: SparsityPattern, values: torch.Tensor, G: torch.Tensor, symmetric: bool
) -> torch.Tensor:
    """``A^T G``."""
    if symmetric:
        return csr_product(pattern, values, G, True)
    transposed, perm = pattern.transpose()
    return csr_product(transposed, values[perm], G, False)


class _Product(torch.autograd.Function):
    @staticmethod
    def forward(
        values: torch.Tensor, X: torch.Tensor, pattern: SparsityPattern, symmetric: bool
    ) -> torch.Tensor:
        return torch_csr(pattern, values) @ X

    @staticmethod
    def setup_context(ctx: Any, inputs: tuple[Any, ...], output: torch.Tensor) -> None:
        values, X, pattern, symmetric = inputs
        ctx.save_for_backward(values, X)
        ctx.pattern, ctx.symmetric = pattern, symmetric

    @staticmethod
    def backward(ctx: Any, G: torch.Tensor) -> tuple[torch.Tensor | None, ...]:
        values, X = ctx.saved_tensors
        grad_values = grad_X = None
        if ctx.needs_input_grad[0]:
            grad_values = sampled_product(ctx.pattern, G, X)
        if ctx.needs_input_grad[1]:
            grad_X = _transposed_product(ctx.pattern, values, G, ctx.symmetric)
        return grad_values, grad_X, None, None


class _Sampled(torch.autograd.Function):
    @staticmethod
    def forward(G: torch.Tensor, X: torch.Tensor, pattern: SparsityPattern) -> torch.Tensor:
        return _sampled(pattern, G, X)

    @staticmethod
    def setup_context(ctx: Any, inputs: tuple[Any, ...], output: torch.Tensor) -> None:
        G, X, pattern = inputs
        ctx.save_for_backward(G, X)
        ctx.pattern = pattern

    @staticmethod
    def backward(ctx: Any, w: torch.Tensor) -> tuple[torch.Tensor | None, ...]:
        G, X = ctx.saved_tensors
        grad_G = grad_X = None
        if ctx.needs_input_grad[0]:
            grad_G = csr_product(ctx.pattern, w, X, False)
        if ctx.needs_input_grad[1]:
            grad_X = _transposed_product(ctx.pattern, w, G, False)
        return grad_G, grad_X, None

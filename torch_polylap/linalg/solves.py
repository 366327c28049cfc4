"""Differentiable sparse solves: ``solve`` (the adjoint method, O(nnz) backward) and
``dirichlet_solve`` (prescribed values at some vertices).

``solve(A, B)`` solves ``A X = B`` for a sparse, symmetric positive definite ``A`` (``M0 + h L``,
``L`` with Dirichlet rows, ...) and is differentiable in ``B`` and in ``A``'s values: with
``G = dLoss/dX``, ``dLoss/dB = A^{-T} G`` and ``dLoss/dA_ij = -(A^{-T} G)_i X_j`` on ``A``'s
pattern only, so memory stays O(nnz). The factorization is cached on ``A`` and reused by the
backward solve and by later solves with the same values.
"""

from __future__ import annotations

from typing import Any

import torch

from ..checks import check_finite_operand, check_index_or_mask
from ..sparse import SparseOperator, as_operator, sparse_values, submatrix
from ..sparse.construct import csr_indices, sampled_gradient
from ..tracing import tracing
from .cg import ConvergenceError as ConvergenceError
from .factor import OpaqueOperator, cached_factorization, cholespy_available, qdldl_available
from .solve_op import solve_op, solve_values


def _solve(
    A: SparseOperator, B: torch.Tensor, backend: str, tol: float, max_iter: int
) -> torch.Tensor:
    values = sparse_values(A)
    if tracing():
        crow, col = csr_indices(A)
        return solve_op(values, crow, col, B, A.symmetric, backend, tol, max_iter)
    if not (torch.is_grad_enabled() and (values.requires_grad or B.requires_grad)):
        return solve_values(A, B, backend, tol, max_iter)
    return _Solve.apply(values, B, OpaqueOperator(A), backend, tol, max_iter)


class _Solve(torch.autograd.Function):
    """``X = A^{-1} B``; backward ``dB = A^{-T} G``, ``dvalues = -(A^{-T} G) X^T`` on the pattern.

    The backward is written with :func:`_solve` and the sampled product, so it is itself
    differentiable (second derivatives through solves, e.g. Hessian-vector products).
    """

    @staticmethod
    def forward(
        values: torch.Tensor,
        B: torch.Tensor,
        held: OpaqueOperator,
        backend: str,
        tol: float,
        max_iter: int,
    ) -> torch.Tensor:
        # `values` here is the plain tensor even under torch.func, whose wrapped tensors have no
        # storage for the factorization cache to check
        A = held.A.with_values(values, share_cache=True)
        return solve_values(A, B, backend, tol, max_iter)

    @staticmethod
    def setup_context(ctx: Any, inputs: tuple[Any, ...], output: torch.Tensor) -> None:
        values, B, held, backend, tol, max_iter = inputs
        ctx.save_for_backward(values, output)
        ctx.A, ctx.options = held.A, (backend, tol, max_iter)

    @staticmethod
    def backward(ctx: Any, G: torch.Tensor) -> tuple[torch.Tensor | None, ...]:
        values, X = ctx.saved_tensors
        backend = ctx.options[0]
        if not torch.is_grad_enabled() and backend != "cg":
            # first-order backward: reuse the factorization for A^T directly
            gB = cached_factorization(ctx.A, backend).solve(G, transpose=True)
        else:
            # A^T = A for the SPD matrices solve() takes (CG needs it anyway)
            A = ctx.A.with_values(values, share_cache=True)
            gB = _solve(A if A.symmetric else A.T, G, *ctx.options)
        grad_values = None
        if ctx.needs_input_grad[0]:
            grad_values = -sampled_gradient(ctx.A, gB, X)
        return grad_values, gB if ctx.needs_input_grad[1] else None, None, None, None, None


def solve(
    A: torch.Tensor,
    B: torch.Tensor,
    *,
    backend: str = "auto",
    tol: float = 1e-10,
    max_iter: int = 10000,
) -> torch.Tensor:
    """``X = A^{-1} B`` for a sparse symmetric positive definite ``A``, differentiable in both.

    Args:
        A: ``(n, n)`` sparse operator, e.g. ``M0 + h L`` (or a torch sparse tensor without grad,
            or a scipy matrix); its values may require grad.
        B: ``(n,)`` or ``(n, c)`` dense right-hand side(s) of ``A``'s dtype.
        backend: ``"cholesky"`` (CHOLMOD through the optional ``cholespy``, on ``A``'s device:
            CPU or CUDA; ``A`` must be symmetric, as ``M0 + h L`` and Dirichlet blocks of ``L``
            are), ``"ldl"`` (QDLDL's ``L D L^T`` through the optional ``qdldl``, symmetric ``A``
            on the CPU: it factors in about half CHOLMOD's time through cholespy up to some
            40k unknowns and solves a little slower), ``"splu"`` (SuperLU on the CPU),
            ``"cg"`` (Jacobi-preconditioned conjugate
            gradients on ``A``'s device), or ``"auto"``: ``"cholesky"`` for a symmetric ``A``
            when cholespy is installed, else ``"splu"`` on the CPU and ``"cg"`` on CUDA.
            Factorizations are cached on ``A`` and reused by the backward solve.
        tol: relative residual ``|B - A X| / |B|`` (the true one, per column) at which
            ``"cg"`` stops.
        max_iter: iteration limit of ``"cg"``.

    Returns:
        ``X`` with ``B``'s shape, dtype and device. The direct solvers work in float64 and
        cast back.

    Raises:
        ValueError: ``A`` singular (e.g. ``L`` without a mass term or Dirichlet values), or
            not positive definite for ``"cholesky"`` and ``"cg"`` (the message says whether it
            is singular or indefinite; ``"splu"`` solves a non-singular indefinite ``A``,
            with partial pivoting where needed), shapes or dtypes that do not match.
        ConvergenceError: (a ``ValueError``, :class:`torch_polylap.linalg.ConvergenceError`)
            ``"cg"`` did not reach ``tol`` (a singular ``A`` with ``B`` outside its range,
            bad conditioning, or ``max_iter`` too small); it carries ``residual`` and
            ``iterations``.

    Examples:
        One implicit smoothing step ``(M0 + h L) X = M0 X0`` on a square and a triangle:

        >>> import torch
        >>> import torch_polylap as tp
        >>> verts = torch.tensor([[0.0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [2, 0.5, 0.5]],
        ...                      dtype=torch.float64)
        >>> L, M0 = tp.laplacian(verts, [[0, 1, 2, 3], [1, 4, 2]])
        >>> X = tp.solve(M0 + 0.1 * L, M0 @ verts)
        >>> X.shape
        torch.Size([5, 3])
        >>> torch.allclose((M0 + 0.1 * L) @ X, M0 @ verts)
        True
    """
    A = as_operator(A)
    if A.dim() != 2 or A.shape[0] != A.shape[1]:
        raise ValueError(f"solve needs a square matrix, got shape {tuple(A.shape)}.")
    if B.dim() not in (1, 2) or B.shape[0] != A.shape[0]:
        raise ValueError(
            f"solve: B of shape {tuple(B.shape)} does not fit A of shape {tuple(A.shape)}."
        )
    if B.dtype != A.dtype:
        raise ValueError(f"solve: A has dtype {A.dtype} but B has {B.dtype}; convert one of them.")
    check_finite_operand(A, "A", "solve")
    check_finite_operand(B, "B", "solve")
    if backend == "auto":
        if A.symmetric and cholespy_available():
            backend = "cholesky"
        else:
            backend = "splu" if A.device.type == "cpu" else "cg"
    if backend not in ("cholesky", "ldl", "splu", "cg"):
        raise ValueError(
            f"backend must be 'auto', 'cholesky', 'ldl', 'splu' or 'cg', got {backend!r}."
        )
    if backend == "ldl":
        if not A.symmetric or A.device.type != "cpu":
            raise ValueError(
                "solve: backend='ldl' factors a symmetric operator on the CPU (M0 + h L, a "
                "Dirichlet block of L); use backend='splu' or 'cg' otherwise."
            )
        if not qdldl_available():
            raise ValueError(
                "solve: backend='ldl' needs the optional package qdldl "
                "(pip install 'torch_polylap[ldl]'); use backend='cholesky' or 'splu' without it."
            )
    if backend == "cholesky":
        if not A.symmetric:
            raise ValueError(
                "solve: backend='cholesky' needs a symmetric operator (M0 + h L, a Dirichlet "
                "block of L, or one built with symmetric=True); use backend='splu' otherwise."
            )
        if not cholespy_available():
            raise ValueError(
                "solve: backend='cholesky' needs the optional package cholespy "
                "(pip install 'torch_polylap[cholmod]'); use backend='splu' or 'cg' without it."
            )
    vec = B.dim() == 1
    X = _solve(A, B[:, None] if vec else B, backend, tol, max_iter)
    return X[:, 0] if vec else X


def dirichlet_solve(
    A: torch.Tensor,
    B: torch.Tensor,
    fixed: torch.Tensor,
    fixed_values: torch.Tensor,
    **solve_options: Any,
) -> torch.Tensor:
    """Solve ``A X = B`` on the free rows with ``X[fixed] = fixed_values`` prescribed.

    The free unknowns solve ``A_FF X_F = B_F - A_FC X_C``; rows of ``B`` at fixed vertices are
    ignored. Differentiable in ``A``'s values, ``B`` and ``fixed_values`` (gathers of ``A``'s
    values keep the O(nnz) backward).

    Args:
        A: ``(n, n)`` sparse matrix, e.g. the Laplacian ``L`` (whose free block is SPD when at
            least one vertex per connected component is fixed).
        B: ``(n,)`` or ``(n, c)``.
        fixed: indices (or an ``(n,)`` bool mask) of the prescribed rows.
        fixed_values: ``(m,)`` or ``(m, c)`` values at ``fixed`` (in the order of ``fixed``).
        solve_options: passed to :func:`solve`.

    Returns:
        ``X`` of ``B``'s shape, equal to ``fixed_values`` on ``fixed``.
    """
    A = as_operator(A)
    n = A.shape[0]
    if A.dim() != 2 or A.shape[1] != n:
        raise ValueError(f"dirichlet_solve needs a square matrix, got shape {tuple(A.shape)}.")
    if B.dim() not in (1, 2) or B.shape[0] != n:
        raise ValueError(
            f"dirichlet_solve: B of shape {tuple(B.shape)} does not fit A of shape "
            f"{tuple(A.shape)}."
        )
    fixed, is_fixed = _fixed_rows(fixed, n, B.device)
    free = torch.nonzero(~is_fixed).reshape(-1)
    if free.numel() == 0:
        raise ValueError("dirichlet_solve: every row is fixed; there is nothing to solve for.")
    vec = B.dim() == 1
    Bm = B[:, None] if vec else B
    try:
        Xc = fixed_values.reshape(fixed.numel(), -1).to(B.dtype)
    except RuntimeError:
        raise ValueError(
            f"dirichlet_solve: fixed_values of shape {tuple(fixed_values.shape)} do not fit "
            f"{fixed.numel()} fixed rows and {Bm.shape[1]} column(s)."
        ) from None
    if Xc.shape[1] not in (1, Bm.shape[1]):
        raise ValueError(
            f"dirichlet_solve: fixed_values have {Xc.shape[1]} columns, B has {Bm.shape[1]}."
        )
    order = torch.argsort(fixed)  # submatrix wants increasing indices
    fixed_sorted, Xc_sorted = fixed[order], Xc[order.to(Xc.device)]
    A_ff = submatrix(A, free, free)
    A_fc = submatrix(A, free, fixed_sorted)
    rhs = Bm[free] - A_fc @ Xc_sorted
    Xf = solve(A_ff, rhs, **solve_options)
    X = torch.zeros_like(Bm).index_put((free,), Xf).index_put((fixed,), Xc.expand_as(Bm[fixed]))
    return X[:, 0] if vec else X


def _fixed_rows(
    fixed: torch.Tensor, n: int, device: torch.device
) -> tuple[torch.Tensor, torch.Tensor]:
    """``(indices (m,), mask (n,))`` of the prescribed rows, from indices or a boolean mask."""
    indices = check_index_or_mask(fixed, n, "fixed").to(device)
    is_fixed = torch.zeros(n, dtype=torch.bool, device=device)
    is_fixed[indices] = True
    return indices, is_fixed

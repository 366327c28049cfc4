"""Differentiable sparse solves: ``solve`` (the adjoint method, O(nnz) backward) and
``dirichlet_solve`` (prescribed values at some vertices).

``solve(A, B)`` solves ``A X = B`` for a sparse, symmetric positive definite ``A`` (``M0 + h L``,
``L`` with Dirichlet rows, ...) and is differentiable in ``B`` and in ``A``'s values: with
``G = dLoss/dX``, ``dLoss/dB = A^{-T} G`` and ``dLoss/dA_ij = -(A^{-T} G)_i X_j`` on ``A``'s
pattern only, so memory stays O(nnz). The factorization is cached on ``A`` and reused by the
backward solve and by later solves with the same values.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, NamedTuple

import torch

from ..checks import check_index_or_mask
from ..sparse import (
    SparseOperator,
    as_operator,
    sampled_gradient,
    sparse_values,
    submatrix,
)
from ..sparse.construct import csr_indices
from ..tracing import tracing
from .factor import _cholespy_available, _factorization, _OpaqueOperator, _qdldl_available
from .solve_op import solve_op


class ConvergenceError(ValueError):
    """An iterative solver stopped without reaching its tolerance.

    A :class:`ValueError` (as the non-convergence of :func:`solve` with ``backend="cg"`` and of
    :func:`eigs` always was), so existing ``except ValueError`` handlers still catch it; the
    message names the residual reached and the iterations spent.

    Attributes:
        iterations: iterations (or attempts) spent.
        residual: the relative residual reached (``|B - A X| / |B|``, the worst column), or NaN
            where it does not apply.
    """

    def __init__(self, message: str, iterations: int, residual: float = float("nan")) -> None:
        super().__init__(message)
        self.iterations = iterations
        self.residual = residual


class CGResult(NamedTuple):
    """What :func:`conjugate_gradients` reached."""

    X: torch.Tensor
    converged: bool
    iterations: int
    residual: float  # true relative residual |B - A X| / |B|, the worst column
    curvature: float | None  # p^T A p / (|p|^2 max|A_ii|) <= 0 met, None if never


def conjugate_gradients(
    A: torch.Tensor,
    B: torch.Tensor,
    precondition: Callable[[torch.Tensor], torch.Tensor],
    tol: float,
    max_iter: int,
) -> CGResult:
    """Preconditioned conjugate gradients on every column of ``(n, c)`` ``B`` at once.

    ``A`` is SPD (anything with ``A @ X``), ``precondition`` applies an SPD approximation of
    ``A^{-1}`` to an ``(n, c)`` block (no autograd). Convergence is judged on the true residual
    ``B - A X``: the updated residual of the recurrence drifts away from it when ``A`` is
    singular or badly conditioned (on a Laplacian alone with ``B`` outside its range it reached
    the tolerance while ``|B - A X| / |B|`` was 20 and ``|X|`` 1e16), so each time the
    recurrence claims convergence the true residual is computed (one product) and the
    iteration restarted from it if it is not there yet, or stopped when the restart did not
    halve it (no further progress is possible). A search direction ``p`` with
    ``p^T A p <= 0`` proves that ``A`` is not positive definite and stops at once.
    """
    X = torch.zeros_like(B)
    R = B.clone()
    Z = precondition(R)
    P = Z.clone()
    rz = (R * Z).sum(0)
    tiny = torch.finfo(B.dtype).tiny
    b_norm = torch.linalg.vector_norm(B, dim=0)
    target = tol * b_norm
    scale = float(A.diagonal().abs().max()) if B.shape[0] else 1.0
    last_true = float("inf")

    def relative(R: torch.Tensor) -> float:
        r = torch.linalg.vector_norm(R, dim=0) / b_norm.clamp_min(tiny)
        return float(r.max()) if r.numel() else 0.0

    for iteration in range(max_iter):
        if bool((torch.linalg.vector_norm(R, dim=0) <= target).all()):
            R = B - A @ X
            true = relative(R)
            if true <= tol:
                return CGResult(X, True, iteration, true, None)
            if true > 0.5 * last_true:
                return CGResult(X, False, iteration, true, None)
            last_true = true
            Z = precondition(R)
            P = Z.clone()
            rz = (R * Z).sum(0)
        AP = A @ P
        pAp = (P * AP).sum(0)
        active = rz > 0
        if bool((active & (pAp <= 0)).any()):
            j = int(torch.nonzero(active & (pAp <= 0))[0, 0])
            curvature = float(pAp[j]) / max(float((P[:, j] ** 2).sum()) * scale, tiny)
            return CGResult(X, False, iteration, relative(B - A @ X), curvature)
        # converged (or zero) columns have rz = 0: keep them where they are instead of 0 / 0
        alpha = torch.where(active, rz / pAp.clamp_min(tiny), 0.0)
        X = X + alpha * P
        R = R - alpha * AP
        Z = precondition(R)
        rz_new = (R * Z).sum(0)
        P = Z + torch.where(active, rz_new / rz.clamp_min(tiny), 0.0) * P
        rz = rz_new
    true = relative(B - A @ X)
    return CGResult(X, true <= tol, max_iter, true, None)


def preconditioned_cg(
    A: torch.Tensor,
    B: torch.Tensor,
    precondition: Callable[[torch.Tensor], torch.Tensor],
    tol: float,
    max_iter: int,
) -> tuple[torch.Tensor, bool]:
    """``X`` and whether every column reached the relative residual ``tol`` within
    ``max_iter`` iterations (see :func:`conjugate_gradients`)."""
    result = conjugate_gradients(A, B, precondition, tol, max_iter)
    return result.X, result.converged


_CURVATURE_ROUNDOFF = 1e-8


def _cg(A: torch.Tensor, B: torch.Tensor, tol: float, max_iter: int) -> torch.Tensor:
    """Jacobi-preconditioned conjugate gradients (SPD ``A``); raises when it does not converge."""
    Ad = A.detach()
    diag = Ad.diagonal()
    if bool((diag <= 0).any()):
        i = int(torch.nonzero(diag <= 0)[0, 0])
        raise ValueError(
            f"solve: backend='cg' needs a symmetric positive definite matrix, but diagonal "
            f"entry {i} is {float(diag[i]):g} (a positive definite matrix has a positive "
            "diagonal); for a non-singular indefinite matrix use backend='splu'."
        )
    inv_diag = (1.0 / diag)[:, None]
    result = conjugate_gradients(Ad, B, lambda R: inv_diag * R, tol, max_iter)
    if result.converged:
        return result.X
    if result.curvature is not None:
        # round-off in p^T A p is a few eps relative; well beyond that, A is indefinite
        indefinite = result.curvature < -_CURVATURE_ROUNDOFF
        what = (
            "indefinite: if it is non-singular, use backend='splu'"
            if indefinite
            else "singular, or indefinite: a Laplacian alone has the constants in its kernel, "
            "solve with M0 + h L or fix values with torch_polylap.dirichlet_solve; a "
            "non-singular indefinite matrix needs backend='splu'"
        )
        raise ValueError(
            f"solve: backend='cg' needs a symmetric positive definite matrix, but this one is "
            f"not positive definite: a search direction p has p^T A p = {result.curvature:.3g} "
            f"|p|^2 max|A_ii| (iteration {result.iterations}), so A is {what}."
        )
    stopped = "it stopped making progress" if result.iterations < max_iter else "max_iter"
    raise ConvergenceError(
        f"solve: conjugate gradients did not converge: relative residual |B - A X| / |B| = "
        f"{result.residual:.3g} after {result.iterations} iterations ({stopped}), tolerance "
        f"{tol:g}. A is singular with B outside its range (e.g. a Laplacian without a mass "
        "term or Dirichlet values: solve with M0 + h L or torch_polylap.dirichlet_solve), or "
        "too badly conditioned for CG: pass a larger max_iter, or use a direct solver "
        "(backend='cholesky' or 'splu').",
        result.iterations,
        result.residual,
    )


def _solve_values(
    A: SparseOperator, B: torch.Tensor, backend: str, tol: float, max_iter: int
) -> torch.Tensor:
    """``A^{-1} B`` for ``(n, c)`` ``B``, no autograd."""
    if backend == "cg":
        return _cg(A, B.detach(), tol, max_iter)
    return _factorization(A, backend).solve(B)


def _solve(
    A: SparseOperator, B: torch.Tensor, backend: str, tol: float, max_iter: int
) -> torch.Tensor:
    values = sparse_values(A)
    if tracing():
        crow, col = csr_indices(A)
        return solve_op(values, crow, col, B, A.symmetric, backend, tol, max_iter)
    if not (torch.is_grad_enabled() and (values.requires_grad or B.requires_grad)):
        return _solve_values(A, B, backend, tol, max_iter)
    return _Solve.apply(values, B, _OpaqueOperator(A), backend, tol, max_iter)


class _Solve(torch.autograd.Function):
    """``X = A^{-1} B``; backward ``dB = A^{-T} G``, ``dvalues = -(A^{-T} G) X^T`` on the pattern.

    The backward is written with :func:`_solve` and the sampled product, so it is itself
    differentiable (second derivatives through solves, e.g. Hessian-vector products).
    """

    @staticmethod
    def forward(
        values: torch.Tensor,
        B: torch.Tensor,
        held: _OpaqueOperator,
        backend: str,
        tol: float,
        max_iter: int,
    ) -> torch.Tensor:
        # `values` here is the plain tensor even under torch.func, whose wrapped tensors have no
        # storage for the factorization cache to check
        A = held.A.with_values(values, share_cache=True)
        return _solve_values(A, B, backend, tol, max_iter)

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
            gB = _factorization(ctx.A, backend).solve(G, transpose=True)
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
    if backend == "auto":
        if A.symmetric and _cholespy_available():
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
        if not _qdldl_available():
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
        if not _cholespy_available():
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

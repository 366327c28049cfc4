"""Jacobi-preconditioned conjugate gradients for the sparse solve's ``backend="cg"``.

:func:`conjugate_gradients` runs on every column of the right-hand side at once and reports
what it reached; :func:`cg_solve` turns a failure into an error that says why (not positive
definite, or not converged: :class:`ConvergenceError`).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import torch

__all__ = ["ConvergenceError", "conjugate_gradients", "preconditioned_cg", "cg_solve"]


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


def cg_solve(A: torch.Tensor, B: torch.Tensor, tol: float, max_iter: int) -> torch.Tensor:
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

"""Differentiable sparse solves and generalized eigenpairs for the operators of this package.

``solve(A, B)`` solves ``A X = B`` for a sparse, symmetric positive definite ``A`` (``M0 + h L``,
``L`` with Dirichlet rows, ...) and is differentiable in ``B`` and in ``A``'s values by the
adjoint method: with ``G = dLoss/dX``, ``dLoss/dB = A^{-T} G`` and
``dLoss/dA_ij = -(A^{-T} G)_i X_j`` on ``A``'s pattern only, so memory stays O(nnz).  The
factorization is cached on ``A`` and reused by the backward solve and by later solves with the
same values.

``eigs(L, M, k)`` returns the ``k`` smallest eigenpairs of ``L phi = mu M phi``; eigenvalues
(``d mu = phi^T (dL - mu dM) phi``) and eigenvectors (one sparse solve with ``L - mu M`` per
eigenpair) are differentiable for simple eigenvalues.
"""

from __future__ import annotations

import atexit
import weakref
from collections.abc import Callable
from typing import Any

import numpy as np
import scipy.linalg
import scipy.sparse as sp
import scipy.sparse.linalg as spla
import torch

from .checks import check_index_or_mask
from .lanczos import block_lanczos
from .sparse import (
    SparseOperator,
    as_operator,
    sampled_gradient,
    solver_cache,
    sparse_values,
    submatrix,
    to_scipy,
)

__all__ = ["solve", "dirichlet_solve", "eigs"]


def spd_splu(S: sp.csc_matrix) -> spla.SuperLU:
    """SuperLU factorization with settings for symmetric positive definite matrices.

    Symmetric mode without row pivoting keeps ``L`` and ``U^T`` on one pattern, as a Cholesky
    would. The column ordering is COLAMD, SuperLU's default: minimum degree on ``A + A^T``
    (``MMD_AT_PLUS_A``) is faster on grid meshes but far slower on some others
    (``benchmarks/README.md`` has the measurements).
    """
    return spla.splu(S, permc_spec="COLAMD", diag_pivot_thresh=0.0, options={"SymmetricMode": True})


class Factorization:
    """A sparse LU factorization (SuperLU, symmetric mode) of a CSR matrix, in float64, on the CPU.

    Built from ``A``'s values at one point in time and cached on ``A`` by
    :func:`torch_polylap.sparse.solver_cache`, which checks the values' storage and version
    counter before reusing it.
    """

    def __init__(self, A: torch.Tensor) -> None:
        S = sp.csc_matrix(to_scipy(A).astype(np.float64))
        try:
            self.lu = spd_splu(S)
        except RuntimeError as err:
            raise ValueError(_singular_message(A, str(err))) from None
        _check_not_singular(A, S, lambda b: self.lu.solve(b))

    def solve(self, B: torch.Tensor, transpose: bool = False) -> torch.Tensor:
        X = self.lu.solve(
            np.ascontiguousarray(B.detach().cpu().numpy(), dtype=np.float64),
            trans="T" if transpose else "N",
        )
        return _finite(torch.from_numpy(X)).to(B)


# cholespy's solver objects are nanobind instances; one still alive at interpreter shutdown
# (cached on an operator that a user's tensor keeps reachable through its autograd graph) makes
# nanobind print a "leaked instances" report. Release them before the interpreter tears down.
_LIVE_CHOLESKY: weakref.WeakSet = weakref.WeakSet()


@atexit.register
def _release_cholesky_factors() -> None:
    for factorization in list(_LIVE_CHOLESKY):
        factorization.factor = None


class CholeskyFactorization:
    """CHOLMOD's supernodal Cholesky of a symmetric positive definite matrix, in float64, on the
    matrix's device (CPU, or CUDA through cholespy's GPU solver), via the optional ``cholespy``.

    Faster than SuperLU for the SPD systems of this package (``M0 + h L``, Dirichlet blocks of
    ``L``) and the only direct solver here that runs on a GPU.
    """

    # cholespy's CUDA solve takes at most this many right-hand sides at once
    _CUDA_COLUMNS = 128

    def __init__(self, A: torch.Tensor | sp.spmatrix, device: torch.device | None = None) -> None:
        from cholespy import CholeskySolverD, MatrixType

        device = A.device if isinstance(A, torch.Tensor) else torch.device(device or "cpu")
        S = sp.coo_matrix((to_scipy(A) if isinstance(A, torch.Tensor) else A).astype(np.float64))
        try:
            self.factor = CholeskySolverD(
                S.shape[0],
                torch.from_numpy(S.row.astype(np.int32)).to(device),
                torch.from_numpy(S.col.astype(np.int32)).to(device),
                torch.from_numpy(S.data).to(device),
                MatrixType.COO,
            )
        except (RuntimeError, ValueError) as err:
            raise ValueError(_singular_message(A, str(err))) from None
        self.device = device
        _LIVE_CHOLESKY.add(self)

        def solve_numpy(b: np.ndarray) -> np.ndarray:
            rhs = torch.from_numpy(b).to(self.device)[:, None]
            return self._solve64(rhs)[:, 0].cpu().numpy()

        _check_not_singular(A, S.tocsc(), solve_numpy)

    def _solve64(self, B: torch.Tensor) -> torch.Tensor:
        X = torch.empty_like(B)
        step = self._CUDA_COLUMNS if B.device.type == "cuda" else max(B.shape[1], 1)
        for start in range(0, B.shape[1], step):
            rhs = B[:, start : start + step].contiguous()
            out = torch.empty_like(rhs)
            self.factor.solve(rhs, out)
            X[:, start : start + step] = out
        return X

    def solve(self, B: torch.Tensor, transpose: bool = False) -> torch.Tensor:
        B64 = B.detach().to(device=self.device, dtype=torch.float64).contiguous()
        return _finite(self._solve64(B64)).to(B)


def _check_not_singular(
    A: torch.Tensor | sp.spmatrix, S: sp.spmatrix, solve: Callable[[np.ndarray], np.ndarray]
) -> None:
    """Refuse a numerically singular ``A``.  A singular PSD matrix (a Laplacian without a mass
    term) factors without complaint, its last pivot being round-off; one solve with a fixed
    random right-hand side shows it, the growth ``|x| |A| / |b|`` then reaching ``1 / eps``
    (reading the pivots would need the whole factor to be copied out of the solver)."""
    n = S.shape[0]
    b = np.random.default_rng(0).standard_normal(n)
    growth = np.abs(solve(b)).max() * abs(S).max() / np.abs(b).max() if n else 0.0
    if not np.isfinite(growth) or growth * n * np.finfo(float).eps >= 1.0:
        raise ValueError(_singular_message(A, f"solution growth {growth:.1e}"))


def _finite(X: torch.Tensor) -> torch.Tensor:
    if not bool(torch.isfinite(X).all()):
        raise ValueError(
            "the solve produced non-finite values: the system matrix is singular or "
            "numerically singular (a Laplacian without a mass term or Dirichlet values?)."
        )
    return X


def _cholespy_available() -> bool:
    try:
        import cholespy  # noqa: F401
    except ImportError:
        return False
    return True


def _singular_message(A: torch.Tensor | sp.spmatrix, detail: str) -> str:
    return (
        f"the {A.shape[0]} x {A.shape[1]} system matrix is singular ({detail}). A Laplacian "
        "alone has the constants in its kernel: solve with M0 + h L, or fix values at some "
        "vertices with torch_polylap.dirichlet_solve."
    )


def _factorization(A: SparseOperator, backend: str) -> Factorization | CholeskyFactorization:
    kind = CholeskyFactorization if backend == "cholesky" else Factorization
    return solver_cache(A, backend, lambda: kind(A))


def _cg(A: torch.Tensor, B: torch.Tensor, tol: float, max_iter: int) -> torch.Tensor:
    """Jacobi-preconditioned conjugate gradients on every column of ``B`` at once (SPD ``A``)."""
    Ad = A.detach()
    diag = Ad.diagonal()
    if bool((diag <= 0).any()):
        raise ValueError("conjugate gradients needs a positive diagonal (an SPD matrix).")
    inv_diag = (1.0 / diag)[:, None]
    X = torch.zeros_like(B)
    R = B.clone()
    Z = inv_diag * R
    P = Z.clone()
    rz = (R * Z).sum(0)
    tiny = torch.finfo(B.dtype).tiny
    target = tol * torch.linalg.vector_norm(B, dim=0)
    for _ in range(max_iter):
        if bool((torch.linalg.vector_norm(R, dim=0) <= target).all()):
            return X
        AP = Ad @ P
        # converged (or zero) columns have rz = 0: keep them where they are instead of 0 / 0
        alpha = torch.where(rz > 0, rz / (P * AP).sum(0).clamp_min(tiny), 0.0)
        X = X + alpha * P
        R = R - alpha * AP
        Z = inv_diag * R
        rz_new = (R * Z).sum(0)
        P = Z + torch.where(rz > 0, rz_new / rz.clamp_min(tiny), 0.0) * P
        rz = rz_new
    if bool((torch.linalg.vector_norm(R, dim=0) <= target).all()):
        return X
    raise ValueError(
        f"conjugate gradients did not reach a relative residual of {tol:g} in {max_iter} "
        "iterations: the matrix may be singular or badly conditioned (pass a larger max_iter)."
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
    if not (torch.is_grad_enabled() and (values.requires_grad or B.requires_grad)):
        return _solve_values(A, B, backend, tol, max_iter)
    return _Solve.apply(values, B, _Held(A), backend, tol, max_iter)


class _Held:
    """A sparse operator passed to an autograd.Function as a plain object: autograd and
    torch.func must see only its value array as the differentiable input."""

    __slots__ = ("A",)

    def __init__(self, A: SparseOperator) -> None:
        self.A = A


class _Solve(torch.autograd.Function):
    """``X = A^{-1} B``; backward ``dB = A^{-T} G``, ``dvalues = -(A^{-T} G) X^T`` on the pattern.

    The backward is written with :func:`_solve` and the sampled product, so it is itself
    differentiable (second derivatives through solves, e.g. Hessian-vector products).
    """

    @staticmethod
    def forward(
        values: torch.Tensor, B: torch.Tensor, held: _Held, backend: str, tol: float, max_iter: int
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
            are), ``"splu"`` (SuperLU on the CPU), ``"cg"`` (Jacobi-preconditioned conjugate
            gradients on ``A``'s device), or ``"auto"``: ``"cholesky"`` for a symmetric ``A``
            when cholespy is installed, else ``"splu"`` on the CPU and ``"cg"`` on CUDA.
            Factorizations are cached on ``A`` and reused by the backward solve.
        tol: relative residual at which ``"cg"`` stops.
        max_iter: iteration limit of ``"cg"``.

    Returns:
        ``X`` with ``B``'s shape, dtype and device. The direct solvers work in float64 and
        cast back.

    Raises:
        ValueError: ``A`` singular (e.g. ``L`` without a mass term or Dirichlet values), shapes
            or dtypes that do not match, or CG that does not converge.

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
    if backend not in ("cholesky", "splu", "cg"):
        raise ValueError(f"backend must be 'auto', 'cholesky', 'splu' or 'cg', got {backend!r}.")
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


_SECOND_ORDER_MESSAGE = (
    "torch_polylap.eigs: second derivatives of eigenvalues and eigenvectors (create_graph=True "
    "through eigs, Hessian-vector products) are not implemented: their backward factorizes with "
    "scipy outside autograd. Take first-order gradients only, or detach the eigenpairs in the "
    "second-order term."
)


class _Eigenvalues(torch.autograd.Function):
    """Eigenvalues ``mu`` of ``L phi = mu M phi`` with the first-order perturbation gradient."""

    @staticmethod
    def forward(
        ctx: Any,
        l_values: torch.Tensor,
        m_values: torch.Tensor,
        evals: torch.Tensor,
        evecs: torch.Tensor,
        held_l: _Held,
        held_m: _Held,
    ) -> torch.Tensor:
        ctx.save_for_backward(evals, evecs)
        ctx.operators = (held_l.A, held_m.A)
        return evals.clone()

    @staticmethod
    def backward(ctx: Any, g: torch.Tensor) -> tuple[torch.Tensor | None, ...]:
        if torch.is_grad_enabled():
            raise RuntimeError(_SECOND_ORDER_MESSAGE)
        evals, evecs = ctx.saved_tensors
        grads = []
        for A, weights, needed in (
            (ctx.operators[0], g, ctx.needs_input_grad[0]),
            (ctx.operators[1], -g * evals, ctx.needs_input_grad[1]),
        ):
            # sum_i w_i phi_i phi_i^T, sampled on the pattern: O(nnz * k)
            grads.append(sampled_gradient(A, evecs * weights, evecs) if needed else None)
        return grads[0], grads[1], None, None, None, None


# A requested eigenvector has no derivative when another eigenvalue lies within this distance of
# its own, relative to the spectral scale max_i |mu_i| of the computed eigenvalues.
EIGENVECTOR_GAP_RTOL = 1e-8
# Inverse-iteration steps that estimate the gap to the first eigenvalue that was not computed.
_GAP_ITERATIONS = 4


def _cluster_message(
    index: int, members: list[int], evals: np.ndarray, scale: float, reason: str
) -> str:
    values = ", ".join(f"mu_{j} = {evals[j]:.12g}" for j in members)
    which = f"eigenvalues {members[0]}..{members[-1]}" if len(members) > 1 else "eigenvalue"
    return (
        f"torch_polylap.eigs: no gradient through evecs[:, {index}]: its eigenvalue is repeated "
        f"({which} {values}{reason}; relative gap below {EIGENVECTOR_GAP_RTOL:g} of the spectral "
        f"scale {scale:.6g}), so each eigenvector of the cluster is any M-orthonormal basis "
        "vector of the eigenspace and not a differentiable function of L and M (a symmetric "
        "mesh, e.g. a regular grid, has exact multiplicities). Use a loss that depends on the "
        "cluster's eigenvectors only through their span, with every eigenpair of the cluster "
        "computed: the projector Phi_C Phi_C^T M (e.g. sum_i (phi_i^T M u)^2 over the cluster) "
        "or symmetric functions of its eigenvalues (evals are differentiable); or use "
        "evecs.detach(), or only columns outside the cluster."
    )


def _clusters(evals: np.ndarray, scale: float) -> list[list[int]]:
    """Runs of consecutive eigenvalues whose neighbours lie within the gap."""
    close = np.abs(np.diff(evals)) <= EIGENVECTOR_GAP_RTOL * scale  # mu_j ~ mu_{j+1}
    runs = [[0]]
    for j in range(1, evals.size):
        if close[j - 1]:
            runs[-1].append(j)
        else:
            runs.append([j])
    return runs


def _eigenvector_adjoint(
    Ls: sp.csr_matrix,
    Ms: sp.csr_matrix,
    mu: float,
    Phi: np.ndarray,
    g: np.ndarray,
    check_next: float | None,
) -> tuple[np.ndarray, float]:
    """The adjoint ``w`` of one eigenvector whose eigenvalue ``mu`` has the cluster ``Phi``
    ``(n, m)`` (itself and the eigenvectors of eigenvalues within the gap; ``m = 1`` for a
    simple one): ``(L - mu M) w = (I - M Phi Phi^T) g`` with ``Phi^T M w = 0``, by Nelson's
    method.

    ``K = L - mu M`` is singular on ``span(Phi)``. Deleting the rows and columns ``P`` of ``m``
    well-conditioned rows of ``Phi`` (pivoted QR; for ``m = 1`` the largest entry) leaves a
    nonsingular matrix (an ``x`` with ``x_P = 0`` and ``K x = e_P c`` has
    ``0 = Phi^T K x = Phi_P^T c``, so ``x`` is in the kernel and ``0``). Its solution with
    ``x_P = 0`` satisfies rows ``P`` as well, because the right-hand side is orthogonal to
    ``Phi``; projecting out ``Phi`` gives ``w``. One sparse LU (SuperLU, partial pivoting: ``K``
    is indefinite) of the ``(n-m) x (n-m)`` matrix, then freed.

    ``check_next``: the spectral scale, when the cluster holds the last computed eigenpair,
    whose upper neighbour is unknown: inverse iteration with the same factorization on
    ``T = (I - Phi Phi^T M) K^+ M``
    (eigenvalues ``1 / (mu_j - mu)`` for the eigenvalues outside the cluster) bounds the
    distance to the nearest one from above, ``|mu_j - mu| <= 1 / |T x|_M``. Returns ``w`` and
    the estimated nearest outside eigenvalue (``nan`` without ``check_next``, or when it is
    farther than the gap).
    """
    n, m = Phi.shape
    if m == 1:
        P = np.array([int(np.abs(Phi[:, 0]).argmax())])
    else:
        P = scipy.linalg.qr(Phi.T, mode="r", pivoting=True)[1][:m]
    keep = np.setdiff1d(np.arange(n), P)
    K = (Ls - mu * Ms).tocsr()
    lu = spla.splu(sp.csc_matrix(K[keep][:, keep]))
    MPhi = Ms @ Phi

    def project_solve(r: np.ndarray) -> np.ndarray:
        x = np.zeros(n)
        x[keep] = lu.solve(np.ascontiguousarray(r[keep]))
        # one step of iterative refinement (the shifted matrix is nearly singular)
        residual = r - K @ x
        x[keep] += lu.solve(np.ascontiguousarray(residual[keep]))
        return x - Phi @ (MPhi.T @ x)

    nearest = float("nan")
    if check_next is not None:
        x = np.random.default_rng(0).standard_normal((n,))
        x -= Phi @ (MPhi.T @ x)
        t = norm = 0.0
        for _ in range(_GAP_ITERATIONS):
            x /= np.sqrt(x @ (Ms @ x))
            y = project_solve(Ms @ x)
            t = float(x @ (Ms @ y))  # Rayleigh quotient of T: about 1 / (mu_j - mu)
            norm = float(np.sqrt(y @ (Ms @ y)))
            x = y
        if 1.0 <= EIGENVECTOR_GAP_RTOL * check_next * norm:
            nearest = mu + 1.0 / t if t != 0 else mu
    return project_solve(g - MPhi @ (Phi.T @ g)), nearest


class _Eigenvectors(torch.autograd.Function):
    """Eigenvectors of ``L phi = mu M phi`` (``M``-orthonormal, sign fixed) with the adjoint
    gradient (see :func:`eigs`)."""

    @staticmethod
    def forward(
        ctx: Any,
        l_values: torch.Tensor,
        m_values: torch.Tensor,
        evals: torch.Tensor,
        evecs: torch.Tensor,
        held_l: _Held,
        held_m: _Held,
    ) -> torch.Tensor:
        ctx.save_for_backward(evals, evecs)
        ctx.operators = (held_l.A, held_m.A)
        return evecs.clone()

    @staticmethod
    def backward(ctx: Any, G: torch.Tensor) -> tuple[torch.Tensor | None, ...]:
        if torch.is_grad_enabled():
            raise RuntimeError(_SECOND_ORDER_MESSAGE)
        need_l, need_m = ctx.needs_input_grad[:2]
        if not (need_l or need_m):
            return None, None, None, None, None, None
        evals_t, evecs_t = ctx.saved_tensors
        L, M = ctx.operators
        evals = evals_t.detach().cpu().double().numpy()
        Phi = evecs_t.detach().cpu().double().numpy()
        Gn = G.detach().cpu().double().numpy()
        k = evals.size
        active = np.any(Gn != 0, axis=0)
        scale = max(float(np.abs(evals).max()), np.finfo(float).tiny)
        # A_ij = phi_i^T g_j on each cluster's diagonal block: the in-cluster coupling
        A = np.zeros((k, k))
        runs = [c for c in _clusters(evals, scale) if active[c].any()]
        for c in runs:
            block = Phi[:, c].T @ Gn[:, c]
            if len(c) > 1:
                # the loss must not change under rotations within the cluster: A symmetric
                tol = np.sqrt(np.finfo(evecs_t.detach().cpu().numpy().dtype).eps)
                size = np.linalg.norm(Phi[:, c]) * np.linalg.norm(Gn[:, c])
                if np.abs(block - block.T).max() > tol * size:
                    index = c[int(np.flatnonzero(active[c])[0])]
                    raise RuntimeError(
                        _cluster_message(
                            index,
                            c,
                            evals,
                            scale,
                            "; the loss is not invariant to rotations "
                            "of the cluster's eigenvectors",
                        )
                    )
                block = 0.5 * (block + block.T)
            A[np.ix_(c, c)] = block
        Ls = to_scipy(L).astype(np.float64)
        Ms = to_scipy(M).astype(np.float64)
        W = np.zeros_like(Phi)
        for c in runs:
            for i in (j for j in c if active[j]):
                try:
                    W[:, i], nearest = _eigenvector_adjoint(
                        Ls,
                        Ms,
                        evals[i],
                        Phi[:, c],
                        Gn[:, i],
                        check_next=scale if c[-1] == k - 1 else None,
                    )
                except RuntimeError as error:  # SuperLU: exactly singular
                    raise RuntimeError(
                        _cluster_message(i, c, evals, scale, f" (SuperLU: {error})")
                    ) from error
                if not np.isnan(nearest):
                    raise RuntimeError(
                        _cluster_message(
                            i,
                            c,
                            evals,
                            scale,
                            f", and the next eigenvalue, which was not "
                            f"computed, near {nearest:.12g}; compute more eigenpairs",
                        )
                    )
        Wt = torch.from_numpy(W).to(evecs_t)
        mu = evals_t.detach()
        Phi_t = evecs_t.detach()
        grad_l = grad_m = None
        # symmetrized (the gradient among symmetric matrices): (w phi^T + phi w^T) / 2
        if need_l:
            grad_l = -0.5 * sampled_gradient(
                L, torch.cat([Wt, Phi_t], 1), torch.cat([Phi_t, Wt], 1)
            )
        if need_m:
            # the M-orthonormality of each cluster: -(1/2) sum_ij A_ij phi_i phi_j^T (for a
            # simple eigenvalue, the normalization term -(phi^T g / 2) phi phi^T)
            At = torch.from_numpy(A).to(evecs_t)
            grad_m = 0.5 * sampled_gradient(
                M,
                torch.cat([Wt * mu, Phi_t * mu, -(Phi_t @ At)], 1),
                torch.cat([Phi_t, Wt, Phi_t], 1),
            )
        return grad_l, grad_m, None, None, None, None


# Route thresholds of eigs, measured by benchmarks/bench_eigs_routes.py (see eigs_route).
_DENSE_EIGS_SIZE = 200
_DENSE_EIGS_PER_K = 5
# Block Lanczos above this many unknowns (log-log interpolation in k; ARPACK below k = 32)
_LANCZOS_SIZE = {32: 100_000, 64: 4_500, 128: 3_000}
# Memory the unrestarted block Lanczos basis may take before ARPACK (restarted) is used.
_LANCZOS_MEMORY = 4 * 2**30


def _check_positive_mass(Ms: sp.csr_matrix) -> None:
    """``M`` must be positive definite: a zero diagonal entry (a vertex that no face references,
    so its lumped mass is zero) would make the generalized problem singular."""
    diagonal = Ms.diagonal()
    bad = np.flatnonzero(~(diagonal > 0))
    if bad.size:
        raise ValueError(
            f"eigs: M is not positive definite: vertex {int(bad[0])} has mass "
            f"{diagonal[bad[0]]:g} ({bad.size} such vertices), e.g. a vertex that no face "
            "references. Remove such vertices first with "
            "torch_polylap.repair.remove_unreferenced_vertices(verts, faces)."
        )


def _is_diagonal(S: sp.csr_matrix) -> bool:
    coo = S.tocoo()
    return bool((coo.row == coo.col).all()) and bool((S.diagonal() > 0).all())


def eigs_route(n: int, k: int, diagonal_mass: bool, cholmod: bool = True) -> str:
    """The route :func:`eigs` takes for ``k`` eigenpairs of an ``n x n`` problem: ``"dense"``,
    ``"arpack"`` or ``"lanczos"`` (``diagonal_mass``: ``M`` is diagonal and the shift negative,
    so ``L - shift M`` has a Cholesky factorization; ``cholmod``: ``cholespy`` is installed).

    The thresholds were chosen by measurement (``benchmarks/bench_eigs_routes.py routes``;
    ``benchmarks/README.md`` has the crossover measurements behind each of them):

    - ``"dense"`` (LAPACK ``eigh`` with ``subset_by_index``) for ``n <= max(200, 5 k)``; its
      cost grows as ``n^3``;
    - ``"arpack"`` (ARPACK on the standard symmetric problem ``M^{1/2} (L - shift M)^{-1}
      M^{1/2}``, one CHOLMOD or SuperLU solve per step, which beats scipy's generalized
      ``eigsh(L, M=M, sigma=shift)``) up to a block Lanczos threshold that falls with ``k``:
      ``_LANCZOS_SIZE`` holds 100,000 unknowns at ``k = 32``, 4,500 at 64 and 3,000 at 128 and
      above, interpolated log-log between, and ARPACK at every size below ``k = 32``;
    - ``"lanczos"`` (block Lanczos with blocks of 8, :mod:`torch_polylap.lanczos`) above it, for
      a diagonal ``M`` only, and only while its basis of ``6 k`` vectors fits in 4 GiB
      (``"arpack"`` otherwise). Without ``cholespy`` its block solves are SuperLU's one column
      at a time, and the threshold is doubled (not measured).
    """
    if n <= max(_DENSE_EIGS_SIZE, _DENSE_EIGS_PER_K * k):
        return "dense"
    if not diagonal_mass or n * _lanczos_dim(n, k) * 8 > _LANCZOS_MEMORY:
        return "arpack"
    ks = sorted(_LANCZOS_SIZE)
    if k < ks[0]:
        return "arpack"
    sizes = [np.log(_LANCZOS_SIZE[key]) for key in ks]
    threshold = round(float(np.exp(np.interp(np.log(k), np.log(ks), sizes))))
    if not cholmod:
        threshold *= 2
    return "lanczos" if n > threshold else "arpack"


def _lanczos_dim(n: int, k: int) -> int:
    """The largest Krylov basis :func:`eigs` lets block Lanczos build (the bases measured in
    ``benchmarks/README.md`` stayed well below it)."""
    return min(n, max(6 * k, k + 200))


def spd_block_solver(
    S: sp.spmatrix, device: torch.device | str = "cpu"
) -> Callable[[np.ndarray], np.ndarray]:
    """Factor a sparse SPD matrix once and return ``B (n, b) -> S^{-1} B`` in float64.

    CHOLMOD's supernodal Cholesky (through the optional ``cholespy`` package) when it is
    installed, on ``device`` (its CUDA solver on a GPU): multi-column solves are several times
    faster per column than SuperLU's (``benchmarks/README.md``), whose own multi-column solve
    is slower still than one column at a time (so the fallback loops over columns).
    """
    if not _cholespy_available():
        lu = spd_splu(sp.csc_matrix(S))
        return lambda B: np.stack([lu.solve(np.ascontiguousarray(b)) for b in B.T], axis=1)
    factor = CholeskyFactorization(S, torch.device(device))
    return lambda B: factor.solve(torch.from_numpy(np.ascontiguousarray(B))).cpu().numpy()


def _eigs_block_lanczos(
    Ls: sp.csr_matrix,
    mass: np.ndarray,
    k: int,
    shift: float,
    tol: float,
    device: torch.device,
) -> tuple[np.ndarray, np.ndarray] | None:
    """Shift-invert block Lanczos for a diagonal ``M``: the standard symmetric problem
    ``C = M^{1/2} (L - shift M)^{-1} M^{1/2}``, whose top eigenvalues ``1 / (mu - shift)`` give
    the smallest ``mu``, with eigenvectors ``phi = M^{-1/2} y``. ``None`` if it did not
    converge (the caller then uses ARPACK)."""
    root = np.sqrt(mass)[:, None]
    solve_shifted = spd_block_solver(Ls - shift * sp.diags(mass), device)
    theta, Y, converged = block_lanczos(
        lambda X: solve_shifted(X * root) * root,
        Ls.shape[0],
        k,
        tol=tol,
        max_dim=_lanczos_dim(Ls.shape[0], k),
    )
    if not converged:
        return None
    return shift + 1.0 / theta, Y / root


def _shifted_vector_solver(
    S: sp.spmatrix, device: torch.device | str
) -> Callable[[np.ndarray], np.ndarray]:
    """``x (n,) -> S^{-1} x`` for a sparse SPD ``S``, one column per call (ARPACK's step):
    CHOLMOD when ``cholespy`` is installed, SuperLU otherwise."""
    if not _cholespy_available():
        lu = spd_splu(sp.csc_matrix(S))
        return lu.solve
    factor = CholeskyFactorization(S, torch.device(device)).factor

    def solve(x: np.ndarray) -> np.ndarray:
        rhs = torch.from_numpy(np.ascontiguousarray(x, dtype=np.float64)[:, None]).to(device)
        out = torch.empty_like(rhs)
        factor.solve(rhs, out)
        return out[:, 0].cpu().numpy()

    return solve


def _eigs_arpack(
    Ls: sp.csr_matrix,
    Ms: sp.csr_matrix,
    k: int,
    sigma: float | None,
    scale: float,
    tol: float,
    diagonal_mass: bool = False,
    device: torch.device | str = "cpu",
) -> tuple[np.ndarray, np.ndarray]:
    """ARPACK shift-invert Lanczos, retried with more vectors and larger shifts.

    For a diagonal ``M`` and a negative shift, on the standard symmetric problem
    ``C = M^{1/2} (L - shift M)^{-1} M^{1/2}`` (as block Lanczos), with one Cholesky solve per
    step: faster than ARPACK's generalized mode, which also multiplies by ``M`` and
    ``M``-orthogonalizes each step (``benchmarks/README.md``). Otherwise scipy's generalized
    shift-invert mode, with SuperLU."""
    n = Ls.shape[0]
    shifts = [sigma] if sigma is not None else [-1e-6 * scale, -1e-5 * scale, -1e-3 * scale]
    for attempt, shift in enumerate(shifts):
        ncv = min(n, max(2 * k + 1, 20) * (attempt + 1))
        try:
            if not (diagonal_mass and shift < 0):
                return spla.eigsh(Ls, k=k, M=Ms, sigma=shift, which="LM", tol=tol, ncv=ncv)
            mass = Ms.diagonal()
            root = np.sqrt(mass)
            solve = _shifted_vector_solver(Ls - shift * sp.diags(mass), device)
            op = spla.LinearOperator(
                Ls.shape,
                matvec=lambda x, solve=solve, root=root: solve(x.reshape(-1) * root) * root,
                dtype=np.float64,
            )
            theta, Y = spla.eigsh(op, k=k, which="LA", tol=tol, ncv=ncv)
            return shift + 1.0 / theta, Y / root[:, None]
        except (spla.ArpackNoConvergence, RuntimeError):
            continue
    raise ValueError(
        f"eigs: ARPACK did not converge for k = {k} with shifts {shifts}; try a different "
        "sigma or a smaller k."
    )


def eigs(
    L: torch.Tensor,
    M: torch.Tensor,
    k: int,
    *,
    sigma: float | None = None,
    tol: float = 0.0,
) -> tuple[torch.Tensor, torch.Tensor]:
    """The ``k`` smallest eigenpairs of ``L phi = mu M phi`` (``L`` PSD, ``M`` SPD, e.g. ``L, M0``).

    Shift-invert around ``sigma`` (default: slightly below zero, so that ``L - sigma M`` is
    positive definite even though ``L`` is singular), by one of three routes, picked by
    :func:`eigs_route` from ``n`` and ``k`` (thresholds measured, see there):

    - small problems (``n <= max(200, 5 k)``): a dense symmetric solver (LAPACK);
    - ARPACK (scipy's ``eigsh``), retried with more Lanczos vectors and a larger shift: for a
      diagonal ``M`` and ``sigma < 0`` on ``M^{1/2} (L - sigma M)^{-1} M^{1/2}`` with one
      Cholesky factorization (CHOLMOD when ``cholespy`` is installed, SuperLU otherwise), else
      in scipy's generalized shift-invert mode with SuperLU; for ``k < 32`` at every size and
      for larger ``k`` up to a threshold (4,500 unknowns at ``k = 64``, 3,000 at ``k >= 128``);
    - above it, for a diagonal ``M`` (the mass matrix ``M0``) and ``sigma < 0``: block Lanczos
      with blocks of 8 (:mod:`torch_polylap.lanczos`) on the same operator, factored once by
      CHOLMOD (on the operators' device: its CUDA solver for CUDA tensors; SuperLU without
      ``cholespy``), while its basis of up to ``6 k`` vectors fits in 4 GiB; ARPACK if it
      does not converge.

    Eigenvector gradients (adjoint method). Differentiating ``(L - mu M) phi = 0`` and
    ``phi^T M phi = 1`` gives ``dphi = v - (phi^T dM phi / 2) phi`` with ``phi^T M v = 0`` and
    ``(L - mu M) v = -(dL - mu dM) phi + dmu M phi``. For an upstream gradient ``g`` of one
    column, the adjoint ``w`` solves ``(L - mu M) w = (I - M phi phi^T) g`` with
    ``phi^T M w = 0`` (then ``g^T v = -w^T (dL - mu dM) phi``, the ``dmu`` term vanishing), so

        dLoss/dL = -sym(w phi^T),   dLoss/dM = mu sym(w phi^T) - (phi^T g / 2) phi phi^T,

    sampled on each operator's pattern (``sym(A) = (A + A^T) / 2``: the gradient among symmetric
    matrices, which is what the symmetric eigensolver sees). The singular, indefinite system is
    solved by Nelson's method: delete the row and column of ``phi``'s largest entry, factor the
    rest with SuperLU (partial pivoting; no Cholesky, ``L - mu M`` is indefinite), one step of
    iterative refinement, project out ``phi``. Cost, per column of ``evecs`` whose gradient is
    not zero (columns that the loss does not use are skipped): one sparse LU of an
    ``(n-1) x (n-1)`` matrix with ``L``'s pattern, on the CPU in float64, freed before the next;
    memory is that factor's fill plus O(nnz + n k) for the gradients. The sign convention is
    locally constant, so it does not enter the derivative (a column whose largest entries tie in
    magnitude flips sign under perturbation and has no derivative there).

    Repeated eigenvalues: eigenvalues within ``1e-8 * max |mu|`` of their neighbour
    (``EIGENVECTOR_GAP_RTOL``, relative to the largest computed eigenvalue) form a cluster ``C``
    whose eigenvectors are any ``M``-orthonormal basis of the eigenspace, not functions of ``L``
    and ``M``. A loss that sees them only through their span (the projector
    ``Phi_C Phi_C^T M``, e.g. ``sum_{i in C} (phi_i^T M u)^2``) still has a gradient: its
    ``A_ij = phi_i^T g_j`` is symmetric on ``C`` (checked to ``sqrt(eps)``), the rotation terms
    ``A_ij phi_j^T (dL - mu_i dM) phi_i / (mu_i - mu_j)`` of ``i, j`` and ``j, i`` sum to
    ``-A_ij phi_i^T dM phi_j`` (finite), and each ``w_i`` solves the system above with the
    whole cluster projected out (Nelson's method deleting ``|C|`` rows chosen by pivoted QR of
    ``Phi_C^T``); the ``M`` term becomes ``-(1/2) sum_{ij in C} A_ij phi_i phi_j^T``. Any
    other loss through a cluster's columns raises a ``RuntimeError`` in the backward that names
    the cluster (indices and values) and what to use instead; so does a cluster that may go on
    past the last computed eigenvalue (four inverse-iteration steps with the same factorization
    bound the distance to the next, uncomputed one: compute more eigenpairs).

    Args:
        L: ``(n, n)`` sparse symmetric matrix; values may require grad.
        M: ``(n, n)`` sparse symmetric positive definite matrix; values may require grad.
        k: number of eigenpairs, ``1 <= k < n``.
        sigma: shift for shift-invert.
        tol: relative residual at which a Ritz pair of the shift-inverted operator counts as
            converged (0: ``1e-10`` for block Lanczos, machine precision for ARPACK).

    Returns:
        ``evals`` ``(k,)`` ascending and ``evecs`` ``(n, k)``, ``M``-orthonormal
        (``evecs^T M evecs = I``), each column's sign fixed so that its entry of largest
        magnitude is positive. ``evals`` is differentiable with respect to the values of ``L``
        and ``M`` (``d mu = phi^T (dL - mu dM) phi``), which is exact for simple eigenvalues;
        for a repeated eigenvalue only symmetric functions of the cluster (e.g. its sum) have
        a well-defined gradient. ``evecs`` is differentiable too (first order; ``create_graph=True``
        raises): for simple eigenvalues, and for losses that see a repeated one's eigenvectors
        only through their span (see above).

    Raises:
        ValueError: ``k`` out of range, or no convergence after the retries.
        RuntimeError: in the backward pass, for a gradient through the eigenvectors of a
            repeated eigenvalue by a loss that depends on more than their span, or for a second
            derivative.

    Examples:
        >>> import torch
        >>> import torch_polylap as tp
        >>> verts = torch.tensor([[0.0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [2, 0.5, 0.5]],
        ...                      dtype=torch.float64)
        >>> L, M0 = tp.laplacian(verts, [[0, 1, 2, 3], [1, 4, 2]])
        >>> evals, evecs = tp.eigs(L, M0, k=3)
        >>> abs(float(evals[0])) < 1e-10  # the constants: one connected component
        True
        >>> bool((evals[1:] > 0).all())
        True
        >>> torch.allclose(evecs.T @ (M0 @ evecs), torch.eye(3, dtype=torch.float64))
        True
    """
    L, M = as_operator(L), as_operator(M)
    n = L.shape[0]
    if isinstance(k, bool) or not isinstance(k, int | np.integer):
        raise TypeError(f"eigs: k must be an integer, got {k!r} ({type(k).__name__}).")
    k = int(k)
    if not 1 <= k < n:
        raise ValueError(f"eigs: k must satisfy 1 <= k < n = {n}, got {k}.")
    if L.shape != (n, n) or M.shape != (n, n):
        raise ValueError(
            f"eigs: L and M must be square and of one size, got {tuple(L.shape)} and "
            f"{tuple(M.shape)}."
        )
    if tol < 0:
        raise ValueError(f"eigs: tol must be >= 0, got {tol}.")
    Ls = to_scipy(L).astype(np.float64)
    Ms = to_scipy(M).astype(np.float64)
    _check_positive_mass(Ms)
    scale = float(abs(Ls).max()) / max(float(Ms.diagonal().max()), np.finfo(float).tiny)
    # -1e-6 of the spectral radius estimate: closer to zero makes L - shift M so ill-conditioned
    # that the block solves lose digits (eigenvalues off by 1e-9 relative at -1e-8 on a
    # 1.5k-vertex sphere, 1e-13 at -1e-6 to -1e-2), while convergence is the same
    shift = sigma if sigma is not None else -1e-6 * scale
    result = None
    diagonal = shift < 0 and _is_diagonal(Ms)
    route = eigs_route(n, k, diagonal, _cholespy_available())
    if route == "dense":
        result = scipy.linalg.eigh(Ls.toarray(), Ms.toarray(), subset_by_index=(0, k - 1))
    elif route == "lanczos":
        result = _eigs_block_lanczos(Ls, Ms.diagonal(), k, shift, tol or 1e-10, L.device)
    if result is None:
        result = _eigs_arpack(Ls, Ms, k, sigma, scale, tol, diagonal, L.device)
    evals, evecs = result
    order = np.argsort(evals)
    evals, evecs = evals[order], evecs[:, order]
    # M-orthonormalize (ARPACK's vectors are, up to round-off) and fix signs for determinism
    evecs = evecs / np.sqrt(np.einsum("ik,ik->k", evecs, Ms @ evecs))
    signs = np.sign(evecs[np.abs(evecs).argmax(0), np.arange(k)])
    evecs = evecs * np.where(signs == 0, 1.0, signs)
    l_values, m_values = sparse_values(L), sparse_values(M)
    evals_t = torch.from_numpy(evals).to(l_values)
    evecs_t = torch.from_numpy(evecs).to(l_values)
    mu = _Eigenvalues.apply(l_values, m_values, evals_t, evecs_t, _Held(L), _Held(M))
    if torch.is_grad_enabled() and (l_values.requires_grad or m_values.requires_grad):
        evecs_t = _Eigenvectors.apply(l_values, m_values, evals_t, evecs_t, _Held(L), _Held(M))
    return mu, evecs_t

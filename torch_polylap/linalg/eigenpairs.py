"""``eigs(L, M, k)``: the ``k`` smallest generalized eigenpairs, by the route measured fastest
(dense LAPACK, ARPACK shift-invert or block Lanczos on a Cholesky factor), differentiable
through :mod:`.derivatives`.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import scipy.linalg
import scipy.sparse as sp
import scipy.sparse.linalg as spla
import torch

from ..checks import check_finite_operand
from ..sparse import (
    SparseOperator,
    as_operator,
    sparse_values,
    to_scipy,
)
from .cg import ConvergenceError
from .derivatives import EIGENVECTOR_GAP_RTOL, Eigenvalues, Eigenvectors
from .factor import CholeskyFactorization, OpaqueOperator, cholespy_available, spd_splu
from .lanczos import block_lanczos

# Route thresholds of eigs, measured by benchmarks/bench_eigs_routes.py (see eigs_route).
_DENSE_EIGS_SIZE = 200
_DENSE_EIGS_PER_K = 5
# Block Lanczos above this many unknowns (log-log interpolation in k; ARPACK below k = 32)
_LANCZOS_SIZE = {32: 100_000, 64: 4_500, 128: 3_000}
# Memory the unrestarted block Lanczos basis may take before ARPACK (restarted) is used.
_LANCZOS_MEMORY = 4 * 2**30
# L and M count as symmetric when no entry differs from its mirror by more than this, relative
# to the largest entry: round-off of symmetric sums passes, a non-symmetric matrix does not.
_SYMMETRY_RTOL = 1e-10
# Rounds of deflated completion after an inertia count found eigenvalues missing.
_COMPLETION_ROUNDS = 8


def _check_symmetric(A: SparseOperator, S: sp.csr_matrix, name: str) -> None:
    """Refuse a non-symmetric ``A`` (``S`` its scipy form): the symmetric eigensolvers would
    answer for its symmetric part, or for its lower triangle, without a word. An operator
    declared symmetric (``A.symmetric``, as ``L`` and ``M0`` are) is trusted; any other is
    compared with its transpose, pattern and values, in O(nnz)."""
    if A.symmetric:
        return
    D = sp.coo_matrix(S - S.T)
    size = float(abs(S).max()) if S.nnz else 0.0
    if D.nnz == 0 or float(np.abs(D.data).max()) <= _SYMMETRY_RTOL * size:
        return
    worst = int(np.abs(D.data).argmax())
    i, j = int(D.row[worst]), int(D.col[worst])
    raise ValueError(
        f"eigs: {name} is not symmetric: {name}[{i}, {j}] = {S[i, j]:.6g} but {name}[{j}, {i}] "
        f"= {S[j, i]:.6g} (largest difference {abs(D.data[worst]):.3g}, relative "
        f"{abs(D.data[worst]) / size:.3g} to max |{name}|; "
        f"{int((np.abs(D.data) > _SYMMETRY_RTOL * size).sum())} such entries). eigs solves "
        "the symmetric generalized problem only. If the asymmetry is round-off, symmetrize "
        f"with 0.5 * ({name} + {name}.T), or build it with "
        "torch_polylap.sparse.operator_from_parts(..., symmetric=True); a non-symmetric "
        "problem needs scipy.sparse.linalg.eigs."
    )


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


def eigs_route(n: int, k: int, *, diagonal_mass: bool, cholmod: bool = True) -> str:
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
    if not cholespy_available():
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
    if not cholespy_available():
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
    *,
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


def _count_below(Ls: sp.csr_matrix, Ms: sp.csr_matrix, sigma: float) -> int | None:
    """The number of eigenvalues of ``L phi = mu M phi`` below ``sigma``, by Sylvester's law of
    inertia: ``L - sigma M`` is congruent to ``M^{-1/2} L M^{-1/2} - sigma I``, and SuperLU's
    symmetric mode without row interchanges factors it as ``P^T L D L^T P`` with ``D`` the
    diagonal of ``U``, whose negative entries count the negative eigenvalues (the "Sturm
    sequence check" of engineering eigensolvers). ``None`` when SuperLU had to interchange
    rows (a zero pivot) or ``sigma`` is an eigenvalue: the caller moves ``sigma``."""
    try:
        lu = spd_splu(sp.csc_matrix(Ls - sigma * Ms))
    except RuntimeError:
        return None
    if not np.array_equal(lu.perm_r, lu.perm_c):
        return None
    return int((lu.U.diagonal() < 0).sum())


def _missing_below(
    evals: np.ndarray, Ls: sp.csr_matrix, Ms: sp.csr_matrix, scale: float, tol: float
) -> tuple[int, int]:
    """``(missing, below)``: how many eigenvalues below the cut lie outside ``evals``, and how
    many of ``evals`` lie below it, for the cut just below the cluster of the largest of
    ``evals`` (those within ``EIGENVECTOR_GAP_RTOL``, or ten times a looser ``tol``, of the
    spectral scale of each other: the eigenvalues that tie with the ``k``-th, any of which may
    be returned).

    Each computed pair has a small residual whatever the route; what a Krylov method can miss
    is a whole direction of a repeated eigenvalue (a block of ``b`` vectors holds at most ``b``
    directions of one eigenspace; the others come in through round-off, or not). The inertia
    count below the cut sees every eigenvalue, found or not.
    """
    order = np.sort(evals)
    rtol = max(EIGENVECTOR_GAP_RTOL, 10 * tol)
    gap = rtol * max(float(np.abs(order).max()), 1e-6 * scale)
    below = order.size - 1
    while below > 0 and order[below] - order[below - 1] <= gap:
        below -= 1
    # midway between two computed eigenvalues at least `gap` apart (order[below - 1] <
    # order[below] - gap), moved down by at most gap / 2 if it hits an eigenvalue
    for step in range(3):
        count = _count_below(Ls, Ms, float(order[below]) - gap / 2 - step * gap / 4)
        if count is not None:
            return count - below, below
    raise ConvergenceError(
        "eigs: could not verify the eigenvalues by an inertia count (SuperLU met a zero pivot "
        "at three shifts near the largest one); pass a different k.",
        3,
    )


def _deflated_eigenpairs(
    Ls: sp.csr_matrix,
    Ms: sp.csr_matrix,
    found: np.ndarray,
    count: int,
    shift: float,
    tol: float,
    device: torch.device,
) -> tuple[np.ndarray, np.ndarray] | None:
    """The ``count`` smallest eigenpairs of ``L phi = mu M phi`` among vectors ``M``-orthogonal
    to the columns of ``found`` (eigenvectors already computed), shift-inverted at ``shift < 0``.

    Diagonal ``M``: block Lanczos on ``P C P`` (``C`` as in :func:`_eigs_block_lanczos`, ``P``
    the orthogonal projector off ``M^{1/2} found``) with blocks of at least ``count`` vectors,
    so that a block holds every direction of an eigenvalue repeated up to ``count`` times.
    Otherwise ARPACK in generalized shift-invert mode, its solve followed by the ``M``-orthogonal
    projector off ``found``. ``None`` if it did not converge."""
    n = Ls.shape[0]
    if _is_diagonal(Ms):
        mass = Ms.diagonal()
        root = np.sqrt(mass)[:, None]
        Y = np.linalg.qr(found * root)[0]
        solve_shifted = spd_block_solver(Ls - shift * sp.diags(mass), device)

        def deflate(X: np.ndarray) -> np.ndarray:
            return X - Y @ (Y.T @ X)

        block = max(8, count)
        theta, Z, converged = block_lanczos(
            lambda X: deflate(solve_shifted(deflate(X) * root) * root),
            n,
            count,
            block=block,
            # ten times looser than the first run: the projector off eigenvectors that are
            # themselves accurate to its tolerance limits the residuals reachable here to it
            tol=10 * (tol or 1e-10),
            max_dim=min(n, max(_lanczos_dim(n, count), count + 2 * block)),
        )
        return (shift + 1.0 / theta, deflate(Z) / root) if converged else None
    Phi = found / np.sqrt(np.einsum("ik,ik->k", found, Ms @ found))
    MPhi = Ms @ Phi
    lu = spd_splu(sp.csc_matrix(Ls - shift * Ms))

    def solve_deflated(x: np.ndarray) -> np.ndarray:
        y = lu.solve(np.asarray(x, dtype=np.float64).reshape(-1))
        return y - Phi @ (MPhi.T @ y)

    op = spla.LinearOperator(Ls.shape, matvec=solve_deflated, dtype=np.float64)
    try:
        return spla.eigsh(
            Ls,
            k=count,
            M=Ms,
            sigma=shift,
            which="LM",
            OPinv=op,
            tol=tol,
            ncv=min(n, max(2 * count + 1, 20)),
        )
    except (spla.ArpackNoConvergence, RuntimeError):
        return None


def _verified(
    result: tuple[np.ndarray, np.ndarray],
    Ls: sp.csr_matrix,
    Ms: sp.csr_matrix,
    scale: float,
    tol: float,
    device: torch.device,
) -> tuple[np.ndarray, np.ndarray]:
    """``result`` (``k`` eigenpairs of a sparse route) checked to be the ``k`` smallest, with
    full multiplicities, by an inertia count (:func:`_missing_below`); where eigenvalues are
    missing, they are computed on the complement of those found (:func:`_deflated_eigenpairs`)
    and merged in, until the count agrees. Raises where it never does."""
    evals, evecs = result
    k = evals.size
    shift = -1e-6 * scale
    for _ in range(_COMPLETION_ROUNDS):
        missing, below = _missing_below(evals, Ls, Ms, scale, tol)
        if missing == 0:
            return evals, evecs
        if missing < 0:
            raise ConvergenceError(
                f"eigs: {below} computed eigenvalues lie below {evals.max():.6g} but the "
                f"inertia count finds only {below + missing} there: the computed eigenpairs are "
                "not accurate (lower tol, or pass sigma=None).",
                0,
            )
        # the `missing` smallest eigenvalues off the found ones are the missing ones: merged
        # in, they push as many of the found top cluster's out of the k smallest
        extra = _deflated_eigenpairs(Ls, Ms, evecs, missing, shift, tol, device)
        if extra is None:
            break
        order = np.argsort(np.concatenate([evals, extra[0]]))[:k]
        evals = np.concatenate([evals, extra[0]])[order]
        evecs = np.concatenate([evecs, extra[1]], axis=1)[:, order]
    raise ConvergenceError(
        f"eigs: the k = {k} computed eigenpairs are not the k smallest, and computing the "
        "missing ones (repeated eigenvalues, e.g. of disjoint copies of one mesh) did not "
        f"converge in {_COMPLETION_ROUNDS} rounds; pass a smaller k, or split the mesh into its "
        "connected components.",
        _COMPLETION_ROUNDS,
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

    The sparse routes' answer is verified: a Krylov method can miss directions of a repeated
    eigenvalue (disjoint copies of a mesh, symmetric shapes) while every pair it returns has a
    tiny residual, so the number of eigenvalues below the cluster of the largest returned one
    is counted by Sylvester's law of inertia (one sparse ``LDL^T`` of ``L - s M``: SuperLU,
    on the CPU; measured at 1-2% of the eigensolve's time on 10k and 22k vertices, k = 64 and
    128, and 8-9% on a 100k-vertex grid, k = 64). Missing eigenpairs are then computed on the
    ``M``-orthogonal complement of those found (block Lanczos with a block as large as the
    count, or ARPACK) and merged in, until the count agrees.
    ``L`` and ``M`` must be symmetric: operators declared so (``L, M0`` of
    :func:`~torch_polylap.laplacian`) are trusted, others compared with their transposes.

    Eigenvector gradients solve one adjoint system per column of ``evecs`` that the loss uses,
    by Nelson's method (one sparse LU of ``L - mu M`` less a row and column, on the CPU in
    float64; memory that factor's fill plus O(nnz + n k)). Eigenvalues within ``1e-8`` times
    the spectral scale (``EIGENVECTOR_GAP_RTOL``; the scale is the largest of ``|mu|`` and
    ``max_i |L_ii| / M_ii``, so that eigenvalues at 0, e.g. one per connected component, are
    judged too) form a cluster whose eigenvectors have a gradient only for losses that see
    them through their span. The derivation, Nelson's method and the rule for
    clusters: ``docs/math/spectral.md`` ("Eigenpairs and their derivatives").

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
        only through their span.

    Raises:
        ValueError: ``k`` out of range, ``L`` or ``M`` not symmetric (names the entry), ``M``
            not positive definite.
        ConvergenceError: (a ``ValueError``, :class:`torch_polylap.linalg.ConvergenceError`)
            no convergence after the retries, or eigenpairs found missing that could not be
            computed.
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
    k, Ls, Ms = _check_input(L, M, k, tol)
    evals, evecs = _solve(Ls, Ms, k, sigma, tol, L.device)
    l_values = sparse_values(L)
    evals_t = torch.from_numpy(evals).to(l_values)
    evecs_t = torch.from_numpy(evecs).to(l_values)
    return eigenpair_gradients(L, M, evals_t, evecs_t)


def eigenpair_gradients(
    L: torch.Tensor, M: torch.Tensor, evals: torch.Tensor, evecs: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Eigenpairs of ``L phi = mu M phi`` computed elsewhere, ``evals`` ``(k,)`` ascending and
    ``evecs`` ``(n, k)`` ``M``-orthonormal (no gradient of their own), returned equal with
    :func:`eigs`'s gradients with respect to the values of ``L`` and ``M`` attached.

    For a caller that knows an eigenpair :func:`eigs` did not return: the twin ``i X`` of a
    complex Hermitian operator's eigenvector ``X`` in its real form, whose eigenvalue is the
    same, so that the backward sees both in one cluster (and no uncomputed eigenvalue there).
    """
    L, M = as_operator(L), as_operator(M)
    l_values, m_values = sparse_values(L), sparse_values(M)
    evals_t, evecs_t = evals.detach(), evecs.detach()
    opaque = OpaqueOperator(L), OpaqueOperator(M)
    mu = Eigenvalues.apply(l_values, m_values, evals_t, evecs_t, *opaque)
    if torch.is_grad_enabled() and (l_values.requires_grad or m_values.requires_grad):
        evecs_t = Eigenvectors.apply(l_values, m_values, evals_t, evecs_t, *opaque)
    return mu, evecs_t


def _check_input(
    L: SparseOperator, M: SparseOperator, k: int, tol: float
) -> tuple[int, sp.csr_matrix, sp.csr_matrix]:
    """Check :func:`eigs`'s input: ``k``, the shapes and ``tol``, then ``L`` and ``M`` symmetric
    and ``M``'s masses positive. Returns ``k`` as an int and the float64 scipy forms of ``L``
    and ``M``."""
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
    check_finite_operand(L, "L", "eigs")
    check_finite_operand(M, "M", "eigs")
    Ls = to_scipy(L).astype(np.float64).tocsr()
    Ms = to_scipy(M).astype(np.float64).tocsr()
    _check_symmetric(L, Ls, "L")
    _check_symmetric(M, Ms, "M")
    _check_positive_mass(Ms)
    return k, Ls, Ms


def _solve(
    Ls: sp.csr_matrix,
    Ms: sp.csr_matrix,
    k: int,
    sigma: float | None,
    tol: float,
    device: torch.device,
) -> tuple[np.ndarray, np.ndarray]:
    """The ``k`` smallest eigenpairs by the route :func:`eigs_route` picks, the sparse routes'
    answer verified; ascending, ``M``-orthonormal, signs fixed."""
    n = Ls.shape[0]
    scale = float(abs(Ls).max()) / max(float(Ms.diagonal().max()), np.finfo(float).tiny)
    # -1e-6 of the spectral radius estimate: closer to zero makes L - shift M so ill-conditioned
    # that the block solves lose digits (eigenvalues off by 1e-9 relative at -1e-8 on a
    # 1.5k-vertex sphere, 1e-13 at -1e-6 to -1e-2), while convergence is the same
    shift = sigma if sigma is not None else -1e-6 * scale
    result = None
    diagonal = shift < 0 and _is_diagonal(Ms)
    route = eigs_route(n, k, diagonal_mass=diagonal, cholmod=cholespy_available())
    if route == "dense":
        result = scipy.linalg.eigh(Ls.toarray(), Ms.toarray(), subset_by_index=(0, k - 1))
    elif route == "lanczos":
        result = _eigs_block_lanczos(Ls, Ms.diagonal(), k, shift, tol or 1e-10, device)
    if result is None:
        result = _eigs_arpack(Ls, Ms, k, sigma, scale, tol, diagonal_mass=diagonal, device=device)
    if route != "dense":
        result = _verified(result, Ls, Ms, scale, tol, device)
    evals, evecs = result
    order = np.argsort(evals)
    evals, evecs = evals[order], evecs[:, order]
    # M-orthonormalize (ARPACK's vectors are, up to round-off) and fix signs for determinism
    evecs = evecs / np.sqrt(np.einsum("ik,ik->k", evecs, Ms @ evecs))
    signs = np.sign(evecs[np.abs(evecs).argmax(0), np.arange(k)])
    evecs = evecs * np.where(signs == 0, 1.0, signs)
    return evals, evecs

"""Sparse factorizations behind :func:`~torch_polylap.solve`: SuperLU and CHOLMOD, cached on the
operator, with a singularity check that names the remedy.
"""

from __future__ import annotations

import atexit
import warnings
import weakref
from collections.abc import Callable

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
import torch

from ..sparse import SparseOperator, to_scipy
from ..sparse.construct import solver_cache
from .etree_solve import EtreePathSolver, LDLTriangles


class IllConditionedWarning(UserWarning):
    """A solve's matrix is non-singular but so ill-conditioned that the solution keeps only a
    few correct digits (a tiny shift, as in ``L + 1e-12 * M0``): it is solved, and the warning
    says how many digits to expect."""


def spd_splu(S: sp.csc_matrix) -> spla.SuperLU:
    """SuperLU factorization with settings for symmetric positive definite matrices.

    Symmetric mode without row pivoting keeps ``L`` and ``U^T`` on one pattern, as a Cholesky
    would. The column ordering is COLAMD, SuperLU's default: minimum degree on ``A + A^T``
    (``MMD_AT_PLUS_A``) is faster on grid meshes but far slower on some others
    (``benchmarks/README.md`` has the measurements).
    """
    return spla.splu(S, permc_spec="COLAMD", diag_pivot_thresh=0.0, options={"SymmetricMode": True})


class Factorization:
    """A sparse LU factorization (SuperLU) of a CSR matrix, in float64, on the CPU.

    Symmetric mode without pivoting first (the fast path for the SPD systems of this package);
    where that breaks down or is inaccurate (a zero or tiny pivot of an indefinite or
    non-symmetric matrix), SuperLU with partial pivoting, which solves any non-singular matrix.
    Built from ``A``'s values at one point in time and cached on ``A`` by
    :func:`torch_polylap.sparse.construct.solver_cache`, which checks the values' storage and
    version counter before reusing it. ``check`` refuses a numerically singular ``A`` (one extra
    solve); a caller that handles ill-conditioning itself (damped Gauss-Newton) passes False.
    """

    def __init__(self, A: torch.Tensor, *, check: bool = True) -> None:
        S = sp.csc_matrix(to_scipy(A).astype(np.float64))
        try:
            self.lu = spd_splu(S)
            problem = _solution_problem(S, self.lu.solve) if check else None
        except RuntimeError as err:
            problem = str(err)
        if problem is None:
            return
        try:
            self.lu = spla.splu(S, permc_spec="COLAMD")
        except RuntimeError as err:
            raise ValueError(_singular_message(A, str(err))) from None
        problem = _solution_problem(S, self.lu.solve) if check else None
        if problem is not None:
            raise ValueError(_singular_message(A, problem))

    def solve(self, B: torch.Tensor, *, transpose: bool = False) -> torch.Tensor:
        X = self.lu.solve(
            np.ascontiguousarray(B.detach().cpu().numpy(), dtype=np.float64),
            trans="T" if transpose else "N",
        )
        return _finite(torch.from_numpy(X)).to(B)

    def solve_array(self, b: np.ndarray) -> np.ndarray:
        """``A^{-1} b`` for a float64 ``(n,)`` or ``(n, k)`` array, without torch tensors."""
        return _finite_array(self.lu.solve(np.ascontiguousarray(b, dtype=np.float64)))


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
    ``L``) and the only direct solver here that runs on a GPU. ``check`` as for
    :class:`Factorization`.
    """

    # cholespy's CUDA solve takes at most this many right-hand sides at once
    _CUDA_COLUMNS = 128

    def __init__(
        self,
        A: torch.Tensor | sp.spmatrix,
        device: torch.device | None = None,
        *,
        check: bool = True,
    ) -> None:
        from cholespy import CholeskySolverD, MatrixType

        device = A.device if isinstance(A, torch.Tensor) else torch.device(device or "cpu")
        S = sp.csr_matrix(
            (to_scipy(A) if isinstance(A, torch.Tensor) else A).astype(np.float64, copy=False)
        )
        # CSR handed over as is: cholespy's COO input costs a sort of the entries (0.2-0.3 s
        # of a 1.3 s factorization at 70k vertices), on top of scipy's own canonical form,
        # which the operators already have (the check is one pass)
        S.sum_duplicates()
        try:
            self.factor = CholeskySolverD(
                S.shape[0],
                torch.from_numpy(S.indptr.astype(np.int32)).to(device),
                torch.from_numpy(S.indices.astype(np.int32)).to(device),
                torch.from_numpy(S.data).to(device),
                MatrixType.CSR,
            )
        except (RuntimeError, ValueError) as err:
            raise ValueError(_not_positive_definite_message(A, str(err))) from None
        self.device = device
        _LIVE_CHOLESKY.add(self)
        if not check:
            return

        def solve_numpy(b: np.ndarray) -> np.ndarray:
            rhs = torch.from_numpy(b).to(self.device)[:, None]
            return self._solve64(rhs)[:, 0].cpu().numpy()

        # the check's product and norm read the CSR arrays (no copy)
        problem = _solution_problem(S, solve_numpy)
        if problem is not None:
            raise ValueError(_not_positive_definite_message(A, problem))

    def _solve64(self, B: torch.Tensor) -> torch.Tensor:
        X = torch.empty_like(B)
        step = self._CUDA_COLUMNS if B.device.type == "cuda" else max(B.shape[1], 1)
        for start in range(0, B.shape[1], step):
            rhs = B[:, start : start + step].contiguous()
            out = torch.empty_like(rhs)
            self.factor.solve(rhs, out)
            X[:, start : start + step] = out
        return X

    def solve(self, B: torch.Tensor, *, transpose: bool = False) -> torch.Tensor:
        B64 = B.detach().to(device=self.device, dtype=torch.float64).contiguous()
        return _finite(self._solve64(B64)).to(B)

    def solve_array(self, b: np.ndarray) -> np.ndarray:
        """``A^{-1} b`` for a float64 ``(n,)`` or ``(n, k)`` array (a CPU factorization)."""
        B = torch.from_numpy(np.ascontiguousarray(b, dtype=np.float64))
        X = self._solve64(B.reshape(B.shape[0], -1).to(self.device)).cpu().numpy()
        return _finite_array(X.reshape(b.shape))


class LDLFactorization:
    """QDLDL's sparse ``L D L^T`` of a symmetric positive definite matrix, after an AMD
    fill-reducing ordering, in float64 on the CPU, via the optional ``qdldl``.

    A simplicial factorization (one column at a time, no dense blocks): on the mesh matrices
    of 10^4 to 3 * 10^4 vertices it factors about twice as fast as
    :class:`CholeskyFactorization` (cholespy's CHOLMOD runs without postordering, on
    reference BLAS), above some 4 * 10^4 more slowly (as the factor fills, CHOLMOD's dense
    supernodal blocks win), while its triangular solves are about 1.2x slower
    (``benchmarks/README.md``, "Heat geodesics"). So it pays where a factorization serves few
    solves, as in :class:`~torch_polylap.HeatGeodesicSolver`.
    Without pivoting, an indefinite matrix may factor; ``check`` (one solve with a random
    ``b``) refuses a numerically singular one as for :class:`Factorization`, and one with
    ``b^T A^{-1} b <= 0``, which is not positive definite.

    The solves can run through copies of the factor with 32-bit indices (:class:`.LDLTriangles`,
    1.2x faster than QDLDL's own, made by the first solve that asks for them);
    :meth:`solve_sparse_array` solves right-hand sides with few nonzeros (heat sources) with a
    forward solve over their elimination-tree paths only (:class:`.EtreePathSolver`). Where the
    factor cannot be read that way, QDLDL solves. :meth:`refactored` factors a second matrix
    of the same pattern with this one's ordering and elimination tree.
    """

    def __init__(self, A: torch.Tensor, *, check: bool = True) -> None:
        import qdldl

        S = to_scipy(A).astype(np.float64, copy=False)
        self._setup(S, *_upper_parts(S))
        try:
            self.factor: object | None = qdldl.Solver(self._upper, upper=True)
        except (RuntimeError, ValueError) as err:
            raise ValueError(_not_positive_definite_message(A, str(err))) from None
        if check:
            self._check(A)

    def _setup(self, S: sp.csr_matrix, upper: sp.csc_matrix, keep: np.ndarray) -> None:
        self.n = int(S.shape[0])
        self._triangles: LDLTriangles | None = None
        self._paths: EtreePathSolver | None = None
        self._built: set[str] = set()
        self._matrix = S  # the copies' check
        self._upper = upper  # what QDLDL factors (again, if its factor was handed on)
        self._keep = keep  # the entries of S in upper
        # (L, d, p) read out of QDLDL's solver before it was handed on (see refactored)
        self._read: tuple[sp.csc_matrix, np.ndarray, np.ndarray] | None = None
        self._order: np.ndarray | None = None  # the AMD ordering, once read (ordering())

    def _check(self, A: torch.Tensor | sp.spmatrix) -> None:
        """Refuse a numerically singular or indefinite factorization (one random solve)."""
        curvature: list[float] = []

        def solve_once(b: np.ndarray) -> np.ndarray:
            x = self._qdldl().solve(b)  # type: ignore[attr-defined]
            # not b @ x: a BLAS dot this long wakes OpenBLAS's threads, which then spin for a
            # while, taking the other core from the next solves
            curvature.append(float(np.einsum("i,i->", b, x)))
            return x

        problem = _solution_problem(self._matrix, solve_once)
        if problem is None and curvature and not curvature[0] > 0:
            problem = f"b^T A^-1 b = {curvature[0]:.3g} for a random b"
        if problem is not None:
            raise ValueError(_not_positive_definite_message(A, problem))

    def refactored(self, B: torch.Tensor, *, keep: bool = True) -> LDLFactorization:
        """The checked factorization of ``B``, a matrix with this one's pattern (the heat and
        Poisson systems of :class:`~torch_polylap.HeatGeodesicSolver`): QDLDL's numeric
        factorization only, reusing this one's AMD ordering and elimination tree (the same
        factor as a fresh one of ``B``, bit for bit): 58-65% of a fresh factorization's
        time on the real meshes loki and rockerArm (20k-28k vertices; the AMD ordering and the
        tree are the rest), 92% on bunny-dual (73k vertices, whose factor fills in more).

        QDLDL refactors in place, so this factorization hands its solver on: with ``keep`` it
        first reads its factor out (a copy of ``L``) and solves through :class:`.LDLTriangles`
        made from it; without, a later solve factors its matrix afresh. A ``B`` of another
        pattern, or a factor that cannot be read, gets a fresh factorization instead.

        Raises:
            ValueError: ``B`` is numerically singular or not positive definite.
        """
        S = to_scipy(B).astype(np.float64, copy=False)
        S0 = self._matrix
        solver = self.factor
        same = (
            solver is not None
            and S.shape == S0.shape
            and np.array_equal(S.indptr, S0.indptr)
            and np.array_equal(S.indices, S0.indices)
        )
        read = None
        if same and keep:
            read = _read_factors(solver)
        if not same or (keep and read is None) or not hasattr(solver, "update"):
            return LDLFactorization(B)
        # the same pattern: the upper triangle is one gather of the values
        upper = sp.csc_matrix(
            (S.data[self._keep], self._upper.indices, self._upper.indptr), shape=S.shape
        )
        other = LDLFactorization.__new__(LDLFactorization)
        other._setup(S, upper, self._keep)
        self.factor, self._read = None, read
        try:
            solver.update(upper, upper=True)
        except (RuntimeError, ValueError) as err:
            raise ValueError(_not_positive_definite_message(B, str(err))) from None
        other.factor = solver
        other._check(B)
        return other

    def _qdldl(self) -> object:
        """QDLDL's solver of this matrix: factored again if it was handed on."""
        if self.factor is None:
            import qdldl

            self.factor = qdldl.Solver(self._upper, upper=True)
        return self.factor

    def _factors(self) -> tuple[sp.csc_matrix, np.ndarray, np.ndarray]:
        """``(L, d, p)``: the factor read out before the solver was handed on, else QDLDL's."""
        return self._read if self._read is not None else self._qdldl().factors()  # type: ignore[attr-defined]

    def ordering(self) -> np.ndarray:
        """``(n,)`` the AMD fill-reducing permutation ``p`` of the factor
        (``A[p][:, p] = (I + L) D (I + L)^T``): from the solve copies where they exist, else
        read out of QDLDL (a copy of the factor, once)."""
        if self._order is None:
            solves = self._triangles or self._paths
            if solves is not None:
                self._order = solves.perm
            else:
                self._order = np.asarray(self._factors()[2], dtype=np.int64)
        return self._order

    def solve(self, B: torch.Tensor, *, transpose: bool = False) -> torch.Tensor:
        # A^T = A: ``transpose`` changes nothing
        return torch.from_numpy(self.solve_array(B.detach().cpu().numpy())).to(B)

    def solve_array(self, b: np.ndarray, *, copy_factor: bool = True) -> np.ndarray:
        """``A^{-1} b`` for a float64 ``(n,)`` or ``(n, k)`` array, without torch tensors;
        ``copy_factor=False`` solves with QDLDL unless the copies exist (for one solve they
        would cost more than they save) or the factor was read out and its solver handed on
        (:meth:`refactored`)."""
        want = copy_factor or (self.factor is None and self._read is not None)
        triangles = self._triangle_solves() if want else self._triangles
        if triangles is not None:
            return _finite_array(triangles.solve(np.asarray(b, dtype=np.float64)))
        factor = self._qdldl()
        if b.ndim == 1:
            return _finite_array(factor.solve(np.ascontiguousarray(b, dtype=np.float64)))  # type: ignore[attr-defined]
        X = np.empty(b.shape)
        for j in range(b.shape[1]):
            X[:, j] = factor.solve(np.ascontiguousarray(b[:, j], dtype=np.float64))  # type: ignore[attr-defined]
        return _finite_array(X)

    def solve_sparse_array(
        self, rows: list[np.ndarray], values: list[np.ndarray], *, copy_factor: bool = True
    ) -> np.ndarray:
        """``(n, Q)`` ``A^{-1} B`` for the ``B`` whose column ``q`` is ``values[q]`` (float64
        ``(m_q,)``) at the rows ``rows[q]`` (``(m_q,)``, no repeats) and zero elsewhere.

        A column whose sources' tree paths are short enough (:meth:`.EtreePathSolver.pays`)
        takes the path solve, about half a full solve's time from one source; the others,
        and all columns where the factor's structure could not be read, a full solve. The
        same result to round-off either way. ``copy_factor`` as for :meth:`solve_array`."""
        want = copy_factor or (self.factor is None and self._read is not None)
        paths = self._path_solver() if want else self._paths
        cheap = [] if paths is None else [q for q, r in enumerate(rows) if paths.pays(r)]
        if paths is not None and len(cheap) == len(rows):
            return _finite_array(paths.solve_sparse(rows, values))
        full = [q for q in range(len(rows)) if q not in cheap]
        B = np.zeros((self.n, len(full)))
        for k, q in enumerate(full):
            B[rows[q], k] = values[q]
        X = np.empty((self.n, len(rows)))
        X[:, full] = self.solve_array(B, copy_factor=copy_factor)
        if paths is not None and cheap:
            X[:, cheap] = paths.solve_sparse([rows[q] for q in cheap], [values[q] for q in cheap])
        return _finite_array(X)

    def _path_solver(self) -> EtreePathSolver | None:
        """The path solver of the factor, built on the first call (it also serves
        :meth:`solve_array`); ``None`` where it fails its checks."""
        if "paths" not in self._built:
            self._built.add("paths")
            paths = _checked_solves(self._factors, self._matrix, EtreePathSolver)
            self._paths = paths if isinstance(paths, EtreePathSolver) else None
            if self._paths is not None and "triangles" not in self._built:
                self._built.add("triangles")
                self._triangles = self._paths
            self._release_read()
        return self._paths

    def _triangle_solves(self) -> LDLTriangles | None:
        """The 32-bit copies of the factor, built on the first call; ``None`` where they fail
        their checks."""
        if "triangles" not in self._built:
            self._built.add("triangles")
            self._triangles = _checked_solves(self._factors, self._matrix, LDLTriangles)
            self._release_read()
        return self._triangles

    def _release_read(self) -> None:
        """Drop the factor read out of QDLDL once the copies made from it are built."""
        if "triangles" in self._built and "paths" in self._built:
            self._read = None


def _read_factors(solver: object) -> tuple[sp.csc_matrix, np.ndarray, np.ndarray] | None:
    """``(L, d, p)`` copied out of a ``qdldl.Solver``, or ``None`` where they cannot be read."""
    try:
        L, d, p = solver.factors()  # type: ignore[attr-defined]
        return sp.csc_matrix(L), np.asarray(d, dtype=np.float64), np.asarray(p)
    except (AttributeError, TypeError, ValueError, RuntimeError):
        return None


def _checked_solves(
    factors: Callable[[], tuple[sp.csc_matrix, np.ndarray, np.ndarray]],
    S: sp.spmatrix,
    kind: type[LDLTriangles],
) -> LDLTriangles | None:
    """``kind`` built from the factors of ``S`` that ``factors()`` returns (QDLDL's
    ``(L, d, p)``) and checked once by the backward error of a solve (a random right-hand
    side; a source at row 0 too for a path solver), or ``None`` when the factors cannot be
    read or a check fails (a qdldl or scipy whose API changed): the callers then solve with
    QDLDL."""
    try:
        L, d, p = factors()
        solves = kind(sp.csc_matrix(L), np.asarray(d), np.asarray(p))
        if _solution_problem(S, solves.solve, warn=False) is not None:
            return None
        if isinstance(solves, EtreePathSolver):
            x = solves.solve_sparse([np.array([0])], [np.array([1.0])])[:, 0]
            r = S @ x
            r[0] -= 1.0
            norm = np.abs(S.data).max(initial=0.0)
            if not np.abs(r).max() <= _BACKWARD_ERROR * (norm * np.abs(x).max() + 1.0):
                return None
    except (AttributeError, TypeError, ValueError, RuntimeError, IndexError):
        return None
    return solves


def _upper_parts(S: sp.csr_matrix) -> tuple[sp.csc_matrix, np.ndarray]:
    """The upper triangle (diagonal included) of a symmetric CSR matrix, as CSC.

    Read as CSC, the CSR arrays of a symmetric matrix are its transpose, that is itself: column
    ``j`` is row ``j``, and its upper part the entries with column index ``<= j``. One mask
    over the entries replaces scipy's ``triu`` (a COO round trip), which qdldl calls otherwise.

    Returns the upper triangle (CSC) and the ``(nnz,)`` mask of the entries of ``S`` it holds.
    """
    n = S.shape[0]
    rows = np.repeat(np.arange(n, dtype=np.int64), np.diff(S.indptr))
    keep = S.indices <= rows
    indptr = np.concatenate(([0], np.cumsum(keep, dtype=np.int64)))[S.indptr]
    indices = S.indices[keep].astype(np.int64, copy=False)
    return sp.csc_matrix((S.data[keep], indices, indptr), shape=S.shape), keep


# An LU of a well-posed system solves it to a backward error of a few eps; a larger one means
# tiny pivots (an indefinite matrix factored without pivoting) or near-singularity.
_BACKWARD_ERROR = 1e-10
# A singular PSD matrix's last pivot is round-off of a few to a few dozen eps |S|, so a solve
# grows a right-hand side by up to about 1 / eps: on 5,596 singular graph Laplacians of 4-40
# vertices CHOLMOD factored, the growth |x| |S| / |b| was down to 0.09 / eps. A growth from
# 1 / (eps max(n, _GROWTH_MIN_N)) on (a 90x margin there) makes the matrix suspect, and
# iterative refinement tells the two apart: a non-singular matrix of condition number c has
# each refinement correction shrink by about c eps, while a singular one gets a correction as
# large as the solution, its kernel component being round-off divided by round-off. With CHOLMOD,
# QDLDL and SuperLU on 1,500 singular graph Laplacians of 4-40 vertices and 33 mesh Laplacians,
# the larger of two corrections was at least 0.022 |x| each time; on the same matrices shifted
# to a condition number of up to 1e13 (L + 1e-12 M0 on spot: 8e12) at most 0.0049 |x|.
# Refinement converges on any matrix that factors exactly (a diagonal one), so a growth from
# _NO_DIGIT / eps on, where not two digits of a solution would be right, is refused outright.
_GROWTH_MIN_N = 1000
_REFINEMENT = 0.01
_NO_DIGIT = 0.01


def _solution_problem(
    S: sp.spmatrix, solve: Callable[[np.ndarray], np.ndarray], *, warn: bool = True
) -> str | None:
    """What is wrong with a factorization of ``S``, or ``None``: one solve with a fixed random
    right-hand side. A singular PSD matrix (a Laplacian without a mass term) factors without
    complaint, its last pivot being round-off, and shows as a growth ``|x| |S| / |b|`` of
    ``1 / eps`` (reading the pivots would need the whole factor to be copied out of the
    solver); an unstable factorization (tiny pivots of an indefinite matrix factored without
    pivoting) as a backward error ``|S x - b| / (|S| |x| + |b|)`` far above round-off.

    A growth near ``1 / eps`` that two steps of iterative refinement (two more solves) show to
    be a non-singular, ill-conditioned matrix passes, with an :class:`IllConditionedWarning`
    when ``warn``."""
    n = S.shape[0]
    if not n:
        return None
    b = np.random.default_rng(0).standard_normal(n)
    x = solve(b)
    # the entries' largest magnitude without abs(S), a copy of the matrix
    norm = float(np.abs(S.data).max(initial=0.0))
    growth = np.abs(x).max() * norm / np.abs(b).max()
    eps = np.finfo(float).eps
    if not np.isfinite(growth):
        return f"solution growth {growth:.1e}"
    if growth * max(n, _GROWTH_MIN_N) * eps >= 1.0:
        if growth * eps >= _NO_DIGIT:
            return f"solution growth {growth:.1e}"
        if not _refinement_converges(S, solve, b, x):
            return f"solution growth {growth:.1e}, and iterative refinement does not converge"
        if warn:
            digits = max(0, int(-np.log10(growth * eps)))
            warnings.warn(
                f"the {n} x {n} system matrix is ill-conditioned (solution growth "
                f"{growth:.1e}, about its condition number) but not singular: it was solved, "
                f"to about {digits} correct digits. A tiny shift (L + 1e-12 M0) gives this; a "
                "larger one (M0 + h L with a larger h, or a Dirichlet condition) solves "
                "accurately.",
                IllConditionedWarning,
                stacklevel=2,
            )
    backward = np.abs(S @ x - b).max() / (norm * np.abs(x).max() + np.abs(b).max())
    if backward > _BACKWARD_ERROR:
        return f"backward error {backward:.1e} of the factorization"
    return None


def _refinement_converges(
    S: sp.spmatrix, solve: Callable[[np.ndarray], np.ndarray], b: np.ndarray, x: np.ndarray
) -> bool:
    """Whether two steps of iterative refinement of ``x = S^-1 b`` each correct ``x`` by less
    than ``_REFINEMENT |x|`` (max norms): true of a non-singular ``S`` up to a condition number
    of about ``_REFINEMENT / eps``, not of a singular one (see above)."""
    for _ in range(2):
        correction = solve(b - S @ x)
        if not np.abs(correction).max() < _REFINEMENT * np.abs(x).max():
            return False
        x = x + correction
    return True


_NOT_FINITE = (
    "the solve produced non-finite values: the system matrix is singular or "
    "numerically singular (a Laplacian without a mass term or Dirichlet values?)."
)


def _finite(X: torch.Tensor) -> torch.Tensor:
    if not bool(torch.isfinite(X).all()):
        raise ValueError(_NOT_FINITE)
    return X


def _finite_array(X: np.ndarray) -> np.ndarray:
    # the sum is one pass without a boolean temporary; it is finite iff every entry is (an
    # overflow of the sum itself would need entries near the float64 maximum)
    if not np.isfinite(X.sum()) and not np.isfinite(X).all():
        raise ValueError(_NOT_FINITE)
    return X


def cholespy_available() -> bool:
    try:
        import cholespy  # noqa: F401
    except ImportError:
        return False
    return True


def qdldl_available() -> bool:
    try:
        import qdldl  # noqa: F401
    except ImportError:
        return False
    return True


def _singular_message(A: torch.Tensor | sp.spmatrix, detail: str) -> str:
    return (
        f"the {A.shape[0]} x {A.shape[1]} system matrix is singular ({detail}). A Laplacian "
        "alone has the constants in its kernel: solve with M0 + h L, or fix values at some "
        "vertices with torch_polylap.dirichlet_solve."
    )


def _not_positive_definite_message(A: torch.Tensor | sp.spmatrix, detail: str) -> str:
    """Why CHOLMOD refused ``A``: singular, or indefinite but non-singular (then SuperLU with
    partial pivoting solves it: the error path may afford that diagnosis)."""
    S = sp.csc_matrix((to_scipy(A) if isinstance(A, torch.Tensor) else A).astype(np.float64))
    try:
        problem = _solution_problem(S, spla.splu(S, permc_spec="COLAMD").solve, warn=False)
    except RuntimeError as err:
        problem = str(err)
    if problem is not None:
        return _singular_message(A, problem)
    return (
        f"the {A.shape[0]} x {A.shape[1]} system matrix is not positive definite ({detail}) "
        "but non-singular: it is indefinite (e.g. L - s M0 with s > 0), and Cholesky "
        "factorizations and conjugate gradients need a positive definite matrix. Solve it "
        "with backend='splu' (SuperLU, which pivots), or check the sign of the terms that "
        "built it (M0 + h L needs h >= 0)."
    )


def spd_factorization(
    A: SparseOperator, *, check: bool = True
) -> Factorization | CholeskyFactorization:
    """An uncached factorization of a symmetric positive definite ``A``: CHOLMOD when cholespy
    is installed (on ``A``'s device), else SuperLU on the CPU."""
    return (
        CholeskyFactorization(A, check=check)
        if cholespy_available()
        else Factorization(A, check=check)
    )


Factor = Factorization | CholeskyFactorization | LDLFactorization


def cached_factorization(A: SparseOperator, backend: str) -> Factor:
    """The factorization of ``A`` for ``backend`` (``"cholesky"``, ``"ldl"``, else SuperLU),
    built once and kept in ``A``'s solver cache for every later solve with the same values."""
    kinds: dict[str, type[Factor]] = {"cholesky": CholeskyFactorization, "ldl": LDLFactorization}
    kind = kinds.get(backend, Factorization)
    return solver_cache(A, backend, lambda: kind(A))


class OpaqueOperator:
    """A sparse operator ``A`` wrapped so that an autograd.Function receives it as a plain
    object: autograd and torch.func must see only its value array as the differentiable
    input."""

    __slots__ = ("A",)

    def __init__(self, A: SparseOperator) -> None:
        self.A = A

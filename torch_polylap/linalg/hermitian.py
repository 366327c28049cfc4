"""``L D L^H`` of a complex Hermitian positive definite matrix, for the vector heat method.

The connection Laplacian's system ``M + t A`` (:class:`~torch_polylap.vector.VectorHeatSolver`)
is a complex Hermitian ``(V, V)`` matrix with the scalar Laplacian's pattern; the package's
operators hold it in real ``(2V, 2V)`` form, each entry ``a + i b`` a block
``[[a, -b], [b, a]]``. Factored in that form (CHOLMOD through cholespy), its factor has four
real entries per complex one, and a solve reads 48 bytes per entry of the scalar factor's
pattern instead of 20: on loki (27k vertices, one thread) the real form took 1.5 s to factor
and 23 ms to solve, the complex one 0.37 s (SuperLU, the scalar factor's AMD ordering) and
6 ms (two triangular passes through :class:`.LDLTriangles`; a right-hand side nonzero at a few
sources has its forward pass over their elimination-tree paths only,
:class:`.EtreePathSolver`).

SuperLU factors ``P^T A P = L U`` without pivoting (symmetric mode, diagonal pivots): for a
Hermitian positive definite matrix the factorization is unique, ``U = D L^H`` with ``D`` real
positive, so ``L`` and ``diag(U)`` are the ``L D L^H`` factor.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from .etree_solve import EtreePathSolver, LDLTriangles
from .factor import _checked_solves, _finite_array, _solution_problem


class HermitianLDL:
    """``A^{-1} b`` for a complex Hermitian positive definite ``(n, n)`` CSR ``A``.

    Args:
        A: the matrix (scipy CSR or CSC, complex128; Hermitian, not checked).
        ordering: ``(n,)`` fill-reducing permutation ``p`` to factor ``A[p][:, p]`` in (e.g.
            the AMD ordering of a real matrix of the same pattern, as QDLDL computed it for
            the scalar heat system); ``None`` lets SuperLU order (minimum degree on
            ``A + A^T``, slower to factor).

    Raises:
        ValueError: ``A`` is numerically singular or not positive definite (a pivot of the
            factor not real positive, or the check solve's growth or backward error, see
            :func:`~torch_polylap.linalg.factor._solution_problem`).
    """

    def __init__(self, A: sp.spmatrix, ordering: np.ndarray | None = None) -> None:
        S = sp.csr_matrix(A, dtype=np.complex128)
        self.n = n = int(S.shape[0])
        if ordering is None:
            order = np.arange(n)
            P, permc = sp.csc_matrix(S), "MMD_AT_PLUS_A"
        else:
            order = np.asarray(ordering, dtype=np.int64)
            P, permc = sp.csc_matrix(S[order][:, order]), "NATURAL"
        try:
            lu = spla.splu(
                P, permc_spec=permc, diag_pivot_thresh=0.0, options={"SymmetricMode": True}
            )
        except RuntimeError as err:
            raise ValueError(_message(n, str(err))) from None
        d = lu.U.diagonal()
        if not (np.all(d.real > 0) and np.all(np.abs(d.imag) <= 1e-8 * d.real)):
            raise ValueError(_message(n, "a pivot of its L D L^H is not real positive"))
        self._lu: spla.SuperLU | None = lu
        self._triangles: LDLTriangles | None = None
        if np.array_equal(lu.perm_r, lu.perm_c):
            # P[q][:, q] = L U with q the inverse of perm_c, so A's ordering is order[q]
            inverse = np.empty(n, dtype=np.int64)
            inverse[lu.perm_c] = np.arange(n)
            strict = _strictly_lower(lu.L)
            factors = (strict, d.real.astype(np.complex128), order[inverse])
            # the path solver where the factor's structure allows it, else the plain copies
            for kind in (EtreePathSolver, LDLTriangles):
                self._triangles = _checked_solves(lambda: factors, S, kind)
                if self._triangles is not None:
                    break
        if self._triangles is None:
            # SuperLU's own solve: the same factor, through its supernodal storage
            self._order = order
            problem = _solution_problem(S, self._superlu_solve, warn=False)
            if problem is not None:
                raise ValueError(_message(n, problem))
        else:
            self._lu = None  # the copies hold the factor

    def _superlu_solve(self, b: np.ndarray) -> np.ndarray:
        assert self._lu is not None
        x = np.empty(b.shape, dtype=np.complex128)
        x[self._order] = self._lu.solve(np.ascontiguousarray(b[self._order], dtype=np.complex128))
        return x

    def solve_sparse(self, rows: np.ndarray, values: np.ndarray) -> np.ndarray:
        """``(n,)`` ``A^{-1} b`` for the ``b`` that is ``values`` (complex ``(m,)``) at
        ``rows`` (``(m,)``, no repeats) and zero elsewhere: the forward solve over the rows'
        elimination-tree paths where that pays (:meth:`.EtreePathSolver.pays`).

        Raises:
            ValueError: the solution is not finite.
        """
        paths = self._triangles
        if isinstance(paths, EtreePathSolver) and paths.pays(rows):
            return _finite_array(paths.solve_sparse([rows], [values])[:, 0])
        b = np.zeros(self.n, dtype=np.complex128)
        b[rows] = values
        return self.solve(b)

    def solve(self, b: np.ndarray) -> np.ndarray:
        """``A^{-1} b`` for a complex ``(n,)`` or ``(n, k)`` array.

        Raises:
            ValueError: the solution is not finite.
        """
        b = np.asarray(b, dtype=np.complex128)
        if self._triangles is not None:
            return _finite_array(self._triangles.solve(b))
        return _finite_array(self._superlu_solve(b))


def _strictly_lower(L: sp.csc_matrix) -> sp.csc_matrix:
    """SuperLU's unit lower ``L`` without its diagonal: SuperLU stores the diagonal first in
    each column, so dropping those entries is one mask (scipy's ``tril`` where not)."""
    n = L.shape[0]
    first = L.indptr[:-1]
    if not np.array_equal(L.indices[first], np.arange(n)):
        return sp.csc_matrix(sp.tril(L, k=-1))
    keep = np.ones(L.nnz, dtype=bool)
    keep[first] = False
    return sp.csc_matrix(
        (L.data[keep], L.indices[keep], L.indptr - np.arange(n + 1)), shape=L.shape
    )


def _message(n: int, detail: str) -> str:
    return (
        f"the {n} x {n} complex vector heat system M + t A is singular or not positive "
        f"definite ({detail}): check the mesh for degenerate faces (zero area) or non-finite "
        "vertex positions, or use a larger t."
    )

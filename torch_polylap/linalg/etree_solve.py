"""Solves with an ``L D L^T`` factor whose right-hand side is nonzero at a few rows only.

With ``A = P (I + L) D (I + L)^T P^T`` (``L`` strictly lower triangular), the forward solve
``(I + L) y = P^T b`` of a ``b`` that is nonzero at one row ``i`` has ``y`` nonzero only on the
path from ``j = p^{-1}(i)`` to the root of the elimination tree of ``L`` (``parent(j)`` = the
smallest row index of an entry in column ``j``), and every entry of a column on that path has
its row on the path too: it is an ancestor (Gilbert's theorem; QDLDL builds the pattern of row
``k`` as the union of the tree paths from the entries of ``A``'s column ``k``, so its stored
entries have this property by construction). The forward solve restricted to the path is a
solve with the small triangular matrix ``(I + L)[path, path]``, 7-20% of ``L``'s entries for
a heat geodesic source on meshes of 20k-30k vertices; the right-hand sides of several rows
add up.
The backward solve ``(I + L)^T z = D^{-1} y`` stays a full one.

Both triangular solves run through SuperLU's ``gstrs`` (scipy's compiled triangular solve, the
routine behind ``scipy.sparse.linalg.spsolve_triangular``, called directly: the public function
copies and rescales the whole matrix on every call). Its lower solve, column by column, is the
fast one (about 1.1 ms for QDLDL's factor of 10^6 entries, where ``gstrs``' own transposed
solve takes 2 ms): the backward solve is therefore done as a lower solve with ``J L^T J``,
``J`` the reversal permutation, stored once.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import scipy.sparse as sp

try:  # scipy's compiled SuperLU triangular solve (private: checked, and optional)
    from scipy.sparse.linalg._dsolve._superlu import gstrs as _gstrs
except ImportError:  # pragma: no cover - older scipy: the callers solve in full
    _gstrs = None

# A path solve costs, per entry of L on the paths, a little more than the full forward solve
# (the copies of its columns), and the backward solve is a full one. From 1-8 random sources on
# loki and rockerArm it was the faster up to paths holding 55-60% of L's entries (summed over
# the sources: 1.5-2 ms at 6-20%, the full solve 3 ms), slower from 65% on.
PATH_SHARE = 0.5
# Sources of one query beyond which the paths are not walked at all (their union is most of
# the tree, and the walk is a Python loop per source).
MAX_SOURCES = 64


class LDLTriangles:
    """``A^{-1} B`` from QDLDL's factors of ``A = P L D L^T P^T``, both triangular solves
    through SuperLU's ``gstrs``: about 1.2x faster than QDLDL's own solve (its indices are
    64-bit, these 32-bit).

    Built from ``(L, d, p)`` (``L`` strictly lower ``(n, n)`` CSC, ``d`` ``(n,)``, ``p``
    ``(n,)`` with ``A[p][:, p] = (I + L) D (I + L)^H``). Holds ``L`` twice (the forward copy
    with ``D`` on its diagonal, the reversed conjugate transpose for the backward solve): 24
    bytes per entry of a real ``L``. A complex ``L`` (the ``L D L^H`` of a Hermitian matrix,
    :class:`.HermitianLDL`) solves complex right-hand sides through ``gstrs``' complex
    routine, 40 bytes per entry.
    """

    def __init__(self, L: sp.csc_matrix, d: np.ndarray, p: np.ndarray) -> None:
        if _gstrs is None:
            raise RuntimeError("scipy has no SuperLU gstrs")
        n = L.shape[0]
        self.n = n
        self.nnz = int(L.nnz)
        indptr = L.indptr.astype(np.int64)
        self.counts = np.diff(indptr)
        # parent = the smallest row below the diagonal; -1 at the roots
        first = np.minimum.reduceat(L.indices, np.minimum(indptr[:-1], max(L.nnz - 1, 0)))
        self.parent = np.where(self.counts > 0, first, -1).astype(np.int64)
        if np.any(self.parent[self.counts > 0] <= np.flatnonzero(self.counts > 0)):
            raise ValueError("the factor is not strictly lower triangular")
        # forward copy: per column the diagonal first (d: gstrs divides by it, so its solve
        # returns D^{-1} L^{-1} b), then the entries
        self.indptr = indptr + np.arange(n + 1)
        self._indptr = self.indptr.astype(np.intc)
        self.values, self.rows = _with_diagonal(
            self.indptr, (d, L.data), (np.arange(n, dtype=np.intc), L.indices)
        )
        # backward: J (I + L)^H J, a lower triangle. The forward copy read as CSR is
        # D + L^T; its CSC has the rows of each column sorted, the diagonal last, and
        # reversed (J's two sides) first, where it is set to 1
        upper = sp.csr_matrix((self.values, self.rows, self._indptr), shape=(n, n)).tocsc()
        # conj makes the copy that the diagonal is written into (a no-op on real values)
        self.back_values = np.conj(upper.data[::-1])
        self.back_indices = np.subtract(n - 1, upper.indices[::-1], dtype=np.intc)
        self.back_indptr = (upper.indptr[-1] - upper.indptr[::-1]).astype(np.intc)
        if not np.array_equal(self.back_indices[self.back_indptr[:-1]], np.arange(n)):
            raise ValueError("the transposed factor's diagonal is not first in its columns")
        self.back_values[self.back_indptr[:-1]] = 1.0
        self.perm = np.asarray(p, dtype=np.int64)
        self.inverse = np.empty(n, dtype=np.int64)
        self.inverse[self.perm] = np.arange(n)
        # x = P z with z = J r, r the reversed backward solve: x = r[n - 1 - p^{-1}]
        self._gather = (n - 1) - self.inverse
        # gstrs' (unused) upper factor: its values' dtype picks the real or complex routine
        self._empty = (
            np.zeros(0, dtype=self.values.dtype),
            np.zeros(0, dtype=np.intc),
            np.zeros(n + 1, dtype=np.intc),
        )

    def solve(self, b: np.ndarray) -> np.ndarray:
        """``A^{-1} b`` for a float64 ``(n,)`` or ``(n, k)`` ``b`` (complex128 for a complex
        factor)."""
        n = self.n
        rhs = b[self.perm].astype(self.values.dtype, copy=False)
        y = self._lower(n, self.values, self.rows, self._indptr, rhs)
        r = self._lower(n, self.back_values, self.back_indices, self.back_indptr, y[::-1])
        return r[self._gather]

    def backward(self, w: np.ndarray) -> np.ndarray:
        """``P L^{-T} J w`` for a float64 ``(n,)`` or ``(n, k)`` ``w`` (``J`` the reversal)."""
        r = self._lower(self.n, self.back_values, self.back_indices, self.back_indptr, w)
        return r[self._gather]

    def _lower(
        self, n: int, values: np.ndarray, indices: np.ndarray, indptr: np.ndarray, b: np.ndarray
    ) -> np.ndarray:
        """``gstrs``' lower solve with the ``(n, n)`` CSC matrix (diagonal first in each
        column), divided by that diagonal."""
        data, rows, ptr = self._empty
        x, info = _gstrs(
            "N", n, values.size, values, indices, indptr, n, 0, data, rows, ptr[: n + 1], b
        )
        if info:
            raise RuntimeError(f"SuperLU gstrs failed (info {info})")
        return x


class EtreePathSolver(LDLTriangles):
    """:class:`LDLTriangles` that also solve for a ``B`` with few nonzero rows per column
    (:meth:`solve_sparse`): the forward solve runs over the rows' elimination-tree paths only.
    The forward copy's row indices, as their depth in the tree, take 4 more bytes per entry.
    """

    def __init__(self, L: sp.csc_matrix, d: np.ndarray, p: np.ndarray) -> None:
        super().__init__(L, d, p)
        n = self.n
        depth = _depths(self.parent).astype(np.intc)
        self.depths = depth[self.rows]
        # every entry's row lies above its column in the tree, the diagonal's at it
        if np.count_nonzero(self.depths >= np.repeat(depth, self.counts + 1)) != n:
            raise ValueError("an entry of the factor lies below its column in the tree")
        # a path climbs runs of consecutive columns (j, j + 1, ...): each column's run top
        run_ends = np.where(self.parent != np.arange(1, n + 1), np.arange(n), n)
        self._top = np.minimum.accumulate(run_ends[::-1])[::-1].tolist()
        self._parent = self.parent.tolist()

    def path_cost(self, rows: np.ndarray) -> int:
        """Entries of ``L`` the paths of ``rows`` (original numbering) hold, summed over the
        rows (diagonals included)."""
        return sum(
            int(self.indptr[top + 1] - self.indptr[start])
            for row in rows.tolist()
            for start, top in self._runs(int(self.inverse[row]))
        )

    def pays(self, rows: np.ndarray) -> bool:
        """Whether the path solve of a right-hand side nonzero at ``rows`` is faster than a
        full solve: at most :data:`MAX_SOURCES` rows whose paths hold at most
        :data:`PATH_SHARE` of ``L``'s entries."""
        return rows.size <= MAX_SOURCES and self.path_cost(rows) <= PATH_SHARE * self.nnz

    def _runs(self, j: int) -> list[tuple[int, int]]:
        """The path from column ``j`` to its root as runs ``(first, last)`` of consecutive
        columns."""
        runs = []
        while j >= 0:
            top = self._top[j]
            runs.append((j, top))
            j = self._parent[top]
        return runs

    def forward(self, row: int, value: float) -> tuple[np.ndarray, np.ndarray]:
        """``D^{-1} L^{-1} P^T (value e_row)`` on its support: ``(columns, values)``, the
        path's columns in increasing order."""
        runs = self._runs(int(self.inverse[row]))
        spans = [(int(self.indptr[a]), int(self.indptr[b + 1])) for a, b in runs]
        values = np.concatenate([self.values[s:e] for s, e in spans])
        # on the path from column j, the column at depth k sits at position depth(j) - k
        rows = np.concatenate([self.depths[s:e] for s, e in spans])
        size = sum(b - a + 1 for a, b in runs)
        np.subtract(size - 1, rows, out=rows)
        # each run's column pointers, shifted to where its entries start in the copies
        starts = np.cumsum([0] + [e - s for s, e in spans]).tolist()
        pieces = [
            self.indptr[a : b + 1] - (s - start)
            for (a, b), (s, _), start in zip(runs, spans, starts, strict=False)
        ]
        indptr = np.concatenate([*pieces, [starts[-1]]]).astype(np.intc)
        rhs = np.zeros(size, dtype=self.values.dtype)
        rhs[0] = value
        y = self._lower(size, values, rows, indptr, rhs)
        columns = np.concatenate([np.arange(a, b + 1) for a, b in runs])
        return columns, y

    def solve_sparse(self, rows: Sequence[np.ndarray], values: Sequence[np.ndarray]) -> np.ndarray:
        """``(n, Q)`` ``A^{-1} B``, column ``q`` of ``B`` ``values[q]`` at ``rows[q]`` (original
        numbering, no repeats), zero elsewhere."""
        n = self.n
        w = np.zeros((n, len(rows)), dtype=self.values.dtype, order="F")
        for q, (idx, val) in enumerate(zip(rows, values, strict=True)):
            for row, value in zip(idx.tolist(), val.tolist(), strict=True):
                if value != 0.0:
                    columns, y = self.forward(row, value)
                    w[(n - 1) - columns, q] += y
        return self.backward(w)


def _depths(parent: np.ndarray) -> np.ndarray:
    """``(n,)`` depth of each node of a forest given by ``parent`` (``-1`` at the roots), by
    pointer jumping: ``log2`` of the height passes over the nodes."""
    n = parent.size
    up = np.where(parent >= 0, parent, np.arange(n))
    depth = (parent >= 0).astype(np.int64)
    while True:
        nxt = up[up]
        if np.array_equal(nxt, up):
            return depth
        depth += depth[up]
        up = nxt


def _with_diagonal(
    indptr: np.ndarray, values: tuple[np.ndarray, np.ndarray], rows: tuple[np.ndarray, np.ndarray]
) -> tuple[np.ndarray, np.ndarray]:
    """CSC values and row indices (``intc``) with each column's diagonal entry first: the
    ``(n,)`` diagonal ``values[0]``, ``rows[0]`` at ``indptr[:-1]``, the other entries
    ``values[1]``, ``rows[1]`` after them in order, for a CSC matrix's ``(n + 1,)``
    ``indptr`` that counts both."""
    below = np.ones(int(indptr[-1]), dtype=bool)
    below[indptr[:-1]] = False
    data = np.empty(below.size, dtype=np.result_type(*values))
    data[indptr[:-1]] = values[0]
    data[below] = values[1]
    index = np.empty(below.size, dtype=np.intc)
    index[indptr[:-1]] = rows[0]
    index[below] = rows[1]
    return data, index

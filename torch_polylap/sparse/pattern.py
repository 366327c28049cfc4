"""The index structure of a sparse matrix, and the index algebra on it, computed once and cached.

A :class:`SparsityPattern` is the CSR index structure ``(crow, col)`` of an ``(n, m)`` matrix with
sorted columns in every row and no duplicates.  Everything the operator algebra needs that depends
on the indices only -- row indices, the transposed pattern and its permutation, the union with
another pattern, the positions of the diagonal -- is computed on first use and kept on the pattern.
The operators of one mesh share one pattern object across training steps (the topology keeps it:
:meth:`torch_polylap.topology.Topology.pattern`), so ``M0 + t * L`` pays for the union of the two
patterns once, not every step.
"""

from __future__ import annotations

import weakref

import numpy as np
import torch

__all__ = ["SparsityPattern"]


def _stable_argsort(key: torch.Tensor) -> torch.Tensor:
    if key.device.type == "cpu":
        # numpy's radix-based stable sort is several times faster than torch's on the CPU
        return torch.from_numpy(np.argsort(key.numpy(), kind="stable"))
    return torch.argsort(key, stable=True)


def _crow_from_rows(row: torch.Tensor, n_rows: int) -> torch.Tensor:
    crow = torch.zeros(n_rows + 1, dtype=torch.int64, device=row.device)
    torch.cumsum(torch.bincount(row, minlength=n_rows), 0, out=crow[1:])
    return crow


class SparsityPattern:
    """CSR indices ``crow (n + 1,)``, ``col (nnz,)`` of an ``(n, m)`` matrix, and derived indices.

    Columns are sorted within each row and unique.  Instances are immutable; the caches only
    grow on first use.  Build one from CSR arrays, with :meth:`from_rows` (from sorted,
    duplicate-free COO indices) or with :meth:`diagonal_of` (an ``n x n`` diagonal).
    """

    __slots__ = (
        "crow",
        "col",
        "shape",
        "_row",
        "_transpose",
        "_diag_pos",
        "_unions",
        "_devices",
        "__weakref__",
    )

    def __init__(self, crow: torch.Tensor, col: torch.Tensor, shape: tuple[int, int]) -> None:
        self.crow = crow
        self.col = col
        self.shape = (int(shape[0]), int(shape[1]))
        self._row: torch.Tensor | None = None
        self._transpose: tuple[SparsityPattern, torch.Tensor] | None = None
        self._diag_pos: torch.Tensor | None = None
        # other pattern -> (union, or None where it is the other pattern itself; index maps)
        self._unions: weakref.WeakKeyDictionary[
            SparsityPattern,
            tuple[SparsityPattern | None, torch.Tensor | None, torch.Tensor | None],
        ] = weakref.WeakKeyDictionary()
        self._devices: dict[torch.device, SparsityPattern] = {}

    @classmethod
    def from_rows(
        cls, row: torch.Tensor, col: torch.Tensor, shape: tuple[int, int]
    ) -> SparsityPattern:
        """From COO indices sorted by row, then column, without duplicates."""
        pattern = cls(_crow_from_rows(row, shape[0]), col, shape)
        pattern._row = row
        return pattern

    @classmethod
    def diagonal_of(cls, n: int, device: torch.device | str | None = None) -> SparsityPattern:
        """The pattern of an ``n x n`` diagonal matrix (every diagonal entry stored)."""
        ar = torch.arange(n, device=device)
        pattern = cls(torch.arange(n + 1, device=device), ar, (n, n))
        pattern._row = ar
        pattern._diag_pos = ar
        return pattern

    @property
    def nnz(self) -> int:
        return self.col.numel()

    @property
    def device(self) -> torch.device:
        return self.col.device

    @property
    def row(self) -> torch.Tensor:
        """``(nnz,)`` row index of every stored entry."""
        if self._row is None:
            self._row = torch.repeat_interleave(
                torch.arange(self.shape[0], device=self.device), self.crow.diff()
            )
        return self._row

    def to(self, device: torch.device | str) -> SparsityPattern:
        """This pattern on ``device``, copied once and cached (with its own caches)."""
        device = torch.device(device)
        if device == self.device or (device.index is None and device.type == self.device.type):
            return self
        if device not in self._devices:
            self._devices[device] = SparsityPattern(
                self.crow.to(device), self.col.to(device), self.shape
            )
        return self._devices[device]

    def transpose(self) -> tuple[SparsityPattern, torch.Tensor]:
        """The pattern of ``A^T`` and ``perm`` with ``values(A^T) = values(A)[perm]``."""
        if self._transpose is None:
            n, m = self.shape
            perm = _stable_argsort(self.col * n + self.row)
            transposed = SparsityPattern.from_rows(self.col[perm], self.row[perm], (m, n))
            transposed._transpose = (self, torch.argsort(perm))
            self._transpose = (transposed, perm)
        return self._transpose

    def diagonal_positions(self) -> torch.Tensor:
        """``(min(n, m),)`` position of entry ``(i, i)`` in the values, ``-1`` where not stored."""
        if self._diag_pos is None:
            k = min(self.shape)
            pos = torch.full((k,), -1, dtype=torch.int64, device=self.device)
            on_diag = torch.nonzero(self.row == self.col).reshape(-1)
            pos[self.col[on_diag]] = on_diag
            self._diag_pos = pos
        return self._diag_pos

    def union(
        self, other: SparsityPattern
    ) -> tuple[SparsityPattern, torch.Tensor | None, torch.Tensor | None]:
        """The pattern of ``A + B`` and where each operand's entries go in it.

        Returns ``(pattern, at_self, at_other)``: ``values(A + B)[at_self] += values(A)``, and
        likewise for ``other``; an index map is ``None`` where it is the identity.  Cached per
        pair of patterns.
        """
        if other is self:
            return self, None, None
        if other.shape != self.shape:
            raise ValueError(f"cannot add matrices of shapes {self.shape} and {other.shape}.")
        cached = self._unions.get(other)
        if cached is None:
            pattern, at_self, at_other = self._compute_union(other)
            # the weak-keyed cache must not hold `other` strongly: None stands for it
            cached = (None if pattern is other else pattern, at_self, at_other)
            self._unions[other] = cached
        union, at_self, at_other = cached
        return (other if union is None else union), at_self, at_other

    def _compute_union(
        self, other: SparsityPattern
    ) -> tuple[SparsityPattern, torch.Tensor | None, torch.Tensor | None]:
        m = self.shape[1]
        keys = torch.cat((self.row * m + self.col, other.row * m + other.col))
        unique, inverse = torch.unique(keys, sorted=True, return_inverse=True)
        at_self, at_other = inverse[: self.nnz], inverse[self.nnz :]
        if unique.numel() == self.nnz:
            return self, None, at_other
        if unique.numel() == other.nnz:
            return other, at_self, None
        row = torch.div(unique, m, rounding_mode="floor")
        return SparsityPattern.from_rows(row, unique - row * m, self.shape), at_self, at_other

    def select(
        self, rows: torch.Tensor, cols: torch.Tensor
    ) -> tuple[SparsityPattern, torch.Tensor]:
        """The pattern of the submatrix ``A[rows][:, cols]`` and the positions of its entries.

        ``rows`` and ``cols`` are increasing index tensors; ``values(sub) = values(A)[positions]``.
        """
        n, m = self.shape
        row_map = torch.full((n,), -1, dtype=torch.int64, device=self.device)
        row_map[rows] = torch.arange(rows.numel(), device=self.device)
        col_map = torch.full((m,), -1, dtype=torch.int64, device=self.device)
        col_map[cols] = torch.arange(cols.numel(), device=self.device)
        new_row, new_col = row_map[self.row], col_map[self.col]
        keep = torch.nonzero((new_row >= 0) & (new_col >= 0)).reshape(-1)
        sub = SparsityPattern.from_rows(new_row[keep], new_col[keep], (rows.numel(), cols.numel()))
        return sub, keep

    def __repr__(self) -> str:
        return f"SparsityPattern(shape={self.shape}, nnz={self.nnz}, device={self.device})"

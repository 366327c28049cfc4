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

import itertools
import weakref
from typing import Any

import numpy as np
import torch

from ..tracing import outside_transforms, run_eagerly, tracing

__all__ = ["SparsityPattern", "block_diagonal_indices"]


def _stable_argsort(key: torch.Tensor) -> torch.Tensor:
    if key.device.type == "cpu":
        # numpy's radix-based stable sort is several times faster than torch's on the CPU
        return torch.from_numpy(np.argsort(key.numpy(), kind="stable"))
    return torch.argsort(key, stable=True)


def _crow_from_rows(row: torch.Tensor, n_rows: int) -> torch.Tensor:
    # counts by index_add, not bincount: its output size does not depend on the data, so the
    # same code traces under torch.compile
    counts = torch.zeros(n_rows + 1, dtype=torch.int64, device=row.device)
    return counts.index_add_(0, row + 1, torch.ones_like(row)).cumsum(0)


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
        "_eager",
        "_contains",
        "_diag_class",
        "key",
        "__weakref__",
    )

    def __init__(self, crow: torch.Tensor, col: torch.Tensor, shape: tuple[int, int]) -> None:
        self.crow = crow
        self.col = col
        self.shape = (int(shape[0]), int(shape[1]))
        self._row: torch.Tensor | None = None
        self._transpose: tuple[SparsityPattern, torch.Tensor] | None = None
        self._diag_pos: torch.Tensor | None = None
        # id(other pattern) -> (weak reference to it; union, or None where it is the other
        # pattern itself; index maps).  A plain dict keyed by id, not a WeakKeyDictionary: the
        # weak reference only checks that the key still names the same pattern, and the dict
        # stays readable by torch.compile's tracer.
        self._unions: dict[
            int,
            tuple[
                weakref.ref,
                SparsityPattern | None,
                torch.Tensor | None,
                torch.Tensor | None,
            ],
        ] = {}
        self._devices: dict[torch.device, SparsityPattern] = {}
        self._contains: dict[int, bool] = {}
        self._diag_class: int | None = None
        # built on real index tensors (not inside a torch.compile trace): its caches can be
        # filled at trace time and enter compiled graphs as constants
        self._eager = not tracing()
        # operators refer to their pattern by this number (a constant that torch.compile's
        # tracer carries through), -1 for patterns built inside traced code
        self.key = _register(self) if self._eager else -1

    @staticmethod
    def registered(key: int) -> SparsityPattern | None:
        """The live pattern numbered ``key``, if any.

        Operators hold their index tensors and this number, not the pattern object (so that
        torch.compile can trace them); this finds the pattern, with its caches, again.
        """
        ref = _PATTERNS.get(key)
        return None if ref is None else ref()

    # Caches are derived data: a pickled pattern (in a checkpoint, a DataLoader worker's
    # batch) carries its indices only and rebuilds the rest on first use.
    def __getstate__(self) -> dict[str, Any]:
        return {"crow": self.crow, "col": self.col, "shape": self.shape}

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__init__(state["crow"], state["col"], state["shape"])  # type: ignore[misc]

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
        if self._row is not None:
            return self._row
        with outside_transforms():
            row = torch.repeat_interleave(
                torch.arange(self.shape[0], device=self.device),
                self.crow.diff(),
                output_size=self.nnz,
            )
        if not tracing():
            self._row = row
        return row

    def to(self, device: torch.device | str) -> SparsityPattern:
        """This pattern on ``device``, copied once and cached (with its own caches)."""
        device = torch.device(device)
        if device == self.device or (device.index is None and device.type == self.device.type):
            return self
        if tracing():
            if self._eager:
                return run_eagerly(SparsityPattern.to, self, device)
            return SparsityPattern(self.crow.to(device), self.col.to(device), self.shape)
        if device not in self._devices:
            with outside_transforms():
                copy = SparsityPattern(self.crow.to(device), self.col.to(device), self.shape)
            self._devices[device] = copy
        return self._devices[device]

    def transpose(self) -> tuple[SparsityPattern, torch.Tensor]:
        """The pattern of ``A^T`` and ``perm`` with ``values(A^T) = values(A)[perm]``."""
        if tracing():
            if self._eager:
                return run_eagerly(SparsityPattern.transpose, self)
            return _transposed(
                self, torch.argsort(self.col * self.shape[0] + self.row, stable=True)
            )
        if self._transpose is None:
            n = self.shape[0]
            with outside_transforms():
                transposed, perm = _transposed(self, _stable_argsort(self.col * n + self.row))
                transposed._transpose = (self, torch.argsort(perm))
            self._transpose = (transposed, perm)
        return self._transpose

    def diagonal_positions(self) -> torch.Tensor:
        """``(min(n, m),)`` position of entry ``(i, i)`` in the values, ``-1`` where not stored."""
        if self._diag_pos is not None:
            return self._diag_pos
        if tracing() and self._eager:
            return run_eagerly(SparsityPattern.diagonal_positions, self)
        # the largest position on the diagonal of each row (the only one): a scatter of fixed
        # size rather than a nonzero(), so that it traces
        with outside_transforms():
            arange = torch.arange(self.nnz, device=self.device)
            on_diag = torch.where(self.row == self.col, arange, -1)
            k = min(self.shape)
            pos = torch.full((k,), -1, dtype=torch.int64, device=self.device)
            pos = pos.scatter_reduce(0, self.row.clamp_max(max(k - 1, 0)), on_diag, "amax")
        if not tracing():
            self._diag_pos = pos
        return pos

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
        if tracing():
            if not (self._eager and other._eager):
                raise NotImplementedError(
                    "torch_polylap: inside torch.compile, operators can be added only when "
                    "their sparsity patterns exist outside the compiled code (those of a mesh's "
                    "operators do); the union of patterns built inside it has a size that "
                    "depends on the data. Build such operators outside the compiled function."
                )
            union, at_self, at_other = run_eagerly(_cache_union, self, other)
        else:
            with outside_transforms():
                union, at_self, at_other = _cache_union(self, other)
        return (other if union is None else union), at_self, at_other

    def _is_diagonal(self) -> bool:
        """Whether the entries are exactly ``(i, i)`` for every ``i`` (a mass matrix's pattern)."""
        k = min(self.shape)
        return self.nnz == k and bool(
            torch.equal(self.row, self.col)
            and torch.equal(self.row, torch.arange(k, device=self.device))
        )

    def _compute_union(
        self, other: SparsityPattern
    ) -> tuple[SparsityPattern, torch.Tensor | None, torch.Tensor | None]:
        # M0 + t L, the common case: a full diagonal against a pattern that stores its diagonal
        # is answered from the diagonal positions, without sorting every entry of both
        for big, small, big_first in ((self, other, True), (other, self, False)):
            if small._is_diagonal():
                pos = big.diagonal_positions()
                if bool((pos >= 0).all()):
                    return (big, None, pos) if big_first else (big, pos, None)
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

    def diagonal_class(self) -> int:
        """2 when the entries are exactly the diagonal, 1 when every diagonal entry is stored
        among others, 0 otherwise (computed once, on the real indices).

        Operators carry it into compiled code: ``M0 + t L`` of patterns of classes 2 and 1
        keeps ``L``'s pattern, which the traced sum must know without reading the indices.
        """
        if self._diag_class is None:
            if self.shape[0] != self.shape[1]:
                self._diag_class = 0
            elif self._is_diagonal():
                self._diag_class = 2
            else:
                self._diag_class = int(bool((self.diagonal_positions() >= 0).all()))
        return self._diag_class

    def contains(self, other: SparsityPattern) -> bool:
        """Whether every entry of ``other`` (same shape) is an entry of this pattern."""
        if other is self:
            return True
        known = self._contains.get(other.key) if other.key >= 0 else None
        if known is None:
            union, _, _ = _cache_union(self, other)
            known = union is self
            if other.key >= 0:
                self._contains[other.key] = known
        return known

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


def _transposed(
    pattern: SparsityPattern, perm: torch.Tensor
) -> tuple[SparsityPattern, torch.Tensor]:
    """The pattern of ``A^T`` from the permutation that sorts ``A``'s entries by column."""
    n, m = pattern.shape
    return SparsityPattern.from_rows(pattern.col[perm], pattern.row[perm], (m, n)), perm


def _cache_union(
    pattern: SparsityPattern, other: SparsityPattern
) -> tuple[SparsityPattern | None, torch.Tensor | None, torch.Tensor | None]:
    """``(union or None where it is other, at_pattern, at_other)``, computed once per pair."""
    key = id(other)
    cached = pattern._unions.get(key)
    if cached is None or cached[0]() is not other:
        union, at_self, at_other = pattern._compute_union(other)
        # the cache must not hold `other` strongly: None stands for it
        ref = weakref.ref(other, lambda _: pattern._unions.pop(key, None))
        cached = (ref, None if union is other else union, at_self, at_other)
        pattern._unions[key] = cached
    return cached[1], cached[2], cached[3]


# key -> the pattern; weak, so that patterns die with their topology
_PATTERNS: dict[int, weakref.ref[SparsityPattern]] = {}
_keys = itertools.count()


def _register(pattern: SparsityPattern) -> int:
    key = next(_keys)
    _PATTERNS[key] = weakref.ref(pattern, lambda _: _PATTERNS.pop(key, None))
    return key


def block_diagonal_indices(
    crow: torch.Tensor, col: torch.Tensor, row: torch.Tensor, batch: int, n: int, m: int
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """CSR indices ``(crow, col, row)`` of ``blockdiag(A, ..., A)``: ``batch`` copies of an
    ``(n, m)`` pattern, as one ``(batch n, batch m)`` pattern (a batch of value arrays on one
    pattern multiplies as this one operator)."""
    nnz = col.shape[0]
    shift = torch.arange(batch, device=col.device)[:, None]
    tail = crow.new_full((1,), batch * nnz)
    crow_b = torch.cat(((crow[:-1][None] + shift * nnz).reshape(-1), tail))
    return crow_b, (col[None] + shift * m).reshape(-1), (row[None] + shift * n).reshape(-1)

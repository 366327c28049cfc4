"""Where every entry of a sum of per-face blocks comes from: the assembly as gathers.

The eager assembly scatters each face's entries onto the CSR value array (``index_add``). A
compiler fuses gathers far better than scatters: a :class:`GatherPlan`, computed once per
topology and device, lists for every stored entry of ``L`` the per-face entries it sums, so that
``L``'s values are

    values = S[first] + S[second] (+ the few entries with more than two contributions)

with ``S`` the per-face off-diagonal entries of every degree group followed by the diagonal
``d_v = -sum of the row sums of v's blocks`` (``L_f 1 = 0``) and a zero. An off-diagonal entry of
``L`` sums the blocks of the faces sharing its two vertices (two for an interior edge, one for a
boundary edge or a diagonal of a face); the per-vertex sums (``d_v`` and the lumped masses) are
gathered over the corners at ``v``, one dense layer per rank of a corner at its vertex while
most vertices have that many corners, the rest added by a short ``index_add``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from ..topology.groups import moved

__all__ = ["GatherPlan", "VertexSums", "gather_plan"]

# dense (V,) layers of a vertex sum while at least this share of the vertices has that many
# corners; the remaining corners are added by one index_add
_DENSE_SHARE = 0.25


@dataclass(frozen=True)
class VertexSums:
    """How to sum per-corner quantities ``C`` (every group's ``(k, F)`` flattened, then one
    zero) per vertex: ``sum_l C[layers[l]] + zeros(V).index_add(0, rest_vertex, C[rest])``."""

    layers: torch.Tensor
    """``(L, V)`` corner indices; the zero's index where a vertex has fewer corners."""
    rest_vertex: torch.Tensor
    """``(R,)`` vertex of each corner beyond the dense layers."""
    rest: torch.Tensor
    """``(R,)`` its corner index."""
    corner_vertex: torch.Tensor
    """``(num_corners,)`` the vertex of every corner (the backward's gather)."""
    symbolic: bool = False
    """The sizes are symbols of a graph traced for many meshes (the number of layers and of
    the rest among them): the layers are then summed by one gather, and the rest always added."""

    def to(self, device: torch.device) -> VertexSums:
        return moved(self, device)

    def corners(self, verts_t: torch.Tensor) -> torch.Tensor:
        """``(3, num_corners)`` the positions ``verts_t`` ``(3, V)`` of every corner; its
        backward sums the corners' gradients per vertex by the same gathers as :meth:`total`
        (no scatter)."""
        out: torch.Tensor = _Corners.apply(
            verts_t, self.corner_vertex, self.layers, self.rest_vertex, self.rest, self.symbolic
        )
        return out

    def total(self, corner_values: torch.Tensor) -> torch.Tensor:
        """``(V,)`` the per-vertex sums of ``corner_values`` ``(num_corners,)``."""
        out: torch.Tensor = _VertexTotal.apply(
            corner_values,
            self.layers,
            self.rest_vertex,
            self.rest,
            self.corner_vertex,
            self.symbolic,
        )
        return out


@dataclass(frozen=True)
class GatherPlan:
    """The gathers that assemble ``L``'s values and the per-vertex sums (see the module)."""

    first: torch.Tensor
    """``(nnz,)`` index into ``S`` of each entry's first contribution (its diagonal sum)."""
    second: torch.Tensor
    """``(nnz,)`` index of its second contribution, the zero's index where it has none."""
    rest_pos: torch.Tensor
    """``(R,)`` entries with more than two contributions (non-manifold edges)..."""
    rest: torch.Tensor
    """``(R,)`` ...and the indices into ``S`` of those contributions."""
    vertex: VertexSums
    """The per-vertex sums over corners."""
    pos_upper: torch.Tensor
    """``(num_off,)`` position of every per-face entry (the backward's gathers)..."""
    pos_lower: torch.Tensor
    """``(num_off,)`` ...and of its mirror;"""
    diag_pos: torch.Tensor
    """``(V,)`` position of every diagonal entry."""
    num_off: int
    """Number of per-face off-diagonal entries (the start of ``d`` in ``S``)."""
    symbolic: bool = False
    """As :attr:`VertexSums.symbolic`: the number of entries with more contributions is a
    symbol, and they are always added."""

    def to(self, device: torch.device) -> GatherPlan:
        return moved(self, device)

    def values(self, off: torch.Tensor, diagonal: torch.Tensor) -> torch.Tensor:
        """``(nnz,)`` values from every group's off-diagonal entries ``off`` (flattened and
        concatenated, ``(num_off,)``) and the diagonal ``diagonal`` ``(V,)``."""
        out: torch.Tensor = _Values.apply(
            off,
            diagonal,
            self.first,
            self.second,
            self.rest_pos,
            self.rest,
            self.pos_upper,
            self.pos_lower,
            self.diag_pos,
            self.symbolic,
        )
        return out


# The gathers' derivatives are gathers too (each per-face entry lands at two known positions,
# each corner at one vertex): written out, the backward a compiler generates holds no scatter
# (which inductor emits as atomic adds, many times slower on the CPU). No forward-mode rule:
# torch.compile cannot trace an autograd.Function that has one.


def _sum_layers(
    source: torch.Tensor,
    layers: list[torch.Tensor],
    rest_pos: torch.Tensor,
    rest: torch.Tensor,
    symbolic: bool = False,
) -> torch.Tensor:
    """``sum_l source[..., layers[l]]``, plus ``source[..., rest]`` added at ``rest_pos``
    (``symbolic``: always, since whether there is a rest is not known while tracing)."""
    out = source[..., layers[0]]
    for layer in layers[1:]:
        out = out + source[..., layer]
    if symbolic or rest.numel():
        out = out.index_add(-1, rest_pos, source[..., rest])
    return out


def _sum_stacked(
    source: torch.Tensor,
    layers: torch.Tensor,
    rest_pos: torch.Tensor,
    rest: torch.Tensor,
    symbolic: bool,
) -> torch.Tensor:
    """:func:`_sum_layers` with the layers ``(D, V)`` one tensor: added one by one, or, where
    ``D`` is a symbol of a graph traced for many meshes (not a Python loop's length), gathered
    at once and summed."""
    if not symbolic:
        return _sum_layers(source, list(layers.unbind(0)), rest_pos, rest)
    out = source[..., layers].sum(-2)
    return out.index_add(-1, rest_pos, source[..., rest])


def _padded(t: torch.Tensor) -> torch.Tensor:
    """``t`` with a zero appended along its last dimension (the gathers' index for none)."""
    return torch.cat((t, t.new_zeros((*t.shape[:-1], 1))), -1)


class _Values(torch.autograd.Function):
    @staticmethod
    def forward(
        off: torch.Tensor,
        diagonal: torch.Tensor,
        first: torch.Tensor,
        second: torch.Tensor,
        rest_pos: torch.Tensor,
        rest: torch.Tensor,
        pos_upper: torch.Tensor,
        pos_lower: torch.Tensor,
        diag_pos: torch.Tensor,
        symbolic: bool,
    ) -> torch.Tensor:
        source = torch.cat((off, diagonal, diagonal.new_zeros(1)))
        return _sum_layers(source, [first, second], rest_pos, rest, symbolic)

    @staticmethod
    def setup_context(ctx: Any, inputs: tuple[Any, ...], output: torch.Tensor) -> None:
        ctx.save_for_backward(*inputs[2:9])

    @staticmethod
    def backward(ctx: Any, grad: torch.Tensor) -> tuple[torch.Tensor | None, ...]:
        _, _, _, _, pos_upper, pos_lower, diag_pos = ctx.saved_tensors
        return (grad[pos_upper] + grad[pos_lower], grad[diag_pos], *([None] * 8))


class _VertexTotal(torch.autograd.Function):
    @staticmethod
    def forward(
        corner_values: torch.Tensor,
        layers: torch.Tensor,
        rest_vertex: torch.Tensor,
        rest: torch.Tensor,
        corner_vertex: torch.Tensor,
        symbolic: bool,
    ) -> torch.Tensor:
        return _sum_stacked(_padded(corner_values), layers, rest_vertex, rest, symbolic)

    @staticmethod
    def setup_context(ctx: Any, inputs: tuple[Any, ...], output: torch.Tensor) -> None:
        ctx.save_for_backward(inputs[4])

    @staticmethod
    def backward(ctx: Any, grad: torch.Tensor) -> tuple[torch.Tensor | None, ...]:
        (corner_vertex,) = ctx.saved_tensors
        return grad[corner_vertex], None, None, None, None, None


def _ranks(target: np.ndarray, size: int) -> tuple[np.ndarray, np.ndarray]:
    """``(order, rank)``: the items sorted by target (stably) and each one's rank among the
    items of its target."""
    order = np.argsort(target, kind="stable")
    counts = np.bincount(target, minlength=size)
    starts = np.zeros(size + 1, np.int64)
    np.cumsum(counts, out=starts[1:])
    rank = np.arange(order.size, dtype=np.int64) - starts[target[order]]
    return order, rank


def _flat(arrays: list[np.ndarray]) -> np.ndarray:
    """The arrays flattened and concatenated (int64; empty for a mesh without faces)."""
    return np.concatenate([a.reshape(-1) for a in arrays] + [np.zeros(0, np.int64)])


def _vertex_sums(corners: list[np.ndarray], num_verts: int) -> VertexSums:
    vertex = _flat(corners)
    zero = vertex.size
    order, rank = _ranks(vertex, num_verts)
    depth = np.bincount(rank) if rank.size else np.zeros(0, np.int64)
    dense = max(1, int(np.count_nonzero(depth >= _DENSE_SHARE * max(num_verts, 1))))
    layers = np.full((dense, num_verts), zero, np.int64)
    keep = rank < dense
    layers[rank[keep], vertex[order[keep]]] = order[keep]
    rest = order[~keep]
    return VertexSums(
        torch.from_numpy(layers),
        torch.from_numpy(vertex[rest]),
        torch.from_numpy(rest),
        torch.from_numpy(vertex),
    )


def gather_plan(
    pos_upper: list[np.ndarray],
    pos_lower: list[np.ndarray],
    corners: list[np.ndarray],
    diag_pos: np.ndarray,
    nnz: int,
) -> GatherPlan:
    """The :class:`GatherPlan` of a topology (CPU tensors).

    Args:
        pos_upper, pos_lower: per degree group, ``(P, F)`` positions in the values of each
            face's entry ``(i, j)``, ``i < j``, and of its mirror.
        corners: per degree group, ``(k, F)`` vertex of each corner.
        diag_pos: ``(V,)`` position of each diagonal entry.
        nnz: number of stored entries.
    """
    num_verts = diag_pos.size
    up, low = _flat(pos_upper), _flat(pos_lower)
    num_off = up.size
    target = np.concatenate((up, low, diag_pos))
    source = np.concatenate(
        (np.tile(np.arange(num_off, dtype=np.int64), 2), num_off + np.arange(num_verts))
    )
    order, rank = _ranks(target, nnz)
    zero = num_off + num_verts
    layers = np.full((2, nnz), zero, np.int64)
    keep = rank < 2
    layers[rank[keep], target[order[keep]]] = source[order[keep]]
    rest = order[~keep]
    return GatherPlan(
        torch.from_numpy(layers[0]),
        torch.from_numpy(layers[1]),
        torch.from_numpy(target[rest]),
        torch.from_numpy(source[rest]),
        _vertex_sums(corners, num_verts),
        torch.from_numpy(up),
        torch.from_numpy(low),
        torch.from_numpy(diag_pos),
        num_off,
    )


class _Corners(torch.autograd.Function):
    @staticmethod
    def forward(
        verts_t: torch.Tensor,
        corner_vertex: torch.Tensor,
        layers: torch.Tensor,
        rest_vertex: torch.Tensor,
        rest: torch.Tensor,
        symbolic: bool,
    ) -> torch.Tensor:
        return verts_t[:, corner_vertex]

    @staticmethod
    def setup_context(ctx: Any, inputs: tuple[Any, ...], output: torch.Tensor) -> None:
        ctx.save_for_backward(*inputs[2:5])
        ctx.symbolic = inputs[5]

    @staticmethod
    def backward(ctx: Any, grad: torch.Tensor) -> tuple[torch.Tensor | None, ...]:
        layers, rest_vertex, rest = ctx.saved_tensors
        total = _sum_stacked(_padded(grad), layers, rest_vertex, rest, ctx.symbolic)
        return total, None, None, None, None, None

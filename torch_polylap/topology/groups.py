"""Faces grouped by degree, with the positions where their per-face entries land in ``L``.

Each :class:`DegreeGroup` lays the faces of one degree out as ``(k, F_k)`` corner indices, the
structure-of-arrays layout the kernels of :mod:`torch_polylap.kernels` evaluate, and splits
them into :class:`GroupChunk` runs that carry the scatter positions into the CSR value array.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any, NamedTuple, TypeVar

import numpy as np
import torch

T = TypeVar("T")


# Faces are processed in chunks whose largest temporary, a (3, P, chunk) array, holds about
# this many elements (8 MB in float64): large enough that per-op overhead is negligible, small
# enough that the allocator recycles the memory instead of mapping fresh pages for every op
# (glibc serves blocks above 32 MB with mmap, and page faults then cost more than the math).
CHUNK_ELEMENTS = 1 << 20


@dataclass(frozen=True)
class GroupChunk:
    """A contiguous run of faces of one degree group, with its scatter positions.

    Attributes:
        start, stop: the run's range within the group.
        corners_t: ``(k, c)`` vertex index of each corner.
        pos_upper, pos_lower: ``(P * c,)`` where entry ``(i, j)``, ``i < j``, and its mirror
            ``(j, i)`` of each face's ``k x k`` block land in ``L``'s CSR value array, in the
            ``(P, c)`` layout of the per-face entries.
        pos_diag: ``(k * c,)`` where each face's diagonal entries land.
    """

    start: int
    stop: int
    corners_t: torch.Tensor
    pos_upper: torch.Tensor
    pos_lower: torch.Tensor
    pos_diag: torch.Tensor

    def to(self, device: torch.device) -> GroupChunk:
        return moved(self, device)


@dataclass(frozen=True)
class DegreeGroup:
    """All faces of one degree ``k``, laid out for vectorized per-face formulas.

    Attributes:
        k: number of corners of every face in the group.
        face_ids: ``(F_k,)`` the faces' indices in the mesh.
        corners_t: ``(k, F_k)`` vertex index of corner ``i`` of each face (transposed so that a
            gather from ``(3, V)`` positions yields a ``(3, k, F_k)`` structure-of-arrays block).
        pair_i, pair_j: ``(P,)`` local corner pairs ``i < j`` with ``P = k (k - 1) / 2``.
        chunks: the group split into :class:`GroupChunk` runs.
    """

    k: int
    face_ids: torch.Tensor
    corners_t: torch.Tensor
    pair_i: torch.Tensor
    pair_j: torch.Tensor
    chunks: tuple[GroupChunk, ...]

    def to(self, device: torch.device) -> DegreeGroup:
        return moved(self, device)


class _DegreeBlock(NamedTuple):
    """The faces of one degree ``k`` as numpy arrays, before they become a
    :class:`DegreeGroup`."""

    k: int
    face_ids: np.ndarray
    """``(F_k,)`` the faces' indices in the mesh."""
    corners_t: np.ndarray
    """``(k, F_k)`` their vertex indices, corner-major."""
    pair_i: np.ndarray
    """``(P,)`` the first corner of each pair ``i < j``."""
    pair_j: np.ndarray
    """``(P,)`` the second corner of each pair."""


def _degree_block(
    k: int, idx: np.ndarray, sizes: np.ndarray, offsets: np.ndarray, *, uniform: bool
) -> _DegreeBlock:
    """The :class:`_DegreeBlock` of degree ``k``; ``uniform``: every face has degree ``k``."""
    if uniform:
        fid = np.arange(sizes.size, dtype=np.int64)
        corners_t = np.ascontiguousarray(idx.reshape(-1, k).T)
    else:
        fid = np.flatnonzero(sizes == k).astype(np.int64)
        corners_t = idx[offsets[fid][None, :] + np.arange(k)[:, None]]
    pi, pj = np.triu_indices(k, 1)
    return _DegreeBlock(k, fid, corners_t, pi.astype(np.int64), pj.astype(np.int64))


def _write_pair_keys(
    corners_t: np.ndarray, pi: np.ndarray, pj: np.ndarray, nv: np.int64, out: np.ndarray
) -> None:
    """Fill ``out`` (``(P * F_k,)``, pair-major) with the keys ``lo * V + hi`` of every corner
    pair of every face.

    Runs of pair rows are processed together so that every step touches about
    ``CHUNK_ELEMENTS`` entries: one row at a time for large groups (views, no temporaries),
    all pairs at once for one high-degree face. A face that visits a vertex twice gives a key
    with ``lo == hi``: the caller checks the distinct keys for that, and
    :func:`_check_simple_faces` names the face.
    """
    f = corners_t.shape[1]
    rows = out.reshape(pi.size, f)
    step = max(1, CHUNK_ELEMENTS // max(f, 1))
    for s in range(0, pi.size, step):
        if step == 1:
            a, b = corners_t[pi[s]][None], corners_t[pj[s]][None]
        else:
            a, b = corners_t[pi[s : s + step]], corners_t[pj[s : s + step]]
        block = rows[s : s + a.shape[0]]
        np.minimum(a, b, out=block)
        block *= nv
        block += np.maximum(a, b)


def _check_simple_faces(
    corners_t: np.ndarray, fid: np.ndarray, pi: np.ndarray, pj: np.ndarray
) -> None:
    """Refuse the first face (in pair-row order) of a degree block that visits a vertex twice.

    Runs of pair rows are compared together so that every step touches about
    ``CHUNK_ELEMENTS`` entries: one row at a time for large groups, all pairs at once for one
    high-degree face.
    """
    f = fid.size
    step = max(1, CHUNK_ELEMENTS // max(f, 1))
    for s in range(0, pi.size, step):
        a, b = corners_t[pi[s : s + step]], corners_t[pj[s : s + step]]
        same = a == b
        if same.any():
            r, c = (int(t[0]) for t in np.nonzero(same))
            raise ValueError(
                f"face {int(fid[c])} (vertices {corners_t[:, c].tolist()[:20]}) visits vertex "
                f"{int(a[r, c])} twice; a polygon must be simple. Split it into simple polygons "
                "or merge the duplicated corners (torch_polylap.repair.remove_degenerate_faces "
                "removes such faces)."
            )


def _cycle_pair_rows(k: int) -> np.ndarray:
    """``(k,)`` row, in ``np.triu_indices(k, 1)`` order, of the pair ``(c, c + 1 mod k)``."""
    c = np.arange(k, dtype=np.int64)
    lo = np.minimum(c, (c + 1) % k)
    hi = np.maximum(c, (c + 1) % k)
    return lo * k - lo * (lo + 1) // 2 + (hi - lo - 1)


def _chunks(
    k: int,
    corners_t: np.ndarray,
    ginv: np.ndarray,
    pos_up_u: np.ndarray,
    pos_low_u: np.ndarray,
    pos_diag_v: np.ndarray,
) -> tuple[GroupChunk, ...]:
    """Split a degree group into runs whose ``(3, P, run)`` temporaries stay near
    ``CHUNK_ELEMENTS`` entries."""
    f = corners_t.shape[1]
    step = max(256, CHUNK_ELEMENTS // (3 * max(ginv.shape[0], k)))
    out = []
    for a in range(0, f, step):
        b = min(a + step, f)
        # one intp copy serves both gathers (numpy converts an int32 index array for each)
        part = ginv[:, a:b].astype(np.intp)
        out.append(
            GroupChunk(
                a,
                b,
                torch.from_numpy(np.ascontiguousarray(corners_t[:, a:b])),
                torch.from_numpy(pos_up_u[part].reshape(-1)),
                torch.from_numpy(pos_low_u[part].reshape(-1)),
                torch.from_numpy(pos_diag_v[corners_t[:, a:b]].reshape(-1)),
            )
        )
    return tuple(out)


def whole_group(grp: DegreeGroup) -> GroupChunk:
    """The group as a single :class:`GroupChunk` (its chunks' scatter maps joined)."""
    if len(grp.chunks) == 1:
        return grp.chunks[0]
    P, k = grp.pair_i.numel(), grp.k

    def joined(name: str, rows: int) -> torch.Tensor:
        parts = [getattr(c, name).reshape(rows, -1) for c in grp.chunks]
        return torch.cat(parts, 1).reshape(-1)

    return GroupChunk(
        0,
        grp.face_ids.numel(),
        grp.corners_t,
        joined("pos_upper", P),
        joined("pos_lower", P),
        joined("pos_diag", k),
    )


def moved(obj: T, device: torch.device) -> T:
    """A copy of the dataclass ``obj`` whose tensor fields are on ``device``; fields that are
    dataclasses, or tuples of them, are moved the same way, the others kept (sizes, ranges).
    The topology's layouts (degree groups, gather plans) are computed once on the CPU and
    moved whole to each device they are used on."""
    changes = {
        field.name: _moved_value(getattr(obj, field.name), device)
        for field in dataclasses.fields(obj)  # type: ignore[arg-type]
    }
    return dataclasses.replace(obj, **changes)  # type: ignore[type-var]


def _moved_value(value: Any, device: torch.device) -> Any:
    if isinstance(value, torch.Tensor):
        return value.to(device)
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return moved(value, device)
    if isinstance(value, tuple):
        return tuple(_moved_value(v, device) for v in value)
    return value

"""Building a :class:`~torch_polylap.topology.Topology` from faces: one sort of all corner pairs.

The keys ``lo * V + hi`` of every corner pair of every face are sorted once; their unique values
are the off-diagonal pattern of ``L``, their inverse permutation the scatter positions of every
per-face entry, and the pairs that half-edges use are the mesh's undirected edges.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import torch

from ..checks import warn_outside_package
from ..faces import FacesLike, PolygonFaces, as_faces
from .analysis import _analyse
from .groups import (
    DegreeGroup,
    _check_simple_faces,
    _chunks,
    _cycle_pair_rows,
    _degree_block,
    _DegreeBlock,
    _write_pair_keys,
)
from .structure import Topology

# A face of degree k contributes k (k - 1) / 2 corner pairs to the pattern, each costing about
# _BYTES_PER_PAIR bytes while the topology is built (keys, sort permutation, inverse, scatter
# positions) and a dense k x k block of L. Faces above MAX_FACE_PAIRS pairs (k > 8192) are
# refused with the memory they would need instead of a MemoryError deep inside numpy; raise it
# if you have the memory.
MAX_FACE_PAIRS = 1 << 25
_BYTES_PER_PAIR = 100
# Keys packed with their positions per step of _sort_keys (512 KiB of int64: stays in L2)
_PACK_STEP = 1 << 16


def _private_copy(faces: FacesLike) -> PolygonFaces:
    """``faces`` as a CPU :class:`PolygonFaces` of its own memory: the topology is cached and
    outlives the call, so it must neither see later in-place edits of the caller's tensor nor
    keep that tensor alive (a view would)."""
    pf = as_faces(faces)
    cpu = pf if pf.device.type == "cpu" else pf.to("cpu")
    # numpy copies: numpy asks for huge pages, which first touch far faster at this size
    return PolygonFaces(
        torch.from_numpy(cpu.indices.numpy().copy()), offsets=cpu.offsets.numpy().copy()
    )


def _pair_keys(blocks: list[_DegreeBlock], nv: np.int64) -> np.ndarray:
    """The keys ``lo * V + hi`` of every block's corner pairs, block after block."""
    all_keys = np.empty(sum(pi.size * fid.size for _, fid, _, pi, _ in blocks), np.int64)
    start = 0
    for _, fid, corners_t, pi, pj in blocks:
        stop = start + pi.size * fid.size
        _write_pair_keys(corners_t, pi, pj, nv, all_keys[start:stop])
        start = stop
    return all_keys


def build_topology(
    faces: FacesLike, num_verts: int | None = None, *, warn: bool = True
) -> Topology:
    """Check ``faces`` and precompute the Laplacian's sparsity pattern and scatter maps.

    Works on any set of simple polygons (see the module docstring); what keeps the mesh from
    being a consistently oriented manifold is recorded in :attr:`Topology.report` and, with
    ``warn=True``, summarized in one ``UserWarning``.

    Args:
        faces: any form accepted by :func:`torch_polylap.as_faces`.
        num_verts: number of vertices ``V``; defaults to ``max index + 1``.
        warn: emit the warning for a non-clean mesh.

    Raises:
        ValueError: an index out of range, a vertex repeated within a face, or a face of so
            high a degree that indexing its ``k (k - 1) / 2`` corner pairs exceeds
            :data:`MAX_FACE_PAIRS`. The message names the face and the vertex.
    """
    own = _private_copy(faces)
    idx, sizes, offsets = own.indices.numpy(), own.sizes.numpy(), own.offsets.numpy()
    if num_verts is None:
        num_verts = int(idx.max()) + 1 if idx.size else 0
    num_verts = int(num_verts)
    _check_index_range(idx, offsets, num_verts)
    _check_face_size(sizes)
    nv = np.int64(max(num_verts, 1))

    # One block per degree; inside a block every per-pair array is laid out (P, F_k), the
    # layout in which the kernels produce the per-face entries.
    degrees = _degrees(sizes)
    uniform = len(degrees) == 1
    blocks = [_degree_block(k, idx, sizes, offsets, uniform=uniform) for k in degrees]
    ulo, uhi, inv = _unique_pairs(_pair_keys(blocks, nv), nv)  # the keys freed on return
    if bool((ulo == uhi).any()):  # a face visits a vertex twice: find and name it
        for _, fid, corners_t, pi, pj in blocks:
            _check_simple_faces(corners_t, fid, pi, pj)
    crow, col, pos_up_u, pos_low_u, pos_diag_v = _symmetric_pattern(ulo, uhi, num_verts)

    groups = []
    # pair id of every half-edge, in packed order; int64: numpy would widen an int32 index
    # array into a fresh (N,) int64 copy for each bincount and gather that reads it
    he_pair = np.empty(idx.size, np.int64)
    start = 0
    for k, fid, corners_t, pi, pj in blocks:
        ginv = inv[start : start + pi.size * fid.size].reshape(pi.size, fid.size)
        start += pi.size * fid.size
        groups.append(
            DegreeGroup(
                k=k,
                face_ids=torch.from_numpy(fid),
                corners_t=torch.from_numpy(corners_t),
                pair_i=torch.from_numpy(pi),
                pair_j=torch.from_numpy(pj),
                chunks=_chunks(k, corners_t, ginv, pos_up_u, pos_low_u, pos_diag_v),
            )
        )
        if len(blocks) == 1:  # packed order is the transpose of the (k, F) layout
            he_pair.reshape(-1, k)[...] = ginv[_cycle_pair_rows(k)].T
        else:
            he_pair[offsets[fid][None, :] + np.arange(k)[:, None]] = ginv[_cycle_pair_rows(k)]

    edges, edge_uses, he_edge = _edges(he_pair, ulo, uhi)

    valence = np.bincount(idx, minlength=num_verts)
    report = _analyse(
        own, num_verts, edges, edge_uses, he_edge, valence, degree=degrees[0] if uniform else None
    )
    if warn and not report.is_clean:
        warn_outside_package(
            f"the mesh ({num_verts} vertices, {sizes.size} faces) is not a consistently oriented "
            f"2-manifold: {report.summary(num_verts)}. L and M0 are well defined on it; what "
            "needs a manifold or an orientation checks for itself. Inspect Topology.report; "
            "repairs (orient_faces, remove_duplicate_faces, remove_unreferenced_vertices, ...) "
            "are in torch_polylap.repair."
        )
    pattern = (torch.from_numpy(crow), torch.from_numpy(col))
    return Topology(
        own,
        num_verts,
        groups,
        pattern,
        (edges, edge_uses, he_edge),
        torch.from_numpy(valence == 0),
        report,
    )


def _unique_pairs(keys: np.ndarray, nv: np.int64) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The distinct pairs among the ``(n,)`` keys ``lo * nv + hi``, by one sort.

    ``keys`` is used as a work buffer (its content is lost).

    Returns:
        ``ulo``, ``uhi`` ``(U,)`` int64, the distinct pairs sorted by ``(lo, hi)``, and
        ``inv`` ``(n,)``, the index of every key's pair, int32 where ``n`` allows (half the
        memory of a buffer that lives through the group building; its running count, the
        cumsum, is several times cheaper into int32 than into fresh int64 pages).
    """
    perm, sk = _sort_keys(keys, nv)
    new = np.empty(sk.size, bool)
    new[:1] = True
    np.not_equal(sk[1:], sk[:-1], out=new[1:])
    itype = np.int32 if sk.size < 2**31 else np.int64
    uid = np.cumsum(new, dtype=itype)
    uid -= 1
    inv = np.empty(sk.size, itype)
    inv[perm] = uid
    del perm, uid
    ukeys = sk[np.flatnonzero(new)]
    del sk, new
    ulo = ukeys // nv  # (numpy divides by a scalar with multiplications; divmod does not)
    uhi = ulo * nv
    np.subtract(ukeys, uhi, out=uhi)
    return ulo, uhi, inv


def _sort_keys(keys: np.ndarray, nv: np.int64) -> tuple[np.ndarray, np.ndarray]:
    """``(perm, sorted_keys)``, both ``(n,)`` int64, of the keys ``lo * nv + hi < nv^2``.

    Where ``nv^2 * n`` fits in int64, each key takes its position in its low bits and the
    packed values are sorted in place: a direct sort, faster than ``argsort``'s indirect one,
    that yields the permutation and the sorted keys without a gather (and without two fresh
    ``(n,)`` buffers). ``keys`` is the work buffer; it ends up holding the sorted keys.
    """
    n = keys.size
    bits = max(n - 1, 0).bit_length()
    # Stable sort (timsort) exploits the long sorted runs that face-ordered keys contain; on
    # structured meshes it is an order of magnitude faster than quicksort.
    if int(nv) ** 2 > 1 << (63 - bits):
        # Ties need no order: equal keys get the same pair index whatever their order.
        perm = np.argsort(keys, kind="stable")
        return perm, keys[perm]
    for s in range(0, n, _PACK_STEP):  # in cache-sized steps: one pass over memory
        part = keys[s : s + _PACK_STEP]
        part <<= bits
        part |= np.arange(s, s + part.size, dtype=np.int64)
    keys.sort(kind="stable")
    perm = keys & np.int64((1 << bits) - 1)
    keys >>= bits
    return perm, keys


def _edges(
    he_pair: np.ndarray, ulo: np.ndarray, uhi: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Undirected edges: the pairs some half-edge uses, renumbered densely.

    Args:
        he_pair: ``(N,)`` the pair of every half-edge.
        ulo, uhi: ``(U,)`` the pairs.

    Returns:
        ``edges`` ``(E, 2)``, ``edge_uses`` ``(E,)`` (half-edges on each edge) and ``he_edge``
        ``(N,)`` (the edge of every half-edge), all int64.
    """
    uses_pair = np.bincount(he_pair, minlength=ulo.size)
    is_edge = uses_pair > 0
    edge_pairs = np.flatnonzero(is_edge)
    edges = np.empty((edge_pairs.size, 2), np.int64)
    edges[:, 0] = ulo[edge_pairs]
    edges[:, 1] = uhi[edge_pairs]
    edge_of_pair = np.cumsum(is_edge, dtype=np.int64)
    edge_of_pair -= 1
    return edges, uses_pair[edge_pairs], edge_of_pair[he_pair]


def _symmetric_pattern(
    ulo: np.ndarray, uhi: np.ndarray, num_verts: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The CSR pattern of the symmetric ``V x V`` matrix whose off-diagonal entries are the
    ``U`` pairs ``(ulo, uhi)``, ``ulo < uhi``, sorted by ``(lo, hi)``, and their mirrors.

    Row ``p`` holds its lower pairs (``q < p``), the diagonal, then its upper pairs (``q > p``),
    so every row comes out sorted by column.

    Returns:
        ``crow`` ``(V + 1,)``, ``col`` ``(2 U + V,)``, and where each pair ``(U,)``, its mirror
        ``(U,)`` and each diagonal entry ``(V,)`` land in ``col``; all int64.
    """
    n_unique, v = ulo.size, np.arange(num_verts, dtype=np.int64)
    u = np.arange(n_unique, dtype=np.int64)
    up_ptr = np.zeros(num_verts + 1, np.int64)
    np.cumsum(np.bincount(ulo, minlength=num_verts), out=up_ptr[1:])
    # The pairs are the CSR rows of the upper triangle; its transpose (scipy's counting sort,
    # O(U + V)) lists the mirrors column by column with rows ascending: the (hi, lo) order,
    # without a second comparison sort.
    upper = sp.csr_matrix((u, uhi, up_ptr), shape=(num_verts, num_verts))
    lower = upper.tocsc()
    low_ptr = lower.indptr.astype(np.int64)
    crow = up_ptr + low_ptr + np.arange(num_verts + 1, dtype=np.int64)
    pos_diag_v = crow[:-1] + np.diff(low_ptr)
    pos_up_u = (pos_diag_v + 1 - up_ptr[:-1])[ulo]
    pos_up_u += u
    # the mirrors in (hi, lo) order land at consecutive places of their rows
    pos_low_sorted = np.repeat(crow[:-1] - low_ptr[:-1], np.diff(low_ptr))
    pos_low_sorted += u
    pos_low_u = np.empty(n_unique, np.int64)
    pos_low_u[lower.data] = pos_low_sorted
    col = np.empty(int(crow[-1]), np.int64)
    col[pos_up_u] = uhi
    col[pos_low_sorted] = lower.indices
    col[pos_diag_v] = v
    return crow, col, pos_up_u, pos_low_u, pos_diag_v


def _degrees(sizes: np.ndarray) -> list[int]:
    """The face degrees present, ascending: a min/max check for the usual one-degree mesh,
    else a count over the degrees (bounded by :func:`_check_face_size`), never a sort of all
    faces."""
    if sizes.size == 0:
        return []
    lo, hi = int(sizes.min()), int(sizes.max())
    if lo == hi:
        return [lo]
    return (np.flatnonzero(np.bincount(sizes - lo)) + lo).tolist()


def _check_index_range(idx: np.ndarray, offsets: np.ndarray, num_verts: int) -> None:
    if idx.size == 0 or (int(idx.min()) >= 0 and int(idx.max()) < num_verts):
        return  # two reductions; the full comparison only to name the first bad index
    bad = np.flatnonzero((idx < 0) | (idx >= num_verts))
    if bad.size:
        c = int(bad[0])
        f = int(np.searchsorted(offsets, c, side="right") - 1)
        raise ValueError(
            f"face {f} refers to vertex {int(idx[c])}, but the mesh has {num_verts} vertices "
            f"(valid indices are 0..{num_verts - 1}). Faces must use 0-based indices into verts; "
            "negative indices are not accepted."
        )


def _check_face_size(sizes: np.ndarray) -> None:
    """Refuse a face whose corner pairs would not fit in memory, before allocating them."""
    if sizes.size == 0:
        return
    f = int(np.argmax(sizes))
    k = int(sizes[f])
    pairs = k * (k - 1) // 2
    if pairs > MAX_FACE_PAIRS:
        raise ValueError(
            f"face {f} has degree {k}: indexing its k (k - 1) / 2 = {pairs:,} corner pairs "
            f"would need about {pairs * _BYTES_PER_PAIR / 2**30:.1f} GiB, and L would hold a "
            f"dense {k} x {k} block for it. Split the face into smaller polygons (a fan of "
            "triangles or quads), or raise torch_polylap.topology.build.MAX_FACE_PAIRS "
            f"(now {MAX_FACE_PAIRS:,}) if you have that memory."
        )

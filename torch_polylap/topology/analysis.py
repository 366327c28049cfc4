"""Connectivity analysis on the packed faces: half-edges, twins, fans, orientation, duplicates.

Everything runs vectorized in numpy on the CPU: walks around all vertices at once (pointer
doubling where a vertex is busy) for the fans, one ``connected_components`` on a doubled face
graph for orientations, one lexicographic sort per degree for duplicated faces.
:func:`~torch_polylap.topology.build_topology` calls :func:`_analyse` on every mesh; the repairs
(:mod:`torch_polylap.repair`) call the public functions here directly.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import numpy as np
import scipy.sparse as sp
import torch
from scipy.sparse.csgraph import connected_components

from ..faces import FacesLike, PolygonFaces, as_faces
from .report import TopologyReport


class OrientationFlips(NamedTuple):
    """What :func:`orientation_flips` finds; unpacks as ``flip, non_orientable, component``."""

    flip: np.ndarray
    """``(F,)`` bool: reverse these faces."""
    non_orientable: np.ndarray
    """``(F,)`` bool: faces in a component without a consistent orientation."""
    component: np.ndarray
    """``(F,)`` int64: a component label per face (not consecutive)."""


class EdgeIncidence(NamedTuple):
    """The edges of faces; unpacks as ``edges, uses, he_edge``."""

    edges: np.ndarray
    """``(E, 2)`` int64 sorted pairs ``p < q``."""
    uses: np.ndarray
    """``(E,)`` int64 how many half-edges lie on each edge."""
    he_edge: np.ndarray
    """``(N,)`` int64 the edge of every half-edge (packed order)."""


def half_edge_vertices(faces: PolygonFaces) -> tuple[torch.Tensor, torch.Tensor]:
    """``(src, dst)``, each ``(N,)``: half-edge ``h`` runs from corner ``h`` to the next corner."""
    return faces.indices, faces.indices[faces.next_corner]


# -- what the report finds -------------------------------------------------------------------


def _analyse(
    faces: PolygonFaces,
    num_verts: int,
    edges: np.ndarray,
    edge_uses: np.ndarray,
    he_edge: np.ndarray,
    valence: np.ndarray,
    degree: int | None = None,
) -> TopologyReport:
    """The :class:`TopologyReport` of a mesh, O(N) for a clean one (``N`` corners).

    The costlier searches (a graph over corners for non-manifold vertices, orientability,
    duplicates) run only when a cheap test has already found a defect. ``faces`` is on the CPU;
    ``degree``: the degree of every face when all have the same one (then no corner maps are
    built for a clean mesh), else ``None``.
    """
    idx = faces.indices.numpy()
    cycle = _CornerCycle(faces, degree)
    forward = cycle.less_than_next(idx)
    heavy = edge_uses > 2
    twin = None if heavy.any() else _oriented_twins(forward, he_edge, edge_uses)
    non_orientable, dups = 0, np.zeros(0, np.int64)
    if twin is None:  # a non-manifold or a misoriented edge
        fwd_count = np.bincount(he_edge[forward], minlength=edge_uses.size)
        misoriented = (edge_uses == 2) & (fwd_count != 1)
        nxt = faces.next_corner.numpy()
        bad_vertex = _fan_counts_general(idx, nxt, forward, he_edge, edge_uses, num_verts) > 1
        # a misoriented edge's faces are stored as (p, q) = the direction both traverse
        mis = edges[misoriented]
        both_back = fwd_count[misoriented] == 0
        mis[both_back] = mis[both_back][:, ::-1]
        if misoriented.any():
            he_face = faces.corner_face.numpy()
            _, bad_face, comp = _orientation(nxt, forward, he_face, he_edge, edge_uses)
            non_orientable = int(np.unique(comp[bad_face]).size)
        dups = duplicate_faces(faces)[0]
    else:
        bad_vertex = _multi_fan_vertices_oriented(idx, cycle.prev_of, twin, valence)
        mis = np.zeros((0, 2), np.int64)
        del twin
    bad_vertex[edges[heavy].reshape(-1)] = True
    return TopologyReport(
        non_manifold_edges=edges[heavy],
        non_manifold_vertices=np.flatnonzero(bad_vertex),
        misoriented_edges=mis,
        non_orientable_components=non_orientable,
        duplicate_faces=dups,
        isolated_vertices=np.flatnonzero(valence == 0),
    )


class _CornerCycle:
    """Per-corner values compared with, or moved from, the neighbouring corners of the same
    face: ``prev_of(a)[c] == a[prev_corner[c]]``, ``less_than_next(a)[c] == a[c] < a[next]``.

    With one degree ``k`` for all faces these are shifts of the packed array with every face's
    wrap-around patched by a strided slice: no ``(N,)`` corner maps, no gather.
    """

    def __init__(self, faces: PolygonFaces, degree: int | None) -> None:
        self.faces = faces
        self.k = degree

    def less_than_next(self, a: np.ndarray) -> np.ndarray:
        """``(N,)`` bool, each corner's value below the next corner's."""
        k = self.k
        if k is None:
            return a < a[self.faces.next_corner.numpy()]
        out = np.empty(a.shape, bool)
        np.less(a[:-1], a[1:], out=out[:-1])
        np.less(a[k - 1 :: k], a[::k], out=out[k - 1 :: k])
        return out

    def prev_of(self, a: np.ndarray) -> np.ndarray:
        k = self.k
        if k is None:
            return a[self.faces.prev_corner.numpy()]
        out = np.empty_like(a)
        out[1:] = a[:-1]
        out[::k] = a[k - 1 :: k]
        return out


def _twins(he_edge: np.ndarray, edge_uses: np.ndarray, itype: type = np.int64) -> np.ndarray:
    """``(N,)`` the other half-edge on the same edge where the edge has two, else negative.

    The two half-edges of an edge sum to a per-edge total, so each twin is that total minus
    itself: one ``bincount``, no sort. (Exact: float64 holds integers below 2^53.) Edges with
    another number of half-edges get a total of ``-N``, which leaves every result negative.
    """
    n = he_edge.size
    total = np.bincount(he_edge, weights=np.arange(n, dtype=np.float64), minlength=edge_uses.size)
    total[edge_uses != 2] = -n
    twin = total.astype(itype)[he_edge]
    twin -= np.arange(n, dtype=itype)
    return twin


def _oriented_twins(
    forward: np.ndarray, he_edge: np.ndarray, edge_uses: np.ndarray
) -> np.ndarray | None:
    """:func:`_twins` (int32 where ``N`` allows) if no edge used by two half-edges has both
    running the same way (``forward`` ``(N,)``: each half-edge runs to a higher vertex), else
    ``None``.

    On a mesh without non-manifold edges this replaces a count of forward half-edges per edge:
    the fan walk needs the twins anyway, and a gather of ``forward`` through them is cheaper.
    """
    n = he_edge.size
    twin = _twins(he_edge, edge_uses, np.int32 if n < 2**31 - 1 else np.int64)
    same_way = twin >= 0
    same_way &= forward == forward.take(twin, mode="clip")  # (clip: unpaired ones are masked)
    return None if same_way.any() else twin


# Vertices with at most this many corners are checked by walking their fan (one vectorized
# step per corner of the busiest vertex); meshes with busier vertices use pointer doubling.
MAX_WALK_VALENCE = 32


def _multi_fan_vertices_oriented(
    idx: np.ndarray,
    prev_of: Callable[[np.ndarray], np.ndarray],
    twin: np.ndarray,
    valence: np.ndarray,
) -> np.ndarray:
    """``(V,)`` bool: vertices whose faces form more than one fan (maximal run of faces linked
    by shared edges), for a mesh whose edges are manifold and consistently oriented.

    ``valence`` ``(V,)`` counts the corners at each vertex; ``prev_of`` moves per-corner values
    to the previous corner (:meth:`_CornerCycle.prev_of`); ``twin`` ``(N,)`` int32 or int64
    is :func:`_twins`.

    Around a vertex, corner ``c`` continues to the corner where the twin of its incoming
    half-edge starts, so every vertex's corners form paths (open fans) and cycles (closed
    fans). A corner whose outgoing half-edge has no twin starts a path. The walk from one
    path start of a vertex (from any corner if it has none) visits all its corners before it
    ends or comes back exactly when they form one fan. The walks advance all vertices
    together, one step per round, dropping finished ones: O(N) work in ``max valence`` rounds,
    so above :data:`MAX_WALK_VALENCE` pointer doubling (O(N log valence) in
    ``log2(max valence)`` rounds) takes over.
    """
    n = idx.size
    itype = twin.dtype
    pos = np.arange(n, dtype=itype)
    succ = prev_of(twin)
    np.copyto(succ, pos, where=succ < 0)  # a path's last corner continues to itself
    max_valence = int(valence.max()) if n else 1
    if max_valence > MAX_WALK_VALENCE:
        return _fan_counts_doubling(idx, pos, succ, max_valence, valence.size) > 1
    opens = np.flatnonzero(twin < 0).astype(itype)
    start = np.empty(valence.size, itype)
    start[idx] = pos  # any corner of each vertex; then a path start where it has one
    start[idx[opens]] = opens
    bad = np.zeros(valence.size, bool)
    verts = np.flatnonzero(valence > 1)
    first = start[verts]
    cur, left = first, valence[verts] - 1  # steps that must all reach a new corner
    while verts.size:
        nxt = succ[cur]
        short = (nxt == cur) | (nxt == first)
        short &= left > 0  # walks already done ride along until the next compaction
        bad[verts[short]] = True
        left -= 1
        left[short] = 0
        n_live = np.count_nonzero(left > 0)
        if n_live < verts.size - verts.size // 8:  # compact once an eighth has finished
            go = left > 0
            verts, first, nxt, left = verts[go], first[go], nxt[go], left[go]
        cur = nxt
    return bad


def _fan_counts_doubling(
    idx: np.ndarray, pos: np.ndarray, succ: np.ndarray, max_valence: int, num_verts: int
) -> np.ndarray:
    """``(V,)`` fans per vertex from the corner successors ``succ`` (``succ[c] == c`` ends a
    path): pointer doubling labels each path by its last corner and each cycle by its smallest
    corner in ``ceil(log2(max valence))`` rounds."""
    rounds = (max_valence - 1).bit_length()  # doubling rounds, not corners
    jump, low = succ, pos
    if rounds:  # the first round gathers nothing: low[succ] is succ while low is pos
        low = np.minimum(pos, succ)
        jump = succ[succ]
    for _ in range(rounds - 1):
        np.minimum(low, low[jump], out=low)
        jump = jump[jump]
    label = np.where(succ[jump] == jump, jump, low)
    return np.bincount(idx[label == pos], minlength=num_verts)


def _fan_counts_general(
    idx: np.ndarray,
    nxt: np.ndarray,
    forward: np.ndarray,
    he_edge: np.ndarray,
    edge_uses: np.ndarray,
    num_verts: int,
) -> np.ndarray:
    """``(V,)`` fans per vertex on any mesh: components of the graph linking the two corners
    at each end of every edge used by two faces (O(N) connected components; only run when
    the mesh already has a non-manifold or misoriented edge)."""
    twin = _twins(he_edge, edge_uses)
    h = np.flatnonzero(twin >= 0)
    t = twin[h]
    same = forward[h] == forward[t]
    # corners at the tail of h and at its head, in h's face and in its twin's face
    at_tail = np.where(same, t, nxt[t])
    at_head = np.where(same, nxt[t], t)
    n = idx.size
    graph = sp.coo_matrix(
        (
            np.ones(2 * h.size, np.int8),
            (np.concatenate([h, nxt[h]]), np.concatenate([at_tail, at_head])),
        ),
        shape=(n, n),
    )
    _, label = connected_components(graph.tocsr(), directed=False)
    first = np.unique(label, return_index=True)[1]
    return np.bincount(idx[first], minlength=num_verts)


def _orientation(
    nxt: np.ndarray,
    forward: np.ndarray,
    he_face: np.ndarray,
    he_edge: np.ndarray,
    edge_uses: np.ndarray,
) -> OrientationFlips:
    """See :func:`orientation_flips`."""
    num_faces = int(he_face[-1]) + 1 if he_face.size else 0
    twin = _twins(he_edge, edge_uses)
    h = np.flatnonzero(twin > np.arange(twin.size))  # each interior edge once
    t = twin[h]
    f, g = he_face[h], he_face[t]
    must_differ = forward[h] == forward[t]
    # Signed graph on faces, solved as plain connectivity on a doubled graph: node f is "f as
    # is", node F + f is "f flipped". An edge traversed both ways links f~g and F+f~F+g (same
    # choice); one traversed the same way links f~F+g and F+f~g (opposite choices).
    shift = np.where(must_differ, num_faces, 0)
    rows = np.concatenate([f, f + num_faces])
    cols = np.concatenate([g + shift, (g + num_faces + shift) % (2 * num_faces)])
    m = 2 * num_faces
    graph = sp.coo_matrix((np.ones(rows.size, np.int8), (rows, cols)), shape=(m, m))
    _, label = connected_components(graph.tocsr(), directed=False)
    keep, flipped = label[:num_faces], label[num_faces:]
    non_orientable = keep == flipped
    component = np.minimum(keep, flipped)
    # Either half of the doubled component is a consistent choice: "flip where the flipped
    # copy has the smaller label" picks one, consistently (both faces of a must-differ edge
    # swap labels). Then flip the smaller side of every component.
    flip = flipped < keep
    n_flip = np.bincount(component, weights=flip, minlength=m)
    n_all = np.bincount(component, minlength=m)
    flip ^= (2 * n_flip > n_all)[component]
    flip &= ~non_orientable
    return OrientationFlips(flip, non_orientable, component)


def orientation_flips(faces: FacesLike, num_verts: int | None = None) -> OrientationFlips:
    """Which faces to reverse for a consistent orientation, per edge-connected component.

    Faces are linked across every edge used by exactly two faces (edges used by 3+ faces
    constrain nothing: no orientation makes them manifold).

    Returns:
        ``flip`` ``(F,)`` bool: reverse these faces (the smaller side of every orientable
        component, so a mostly oriented mesh changes little); ``non_orientable`` ``(F,)`` bool:
        faces in a component without a consistent orientation (left as they are);
        ``component`` ``(F,)`` int64: a component label per face (not consecutive).

    Complexity: O(N) for the half-edges plus one ``connected_components`` on a graph with
    ``2 F`` nodes and ``2 E_interior`` edges (linear in practice).
    """
    pf = as_faces(faces)
    idx, nxt, he_face = (t.cpu().numpy() for t in (pf.indices, pf.next_corner, pf.corner_face))
    edges, edge_uses, he_edge = edge_incidence(pf, num_verts)
    return _orientation(nxt, idx < idx[nxt], he_face, he_edge, edge_uses)


def edge_incidence(faces: FacesLike, num_verts: int | None = None) -> EdgeIncidence:
    """``(edges (E, 2), uses (E,), he_edge (N,))`` of any faces, by one sort of the half-edges.

    ``edges`` are sorted pairs ``p < q``, ``uses`` how many half-edges lie on each, ``he_edge``
    the edge of every half-edge (packed order). :func:`build_topology` gets the same arrays from
    its pair sort; this is the light version for repairs, which need no pattern.
    """
    pf = as_faces(faces)
    idx, nxt = pf.indices.cpu().numpy(), pf.next_corner.cpu().numpy()
    if idx.size == 0:
        none = np.zeros(0, np.int64)
        return EdgeIncidence(none.reshape(0, 2), none, none)
    nv = np.int64(max(int(idx.max()) + 1, num_verts or 0, 1))
    a, b = idx, idx[nxt]
    keys, he_edge, uses = np.unique(
        np.minimum(a, b) * nv + np.maximum(a, b), return_inverse=True, return_counts=True
    )
    lo = keys // nv
    return EdgeIncidence(
        np.stack([lo, keys - lo * nv], 1), uses.astype(np.int64), he_edge.reshape(-1)
    )


def duplicate_faces(faces: FacesLike) -> tuple[np.ndarray, np.ndarray]:
    """Faces that repeat an earlier face's vertex cycle, up to rotation and reflection.

    Each face is brought to a canonical cycle (start at its smallest vertex, continue towards
    the smaller neighbour), then equal rows are found by one lexicographic sort per degree.
    ``[0, 1, 2, 3]``, ``[2, 3, 0, 1]`` and ``[3, 2, 1, 0]`` are duplicates; ``[0, 2, 1, 3]`` (the
    same vertex set in another cycle, a different polygon) is not.

    Returns:
        ``(dup, first)``, each ``(n,)`` int64, sorted by ``dup``: the repeating faces and the
        lowest-indexed face each repeats.
    """
    pf = as_faces(faces)
    idx, sizes, offsets = (t.cpu().numpy() for t in (pf.indices, pf.sizes, pf.offsets))
    dup, first = [np.zeros(0, np.int64)], [np.zeros(0, np.int64)]
    for k in np.unique(sizes).tolist():  # one pass per degree
        fid = np.flatnonzero(sizes == k)
        rows = idx[offsets[fid][:, None] + np.arange(k)]
        canon = _canonical_cycles(rows)
        order = np.lexsort(canon.T[::-1])  # stable: equal rows stay in face order
        sc = canon[order]
        same = np.zeros(fid.size, bool)
        same[1:] = (sc[1:] == sc[:-1]).all(1)
        run_start = np.maximum.accumulate(np.where(same, 0, np.arange(fid.size)))
        dup.append(fid[order[same]])
        first.append(fid[order[run_start[same]]])
    d, f = np.concatenate(dup), np.concatenate(first)
    o = np.argsort(d)
    return d[o], f[o]


def _canonical_cycles(rows: np.ndarray) -> np.ndarray:
    """``(F, k)`` each row's cycle rotated to start at its minimum, in the direction of the
    smaller neighbour of that minimum."""
    f, k = rows.shape
    r = np.arange(f)[:, None]
    m = rows.argmin(1)[:, None]
    ar = np.arange(k)
    fwd = rows[r, (m + ar) % k]
    bwd = rows[r, (m - ar) % k]
    return np.where((fwd[:, 1] <= bwd[:, 1])[:, None], fwd, bwd)

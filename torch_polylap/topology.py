"""Everything about a polygon mesh that depends only on its faces, computed once and cached.

:class:`Topology` checks the connectivity and precomputes what every later assembly of ``L``
reuses: faces grouped by degree, the half-edges and undirected edges, the boundary, the CSR
sparsity pattern of ``L`` and, for each per-face matrix entry, its position in ``L``'s value
array.  Assembling ``L`` for new vertex positions is then pure arithmetic plus one scatter onto
this fixed pattern.

``L = sum_f P_f^T L_f P_f`` and ``M0`` are sums of per-face blocks (AW11 eq. 3, 10) that depend
neither on the face's orientation (reversing the corner order leaves ``L_f`` unchanged) nor on
how faces meet, so the pattern and the scatter map are built for *any* set of simple polygons:
non-manifold edges and vertices, inconsistent or impossible orientation (a Moebius band),
duplicated faces and several components are recorded in :attr:`Topology.report` and announced
by one ``UserWarning``, not refused.  Only what needs a manifold or an orientation (half-edge
twins, boundary loops) checks at its own entry, through :meth:`Topology.require_manifold` and
:meth:`Topology.require_oriented`, and says which repair to run (:mod:`torch_polylap.repair`).
Hard errors remain for what no polygon mesh can have: an index out of range, a face that visits
a vertex twice, a face too large to index.

:func:`get_topology` caches topologies in one bounded, weakly keyed cache (see
:class:`_TopologyCache`), shared by the functional API and :class:`PolygonLaplacian`.

The index work runs in numpy on the CPU (its ``argsort`` is several times faster than
``torch.sort`` there); the resulting index tensors are copied to each device once, on demand.
"""

from __future__ import annotations

import os
import sys
import threading
import warnings
import weakref
import zlib
from collections import OrderedDict
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
import torch
from scipy.sparse.csgraph import connected_components, depth_first_order

from .faces import FacesLike, PolygonFaces, as_faces
from .sparse import SparsityPattern

__all__ = [
    "Topology",
    "TopologyReport",
    "DegreeGroup",
    "GroupChunk",
    "build_topology",
    "get_topology",
    "clear_topology_cache",
    "set_topology_cache_limits",
    "duplicate_faces",
    "orientation_flips",
    "edge_incidence",
    "half_edge_vertices",
]

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
        return GroupChunk(
            self.start,
            self.stop,
            *(
                t.to(device)
                for t in (self.corners_t, self.pos_upper, self.pos_lower, self.pos_diag)
            ),
        )


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
        return DegreeGroup(
            self.k,
            self.face_ids.to(device),
            self.corners_t.to(device),
            self.pair_i.to(device),
            self.pair_j.to(device),
            tuple(c.to(device) for c in self.chunks),
        )


# A face of degree k contributes k (k - 1) / 2 corner pairs to the pattern, each costing about
# _BYTES_PER_PAIR bytes while the topology is built (keys, sort permutation, inverse, scatter
# positions) and a dense k x k block of L. Faces above MAX_FACE_PAIRS pairs (k > 8192) are
# refused with the memory they would need instead of a MemoryError deep inside numpy; raise it
# if you have the memory.
MAX_FACE_PAIRS = 1 << 25
_BYTES_PER_PAIR = 100

# Index tensors up to this many elements get a CRC32 in the cache stamp (about 3 ms per 2^20
# int64 entries), which catches edits through a numpy array sharing their memory; larger ones
# rely on the tensor version counter alone (see get_topology).
CHECKSUM_MAX_ELEMENTS = 1 << 20

# How many of the first offending elements the warning and the error messages list.
_SHOW = 5


@dataclass(frozen=True)
class TopologyReport:
    """What a mesh has that a consistently oriented 2-manifold would not.

    None of it changes ``L`` or ``M0``; it matters to what needs a manifold or an orientation
    (half-edge twins, boundary loops, normals of neighbouring faces).  All arrays are numpy
    int64 and sorted.

    Attributes:
        non_manifold_edges: ``(n, 2)`` vertex pairs ``p < q`` used as an edge by 3+ faces.
        non_manifold_vertices: ``(n,)`` vertices whose faces do not form one fan (two cones
            touching at their tips, two sheets sharing one vertex), plus the endpoints of
            non-manifold edges.
        misoriented_edges: ``(n, 2)`` edges ``(p, q)`` whose two faces both traverse
            ``p -> q`` (one of them is flipped relative to the other).
        non_orientable_components: number of components (faces connected through edges used
            by two faces) that admit no consistent orientation, e.g. a Moebius band. Searched
            only when misoriented edges exist (an oriented mesh is orientable).
        duplicate_faces: ``(n,)`` faces repeating the vertex cycle of an earlier face, up to
            rotation and reflection. Searched only when the mesh has non-manifold or
            misoriented edges, which every duplicate creates except one: a lone face and its
            reverse, a closed two-face "pillow", which is a valid manifold.
        isolated_vertices: ``(n,)`` vertices used by no face (zero mass, empty rows of ``L``).
    """

    non_manifold_edges: np.ndarray
    non_manifold_vertices: np.ndarray
    misoriented_edges: np.ndarray
    non_orientable_components: int
    duplicate_faces: np.ndarray
    isolated_vertices: np.ndarray

    @property
    def is_manifold(self) -> bool:
        """No non-manifold edge or vertex."""
        return self.non_manifold_edges.size == 0 and self.non_manifold_vertices.size == 0

    @property
    def is_oriented(self) -> bool:
        """Every edge used by two faces is traversed in opposite directions."""
        return self.misoriented_edges.size == 0

    @property
    def is_clean(self) -> bool:
        """Manifold, oriented, no duplicated face, no isolated vertex."""
        return (
            self.is_manifold
            and self.is_oriented
            and self.duplicate_faces.size == 0
            and self.isolated_vertices.size == 0
        )

    def lines(self, num_verts: int | None = None) -> list[str]:
        """One line per finding: what, how many, the first few by index."""
        out = []
        if self.non_manifold_edges.size:
            out.append(
                f"{len(self.non_manifold_edges)} non-manifold edge(s) used by 3+ faces "
                f"(first: {_first(self.non_manifold_edges)})"
            )
        if self.non_manifold_vertices.size:
            out.append(
                f"{self.non_manifold_vertices.size} non-manifold vertex(es) "
                f"(first: {_first(self.non_manifold_vertices)})"
            )
        if self.misoriented_edges.size:
            out.append(
                f"{len(self.misoriented_edges)} edge(s) traversed in the same direction by both "
                f"faces, i.e. inconsistent orientation (first: {_first(self.misoriented_edges)})"
            )
        if self.non_orientable_components:
            out.append(
                f"{self.non_orientable_components} non-orientable component(s) "
                "(e.g. a Moebius band)"
            )
        if self.duplicate_faces.size:
            out.append(
                f"{self.duplicate_faces.size} duplicated face(s) (first: "
                f"{_first(self.duplicate_faces)})"
            )
        if self.isolated_vertices.size:
            of = "" if num_verts is None else f" of {num_verts}"
            out.append(
                f"{self.isolated_vertices.size}{of} vertices belong to no face "
                f"(first: {_first(self.isolated_vertices)}); they get zero mass and empty rows "
                "in L"
            )
        return out

    def summary(self, num_verts: int | None = None) -> str:
        """The findings in one paragraph (empty for a clean mesh)."""
        return "; ".join(self.lines(num_verts))


def _first(a: np.ndarray) -> list:
    return a[:_SHOW].tolist()


class Topology:
    """Connectivity of a polygon mesh and the cached sparsity pattern of its Laplacian.

    Build it with :func:`build_topology` (or let :func:`torch_polylap.laplacian` and
    :class:`torch_polylap.PolygonLaplacian` build and cache it through :func:`get_topology`).

    Attributes:
        faces: the packed faces (CPU; a private copy, unaffected by later edits of the input).
        num_verts: ``V``; vertices never referenced by a face are *isolated*.
        groups: one :class:`DegreeGroup` per face degree present.
        crow, col: CSR pattern of the ``V x V`` Laplacian (sorted columns in every row).
        isolated: ``(V,)`` bool, vertices referenced by no face.
        report: :class:`TopologyReport`, what keeps the mesh from being a consistently
            oriented manifold (see :attr:`is_manifold`, :attr:`is_oriented`).
    """

    def __init__(
        self,
        faces: PolygonFaces,
        num_verts: int,
        groups: list[DegreeGroup],
        pattern: tuple[torch.Tensor, torch.Tensor],
        edge_data: tuple[np.ndarray, np.ndarray, np.ndarray],
        isolated: torch.Tensor,
        report: TopologyReport,
    ) -> None:
        self.faces = faces
        self.num_verts = num_verts
        self._groups_cpu = groups
        self.crow, self.col = pattern
        edges, uses, he_edge = edge_data
        self.edges = torch.from_numpy(edges)
        self.edge_faces = torch.from_numpy(uses)
        self.half_edge_edge = torch.from_numpy(he_edge)
        self.isolated = isolated
        self.report = report
        self._patterns: dict[torch.device, SparsityPattern] = {}
        self._device_cache: dict[torch.device, tuple] = {}
        self._row: torch.Tensor | None = None
        self._components: tuple[int, torch.Tensor] | None = None

    # -- what needs a manifold or an orientation ------------------------------------------

    @property
    def is_manifold(self) -> bool:
        """Every edge is used by at most two faces and the faces at every vertex form one fan."""
        return self.report.is_manifold

    @property
    def is_oriented(self) -> bool:
        """Every edge used by two faces is traversed in opposite directions by them."""
        return self.report.is_oriented

    def require_manifold(self, what: str, *, vertices: bool = True) -> None:
        """Raise a ValueError unless the mesh is manifold (``vertices=False``: edges only).

        Call it at the entry of anything that needs a manifold (twins, boundary loops).
        """
        r = self.report
        if r.non_manifold_edges.size or (vertices and r.non_manifold_vertices.size):
            found = [line for line in r.lines() if "non-manifold" in line]
            dup = (
                " Start with torch_polylap.repair.remove_duplicate_faces: the mesh has "
                f"{r.duplicate_faces.size} duplicated face(s)."
                if r.duplicate_faces.size
                else ""
            )
            raise ValueError(
                f"{what} needs a manifold mesh, but it has {'; '.join(found)}. L, M0 and "
                "everything built on them do not; for this, split the mesh at those edges and "
                f"vertices (duplicate their vertices per sheet).{dup}"
            )

    def require_oriented(self, what: str) -> None:
        """Raise a ValueError unless every edge used by two faces is traversed both ways."""
        r = self.report
        if r.is_oriented:
            return
        if r.non_orientable_components:
            raise ValueError(
                f"{what} needs an oriented mesh, but {r.non_orientable_components} of its "
                f"components cannot be oriented (a Moebius band, say; misoriented edges: "
                f"{_first(r.misoriented_edges)}). L and M0 work on it; this does not."
            )
        raise ValueError(
            f"{what} needs consistently oriented faces, but {len(r.misoriented_edges)} edge(s) "
            f"are traversed in the same direction by both their faces (first: "
            f"{_first(r.misoriented_edges)}). Run "
            "`verts, faces, rep = torch_polylap.repair.orient_faces(verts, faces)` first."
        )

    @property
    def half_edge_twin(self) -> torch.Tensor:
        """``(N,)`` the opposite half-edge of every half-edge, ``-1`` on the boundary.

        Needs manifold edges and a consistent orientation (:meth:`require_manifold`,
        :meth:`require_oriented`).
        """
        self.require_manifold("Topology.half_edge_twin", vertices=False)
        self.require_oriented("Topology.half_edge_twin")
        he_edge = self.half_edge_edge.numpy()
        twin = _twins(he_edge, self.edge_faces.numpy())
        return torch.from_numpy(np.maximum(twin, -1))

    def boundary_loops(self) -> list[torch.Tensor]:
        """The boundary loops, each a ``(n_i,)`` tensor of vertices in the faces' orientation.

        Needs a manifold, consistently oriented mesh: then every boundary vertex has exactly
        one outgoing boundary half-edge and the loops are well defined.
        """
        self.require_manifold("Topology.boundary_loops")
        self.require_oriented("Topology.boundary_loops")
        src, dst = (t.numpy() for t in half_edge_vertices(self.faces))
        on_boundary = self.edge_faces.numpy()[self.half_edge_edge.numpy()] == 1
        src, dst = src[on_boundary], dst[on_boundary]
        if src.size == 0:
            return []
        slot = np.empty(self.num_verts, np.int64)
        slot[src] = np.arange(src.size)
        succ = sp.csr_matrix(
            (np.ones(src.size), (np.arange(src.size), slot[dst])), shape=(src.size, src.size)
        )
        _, label = connected_components(succ, directed=False)
        starts = np.unique(label, return_index=True)[1]
        # one depth-first walk per loop (a handful of loops; each walk runs in C)
        return [
            torch.from_numpy(src[depth_first_order(succ, s, return_predecessors=False)])
            for s in starts.tolist()
        ]

    # -- connectivity that any mesh has ----------------------------------------------------

    @property
    def boundary_edges(self) -> torch.Tensor:
        """``(E_B, 2)`` edges used by exactly one face (defined on any mesh)."""
        return self.edges[self.edge_faces == 1]

    @property
    def boundary_vertices(self) -> torch.Tensor:
        """Sorted indices of the vertices on a boundary edge."""
        return torch.unique(self.boundary_edges)

    @property
    def num_edges(self) -> int:
        return self.edges.shape[0]

    @property
    def num_faces(self) -> int:
        return self.faces.num_faces

    def euler_characteristic(self) -> int:
        """``V - E + F`` counted over the vertices used by faces."""
        used = self.num_verts - int(self.isolated.sum())
        return used - self.num_edges + self.num_faces

    def connected_components(self) -> tuple[int, torch.Tensor]:
        """``(n, labels)``: components of the graph of ``L`` (vertices sharing a face), with
        every isolated vertex a component of its own; ``labels`` is ``(V,)``.

        ``n`` is the dimension of the kernel of ``L``.
        """
        if self._components is None:
            n = self.num_verts
            graph = sp.csr_matrix(
                (np.ones(self.nnz, np.int8), self.col.numpy(), self.crow.numpy()), shape=(n, n)
            )
            count, labels = connected_components(graph, directed=False)
            self._components = (int(count), torch.from_numpy(labels.astype(np.int64)))
        return self._components

    @property
    def row(self) -> torch.Tensor:
        """``(nnz,)`` row index of every stored entry (the COO pattern), built on first use."""
        if self._row is None:
            self._row = torch.repeat_interleave(torch.arange(self.num_verts), self.crow.diff())
        return self._row

    @property
    def nnz(self) -> int:
        return self.col.numel()

    @property
    def groups(self) -> list[DegreeGroup]:
        return self._groups_cpu

    @property
    def nbytes(self) -> int:
        """Approximate memory held by the topology's CPU arrays (for the cache's budget)."""
        tensors = [self.crow, self.col, self.edges, self.edge_faces, self.half_edge_edge]
        tensors += [self.faces.indices, self.faces.offsets]
        for g in self._groups_cpu:
            tensors += [g.face_ids, g.corners_t]
            for c in g.chunks:
                tensors += [c.corners_t, c.pos_upper, c.pos_lower, c.pos_diag]
        return sum(t.numel() * t.element_size() for t in tensors)

    def on(self, device: torch.device) -> tuple[list[DegreeGroup], torch.Tensor, torch.Tensor]:
        """``(groups, crow, col)`` on ``device``, copied there once and cached."""
        device = torch.device(device)
        if device.type == "cpu":
            return self._groups_cpu, self.crow, self.col
        if device not in self._device_cache:
            self._device_cache[device] = (
                [g.to(device) for g in self._groups_cpu],
                self.crow.to(device),
                self.col.to(device),
            )
        return self._device_cache[device]

    def pattern(self, device: torch.device) -> SparsityPattern:
        """The Laplacian's :class:`~torch_polylap.sparse.SparsityPattern` on ``device``: one
        object per device for the topology's lifetime, so the operators of every step share its
        cached transposes and unions (``M0 + t * L`` computes the union of patterns once)."""
        device = torch.device(device)
        if device not in self._patterns:
            _, crow, col = self.on(device)
            self._patterns[device] = SparsityPattern(crow, col, (self.num_verts, self.num_verts))
        return self._patterns[device]

    def __repr__(self) -> str:
        degs = ", ".join(f"{g.k}:{g.face_ids.numel()}" for g in self._groups_cpu)
        flags = "" if self.report.is_clean else f", report={self.report.lines()}"
        return (
            f"Topology(V={self.num_verts}, F={self.num_faces}, E={self.num_edges}, "
            f"boundary_edges={int((self.edge_faces == 1).sum())}, degrees={{{degs}}}, "
            f"nnz={self.nnz}{flags})"
        )


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
    pf = as_faces(faces)
    cpu = pf if pf.device.type == "cpu" else pf.to("cpu")
    # A private copy: the topology is cached and outlives the call, so it must neither see
    # later in-place edits of the caller's tensor nor keep that tensor alive (a view would).
    own = PolygonFaces(cpu.indices.clone(), offsets=cpu.offsets.clone())
    idx, sizes, offsets = own.indices.numpy(), own.sizes.numpy(), own.offsets.numpy()
    if num_verts is None:
        num_verts = int(idx.max()) + 1 if idx.size else 0
    num_verts = int(num_verts)
    _check_index_range(idx, offsets, num_verts)
    _check_face_size(sizes)
    nv = np.int64(max(num_verts, 1))

    # One block per degree; inside a block every per-pair array is laid out (P, F_k), the
    # layout in which the kernels produce the per-face entries.
    degrees = np.unique(sizes)
    blocks = [_degree_block(k, idx, sizes, offsets, degrees.size == 1) for k in degrees.tolist()]
    all_keys = np.empty(sum(pi.size * fid.size for _, fid, _, pi, _ in blocks), np.int64)
    start = 0
    for _, fid, corners_t, pi, pj in blocks:
        stop = start + pi.size * fid.size
        _write_pair_keys(corners_t, fid, pi, pj, nv, all_keys[start:stop])
        start = stop

    # Stable sort (timsort) exploits the long sorted runs that face-ordered keys contain; on
    # structured meshes it is an order of magnitude faster than quicksort.
    perm = np.argsort(all_keys, kind="stable")
    sk = all_keys[perm]
    new = np.ones(sk.size, bool)
    np.not_equal(sk[1:], sk[:-1], out=new[1:])
    uid = np.cumsum(new, dtype=np.int64)
    uid -= 1
    inv = np.empty_like(perm)
    inv[perm] = uid
    del perm, uid
    ukeys = sk[new]
    ulo = ukeys // nv
    uhi = ukeys - ulo * nv
    n_unique = ukeys.size

    # CSR pattern of the full symmetric matrix: row p holds its lower pairs (q < p), then the
    # diagonal, then its upper pairs (q > p), so every row comes out sorted by column.
    n_low = np.bincount(uhi, minlength=num_verts)
    n_up = np.bincount(ulo, minlength=num_verts)
    crow = np.zeros(num_verts + 1, np.int64)
    np.cumsum(n_low + n_up + 1, out=crow[1:])
    up_start = crow[:-1] + n_low + 1 - np.concatenate(([0], np.cumsum(n_up)[:-1]))
    u = np.arange(n_unique, dtype=np.int64)
    pos_up_u = up_start[ulo] + u
    # ukeys is sorted by (lo, hi), so a stable sort by hi alone orders the mirrors by (hi, lo).
    low_order = np.argsort(uhi, kind="stable")
    low_start = crow[:-1] - np.concatenate(([0], np.cumsum(n_low)[:-1]))
    pos_low_u = np.empty(n_unique, np.int64)
    pos_low_u[low_order] = low_start[uhi[low_order]] + u
    pos_diag_v = crow[:-1] + n_low
    col = np.empty(crow[-1], np.int64)
    col[pos_up_u] = uhi
    col[pos_low_u] = ulo
    col[pos_diag_v] = np.arange(num_verts)

    groups = []
    he_pair = np.empty(idx.size, np.int64)  # pair id of every half-edge, in packed order
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

    # Undirected edges: the pairs some half-edge uses, renumbered densely.
    uses_pair = np.bincount(he_pair, minlength=n_unique)
    is_edge = uses_pair > 0
    edge_of_pair = np.cumsum(is_edge) - 1
    edges = np.stack([ulo[is_edge], uhi[is_edge]], 1)
    he_edge = edge_of_pair[he_pair]
    edge_uses = uses_pair[is_edge]

    valence = np.bincount(idx, minlength=num_verts)
    report = _analyse(idx, offsets, sizes, num_verts, edges, edge_uses, he_edge, valence)
    if warn and not report.is_clean:
        _warn_outside_package(
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


def _degree_block(
    k: int, idx: np.ndarray, sizes: np.ndarray, offsets: np.ndarray, uniform: bool
) -> tuple[int, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``(k, face_ids (F_k,), corners_t (k, F_k), pair_i (P,), pair_j (P,))`` of one degree."""
    if uniform:
        fid = np.arange(sizes.size, dtype=np.int64)
        corners_t = np.ascontiguousarray(idx.reshape(-1, k).T)
    else:
        fid = np.flatnonzero(sizes == k).astype(np.int64)
        corners_t = idx[offsets[fid][None, :] + np.arange(k)[:, None]]
    pi, pj = np.triu_indices(k, 1)
    return k, fid, corners_t, pi.astype(np.int64), pj.astype(np.int64)


def _write_pair_keys(
    corners_t: np.ndarray,
    fid: np.ndarray,
    pi: np.ndarray,
    pj: np.ndarray,
    nv: np.int64,
    out: np.ndarray,
) -> None:
    """Fill ``out`` (``(P * F_k,)``, pair-major) with the keys ``lo * V + hi`` of every corner
    pair of every face, refusing a face that visits a vertex twice.

    Runs of pair rows are processed together so that every step touches about
    ``CHUNK_ELEMENTS`` entries: one row at a time for large groups (views, no temporaries),
    all pairs at once for one high-degree face.
    """
    f = fid.size
    rows = out.reshape(pi.size, f)
    step = max(1, CHUNK_ELEMENTS // max(f, 1))
    for s in range(0, pi.size, step):
        if step == 1:
            a, b = corners_t[pi[s]][None], corners_t[pj[s]][None]
        else:
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
        block = rows[s : s + a.shape[0]]
        np.minimum(a, b, out=block)
        block *= nv
        block += np.maximum(a, b)


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
        part = ginv[:, a:b]
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


def _check_index_range(idx: np.ndarray, offsets: np.ndarray, num_verts: int) -> None:
    if idx.size == 0:
        return
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
            "triangles or quads), or raise torch_polylap.topology.MAX_FACE_PAIRS "
            f"(now {MAX_FACE_PAIRS:,}) if you have that memory."
        )


def half_edge_vertices(faces: PolygonFaces) -> tuple[torch.Tensor, torch.Tensor]:
    """``(src, dst)``, each ``(N,)``: half-edge ``h`` runs from corner ``h`` to the next corner."""
    pos = torch.arange(faces.num_corners, device=faces.device)
    last = torch.repeat_interleave(faces.offsets[1:] - 1, faces.sizes)
    first = torch.repeat_interleave(faces.offsets[:-1], faces.sizes)
    nxt = torch.where(pos == last, first, pos + 1)
    return faces.indices, faces.indices[nxt]


# -- what the report finds -------------------------------------------------------------------


def _analyse(
    idx: np.ndarray,
    offsets: np.ndarray,
    sizes: np.ndarray,
    num_verts: int,
    edges: np.ndarray,
    edge_uses: np.ndarray,
    he_edge: np.ndarray,
    valence: np.ndarray,
) -> TopologyReport:
    """The :class:`TopologyReport` of a mesh, O(N) for a clean one (``N`` corners).

    The costlier searches (a graph over corners for non-manifold vertices, orientability,
    duplicates) run only when a cheap test has already found a defect.
    """
    nxt, prv = _next_prev(offsets, sizes)
    forward = idx < idx[nxt]
    heavy = edge_uses > 2
    fwd_count = np.bincount(he_edge[forward], minlength=edge_uses.size)
    misoriented = (edge_uses == 2) & (fwd_count != 1)
    if heavy.any() or misoriented.any():
        fans = _fan_counts_general(idx, nxt, forward, he_edge, edge_uses, num_verts)
    else:
        fans = _fan_counts_oriented(idx, prv, he_edge, edge_uses, valence)
    bad_vertex = fans > 1
    bad_vertex[edges[heavy].reshape(-1)] = True
    # a misoriented edge's faces are stored as (p, q) = the direction both traverse
    mis = edges[misoriented]
    both_back = fwd_count[misoriented] == 0
    mis[both_back] = mis[both_back][:, ::-1]
    non_orientable, dups = 0, np.zeros(0, np.int64)
    if misoriented.any():
        he_face = np.repeat(np.arange(sizes.size, dtype=np.int64), sizes)
        _, bad_face, comp = _orientation(nxt, forward, he_face, he_edge, edge_uses)
        non_orientable = int(np.unique(comp[bad_face]).size)
    if heavy.any() or misoriented.any():
        dups = duplicate_faces(PolygonFaces(torch.from_numpy(idx), offsets=offsets))[0]
    return TopologyReport(
        non_manifold_edges=edges[heavy],
        non_manifold_vertices=np.flatnonzero(bad_vertex),
        misoriented_edges=mis,
        non_orientable_components=non_orientable,
        duplicate_faces=dups,
        isolated_vertices=np.flatnonzero(valence == 0),
    )


def _next_prev(offsets: np.ndarray, sizes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(N,)`` next and previous corner of every corner within its face (packed order)."""
    pos = np.arange(offsets[-1], dtype=np.int64)
    nxt, prv = pos + 1, pos - 1
    nxt[offsets[1:] - 1] = offsets[:-1]
    prv[offsets[:-1]] = offsets[1:] - 1
    return nxt, prv


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


def _fan_counts_oriented(
    idx: np.ndarray,
    prv: np.ndarray,
    he_edge: np.ndarray,
    edge_uses: np.ndarray,
    valence: np.ndarray,
) -> np.ndarray:
    """``(V,)`` number of fans (maximal runs of faces linked by shared edges) at each vertex,
    for a mesh whose edges are manifold and consistently oriented; ``valence`` ``(V,)`` counts
    the corners at each vertex.

    Around a vertex, corner ``c`` continues to the corner where the twin of its incoming
    half-edge starts, so every vertex's corners form paths (open fans) and cycles (closed
    fans). Pointer doubling labels each path by its last corner and each cycle by its smallest
    corner in ``ceil(log2(max valence))`` vectorized rounds, O(N log valence), with no graph
    library: cheap enough to run on every mesh. int32 indices halve the memory traffic of the
    gathers, which dominate.
    """
    n = idx.size
    itype = np.int32 if n < 2**31 - 1 else np.int64
    pos = np.arange(n, dtype=itype)
    succ = _twins(he_edge, edge_uses, itype)[prv]
    np.copyto(succ, pos, where=succ < 0)
    jump, low = succ, pos.copy()
    max_valence = int(valence.max()) if n else 1
    for _ in range((max_valence - 1).bit_length()):  # doubling rounds, not corners
        np.minimum(low, low[jump], out=low)
        jump = jump[jump]
    label = np.where(succ[jump] == jump, jump, low)
    return np.bincount(idx[label == pos], minlength=valence.size)


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
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(flip, non_orientable, component)``, each ``(F,)``; see :func:`orientation_flips`."""
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
    return flip, non_orientable, component


def orientation_flips(
    faces: FacesLike, num_verts: int | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
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
    idx, sizes, offsets = (t.cpu().numpy() for t in (pf.indices, pf.sizes, pf.offsets))
    edges, edge_uses, he_edge = edge_incidence(pf, num_verts)
    nxt, _ = _next_prev(offsets, sizes)
    he_face = np.repeat(np.arange(sizes.size, dtype=np.int64), sizes)
    return _orientation(nxt, idx < idx[nxt], he_face, he_edge, edge_uses)


def edge_incidence(
    faces: FacesLike, num_verts: int | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(edges (E, 2), uses (E,), he_edge (N,))`` of any faces, by one sort of the half-edges.

    ``edges`` are sorted pairs ``p < q``, ``uses`` how many half-edges lie on each, ``he_edge``
    the edge of every half-edge (packed order). :func:`build_topology` gets the same arrays from
    its pair sort; this is the light version for repairs, which need no pattern.
    """
    pf = as_faces(faces)
    idx, sizes, offsets = (t.cpu().numpy() for t in (pf.indices, pf.sizes, pf.offsets))
    if idx.size == 0:
        return np.zeros((0, 2), np.int64), np.zeros(0, np.int64), np.zeros(0, np.int64)
    nv = np.int64(max(int(idx.max()) + 1, num_verts or 0, 1))
    nxt, _ = _next_prev(offsets, sizes)
    a, b = idx, idx[nxt]
    keys, he_edge, uses = np.unique(
        np.minimum(a, b) * nv + np.maximum(a, b), return_inverse=True, return_counts=True
    )
    lo = keys // nv
    return np.stack([lo, keys - lo * nv], 1), uses.astype(np.int64), he_edge.reshape(-1)


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


def _warn_outside_package(message: str) -> None:
    """``warnings.warn`` attributed to the first caller outside torch_polylap."""
    package = os.path.dirname(os.path.abspath(__file__))
    level, frame = 2, sys._getframe(1)  # level 2: the caller of this helper
    while frame is not None and os.path.abspath(frame.f_code.co_filename).startswith(package):
        level += 1
        frame = frame.f_back
    warnings.warn(message, UserWarning, stacklevel=level)


# -- the one topology cache of the package ---------------------------------------------------


class _TopologyCache:
    """Topologies keyed by the faces tensor they were built from, bounded in entries and bytes.

    Keys are ``id(tensor)`` guarded by a weak reference: the cache never keeps a faces tensor
    alive (nor does the topology, which holds a private copy of the indices), and an entry
    goes when its tensor is garbage collected. Least recently used entries are evicted beyond
    ``max_entries`` or ``max_bytes`` (the newest entry always stays). The weakref callback only
    records the dead key; removal happens under the lock on the next access, so a callback
    fired by the garbage collector in the middle of an update cannot deadlock or corrupt it.
    """

    def __init__(self, max_entries: int = 64, max_bytes: int = 2 << 30) -> None:
        self.max_entries = max_entries
        self.max_bytes = max_bytes
        self._entries: OrderedDict[int, tuple[weakref.ref, tuple, Topology, int]] = OrderedDict()
        self._bytes = 0
        self._dead: list[tuple[int, weakref.ref]] = []
        self._lock = threading.Lock()

    def get(self, holder: torch.Tensor, stamp: tuple) -> Topology | None:
        with self._lock:
            self._purge()
            entry = self._entries.get(id(holder))
            if entry is None or entry[0]() is not holder or entry[1] != stamp:
                return None
            self._entries.move_to_end(id(holder))
            return entry[2]

    def put(self, holder: torch.Tensor, stamp: tuple, topo: Topology) -> None:
        key = id(holder)
        ref = weakref.ref(holder, lambda r, key=key: self._dead.append((key, r)))
        size = topo.nbytes
        with self._lock:
            self._purge()
            self._remove(key)
            self._entries[key] = (ref, stamp, topo, size)
            self._bytes += size
            while len(self._entries) > 1 and (
                len(self._entries) > self.max_entries or self._bytes > self.max_bytes
            ):
                self._remove(next(iter(self._entries)))

    def clear(self) -> None:
        with self._lock:
            self._entries.clear()
            self._bytes = 0

    def __len__(self) -> int:
        with self._lock:
            self._purge()
            return len(self._entries)

    def _purge(self) -> None:
        while self._dead:
            key, ref = self._dead.pop()
            entry = self._entries.get(key)
            if entry is not None and entry[0] is ref:
                self._remove(key)

    def _remove(self, key: int) -> None:
        entry = self._entries.pop(key, None)
        if entry is not None:
            self._bytes -= entry[3]


_CACHE = _TopologyCache()


def set_topology_cache_limits(max_entries: int = 64, max_bytes: int = 2 << 30) -> None:
    """Bound the topology cache of :func:`get_topology` (defaults: 64 entries, 2 GiB)."""
    _CACHE.max_entries, _CACHE.max_bytes = int(max_entries), int(max_bytes)


def clear_topology_cache() -> None:
    """Drop every cached topology."""
    _CACHE.clear()


def _stamp(faces: object, holder: torch.Tensor, num_verts: int) -> tuple:
    """What must be unchanged for a cached topology to be reused."""
    parts: list = [num_verts, *_tensor_stamp(holder)]
    if isinstance(faces, PolygonFaces):
        parts += _tensor_stamp(faces.offsets)
    return tuple(parts)


def _tensor_stamp(t: torch.Tensor) -> tuple:
    # The version counter misses writes through a numpy array sharing the memory
    # (np_view = t.numpy(); np_view[0] = 5): a CRC32 of small CPU tensors catches them.
    crc = None
    if t.device.type == "cpu" and t.numel() <= CHECKSUM_MAX_ELEMENTS:
        crc = zlib.crc32(t.detach().contiguous().numpy())
    return (t._version, t.data_ptr(), tuple(t.shape), t.stride(), t.dtype, t.device, crc)


def get_topology(faces: FacesLike | Topology, num_verts: int) -> Topology:
    """The :class:`Topology` of ``faces``, from the package's one cache where possible.

    A :class:`Topology` is used as is. For a ``PolygonFaces`` or an index tensor the topology
    is cached (keyed weakly on the tensor, see :class:`_TopologyCache`) and reused while the
    content is unchanged: same version counter, same storage, same shape and, for CPU tensors
    up to :data:`CHECKSUM_MAX_ELEMENTS` entries, the same CRC32. Larger tensors edited in place
    through a numpy array that shares their memory bypass the version counter and are not
    detected: edit them with torch operations, or pass a new tensor. Lists and numpy arrays
    are converted anew on every call: keep a ``PolygonFaces``, a tensor, a ``Topology`` or a
    :class:`~torch_polylap.PolygonLaplacian` for repeated use.
    """
    if isinstance(faces, Topology):
        if faces.num_verts != num_verts:
            raise ValueError(
                f"the topology was built for {faces.num_verts} vertices "
                f"but verts has {num_verts} rows."
            )
        return faces
    holder = faces.indices if isinstance(faces, PolygonFaces) else faces
    if not isinstance(holder, torch.Tensor):
        return build_topology(faces, num_verts)
    stamp = _stamp(faces, holder, num_verts)
    topo = _CACHE.get(holder, stamp)
    if topo is None:
        topo = build_topology(faces, num_verts)
        _CACHE.put(holder, stamp, topo)
    return topo

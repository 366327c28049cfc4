"""The :class:`Topology` of a mesh: connectivity, the Laplacian's pattern, per-device views."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
import scipy.sparse as sp
import torch
from scipy.sparse.csgraph import connected_components, depth_first_order

from ..faces import PolygonFaces
from ..sparse.construct import diagonal_pattern
from ..sparse.pattern import SparsityPattern
from ..tracing import outside_transforms, run_eagerly, tracing
from .analysis import _twins, half_edge_vertices
from .groups import DegreeGroup, GroupChunk, whole_group
from .report import TopologyReport, _first


@dataclass(frozen=True)
class TopologyView:
    """A :class:`Topology`'s index data on one device (from :meth:`Topology.on`).

    Attributes:
        groups: the :class:`~torch_polylap.topology.DegreeGroup` list on that device.
        crow, col: the CSR pattern of ``L`` on that device.
        pattern: the :class:`~torch_polylap.sparse.pattern.SparsityPattern` that every operator
            assembled on this topology and device shares.
        face_indices: the packed face indices on that device (what a compiled graph checks
            its faces against).
        diagonal: the pattern of ``M0`` (``V x V`` diagonal), shared with
            :func:`torch_polylap.sparse.diag` of that size.
    """

    groups: list[DegreeGroup]
    crow: torch.Tensor
    col: torch.Tensor
    pattern: SparsityPattern
    face_indices: torch.Tensor
    diagonal: SparsityPattern
    _wholes: dict[int, GroupChunk] = field(default_factory=dict, repr=False, compare=False)

    def whole(self, i: int) -> GroupChunk:
        """Group ``i`` as one chunk (traced and vmapped assembly: one pass, no loop)."""
        if tracing():
            return run_eagerly(_whole_chunk, self, i)
        chunk = self._wholes.get(i)
        return _whole_chunk(self, i) if chunk is None else chunk


def _whole_chunk(view: TopologyView, i: int) -> GroupChunk:
    if i not in view._wholes:
        view._wholes[i] = whole_group(view.groups[i])
    return view._wholes[i]


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
        self._views: dict[torch.device, TopologyView] = {}
        # Layouts of other operators that depend only on the faces (the gradient's pattern and
        # its scatter order), cached here by the modules that build them, keyed by
        # (name, device): computed once per topology like the Laplacian's pattern.
        self.derived: dict[tuple[str, torch.device], Any] = {}
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

    def on(self, device: torch.device | str) -> TopologyView:
        """The :class:`TopologyView` on ``device``: index tensors copied there once, and one
        :class:`~torch_polylap.sparse.pattern.SparsityPattern`
        per device for the topology's lifetime,
        so the operators of every step share its cached transposes and unions (``M0 + t * L``
        computes the union of patterns once). Take it once per call and pass it down."""
        device = torch.device(device)
        if tracing():
            return run_eagerly(_make_view, self, device)
        view = self._views.get(device)
        if view is None:
            with outside_transforms():
                view = _make_view(self, device)
        return view

    def __getstate__(self) -> dict[str, Any]:
        # device views and derived layouts are caches, rebuilt on first use after unpickling
        state = self.__dict__.copy()
        state["_views"], state["derived"] = {}, {}
        return state

    def __repr__(self) -> str:
        degs = ", ".join(f"{g.k}:{g.face_ids.numel()}" for g in self._groups_cpu)
        flags = "" if self.report.is_clean else f", report={self.report.lines()}"
        return (
            f"Topology(V={self.num_verts}, F={self.num_faces}, E={self.num_edges}, "
            f"boundary_edges={int((self.edge_faces == 1).sum())}, degrees={{{degs}}}, "
            f"nnz={self.nnz}{flags})"
        )


def _make_view(topo: Topology, device: torch.device) -> TopologyView:
    """Build and keep ``topo``'s view on ``device`` (eagerly, also at torch.compile trace time).

    The view's pattern gets its row indices and diagonal positions at once, so operators built
    in traced code find every index they need already computed.
    """
    view = topo._views.get(device)
    if view is None:
        if device.type == "cpu":
            groups, crow, col = topo._groups_cpu, topo.crow, topo.col
            indices = topo.faces.indices
        else:
            groups = [g.to(device) for g in topo._groups_cpu]
            crow, col = topo.crow.to(device), topo.col.to(device)
            indices = topo.faces.indices.to(device)
        shape = (topo.num_verts, topo.num_verts)
        pattern = SparsityPattern(crow, col, shape)
        pattern.row  # noqa: B018  (fills the cache)
        pattern.diagonal_positions()
        diagonal = diagonal_pattern(topo.num_verts, device)
        pattern.contains(diagonal)  # M0 + t L: known while tracing whether it needs a union
        view = TopologyView(groups, crow, col, pattern, indices, diagonal)
        topo._views[device] = view
    return view

"""Everything about a polygon mesh that depends only on its faces, computed once and cached.

:class:`Topology` validates the connectivity (clear errors that name the face, edge or vertex)
and precomputes what every later assembly of ``L`` reuses: faces grouped by degree, the
half-edges and undirected edges, the boundary, the CSR sparsity pattern of ``L`` and, for each
per-face matrix entry, its position in ``L``'s value array.  Assembling ``L`` for new vertex
positions is then pure arithmetic plus one scatter onto this fixed pattern.

The index work runs in numpy on the CPU (its ``argsort`` is several times faster than
``torch.sort`` there); the resulting index tensors are copied to each device once, on demand.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np
import torch

from .faces import FacesLike, PolygonFaces, as_faces

__all__ = ["Topology", "DegreeGroup", "GroupChunk", "build_topology"]


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


class Topology:
    """Validated connectivity of a polygon mesh and the cached sparsity pattern of its Laplacian.

    Build it with :func:`build_topology` (or let :func:`torch_polylap.laplacian` and
    :class:`torch_polylap.PolygonLaplacian` build and cache it).

    Attributes:
        faces: the packed faces (CPU).
        num_verts: ``V``; vertices never referenced by a face are *isolated*.
        groups: one :class:`DegreeGroup` per face degree present.
        crow, col: CSR pattern of the ``V x V`` Laplacian (sorted columns in every row).
        isolated: ``(V,)`` bool, vertices referenced by no face.

    Edges (:attr:`edges`, :attr:`edge_faces`, :attr:`half_edge_edge`) are derived on first use.
    """

    def __init__(self, faces: PolygonFaces, num_verts: int, groups, pattern, pair_data, isolated):
        self.faces = faces
        self.num_verts = num_verts
        self._groups_cpu: list[DegreeGroup] = groups
        self.crow, self.col = pattern
        # unique vertex pairs (lo * V + hi, sorted) and how many faces use each as an edge
        self._pair_keys, self._pair_uses = pair_data
        self.isolated = isolated
        self._device_cache: dict[torch.device, tuple] = {}
        self._row: torch.Tensor | None = None
        self._edges: tuple[torch.Tensor, torch.Tensor] | None = None
        self._half_edge_edge: torch.Tensor | None = None

    def _edge_arrays(self) -> tuple[torch.Tensor, torch.Tensor]:
        if self._edges is None:
            is_edge = self._pair_uses > 0
            keys = self._pair_keys[is_edge]
            nv = max(self.num_verts, 1)
            lo = keys // nv
            edges = np.stack([lo, keys - lo * nv], 1)
            self._edges = (torch.from_numpy(edges), torch.from_numpy(self._pair_uses[is_edge]))
        return self._edges

    @property
    def edges(self) -> torch.Tensor:
        """``(E, 2)`` undirected edges ``(p, q)`` with ``p < q``, sorted."""
        return self._edge_arrays()[0]

    @property
    def edge_faces(self) -> torch.Tensor:
        """``(E,)`` how many faces use each edge (1 on the boundary, 2 inside)."""
        return self._edge_arrays()[1]

    @property
    def half_edge_edge(self) -> torch.Tensor:
        """``(N,)`` the undirected edge (row of :attr:`edges`) of every half-edge.

        Half-edge ``h`` runs from corner ``h`` of the packed faces to the next corner of its face.
        """
        if self._half_edge_edge is None:
            src, dst = half_edge_vertices(self.faces)
            nv = max(self.num_verts, 1)
            keys = (torch.minimum(src, dst) * nv + torch.maximum(src, dst)).numpy()
            edges = self.edges.numpy()
            edge_keys = edges[:, 0] * nv + edges[:, 1]
            self._half_edge_edge = torch.from_numpy(np.searchsorted(edge_keys, keys))
        return self._half_edge_edge

    @property
    def num_faces(self) -> int:
        return self.faces.num_faces

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
    def boundary_edges(self) -> torch.Tensor:
        """``(E_B, 2)`` edges used by exactly one face."""
        return self.edges[self.edge_faces == 1]

    @property
    def boundary_vertices(self) -> torch.Tensor:
        """Sorted indices of the vertices on the boundary."""
        return torch.unique(self.boundary_edges)

    @property
    def num_edges(self) -> int:
        return self.edges.shape[0]

    def euler_characteristic(self) -> int:
        """``V - E + F`` counted over the vertices used by faces."""
        used = self.num_verts - int(self.isolated.sum())
        return used - self.num_edges + self.num_faces

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

    def __repr__(self) -> str:
        degs = ", ".join(f"{g.k}:{g.face_ids.numel()}" for g in self._groups_cpu)
        return (
            f"Topology(V={self.num_verts}, F={self.num_faces}, E={self.num_edges}, "
            f"boundary_edges={int((self.edge_faces == 1).sum())}, degrees={{{degs}}}, "
            f"nnz={self.nnz})"
        )


def _pairs(k: int) -> tuple[np.ndarray, np.ndarray]:
    i, j = np.triu_indices(k, 1)
    return i.astype(np.int64), j.astype(np.int64)


def build_topology(faces: FacesLike, num_verts: int | None = None) -> Topology:
    """Validate ``faces`` and precompute the Laplacian's sparsity pattern and scatter maps.

    Args:
        faces: any form accepted by :func:`torch_polylap.as_faces`.
        num_verts: number of vertices ``V``; defaults to ``max index + 1``.

    Raises:
        ValueError: an index out of range, a vertex repeated within a face, an edge shared by
            more than two faces, or two faces that traverse a shared edge in the same direction
            (inconsistent orientation). The message names the face(s), edge or vertex.
    """
    pf = as_faces(faces)
    cpu = pf if pf.device.type == "cpu" else pf.to("cpu")
    idx = cpu.indices.numpy()
    sizes = cpu.sizes.numpy()
    offsets = cpu.offsets.numpy()
    if num_verts is None:
        num_verts = int(idx.max()) + 1 if idx.size else 0
    num_verts = int(num_verts)
    _check_index_range(idx, offsets, num_verts)
    nv = np.int64(max(num_verts, 1))

    # One block per degree; inside a block every per-pair array is laid out (P, F_k), the
    # layout in which operators.py produces the per-face entries. The pair keys lo * V + hi
    # are written row by row into one preallocated array (fresh large temporaries cost page
    # faults that rival the arithmetic).
    degrees = np.unique(sizes)
    counts = {k: int((sizes == k).sum()) for k in degrees.tolist()}
    all_keys = np.empty(sum(k * (k - 1) // 2 * n for k, n in counts.items()), np.int64)
    blocks = []
    start = 0
    for k in degrees.tolist():
        if degrees.size == 1:
            fid = np.arange(sizes.size, dtype=np.int64)
            corners_t = np.ascontiguousarray(idx.reshape(-1, k).T)
        else:
            fid = np.flatnonzero(sizes == k)
            corners_t = idx[offsets[fid][None, :] + np.arange(k)[:, None]]
        pi, pj = _pairs(k)
        for i, j in zip(pi.tolist(), pj.tolist(), strict=True):
            a, b = corners_t[i], corners_t[j]
            same = a == b
            if same.any():
                f_local = int(np.flatnonzero(same)[0])
                raise ValueError(
                    f"face {int(fid[f_local])} (vertices {corners_t[:, f_local].tolist()}) visits "
                    f"vertex {int(a[f_local])} twice; a polygon must be simple. Split it into "
                    "simple polygons or merge the duplicated corners."
                )
            row = all_keys[start : start + fid.size]
            np.minimum(a, b, out=row)
            row *= nv
            row += np.maximum(a, b)
            start += fid.size
        blocks.append((k, fid, corners_t, pi, pj))

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
    he_uid, he_forward, groups_np_faces = [], [], []
    start = 0
    for k, fid, corners_t, pi, pj in blocks:
        ginv = inv[start : start + pi.size * fid.size].reshape(pi.size, fid.size)
        start += pi.size * fid.size
        step = max(256, CHUNK_ELEMENTS // (3 * max(pi.size, k)))
        chunks = []
        for a in range(0, fid.size, step):
            b = min(a + step, fid.size)
            part = ginv[:, a:b]
            chunks.append(
                GroupChunk(
                    a,
                    b,
                    torch.from_numpy(np.ascontiguousarray(corners_t[:, a:b])),
                    torch.from_numpy(pos_up_u[part].reshape(-1)),
                    torch.from_numpy(pos_low_u[part].reshape(-1)),
                    torch.from_numpy(pos_diag_v[corners_t[:, a:b]].reshape(-1)),
                )
            )
        groups.append(
            DegreeGroup(
                k=k,
                face_ids=torch.from_numpy(fid.astype(np.int64)),
                corners_t=torch.from_numpy(np.ascontiguousarray(corners_t)),
                pair_i=torch.from_numpy(pi),
                pair_j=torch.from_numpy(pj),
                chunks=tuple(chunks),
            )
        )
        # half-edge c of a face runs from corner c to corner c+1 (mod k): pair row of (c, c+1)
        he_rows = [
            _pair_row(k, c, c + 1) if c + 1 < k else _pair_row(k, 0, k - 1) for c in range(k)
        ]
        he_uid.append(ginv[he_rows].reshape(-1))
        he_forward.append((corners_t < np.roll(corners_t, -1, axis=0)).reshape(-1))
        groups_np_faces.append((k, fid))

    uses = _check_edges(
        np.concatenate(he_uid), np.concatenate(he_forward), ulo, uhi, n_unique, groups_np_faces
    )

    isolated = np.bincount(idx, minlength=num_verts) == 0
    if isolated.any():
        first = np.flatnonzero(isolated)[:5].tolist()
        warnings.warn(
            f"{int(isolated.sum())} of {num_verts} vertices belong to no face (first: {first}); "
            "they get zero mass and empty rows in L. Remove unreferenced vertices "
            "(e.g. trimesh's remove_unreferenced_vertices) if you need an invertible M0.",
            stacklevel=3,
        )

    pattern = (torch.from_numpy(crow), torch.from_numpy(col))
    return Topology(cpu, num_verts, groups, pattern, (ukeys, uses), torch.from_numpy(isolated))


def _pair_row(k: int, i: int, j: int) -> int:
    """Row of the local pair ``(i, j)``, ``i < j``, in ``np.triu_indices(k, 1)`` order."""
    return i * k - i * (i + 1) // 2 + (j - i - 1)


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


def half_edge_vertices(faces: PolygonFaces) -> tuple[torch.Tensor, torch.Tensor]:
    """``(src, dst)``, each ``(N,)``: half-edge ``h`` runs from corner ``h`` to the next corner."""
    pos = torch.arange(faces.num_corners, device=faces.device)
    last = torch.repeat_interleave(faces.offsets[1:] - 1, faces.sizes)
    first = torch.repeat_interleave(faces.offsets[:-1], faces.sizes)
    nxt = torch.where(pos == last, first, pos + 1)
    return faces.indices, faces.indices[nxt]


def _check_edges(he_uid, he_forward, ulo, uhi, n_unique, he_faces) -> np.ndarray:
    """Face count of every vertex pair used as an edge; errors for non-manifold or flipped edges.

    A manifold edge is used by one face (boundary) or two; two faces of a consistently
    oriented mesh traverse it in opposite directions, so exactly one of them goes from the
    lower to the higher vertex index.
    """
    uses = np.bincount(he_uid, minlength=n_unique)
    forward = np.bincount(he_uid[he_forward], minlength=n_unique)
    if (uses > 2).any():
        u = int(np.flatnonzero(uses > 2)[0])
        faces = _faces_of(he_uid == u, he_faces)
        raise ValueError(
            f"edge ({int(ulo[u])}, {int(uhi[u])}) is shared by {int(uses[u])} faces {faces}; a "
            "manifold polygon mesh allows at most two. Split the mesh along this edge "
            "(duplicate its vertices for the extra faces) or remove duplicate faces."
        )
    bad = (uses == 2) & (forward != 1)
    if bad.any():
        u = int(np.flatnonzero(bad)[0])
        faces = _faces_of(he_uid == u, he_faces)
        a, b = (int(ulo[u]), int(uhi[u])) if forward[u] == 2 else (int(uhi[u]), int(ulo[u]))
        raise ValueError(
            f"faces {faces[0]} and {faces[1]} both traverse edge {a} -> {b} in the same direction: "
            f"the mesh is not consistently oriented ({int(bad.sum())} such edge(s)). Reverse the "
            "corner order of the faces on one side (PolygonFaces.flipped reverses faces); a "
            "non-orientable mesh such as a Moebius band has no consistent orientation and is "
            "not supported."
        )
    return uses


def _faces_of(mask: np.ndarray, he_faces: list[tuple[int, np.ndarray]]) -> list[int]:
    """Faces owning the masked half-edges (laid out like ``he_uid``: per group, corner-major)."""
    owner = np.concatenate([np.broadcast_to(fid, (k, fid.size)).reshape(-1) for k, fid in he_faces])
    return sorted(set(owner[mask].tolist()))

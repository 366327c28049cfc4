"""Repairs for meshes as people download them, polygons kept as polygons.

Every function takes ``(verts, faces)`` and returns a :class:`Repaired` ``(verts, faces,
report)``: the new vertex positions (same type as given: tensor or array), the new faces as
:class:`~torch_polylap.PolygonFaces`, and a :class:`RepairReport` saying what changed, with
index maps so that per-vertex and per-face data can follow:

    verts2, faces2, rep = orient_faces(verts, faces)
    colors2 = colors[rep.vertex_source]      # per-vertex data
    labels2 = labels[rep.face_source]        # per-face data

Why not trimesh (a dependency of the I/O helpers): its ``Trimesh`` triangulates every polygon
on load, and its repair functions (``fix_winding``, ``merge_vertices``,
``remove_duplicate_faces``, ``remove_unreferenced_vertices``) work on that triangle array, so
polygon faces and their per-face data would not survive. Here everything works on the packed
polygon arrays with numpy/scipy, vectorized (no loop over faces or vertices):

* :func:`orient_faces`: O(N) half-edges plus one ``connected_components`` on a doubled face
  graph (``2F`` nodes; see :func:`torch_polylap.topology.orientation_flips`);
* :func:`weld_vertices`: a k-d tree radius query, O(V log V + pairs), and connected components
  of the pairs, so welding is transitive;
* :func:`remove_degenerate_faces`: O(N) plus one vector area per face;
* :func:`remove_duplicate_faces`: one lexicographic sort of the canonical cycles, O(N log F);
* :func:`remove_unreferenced_vertices`: O(N + V).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np
import scipy.sparse as sp
import torch
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from .checks import check_verts_array
from .faces import FacesLike, PolygonFaces, as_faces
from .kernels.frames import corner_terms
from .topology import duplicate_faces, orientation_flips

__all__ = [
    "RepairReport",
    "Repaired",
    "orient_faces",
    "weld_vertices",
    "remove_degenerate_faces",
    "remove_duplicate_faces",
    "remove_unreferenced_vertices",
]

VertsLike = torch.Tensor | np.ndarray
_EMPTY = np.zeros(0, np.int64)


@dataclass(frozen=True)
class RepairReport:
    """What a repair changed.

    Attributes:
        operation: the repair's name.
        vertex_source: ``(V_new,)`` old index of every new vertex (``new = old[vertex_source]``).
        vertex_map: ``(V_old,)`` new index of every old vertex, ``-1`` where it was removed.
        face_source: ``(F_new,)`` old index of every new face.
        face_map: ``(F_old,)`` new index of every old face, ``-1`` where it was removed.
        flipped_faces: ``(n,)`` new faces whose corner order was reversed.
        changed_faces: ``(n,)`` new faces whose corners changed otherwise (welded, collapsed).
        non_orientable_faces: ``(n,)`` faces in components with no consistent orientation.
        non_orientable_components: how many such components.
        notes: anything else worth knowing, one line each.
    """

    operation: str
    vertex_source: np.ndarray
    vertex_map: np.ndarray
    face_source: np.ndarray
    face_map: np.ndarray
    flipped_faces: np.ndarray = field(default_factory=lambda: _EMPTY)
    changed_faces: np.ndarray = field(default_factory=lambda: _EMPTY)
    non_orientable_faces: np.ndarray = field(default_factory=lambda: _EMPTY)
    non_orientable_components: int = 0
    notes: tuple[str, ...] = ()

    @property
    def removed_vertices(self) -> np.ndarray:
        """``(n,)`` old vertices that have no new counterpart."""
        return np.flatnonzero(self.vertex_map < 0)

    @property
    def removed_faces(self) -> np.ndarray:
        """``(n,)`` old faces that were dropped."""
        return np.flatnonzero(self.face_map < 0)

    def summary(self) -> str:
        parts = [
            f"{self.operation}: {self.vertex_map.size} -> {self.vertex_source.size} vertices, "
            f"{self.face_map.size} -> {self.face_source.size} faces"
        ]
        if self.flipped_faces.size:
            parts.append(f"{self.flipped_faces.size} face(s) flipped")
        if self.changed_faces.size:
            parts.append(f"{self.changed_faces.size} face(s) changed")
        if self.non_orientable_components:
            parts.append(
                f"{self.non_orientable_components} non-orientable component(s) "
                f"({self.non_orientable_faces.size} faces) left as they were"
            )
        return "; ".join(parts + list(self.notes))


class Repaired(NamedTuple):
    """What every repair returns; unpacks as ``verts, faces, report``."""

    verts: VertsLike
    """``(V', 3)`` the new vertex positions, a tensor or an array as given."""
    faces: PolygonFaces
    """The new faces."""
    report: RepairReport
    """What changed, with the index maps for per-vertex and per-face data."""


def orient_faces(verts: VertsLike, faces: FacesLike) -> Repaired:
    """Reverse faces so that every edge shared by two faces is traversed both ways.

    Each component (faces linked through edges used by exactly two faces) is oriented
    consistently by flipping its smaller side, so a mostly oriented mesh keeps its majority
    orientation. Components without a consistent orientation (a Moebius band) are left as
    they are and reported. Edges used by 3+ faces impose nothing. On a closed surface the
    result may face inwards; the orientation of each component is not chosen geometrically.
    """
    pf = _faces(faces)
    n_verts = _num_verts(verts, pf)
    flip, bad, comp = orientation_flips(pf, n_verts)
    flipped_idx = pf.flipped().indices
    corner_flip = torch.from_numpy(np.repeat(flip, pf.sizes.numpy()))
    out = PolygonFaces(torch.where(corner_flip, flipped_idx, pf.indices), sizes=pf.sizes)
    ident_v, ident_f = np.arange(n_verts), np.arange(pf.num_faces)
    report = RepairReport(
        "orient_faces",
        ident_v,
        ident_v,
        ident_f,
        ident_f,
        flipped_faces=np.flatnonzero(flip),
        non_orientable_faces=np.flatnonzero(bad),
        non_orientable_components=int(np.unique(comp[bad]).size),
    )
    return Repaired(verts, out, report)


def weld_vertices(verts: VertsLike, faces: FacesLike, tol: float = 1e-9) -> Repaired:
    """Merge vertices closer than ``tol`` times the bounding-box diagonal.

    Welding is transitive (chains of close vertices become one vertex). Each merged vertex
    keeps the position of its lowest-indexed member. Faces that then visit a vertex twice are
    reported in ``notes``; :func:`remove_degenerate_faces` collapses or removes them.

    Examples:
        Vertex 5 duplicates vertex 2, so the two faces did not share an edge:

        >>> import torch
        >>> from torch_polylap.repair import weld_vertices
        >>> verts = torch.tensor([[0.0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [2, 0.5, 0],
        ...                       [1, 1, 0]])
        >>> verts2, faces2, report = weld_vertices(verts, [[0, 1, 2, 3], [1, 4, 5]])
        >>> verts2.shape, faces2.tolist(), report.notes
        (torch.Size([5, 3]), [[0, 1, 2, 3], [1, 4, 2]], ('1 vertex(es) merged',))
    """
    pf = _faces(faces)
    x = _numpy_verts(verts)
    n = x.shape[0]
    diag = float(np.linalg.norm(x.max(0) - x.min(0))) if n else 0.0
    pairs = cKDTree(x).query_pairs(tol * diag, output_type="ndarray") if n else np.zeros((0, 2))
    graph = sp.coo_matrix((np.ones(len(pairs), np.int8), (pairs[:, 0], pairs[:, 1])), (n, n))
    _, label = connected_components(graph.tocsr(), directed=False)
    # representative: the lowest index of each cluster; new indices in representative order
    rep = np.full(label.max() + 1 if n else 0, n, np.int64)
    np.minimum.at(rep, label, np.arange(n))
    source = np.sort(rep)
    new_of_label = np.empty_like(rep)
    new_of_label[np.argsort(rep)] = np.arange(rep.size)
    vertex_map = new_of_label[label]
    old_idx = pf.indices.numpy()
    new_idx = vertex_map[old_idx]
    out = PolygonFaces(torch.from_numpy(new_idx), sizes=pf.sizes)
    face_ids = np.repeat(np.arange(pf.num_faces), pf.sizes.numpy())
    changed = np.unique(face_ids[new_idx != old_idx])
    notes: tuple[str, ...] = ()
    repeats = _faces_repeating_a_vertex(out)
    if repeats.size:
        notes = (
            f"{repeats.size} face(s) now visit a vertex twice (first: {repeats[:5].tolist()}); "
            "run remove_degenerate_faces",
        )
    ident_f = np.arange(pf.num_faces)
    report = RepairReport(
        "weld_vertices",
        source,
        vertex_map,
        ident_f,
        ident_f,
        changed_faces=changed,
        notes=(f"{n - source.size} vertex(es) merged", *notes),
    )
    return Repaired(_take(verts, source), out, report)


def remove_degenerate_faces(verts: VertsLike, faces: FacesLike) -> Repaired:
    """Collapse repeated consecutive corners, then drop faces that still repeat a vertex, have
    fewer than three corners, or have zero vector area.

    A quad with a collapsed edge (``[0, 1, 1, 2]``, what welding leaves) becomes the triangle
    ``[0, 1, 2]``; ``[0, 1, 0, 2]`` is removed. Zero area means ``|a_f| <= eps * sum_i |g_i|^2``
    (AW11 eq. 8; the test of :func:`torch_polylap.laplacian`), computed in the per-face scaled
    frame so that it does not underflow for tiny faces.
    """
    pf = _faces(faces)
    idx, sizes = pf.indices.numpy(), pf.sizes.numpy()
    offsets = pf.offsets.numpy()
    prv = np.arange(idx.size) - 1
    prv[offsets[:-1]] = offsets[1:] - 1
    keep_corner = idx != idx[prv]
    face_ids = np.repeat(np.arange(pf.num_faces), sizes)
    new_sizes = np.bincount(face_ids[keep_corner], minlength=pf.num_faces)
    collapsed = np.flatnonzero(new_sizes != sizes)
    ok = new_sizes >= 3
    keep_corner &= ok[face_ids]
    compact = PolygonFaces(torch.from_numpy(idx[keep_corner]), sizes=new_sizes[ok])
    ok_ids = np.flatnonzero(ok)
    repeats = ok_ids[_faces_repeating_a_vertex(compact)]
    ok[repeats] = False
    live = keep_corner & ok[face_ids]
    zero = _zero_area_faces(verts, idx[live], new_sizes[ok], np.flatnonzero(ok))
    ok[zero] = False
    out, face_map, face_source = _select(idx, keep_corner & ok[face_ids], new_sizes, ok)
    ident_v = np.arange(_num_verts(verts, pf))
    report = RepairReport(
        "remove_degenerate_faces",
        ident_v,
        ident_v,
        face_source,
        face_map,
        changed_faces=face_map[collapsed][face_map[collapsed] >= 0],
        notes=(
            f"{int((new_sizes < 3).sum())} face(s) with fewer than 3 distinct corners, "
            f"{repeats.size} repeating a vertex, {zero.size} of zero area removed",
        ),
    )
    return Repaired(verts, out, report)


def remove_duplicate_faces(verts: VertsLike, faces: FacesLike) -> Repaired:
    """Drop faces repeating an earlier face's vertex cycle up to rotation and reflection
    (see :func:`torch_polylap.topology.duplicate_faces`); the first occurrence stays."""
    pf = _faces(faces)
    dup, first = duplicate_faces(pf)
    ok = np.ones(pf.num_faces, bool)
    ok[dup] = False
    idx, sizes = pf.indices.numpy(), pf.sizes.numpy()
    corner_ok = np.repeat(ok, sizes)
    out, face_map, face_source = _select(idx, corner_ok, sizes, ok)
    ident_v = np.arange(_num_verts(verts, pf))
    notes = (
        f"{dup.size} duplicate face(s) removed (first: {dup[:5].tolist()}, repeating faces "
        f"{first[:5].tolist()})",
    )
    report = RepairReport(
        "remove_duplicate_faces",
        ident_v,
        ident_v,
        face_source,
        face_map,
        notes=notes if dup.size else (),
    )
    return Repaired(verts, out, report)


def remove_unreferenced_vertices(verts: VertsLike, faces: FacesLike) -> Repaired:
    """Drop vertices no face uses (they get zero mass and empty rows of ``L``)."""
    pf = _faces(faces)
    n = _num_verts(verts, pf)
    idx = pf.indices.numpy()
    used = np.bincount(idx, minlength=n) > 0
    source = np.flatnonzero(used)
    vertex_map = np.full(n, -1, np.int64)
    vertex_map[source] = np.arange(source.size)
    out = PolygonFaces(torch.from_numpy(vertex_map[idx]), sizes=pf.sizes)
    ident_f = np.arange(pf.num_faces)
    report = RepairReport("remove_unreferenced_vertices", source, vertex_map, ident_f, ident_f)
    return Repaired(_take(verts, source), out, report)


# -- helpers ----------------------------------------------------------------------------------


def _faces(faces: FacesLike) -> PolygonFaces:
    pf = as_faces(faces)
    return pf if pf.device.type == "cpu" else pf.to("cpu")


def _num_verts(verts: VertsLike, pf: PolygonFaces) -> int:
    n = check_verts_array(verts).shape[0]
    if pf.num_corners and int(pf.indices.max()) >= n:
        f = int(torch.nonzero(pf.indices >= n)[0, 0])
        raise ValueError(
            f"corner {f} of the faces refers to vertex {int(pf.indices[f])}, but verts has {n} "
            "rows."
        )
    return n


def _numpy_verts(verts: VertsLike) -> np.ndarray:
    return check_verts_array(verts)


def _take(verts: VertsLike, rows: np.ndarray) -> VertsLike:
    if isinstance(verts, torch.Tensor):
        return verts[torch.from_numpy(rows).to(verts.device)]
    return np.asarray(verts)[rows]


def _select(
    idx: np.ndarray, corner_ok: np.ndarray, sizes: np.ndarray, ok: np.ndarray
) -> tuple[PolygonFaces, np.ndarray, np.ndarray]:
    """The kept faces, with ``face_map`` ``(F_old,)`` and ``face_source`` ``(F_new,)``."""
    face_source = np.flatnonzero(ok)
    face_map = np.full(ok.size, -1, np.int64)
    face_map[face_source] = np.arange(face_source.size)
    out = PolygonFaces(torch.from_numpy(idx[corner_ok]), sizes=sizes[ok])
    return out, face_map, face_source


def _faces_repeating_a_vertex(pf: PolygonFaces) -> np.ndarray:
    """``(n,)`` faces visiting some vertex twice (one sort per degree, O(N log k))."""
    idx, sizes, offsets = pf.indices.numpy(), pf.sizes.numpy(), pf.offsets.numpy()
    bad = [_EMPTY]
    for k in np.unique(sizes).tolist():  # one pass per degree
        fid = np.flatnonzero(sizes == k)
        rows = np.sort(idx[offsets[fid][:, None] + np.arange(k)], axis=1)
        bad.append(fid[(rows[:, 1:] == rows[:, :-1]).any(1)])
    return np.sort(np.concatenate(bad))


def _zero_area_faces(
    verts: VertsLike, idx: np.ndarray, sizes: np.ndarray, face_ids: np.ndarray
) -> np.ndarray:
    """Which of the faces ``face_ids`` (packed as ``idx``, ``sizes``) have zero vector area."""
    x = torch.as_tensor(_numpy_verts(verts))
    if not x.is_floating_point():
        x = x.double()
    xt = x.t().contiguous()
    offsets = np.concatenate(([0], np.cumsum(sizes)))
    eps = torch.finfo(x.dtype).eps
    tiny = torch.finfo(x.dtype).tiny
    zero = [_EMPTY]
    for k in np.unique(sizes).tolist():  # one pass per degree
        local = np.flatnonzero(sizes == k)
        corners = torch.from_numpy(idx[offsets[local][None, :] + np.arange(k)[:, None]])
        _, g, a = corner_terms(xt[:, corners])  # (3, k, F_k)
        r2 = 1.0 / (g * g).sum((0, 1)).clamp_min(tiny)
        area_scaled = torch.linalg.vector_norm(a * r2, dim=0)  # |f| / s^2
        zero.append(face_ids[local[(area_scaled <= eps).numpy()]])
    return np.sort(np.concatenate(zero))

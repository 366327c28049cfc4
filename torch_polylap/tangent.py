"""Per-vertex tangent frames and the tangent gradient at the vertices: what the vector calculus
(:mod:`torch_polylap.vector`), the learning layers (:mod:`torch_polylap.nn`), DiffusionNet's
operators (:func:`torch_polylap.interop.to_diffusionnet`) and the datasets share.

- :func:`vertex_tangent_frames`: a unit normal per vertex (the normalized sum of the vector
  areas ``a_f`` of the faces around it, i.e. area-weighted face normals) and two tangent axes.
- :func:`vertex_gradient_operators`: ``(V, V)`` sparse operators ``grad_x, grad_y`` giving the
  components, in the vertex's tangent frame, of the area-weighted mean of the face gradients
  around the vertex (:func:`torch_polylap.gradient_operator`, exact for linear functions on
  every face):

      grad_v u = sum_{f ~ v} |f| grad_f u / sum_{f ~ v} |f|,
      (grad_x u)_v = e_x(v) . grad_v u,    (grad_y u)_v = e_y(v) . grad_v u.

  DiffusionNet stores the pair as one complex operator ``grad_x + i grad_y``; here it is two
  real :class:`~torch_polylap.sparse.SparseOperator` tensors (O(nnz) gradients, batches by
  :func:`torch_polylap.sparse.block_diag`).
"""

from __future__ import annotations

from typing import NamedTuple

import torch

from ._typing import MeshFaces
from .calculus import gradient_operator_of
from .checks import check_verts
from .faces import PolygonFaces
from .kernels.frames import stable_norm
from .measures import vector_area
from .sparse import SparseOperator, operator_from_parts, sparse_values
from .sparse.construct import pattern_of
from .topology import Topology, get_topology
from .tracing import outside_transforms

__all__ = [
    "TangentFrames",
    "vertex_tangent_frames",
    "tangent_frames",
    "vertex_gradient_operators",
    "reference_neighbours",
]


class TangentFrames(NamedTuple):
    """Orthonormal frames per vertex, each ``(V, 3)``; unpacks as ``normal, e_x, e_y``."""

    normal: torch.Tensor
    """The unit normal."""
    e_x: torch.Tensor
    """The first tangent axis."""
    e_y: torch.Tensor
    """The second tangent axis, ``normal x e_x``."""


def _corner_sums(face_values: torch.Tensor, faces: PolygonFaces, num_verts: int) -> torch.Tensor:
    """``(V, ...)`` sum over the faces around each vertex of ``face_values (F, ...)``."""
    idx = faces.indices.to(face_values.device)
    per_corner = face_values[faces.corner_face.to(face_values.device)]
    out = face_values.new_zeros((num_verts,) + tuple(face_values.shape[1:]))
    return out.index_add(0, idx, per_corner)


# An edge whose tangent part is shorter than this fraction of its length (within 0.06 degrees
# of the normal) does not give the vertex a tangent axis: the next reference is taken.
_EDGE_SINE_MIN = 1e-3


def vertex_tangent_frames(verts: torch.Tensor, faces: MeshFaces) -> TangentFrames:
    """Per-vertex orthonormal frames :class:`TangentFrames` ``(normal, e_x, e_y)``, each
    ``(V, 3)``, smooth functions of the vertex positions.

    ``normal`` is the normalized sum of the vector areas of the faces around the vertex (the
    area-weighted face normals).  ``e_x`` is the vertex's reference edge projected onto the
    tangent plane and normalized (as geometry-central's vertex tangent basis): the first
    outgoing edge ``v -> w`` of its first corner in the packed face order, a choice made once
    from the faces, so that the frames are differentiable in ``verts`` wherever the normal is
    defined, and turn with the mesh (``R`` applied to the mesh applies ``R`` to the frames).
    ``e_y = normal x e_x``.  The features of
    :class:`~torch_polylap.nn.SpatialGradientFeatures` do not depend on the choice of ``e_x``;
    vector fields stored in frame coordinates do.

    What remains a choice made from the positions, only at degenerate vertices: where the
    reference edge lies within 0.06 degrees of the normal (its tangent part shorter than
    ``1e-3`` times its length), ``e_x`` comes from the other edge of that corner, ``v -> u``
    (``u`` the previous corner), and where that one does too, from the coordinate axis least
    aligned with the normal; a vertex switching between these is not differentiable there.
    Isolated vertices (and vertices whose faces' vector areas cancel) get the normal
    ``(0, 0, 1)`` and ``e_x = (1, 0, 0)``.
    """
    check_verts(verts)
    return tangent_frames(verts, get_topology(faces, verts.shape[0]))


def tangent_frames(verts: torch.Tensor, topo: Topology) -> TangentFrames:
    """:func:`vertex_tangent_frames` on a topology, without checking ``verts`` again (for
    callers that have checked it)."""
    summed = _corner_sums(vector_area(verts, topo, validate=False), topo.faces, topo.num_verts)
    norm = stable_norm(summed, 1, keepdim=True)
    degenerate = (norm <= torch.finfo(verts.dtype).tiny).expand_as(summed)
    fallback = torch.zeros_like(summed)
    fallback[:, 2] = 1.0
    normal = torch.where(degenerate, fallback, summed / torch.where(degenerate, 1.0, norm))
    # the last resort: the coordinate axis least aligned with the normal (|n . ref| <=
    # 1/sqrt(3), so its tangent part is never short)
    # (a comparison, not one_hot, which reads its indices on the host and so refuses vmap)
    least = normal.detach().abs().argmin(1, keepdim=True)
    axis = (torch.arange(3, device=verts.device) == least).to(verts.dtype)
    tangent = _tangent_part(axis, normal)
    # the references in reverse order of preference: each where() keeps the later one wherever
    # it is usable, and the gradient flows only into the one taken
    for head in reversed(reference_neighbours(topo, verts.device)):
        edge = verts[head] - verts
        part = _tangent_part(edge, normal)
        usable = stable_norm(part, 1) > _EDGE_SINE_MIN * stable_norm(edge, 1)
        tangent = torch.where(usable.detach()[:, None], part, tangent)
    e_x = tangent / stable_norm(tangent, 1, keepdim=True)
    e_y = torch.linalg.cross(normal, e_x, dim=1)
    return TangentFrames(normal, e_x, e_y)


def _tangent_part(x: torch.Tensor, normal: torch.Tensor) -> torch.Tensor:
    """``(V, 3)`` the part of each ``x`` orthogonal to the unit ``normal``."""
    return x - (x * normal).sum(1, keepdim=True) * normal


def reference_neighbours(topo: Topology, device: torch.device) -> tuple[torch.Tensor, torch.Tensor]:
    """``(V,)`` twice: the ends ``w`` and ``u`` of the two edges ``v -> w``, ``v -> u`` of each
    vertex's first corner in the packed face order (``w`` the next corner of that face, ``u``
    the previous one), the reference edges of :func:`vertex_tangent_frames`; ``v`` itself for
    an isolated vertex.  From the faces alone; cached on the topology per device."""
    key = ("tangent_reference_neighbours", torch.device(device))
    cached = topo.derived.get(key)
    if cached is None:
        with outside_transforms():
            faces = topo.faces
            idx = faces.indices
            count, num_verts = idx.numel(), topo.num_verts
            own = torch.arange(num_verts)
            first = torch.full((num_verts,), count, dtype=torch.int64)
            first = first.scatter_reduce(0, idx, torch.arange(count), "amin")
            used = first < count
            corner = torch.where(used, first, 0)
            if count:
                ahead = torch.where(used, idx[faces.next_corner[corner]], own)
                behind = torch.where(used, idx[faces.prev_corner[corner]], own)
            else:
                ahead = behind = own
            cached = (ahead.to(device), behind.to(device))
        topo.derived[key] = cached
    return cached


def vertex_gradient_operators(
    verts: torch.Tensor,
    faces: MeshFaces,
    frames: tuple[torch.Tensor, torch.Tensor] | None = None,
) -> tuple[SparseOperator, SparseOperator]:
    """``(V, V)`` sparse operators ``grad_x, grad_y``: the tangent components of the
    area-weighted mean of the face gradients around each vertex (see the module docstring).

    For a linear function ``u(x) = w . x + c`` on a planar mesh every face gradient is ``w``
    (projected on the plane), so ``grad_x u = e_x . w`` exactly at every vertex.  On a curved
    mesh the face gradients lie in the faces' planes and are projected on the vertex's tangent
    plane.

    Args:
        verts: ``(V, 3)`` vertex positions.
        faces: faces in any accepted form, or a :class:`~torch_polylap.topology.Topology`.
        frames: ``(e_x, e_y)``, each ``(V, 3)``, the tangent axes to use; default the ones of
            :func:`vertex_tangent_frames`.

    Returns:
        ``(grad_x, grad_y)``, :class:`~torch_polylap.sparse.SparseOperator` tensors with the
        pattern of the vertex-face-vertex adjacency (``sum_f k_f^2`` entries before merging),
        values differentiable in ``verts`` (and in ``frames``) with O(nnz) gradients.
        Isolated vertices get empty rows.
    """
    check_verts(verts)
    topo = get_topology(faces, verts.shape[0])
    faces_ = topo.faces
    n = topo.num_verts
    if frames is None:
        _, e_x, e_y = tangent_frames(verts, topo)
    else:
        e_x, e_y = frames
        if e_x.shape != (n, 3) or e_y.shape != (n, 3):
            raise ValueError(
                f"vertex_gradient_operators: frames must be two ({n}, 3) tensors, got "
                f"{tuple(e_x.shape)} and {tuple(e_y.shape)}."
            )
    device = verts.device
    G = gradient_operator_of(verts, topo)  # (3F, V), row 3 f + c
    on_device = faces_.to(device)
    sizes, offsets, indices = on_device.sizes, on_device.offsets, on_device.indices
    face, col, w = _face_gradient_entries(G, on_device)  # w (N, 3): grad_f of hat u

    area = stable_norm(vector_area(verts, topo, validate=False), 1)  # (F,)
    vert_area = _corner_sums(area, faces_, n)
    vert_area = torch.where(vert_area > 0, vert_area, torch.ones_like(vert_area))

    # Pair every face-gradient vector w (face f, column u) with every corner v of face f: the
    # entry |f| / A_v * e(v) . w of row v, column u.
    repeats = sizes[face]
    entry = torch.repeat_interleave(torch.arange(face.numel(), device=device), repeats)
    first = torch.cumsum(repeats, 0) - repeats
    local = torch.arange(entry.numel(), device=device) - first[entry]
    f_e = face[entry]
    v = indices[offsets[f_e] + local]
    scaled = w[entry] * (area[f_e] / vert_area[v])[:, None]
    # One sort of the (row, column) keys for both operators, which share the pattern.
    unique, inverse = torch.unique(v * n + col[entry], sorted=True, return_inverse=True)
    rows = torch.div(unique, n, rounding_mode="floor")
    crow = torch.zeros(n + 1, dtype=torch.int64, device=device)
    crow[1:] = torch.cumsum(torch.bincount(rows, minlength=n), 0)
    values = [
        scaled.new_zeros(unique.numel()).index_add(0, inverse, (scaled * e[v]).sum(1))
        for e in (e_x, e_y)
    ]
    grad_x = operator_from_parts(crow, unique - rows * n, values[0], (n, n))
    return grad_x, grad_x.with_values(values[1])


def _face_gradient_entries(
    G: SparseOperator, faces: PolygonFaces
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``(face (N,), column (N,), w (N, 3))``: the face gradients ``w = grad_f`` of the hat
    functions of the columns, from the ``(3F, V)`` operator ``G`` of
    :func:`~torch_polylap.calculus.gradient_operator` (differentiable in its values)."""
    pattern = pattern_of(G)
    g_col, g_val = pattern.col, sparse_values(G)
    sizes, offsets, face = faces.sizes, faces.offsets, faces.corner_face
    # Faces are simple polygons (the topology refuses a repeated vertex), so every row 3 f + c
    # holds the k_f distinct corners of face f, sorted: row 3 f + c starts at 3 offsets[f] + c k_f.
    if g_val.numel() != 3 * int(sizes.sum()):
        raise RuntimeError(
            f"vertex_gradient_operators: the face gradient operator has {g_val.numel()} entries, "
            f"expected 3 per corner ({3 * int(sizes.sum())})."
        )
    j = torch.arange(face.numel(), device=sizes.device) - offsets[face]
    first = 3 * offsets[face] + j
    pos = first[:, None] + sizes[face][:, None] * torch.arange(3, device=sizes.device)
    return face, g_col[first], g_val[pos]

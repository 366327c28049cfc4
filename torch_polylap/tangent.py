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

__all__ = [
    "TangentFrames",
    "vertex_tangent_frames",
    "tangent_frames",
    "vertex_gradient_operators",
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


def vertex_tangent_frames(verts: torch.Tensor, faces: MeshFaces) -> TangentFrames:
    """Per-vertex orthonormal frames :class:`TangentFrames` ``(normal, e_x, e_y)``, each ``(V, 3)``.

    ``normal`` is the normalized sum of the vector areas of the faces around the vertex (the
    area-weighted face normals).  ``e_x`` is the projection onto the tangent plane of the
    coordinate axis least aligned with the normal (the first of the smallest ``|n_i|``),
    normalized; ``e_y = normal x e_x``.  The choice is deterministic; the features of
    :class:`SpatialGradientFeatures` do not depend on it.  Isolated vertices (and vertices whose
    faces' vector areas cancel) get the normal ``(0, 0, 1)``.  Differentiable in ``verts``
    (except where the choice of axis switches).
    """
    check_verts(verts)
    return tangent_frames(verts, get_topology(faces, verts.shape[0]))


def tangent_frames(verts: torch.Tensor, topo: Topology) -> TangentFrames:
    """:func:`vertex_tangent_frames` on a topology, without checking ``verts`` again (for
    callers that have checked it)."""
    summed = _corner_sums(vector_area(verts, topo), topo.faces, topo.num_verts)
    norm = stable_norm(summed, 1, keepdim=True)
    degenerate = (norm <= torch.finfo(verts.dtype).tiny).expand_as(summed)
    fallback = torch.zeros_like(summed)
    fallback[:, 2] = 1.0
    normal = torch.where(degenerate, fallback, summed / torch.where(degenerate, 1.0, norm))
    axis = normal.detach().abs().argmin(1)
    ref = torch.nn.functional.one_hot(axis, 3).to(verts.dtype)
    e_x = ref - (ref * normal).sum(1, keepdim=True) * normal
    e_x = e_x / stable_norm(e_x, 1, keepdim=True)  # |n . ref| <= 1/sqrt(3): no cancellation
    e_y = torch.linalg.cross(normal, e_x, dim=1)
    return TangentFrames(normal, e_x, e_y)


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

    area = stable_norm(vector_area(verts, topo), 1)  # (F,)
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

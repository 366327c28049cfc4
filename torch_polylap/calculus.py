"""Vector calculus on polygon meshes: face gradients and divergence.

The per-face gradient follows from AW11's discrete exterior calculus.  With ``d u`` the values'
differences along the face's half-edges and ``B_f`` the edge midpoints relative to the face
centroid, ``B_f^T d u = -sum_i u_i g_i`` (summation by parts, ``g_i = (x_{i+1} - x_{i-1}) / 2``),
so

    grad_f u = (1 / |f|) n_f x (B_f^T d u) = sum_i u_i (g_i x a_f) / |a_f|^2        (1)

with ``a_f`` the vector area and ``n_f = a_f / |a_f|``.  For a linear ``u(x) = w . x + c``,
``d u = E_f w`` and AW11 Lemma 1 (``A_f = E_f^T B_f`` is skew-symmetric with Darboux vector
``a_f``, eq. 8) give ``B_f^T d u = A_f^T w = w x a_f``, so (1) returns
``n_f x (w x n_f) = w - (w . n_f) n_f``: exactly the part of ``w`` tangent to the maximal
projection plane, for every polygon, planar or not.  The rotated midpoints ``n_f x b_i`` are
the dual edges of the proof of AW11 Lemma 4 (linear precision of ``B_f B_f^T / |f|``).  On a
triangle the coefficient ``(g_i x a_f) / |a_f|^2 = n_f x (x_{i-1} - x_{i+1}) / (2 A)`` is the
gradient of the linear hat function, and on a planar face
``|f| |grad_f u|^2 = u^T G G^T u / |f|``, the
geometric part of ``L_f`` (AW11 eq. 9).

The heat-method geodesics built on (1) are in :mod:`torch_polylap.geodesics`.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence

import torch

from ._typing import MeshFaces
from .checks import check_verts
from .kernels.frames import component_norm, corner_terms, gather_corners
from .sparse import SparseOperator
from .sparse.operator import operator_on
from .sparse.pattern import SparsityPattern
from .topology import DegreeGroup, Topology, get_topology
from .tracing import outside_transforms

__all__ = [
    "face_gradient",
    "corner_gradients",
    "gradient_operator",
    "divergence",
]


def grouped_corner_gradients(
    verts: torch.Tensor, topo: Topology
) -> Iterator[tuple[DegreeGroup, torch.Tensor, torch.Tensor]]:
    """Per degree group: ``(grp, w (3, k, F_k), area (F_k,))`` with ``w_i = (g_i x a_f) / |a_f|^2``
    the gradient on face ``f`` of the hat function of its corner ``i`` (eq. (1) above)."""
    groups = topo.on(verts.device).groups
    verts_t = verts.t().contiguous()
    for grp in groups:
        _, g, a = corner_terms(gather_corners(verts_t, grp.corners_t))
        area = component_norm(a[0], a[1], a[2])
        # Divide a by |a| twice rather than by |a|^2: no underflow for tiny faces.
        n = a / area
        w = torch.linalg.cross(g, (n / area)[:, None].expand_as(g), dim=0)
        yield grp, w, area


def _topology(verts: torch.Tensor, faces: MeshFaces) -> Topology:
    check_verts(verts)
    return get_topology(faces, verts.shape[0])


def face_gradient(verts: torch.Tensor, faces: MeshFaces, u: torch.Tensor) -> torch.Tensor:
    """Per-face gradient ``grad_f u = (1/|f|) n_f x (B_f^T d u)`` of a vertex function.

    Exact for linear functions on every face (it returns the part of the gradient tangent to the
    maximal projection plane, normal ``a_f / |a_f|``), equal to the linear finite-element
    gradient on triangles.  Differentiable in ``verts`` and ``u``.

    Args:
        verts: ``(V, 3)`` vertex positions.
        faces: faces in any accepted form, or a :class:`~torch_polylap.topology.Topology`.
        u: ``(V,)`` or ``(V, C)`` values at the vertices.

    Returns:
        ``(F, 3)``, or ``(F, 3, C)`` for ``u`` of shape ``(V, C)``.

    Examples:
        The gradient of a linear function is exact on every face, here a square and a triangle:

        >>> import torch
        >>> import torch_polylap as tp
        >>> verts = torch.tensor([[0.0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [2, 0.5, 0]],
        ...                      dtype=torch.float64)
        >>> faces = [[0, 1, 2, 3], [1, 4, 2]]
        >>> u = 2 * verts[:, 0] - verts[:, 1]
        >>> g = tp.face_gradient(verts, faces, u)
        >>> g.shape
        torch.Size([2, 3])
        >>> torch.allclose(g, torch.tensor([2.0, -1.0, 0.0], dtype=torch.float64))
        True
    """
    return face_gradient_of(verts, _topology(verts, faces), u)


def face_gradient_of(verts: torch.Tensor, topo: Topology, u: torch.Tensor) -> torch.Tensor:
    """:func:`face_gradient` on a topology, without checking ``verts`` again (for callers that
    have checked it)."""
    if u.dim() not in (1, 2) or u.shape[0] != topo.num_verts:
        raise ValueError(
            f"face_gradient: u must have shape ({topo.num_verts},) or ({topo.num_verts}, C), "
            f"got {tuple(u.shape)}."
        )
    u = u.to(verts.dtype)
    out = verts.new_zeros((topo.num_faces, 3) + tuple(u.shape[1:]))
    for grp, w, _ in grouped_corner_gradients(verts, topo):
        uc = u[grp.corners_t]  # (k, F_k) or (k, F_k, C)
        grad = torch.einsum("dkf,kf...->fd...", w, uc)
        out = out.index_copy(0, grp.face_ids, grad)
    return out


def corner_gradients(verts: torch.Tensor, faces: MeshFaces) -> torch.Tensor:
    """The weights of the face gradient (1): ``(N, 3)``, one row per corner in the packed order
    of ``faces.indices``, the row of corner ``i`` of face ``f`` being
    ``w_{f,i} = (g_i x a_f) / |a_f|^2``, so that ``grad_f u = sum_{i in f} u_i w_{f,i}``.

    On a triangle ``w_{f,i}`` is the gradient of the linear hat function of corner ``i``; on
    any polygon the rows of a face sum to zero (constants have no gradient) and reproduce the
    tangent part of ``w`` for linear ``u = w . x`` (AW11 Lemma 1).  These are the entries of
    :func:`gradient_operator`, per corner rather than summed per vertex, for constructions
    that need them face by face (finite elements on a refinement, per-face tensors).
    Differentiable in ``verts``.

    Examples:
        >>> import torch, torch_polylap as tp
        >>> verts, faces = tp.shapes.quad_sphere(2)
        >>> w = tp.corner_gradients(verts, faces).reshape(-1, 4, 3)
        >>> bool(w.sum(1).abs().max() < 1e-12)
        True
    """
    return corner_gradients_of(verts, _topology(verts, faces))


def corner_gradients_of(verts: torch.Tensor, topo: Topology) -> torch.Tensor:
    """:func:`corner_gradients` on a topology, without checking ``verts`` again (for callers
    that have checked it)."""
    offsets = topo.faces.offsets.to(verts.device)
    out = verts.new_zeros(topo.faces.num_corners, 3)
    for grp, w, _ in grouped_corner_gradients(verts, topo):
        k = grp.corners_t.shape[0]
        corner = offsets[grp.face_ids][None, :] + torch.arange(k, device=verts.device)[:, None]
        out = out.index_copy(0, corner.reshape(-1), w.permute(1, 2, 0).reshape(-1, 3))
    return out


def gradient_operator(verts: torch.Tensor, faces: MeshFaces) -> SparseOperator:
    """The face gradient as a ``(3F, V)`` sparse operator ``G``: row ``3 f + c`` is component
    ``c`` of ``grad_f`` (eq. (1) above), so ``(G @ u).view(F, 3) == face_gradient(verts, faces,
    u)``.  Its values are differentiable in ``verts``, and its algebra (``G @ u``, ``G.T @ X``)
    keeps O(nnz) gradients. The pattern and the order of the entries in it depend only on the
    faces: they are computed on the first call and kept with the topology, so later calls on
    the same faces only evaluate the per-corner weights."""
    return gradient_operator_of(verts, _topology(verts, faces))


def gradient_operator_of(verts: torch.Tensor, topo: Topology) -> SparseOperator:
    """:func:`gradient_operator` on a topology, without checking ``verts`` again (for callers
    that have checked it)."""
    parts = list(grouped_corner_gradients(verts, topo))
    pattern, order = gradient_layout(topo, [grp for grp, _, _ in parts], verts.device)
    values = torch.cat([verts.new_zeros(0)] + [w.reshape(-1) for _, w, _ in parts])
    return operator_on(pattern, values.index_select(0, order))


def gradient_layout(
    topo: Topology, groups: Sequence[DegreeGroup], device: torch.device
) -> tuple[SparsityPattern, torch.Tensor]:
    """The CSR pattern of the gradient operator and, for the weights concatenated in the order
    of :func:`grouped_corner_gradients` (component, corner, face per degree group), the
    permutation that sorts them into it; cached on the topology per device."""
    key = ("gradient_operator", torch.device(device))
    cached = topo.derived.get(key)
    if cached is None:
        with outside_transforms():
            empty = torch.zeros(0, dtype=torch.int64, device=device)
            rows, cols = [empty], [empty]
            for grp in groups:
                shape = (3, grp.k, grp.face_ids.numel())
                comp = torch.arange(3, device=device)[:, None, None]
                rows.append((3 * grp.face_ids[None, None, :] + comp).expand(shape).reshape(-1))
                cols.append(grp.corners_t[None].expand(shape).reshape(-1))
            row, col = torch.cat(rows), torch.cat(cols)
            # a simple polygon visits each vertex once: the (row, col) keys are distinct
            order = torch.argsort(row * max(topo.num_verts, 1) + col)
            shape2 = (3 * topo.num_faces, topo.num_verts)
            cached = (SparsityPattern.from_rows(row[order], col[order], shape2), order)
        topo.derived[key] = cached
    return cached


def divergence(verts: torch.Tensor, faces: MeshFaces, field: torch.Tensor) -> torch.Tensor:
    """Integrated divergence ``div X = -G^T A_F X`` of a face vector field (``A_F`` the face
    areas repeated per component): the negative adjoint of :func:`face_gradient`,
    ``sum_f |f| <X_f, grad_f u> = -<div X, u>`` for every ``u``.  On triangles it is the
    cotangent divergence of Crane et al. 2013, with their sign (``L_C phi = div X`` there is
    ``L phi = -div X`` here, ``L = -L_C``).

    Args:
        field: ``(F, 3)`` or ``(F, 3, C)``.

    Returns:
        ``(V,)`` or ``(V, C)``; zero at isolated vertices.
    """
    topo = _topology(verts, faces)
    if field.dim() not in (2, 3) or field.shape[:2] != (topo.num_faces, 3):
        raise ValueError(
            f"divergence: field must have shape ({topo.num_faces}, 3) or "
            f"({topo.num_faces}, 3, C), got {tuple(field.shape)}."
        )
    field = field.to(verts.dtype)
    out = verts.new_zeros((topo.num_verts,) + tuple(field.shape[2:]))
    for grp, w, area in grouped_corner_gradients(verts, topo):
        X = field[grp.face_ids]  # (F_k, 3) or (F_k, 3, C)
        flux = torch.einsum("dkf,f,fd...->kf...", w, area, X)
        out = out.index_add(0, grp.corners_t.reshape(-1), flux.flatten(0, 1), alpha=-1)
    return out

"""Face and vertex measures of polygon meshes: vector areas, areas, normals, masses, planarity.

All are differentiable functions of the vertex positions, evaluated per degree group without
assembling an operator. The vector area ``a_f`` (AW11 Lemma 1, eq. 8) defines the maximal
projection on which AW11 builds everything; ``|a_f|`` is the face area the lumped mass
(eq. 10) shares among the corners; the planarity energy is the stabilizer's quadratic form
(sec. 5.3), summed face by face.
"""

from __future__ import annotations

import torch

from ._typing import MeshFaces
from .assembly import face_groups
from .checks import Lam, check_lam, check_verts
from .kernels.frames import corner_terms, gather_corners, plane_basis, stable_norm
from .topology import get_topology

__all__ = [
    "vector_area",
    "face_areas",
    "face_normals",
    "edge_lengths",
    "mean_edge_length",
    "mass",
    "face_nonplanarity",
    "face_planarity_energy",
    "planarity_energy",
]


def mass(verts: torch.Tensor, faces: MeshFaces, *, validate: bool = True) -> torch.Tensor:
    """``(V,)`` lumped masses ``m_p = sum_{f ni p} |f| / k_f`` (AW11 eq. 10), diagonal of ``M0``.

    ``validate``: refuse non-finite coordinates (a ValueError naming the first such vertex; one
    device sync), as :func:`~torch_polylap.laplacian` does; ``False`` skips the test.
    """
    check_verts(verts, finite=validate)
    topo = get_topology(faces, verts.shape[0])
    verts_t = verts.t().contiguous()
    m = verts.new_zeros(topo.num_verts)
    for grp in topo.on(verts.device).groups:
        _, _, a = corner_terms(gather_corners(verts_t, grp.corners_t))
        share = (stable_norm(a, 0) / grp.k).expand(grp.k, -1).reshape(-1)
        m = m.index_add(0, grp.corners_t.reshape(-1), share)
    return m


def vector_area(verts: torch.Tensor, faces: MeshFaces, *, validate: bool = True) -> torch.Tensor:
    """``(F, 3)`` vector area ``a_f = 1/2 sum_i x_i x x_{i+1}`` of every face (AW11 Lemma 1, eq. 8).

    Its norm is the area of the maximal projection and its direction that projection's normal;
    it depends only on the boundary loop, so it is well defined for non-planar faces.
    ``validate`` as for :func:`mass`.

    >>> import torch, torch_polylap as tp
    >>> tilted = torch.tensor([[0.0, 0, 0], [2, 0, 0], [2, 1, 1], [0, 1, 1]])
    >>> tp.vector_area(tilted, [[0, 1, 2, 3]]).tolist()  # 2 x sqrt(2) rectangle, tilted 45 deg
    [[0.0, -2.0, 2.0]]
    """
    check_verts(verts, finite=validate)
    out = None
    for topo, grp, x in face_groups(verts, faces):
        if out is None:
            out = verts.new_zeros(topo.num_faces, 3)
        _, _, a = corner_terms(x)
        out = out.index_copy(0, grp.face_ids, a.t())
    return out if out is not None else verts.new_zeros(0, 3)


def face_areas(verts: torch.Tensor, faces: MeshFaces, *, validate: bool = True) -> torch.Tensor:
    """``(F,)`` face areas ``|f| = |a_f|`` (area of the maximal projection); ``validate`` as
    for :func:`mass`."""
    return stable_norm(vector_area(verts, faces, validate=validate), 1)


def edge_lengths(verts: torch.Tensor, faces: MeshFaces, *, validate: bool = True) -> torch.Tensor:
    """``(E,)`` lengths ``|x_q - x_p|`` of the undirected edges, in the order of
    :attr:`Topology.edges <torch_polylap.topology.Topology.edges>`; ``validate`` as for
    :func:`mass`.

    >>> import torch, torch_polylap as tp
    >>> square = torch.tensor([[0.0, 0, 0], [2, 0, 0], [2, 1, 0], [0, 1, 0]])
    >>> tp.edge_lengths(square, [[0, 1, 2, 3]]).tolist()
    [2.0, 1.0, 1.0, 2.0]
    """
    check_verts(verts, finite=validate)
    edges = get_topology(faces, verts.shape[0]).edges.to(verts.device)
    return torch.linalg.vector_norm(verts[edges[:, 1]] - verts[edges[:, 0]], dim=1)


def mean_edge_length(
    verts: torch.Tensor, faces: MeshFaces, *, validate: bool = True
) -> torch.Tensor:
    """Mean length ``h`` of the undirected edges, a 0-dim tensor differentiable in ``verts``:
    the mesh's length scale (the heat method's default time is ``4 h^2``); ``validate`` as
    for :func:`mass`.

    Raises:
        ValueError: the mesh has no edge (no face), so it has no length scale.
    """
    lengths = edge_lengths(verts, faces, validate=validate)
    if lengths.numel() == 0:
        raise ValueError(
            "mean_edge_length: the mesh has no faces, hence no edges and no length scale; "
            "pass a mesh with at least one face."
        )
    return lengths.mean()


def face_normals(verts: torch.Tensor, faces: MeshFaces, *, validate: bool = True) -> torch.Tensor:
    """``(F, 3)`` unit normals of the faces' maximal projections, ``a_f / |a_f|``; ``validate``
    as for :func:`mass`."""
    a = vector_area(verts, faces, validate=validate)
    return a / stable_norm(a, 1, keepdim=True)


def face_nonplanarity(
    verts: torch.Tensor, faces: MeshFaces, plane: str = "projection", *, validate: bool = True
) -> torch.Tensor:
    """``(F,)`` non-planarity of every face: the largest distance of a corner from a plane through
    the corners' centroid, over the face diameter. Zero for planar faces and for triangles; scale
    invariant.

    Args:
        verts: ``(V, 3)`` vertex positions.
        faces: faces in any accepted form, or a :class:`Topology`.
        plane: ``"projection"``: the plane of the maximal projection (normal ``a_f / |a_f|``,
            AW11 sec. 3), differentiable; ``"fit"``: the least-squares plane of the corners
            (normal: the eigenvector of the smallest eigenvalue of their covariance), the usual
            measure in planarization papers. ``"fit"`` is a measure, not a loss: it is computed
            without gradient (an eigenvector's derivative is unstable where the two smallest
            eigenvalues meet); use ``planarity_energy`` as a loss.
        validate: as for :func:`mass`.
    """
    check_verts(verts, finite=validate)
    if plane not in ("projection", "fit"):
        raise ValueError(f'face_nonplanarity: plane must be "projection" or "fit", got {plane!r}.')
    out = verts.new_zeros(0)
    for topo, grp, x in face_groups(verts if plane == "projection" else verts.detach(), faces):
        if out.numel() == 0:
            out = verts.new_zeros(topo.num_faces)
        centered = x - x.mean(1, keepdim=True)  # (3, k, F)
        if plane == "projection":
            _, _, a = corner_terms(x)
            n = a / stable_norm(a, 0)
        else:
            covariance = torch.einsum("ikf,jkf->fij", centered, centered)
            n = torch.linalg.eigh(covariance)[1][:, :, 0].T
        height = (centered * n[:, None]).sum(0).abs().amax(0)
        diff = x.index_select(1, grp.pair_i) - x.index_select(1, grp.pair_j)
        diameter = torch.linalg.vector_norm(diff, dim=0).amax(0)
        out = out.index_copy(0, grp.face_ids, height / diameter)
    return out


def face_planarity_energy(
    verts: torch.Tensor, faces: MeshFaces, lam: Lam = 1.0, *, validate: bool = True
) -> torch.Tensor:
    """``(F,)`` per-face planarity energy ``lambda/2 |Pi E|_F^2`` (AW11 sec. 5.3).

    ``E`` is the face's ``k x 3`` edge matrix and ``Pi E`` its part outside the column space of
    the maximal projection's edges, which vanishes exactly for planar faces (and triangles).
    Summed over faces it is ``E_plan = 1/2 sum_c X_c^T Lplan X_c``; evaluated face by face
    without building ``Lplan``.  On a mesh of triangles only it is zero, and still connected to
    ``verts`` (a zero gradient, so a loss built on it can always call ``backward()``).
    ``validate`` as for :func:`mass`.
    """
    check_verts(verts, finite=validate)
    lam = check_lam(lam)
    out = verts.new_zeros(0)
    for topo, grp, x in face_groups(verts, faces):
        if out.numel() == 0:
            out = verts.new_zeros(topo.num_faces) + 0.0 * verts.sum()
        if grp.k == 3:
            continue
        e, _, a = corner_terms(x)
        n = a / stable_norm(a, 0).clamp_min(torch.finfo(verts.dtype).tiny)
        q1, q2 = plane_basis(e, n)
        # Pi E = E - q1 (q1^T E) - q2 (q2^T E), formed explicitly: subtracting squared norms
        # instead would cancel catastrophically exactly where a planarizing flow converges.
        residual = e - q1 * (e * q1).sum(1, keepdim=True) - q2 * (e * q2).sum(1, keepdim=True)
        out = out.index_copy(0, grp.face_ids, 0.5 * lam * (residual * residual).sum((0, 1)))
    return out


def planarity_energy(
    verts: torch.Tensor, faces: MeshFaces, lam: Lam = 1.0, *, validate: bool = True
) -> torch.Tensor:
    """``E_plan = 1/2 sum_c X_c^T Lplan X_c`` (AW11 sec. 5.3), a differentiable scalar: the sum
    of :func:`face_planarity_energy` (``validate`` as for :func:`mass`)."""
    return face_planarity_energy(verts, faces, lam, validate=validate).sum()

"""The Hodge decomposition of tangent vector fields on polygon meshes.

A tangent field ``X`` on a closed surface splits, orthogonally in ``L^2``, into

    X = grad u + J grad v + h,                                                        (1)

an exact part (a gradient), a co-exact part (a gradient rotated by ``J``, the quarter turn
``J Y = n x Y``) and a harmonic part (``div h = curl h = 0``), whose space has dimension
``2 g`` on a surface of genus ``g``.

Discretization.  A polygon's vertices carry only ``k_f - 1`` independent differences, so a field
that is constant on each polygon (two numbers per face) cannot hold both the gradients and the
rotated gradients of the vertex functions: on a hexagon mesh ``2 F < 2 (V - 1)`` and the two
spaces must intersect (and they do: on the hexagonal and Voronoi spheres of the tests, the
largest cosine between them is 1).  We therefore work on the *virtual refinement* of the
polygon mesh, which splits face ``f`` into its ``k_f`` corner triangles ``(x_i, x_{i+1}, c_f)``
around the face's vertex centroid ``c_f`` (a virtual refinement like that of Bunge et al.
2020, with the centroid as the virtual vertex and its value left free; every triangle is planar
even where the polygon is not).  Fields are constant per corner
triangle ``t``, tangent to it, and the inner product is

    <X, Y> = sum_t |t| X_t . Y_t.                                                     (2)

On that triangle mesh the decomposition of Polthier and Preuss (2003) is exact:

* ``u`` is continuous and piecewise linear (values at the ``V`` vertices and the ``F``
  centroids), ``grad u`` its per-triangle gradient (the package's face gradient, which is the
  linear finite-element gradient on triangles).  The exact part is the ``L^2`` projection on
  those gradients, ``u`` solving the Poisson problem ``L u = -div X`` with ``L`` the cotangent
  Laplacian of the refinement (:func:`~torch_polylap.laplacian`) and ``div`` its divergence
  (:func:`~torch_polylap.divergence`, the negative adjoint of the gradient in (2)).
* ``v`` is piecewise linear and continuous only at edge midpoints (Crouzeix-Raviart: one value
  per edge of the refinement, zero on boundary edges); the co-exact part ``J grad v`` is the
  projection on those rotated gradients, ``v`` solving ``L_CR v = -div_CR (J^T X)`` with the
  Crouzeix-Raviart Laplacian.  On a triangle the Crouzeix-Raviart function of the edge opposite
  corner ``a`` is ``1 - 2 phi_a``, so its gradient is ``-2 grad phi_a`` and ``L_CR`` holds four
  times the cotangent blocks, re-indexed from corners to opposite edges.
* ``h = X - grad u - J grad v``.

Why the parts are orthogonal in (2): the projections make ``h`` orthogonal to both spaces, and
the two spaces are orthogonal to each other because, triangle by triangle,
``|t| grad u . J grad v`` integrates to a sum over the triangle's edges of
``|e| v(m_e) d_s u`` (``m_e`` the midpoint, ``d_s u`` the derivative of ``u`` along the edge):
``u`` is continuous, so ``d_s u`` is the same on both sides of an interior edge, ``v(m_e)`` too,
and the two triangles traverse the edge in opposite directions; boundary edges have
``v(m_e) = 0``.  Every linear function is a Crouzeix-Raviart function too, so the rotated
gradient of a continuous ``u`` is exactly co-exact.  Counting dimensions on a closed surface
(``V' - 1`` gradients, ``E' - 1`` rotated gradients, ``2 T`` field values on ``T`` triangles,
``V' - E' + T = 2 - 2 g``) leaves exactly ``2 g`` harmonic dimensions, as in the smooth case.
"""

from __future__ import annotations

from typing import NamedTuple

import torch

from .._typing import MeshFaces
from ..calculus import corner_gradients_of, divergence, gradient_operator_of
from ..checks import check_verts
from ..kernels.frames import stable_norm
from ..linalg import dirichlet_solve
from ..measures import vector_area
from ..operators import laplacian
from ..sparse import SparseOperator, from_coo
from ..topology import Topology, build_topology, get_topology
from ..topology.analysis import half_edge_vertices
from ..tracing import outside_transforms

__all__ = ["HodgeDecomposition", "HodgeParts", "virtual_refinement"]


class HodgeParts(NamedTuple):
    """The parts of (1), each ``(T, 3)`` (or ``(T, 3, C)``) per corner triangle, and the
    potentials: ``u`` ``(V + F[, C])`` at the vertices then the face centroids, ``v``
    ``(E'[, C])`` at the edges of the refinement (:attr:`HodgeDecomposition.edges`)."""

    exact: torch.Tensor
    coexact: torch.Tensor
    harmonic: torch.Tensor
    u: torch.Tensor
    v: torch.Tensor


class _Refinement(NamedTuple):
    """Index data of the virtual refinement, fixed by the faces (cached on the topology)."""

    triangles: torch.Tensor  # (T, 3): (x_i, x_{i+1}, V + f) for the corner i of face f
    face: torch.Tensor  # (T,) the polygon of each triangle
    topology: Topology  # of the refinement, V + F vertices
    opposite_edge: torch.Tensor  # (T, 3) refined edge opposite each corner
    pin_u: torch.Tensor  # one refined vertex per connected component
    pin_v: torch.Tensor  # boundary edges, and one edge per closed component


def _refinement(topo: Topology) -> _Refinement:
    key = ("vector.refinement", torch.device("cpu"))
    cached = topo.derived.get(key)
    if cached is None:
        with outside_transforms():
            faces = topo.faces
            topo.require_manifold("hodge decomposition", vertices=False)
            topo.require_oriented("hodge decomposition")
            src, dst = half_edge_vertices(faces)
            face = faces.corner_face
            n = topo.num_verts + faces.num_faces
            triangles = torch.stack((src, dst, topo.num_verts + face), 1)
            refined = build_topology(triangles, n, warn=False)
            # corner p of triangle t starts half-edge 3 t + p; the edge opposite p is the next one
            he = torch.arange(3 * triangles.shape[0]).reshape(-1, 3).roll(-1, dims=1)
            opposite = refined.half_edge_edge[he]
            count, labels = refined.connected_components()
            first = torch.full((count,), n, dtype=torch.int64).scatter_reduce(
                0, labels, torch.arange(n), reduce="amin"
            )
            edge_label = labels[refined.edges[:, 0]]
            on_boundary = refined.edge_faces == 1
            open_component = torch.zeros(count, dtype=torch.bool)
            open_component[edge_label[on_boundary]] = True
            num_edges = refined.num_edges
            first_edge = torch.full((count,), num_edges, dtype=torch.int64).scatter_reduce(
                0, edge_label, torch.arange(num_edges), reduce="amin"
            )
            closed = (~open_component) & (first_edge < num_edges)
            pin_v = torch.unique(torch.cat((torch.nonzero(on_boundary)[:, 0], first_edge[closed])))
            cached = _Refinement(triangles, face, refined, opposite, first, pin_v)
        topo.derived[key] = cached
    return cached


def virtual_refinement(verts: torch.Tensor, faces: MeshFaces) -> tuple[torch.Tensor, torch.Tensor]:
    """The corner triangles of every polygon around its vertex centroid.

    Returns:
        ``(refined_verts (V + F, 3), triangles (T, 3))``: the vertices followed by the face
        centroids (differentiable in ``verts``), and triangle ``(x_i, x_{i+1}, c_f)`` for the
        ``i``-th corner of every face ``f``, in the order of the packed corners (``T`` = number
        of corners), oriented like its face.
    """
    check_verts(verts)
    topo = get_topology(faces, verts.shape[0])
    ref = _refinement(topo)
    return _refined_verts(verts, topo), ref.triangles.to(verts.device)


def _refined_verts(verts: torch.Tensor, topo: Topology) -> torch.Tensor:
    faces = topo.faces
    idx = faces.indices.to(verts.device)
    face = faces.corner_face.to(verts.device)
    sums = verts.new_zeros(faces.num_faces, 3).index_add(0, face, verts[idx])
    centroids = sums / faces.sizes.to(verts.device, verts.dtype)[:, None]
    return torch.cat((verts, centroids))


class HodgeDecomposition:
    """The Hodge decomposition (1) of tangent fields on a polygon mesh, prefactored.

    Builds the virtual refinement, the two Laplacians (cotangent for ``u``, Crouzeix-Raviart
    for ``v``) and the per-triangle gradients once; :func:`~torch_polylap.solve` caches the
    factorizations on the operators, so repeated :meth:`__call__` reuse them.  Differentiable
    with respect to ``verts`` and the fields (O(nnz) backward through the solves).

    Args:
        verts: ``(V, 3)`` vertex positions.
        faces: faces in any accepted form, or a :class:`~torch_polylap.topology.Topology`;
            manifold and consistently oriented (the orthogonality argument needs every interior
            edge traversed in both directions).

    Attributes:
        refined_verts: ``(V + F, 3)`` the vertices, then the face centroids.
        triangles: ``(T, 3)`` the corner triangles (see :func:`virtual_refinement`).
        areas: ``(T,)`` triangle areas, the weights of the inner product (2).
        normals: ``(T, 3)`` unit triangle normals (``J Y = normals x Y``).
        edges: ``(E', 2)`` the refinement's edges, where ``v`` lives.
        laplacian: ``(V + F, V + F)`` cotangent Laplacian of the refinement.
        cr_laplacian: ``(E', E')`` Crouzeix-Raviart Laplacian of the refinement.

    Raises:
        ValueError: a non-manifold or inconsistently oriented mesh, or bad ``verts``.

    Examples:
        The gradient of a function is its own exact part:

        >>> import torch, torch_polylap as tp
        >>> verts, faces = tp.shapes.torus(8, 6)
        >>> hodge = tp.vector.HodgeDecomposition(verts, faces)
        >>> parts = hodge(hodge.gradient(verts[:, 2] ** 2))
        >>> bool(parts.coexact.abs().max() < 1e-12 and parts.harmonic.abs().max() < 1e-12)
        True
    """

    def __init__(self, verts: torch.Tensor, faces: MeshFaces) -> None:
        check_verts(verts)
        self.topology = get_topology(faces, verts.shape[0])
        ref = _refinement(self.topology)
        device = verts.device
        self._ref = ref
        self.num_verts = verts.shape[0]
        self.refined_verts = _refined_verts(verts, self.topology)
        self.triangles = ref.triangles.to(device)
        self.edges = ref.topology.edges.to(device)
        a = vector_area(self.refined_verts, ref.topology, validate=False)
        self.areas = stable_norm(a, 1)
        self.normals = a / self.areas[:, None]
        self.laplacian, _ = laplacian(self.refined_verts, ref.topology)
        # refined_verts are checked: they are verts and face centroids
        self._gradient = gradient_operator_of(self.refined_verts, ref.topology)
        self._hat = self._hat_gradients()
        self.cr_laplacian = self._cr_laplacian()

    def _hat_gradients(self) -> torch.Tensor:
        """``(T, 3, 3)``: ``[t, p]`` the gradient on triangle ``t`` of the hat function of its
        corner ``p``."""
        # the refinement's corners are packed triangle by triangle
        return corner_gradients_of(self.refined_verts, self._ref.topology).reshape(-1, 3, 3)

    def _cr_laplacian(self) -> SparseOperator:
        hat = self._hat
        blocks = 4 * self.areas[:, None, None] * (hat @ hat.transpose(1, 2))  # (T, 3, 3)
        opp = self._ref.opposite_edge.to(hat.device)
        rows = opp[:, :, None].expand(-1, 3, 3).reshape(-1)
        cols = opp[:, None, :].expand(-1, 3, 3).reshape(-1)
        n = self._ref.topology.num_edges
        return from_coo(rows, cols, blocks.reshape(-1), (n, n), symmetric=True)

    # -- fields on the refinement -----------------------------------------------------------

    def gradient(self, u: torch.Tensor) -> torch.Tensor:
        """``(T, 3[, C])`` per-triangle gradient of ``u`` given at the ``V`` vertices (the
        centroids get the mean of their face's corners) or at all ``V + F`` refined vertices."""
        u = self._extend(u)
        tail = u.shape[1:]
        g = self._gradient @ u.reshape(u.shape[0], -1)
        return g.reshape((self.triangles.shape[0], 3) + tail)

    def _extend(self, u: torch.Tensor) -> torch.Tensor:
        n, m = self.num_verts, self.refined_verts.shape[0]
        if u.shape[0] == m:
            return u
        if u.shape[0] != n:
            raise ValueError(
                f"expected values at the {n} vertices or the {m} refined vertices, got shape "
                f"{tuple(u.shape)}."
            )
        faces = self.topology.faces
        idx = faces.indices.to(u.device)
        face = faces.corner_face.to(u.device)
        sums = u.new_zeros((faces.num_faces,) + u.shape[1:]).index_add(0, face, u[idx])
        sizes = faces.sizes.to(u.device, u.dtype).reshape((-1,) + (1,) * (u.dim() - 1))
        return torch.cat((u, sums / sizes))

    def rotate(self, field: torch.Tensor) -> torch.Tensor:
        """``J X = n_t x X_t``, the quarter turn in each triangle's plane."""
        n = self.normals.reshape(self.normals.shape + (1,) * (field.dim() - 2))
        return torch.linalg.cross(n.expand_as(field), field, dim=1)

    def tangential(self, field: torch.Tensor) -> torch.Tensor:
        """``X_t`` minus its component along the triangle's normal."""
        n = self.normals.reshape(self.normals.shape + (1,) * (field.dim() - 2))
        return field - (field * n).sum(1, keepdim=True) * n

    def from_vertices(self, field: torch.Tensor) -> torch.Tensor:
        """``(V, 3[, C])`` vertex vectors -> ``(T, 3[, C])`` per triangle: the mean of the
        triangle's three values (the centroid's being the mean of its face's corners), made
        tangent to the triangle."""
        X = self._extend(field)
        return self.tangential(X[self.triangles].mean(1))

    def to_vertices(self, field: torch.Tensor) -> torch.Tensor:
        """``(T, 3[, C])`` -> ``(V, 3[, C])``: the area-weighted mean of the triangles around
        each vertex (not projected on any tangent plane; zero at isolated vertices)."""
        w = self.areas.reshape(self.areas.shape + (1,) * (field.dim() - 1))
        tri = self.triangles[:, :2]  # the centroid corner does not belong to a vertex
        out = field.new_zeros((self.num_verts,) + field.shape[1:])
        weight = self.areas.new_zeros(self.num_verts)
        for p in range(2):
            out = out.index_add(0, tri[:, p], w * field)
            weight = weight.index_add(0, tri[:, p], self.areas)
        weight = torch.where(weight > 0, weight, torch.ones_like(weight))
        return out / weight.reshape(weight.shape + (1,) * (field.dim() - 1))

    def inner(self, X: torch.Tensor, Y: torch.Tensor) -> torch.Tensor:
        """The inner product (2), ``sum_t |t| X_t . Y_t`` (per channel for ``(T, 3, C)``)."""
        w = self.areas.reshape(self.areas.shape + (1,) * (X.dim() - 1))
        return (w * X * Y).sum((0, 1))

    # -- the decomposition ------------------------------------------------------------------

    def __call__(self, field: torch.Tensor) -> HodgeParts:
        """Decompose ``field`` ``(T, 3)`` or ``(T, 3, C)`` (per corner triangle; its normal
        components are dropped first) into the parts of (1).

        Raises:
            ValueError: a field whose shape does not match the refinement.
        """
        T = self.triangles.shape[0]
        if field.dim() not in (2, 3) or field.shape[:2] != (T, 3):
            raise ValueError(
                f"the field must have shape ({T}, 3) or ({T}, 3, C) (one vector per corner "
                f"triangle; use from_vertices for vertex vectors), got {tuple(field.shape)}."
            )
        X = self.tangential(field.to(self.areas.dtype))
        flat = X.dim() == 2
        Xc = X[:, :, None] if flat else X
        C = Xc.shape[2]
        ref = self._ref
        device = X.device
        rhs_u = -divergence(self.refined_verts, ref.topology, Xc)
        pin_u = ref.pin_u.to(device)
        u = dirichlet_solve(self.laplacian, rhs_u, pin_u, rhs_u.new_zeros(pin_u.numel(), C))
        exact = (self._gradient @ u).reshape(T, 3, C)
        # <J grad psi_e, X> = <grad psi_e, J^T X>; grad psi_e = -2 grad phi_a on each triangle
        Jt_X = -self.rotate(Xc)
        weighted = self.areas[:, None, None] * Jt_X
        per_corner = -2 * torch.einsum("tpd,tdc->tpc", self._hat, weighted)
        opp = ref.opposite_edge.to(device)
        rhs_v = Xc.new_zeros(ref.topology.num_edges, C).index_add(
            0, opp.reshape(-1), per_corner.reshape(-1, C)
        )
        pin_v = ref.pin_v.to(device)
        v = dirichlet_solve(self.cr_laplacian, rhs_v, pin_v, rhs_v.new_zeros(pin_v.numel(), C))
        grad_v = -2 * torch.einsum("tpd,tpc->tdc", self._hat, v[opp])
        coexact = self.rotate(grad_v)
        harmonic = Xc - exact - coexact
        if flat:
            return HodgeParts(exact[..., 0], coexact[..., 0], harmonic[..., 0], u[:, 0], v[:, 0])
        return HodgeParts(exact, coexact, harmonic, u, v)

"""Per-face kernel of the "Polygon Laplacian Made Simple" operator (PLMS).

Bunge, Herholz, Kazhdan and Botsch 2020, "Polygon Laplacian Made Simple" (Comput. Graph. Forum
39(2)), sec. 3: every face ``f`` with corners ``x_0 .. x_{k-1}`` gets a virtual vertex
``x_f = sum_i w_i x_i`` with affine weights (``sum_i w_i = 1``) at the point that minimizes the
sum of squared areas of the triangle fan ``(x_i, x_{i+1}, x_f)``; for ``k > 4``, or
planar faces, the weights realizing that point are not unique and the minimum-norm ones are
taken. With the prolongation ``P = [I; w^T]`` (``(k + 1) x k``) the face's blocks are

    L_f = P^T L_fan P,        m_f = diag(P^T M_fan P 1)

where ``L_fan`` is the cotangent Laplacian of the fan and ``M_fan`` its Galerkin mass; lumped,
``P^T M_fan P 1 = P^T M_fan 1`` gives each fan triangle's area in thirds to its corners, the
virtual vertex's share prolonged with ``w`` (what the authors' polyLaplace code does, and the
mass with which its published errors reproduce). ``L_f`` is what libigl's polygon
``cotmatrix(V, I, C)`` returns (up to sign; the tests compare the two to round-off); libigl's
mass uses mixed Voronoi corner areas instead (Meyer et al. 2003), which differ on curved or
non-convex fans.

Everything is evaluated in structure-of-arrays layout (``(3, k, F)`` per degree group), in the
face's centered and scaled frame ``y = (x - c) / s`` (``c`` the corner centroid,
``s^2 = sum_i |g_i|^2`` as in :func:`~torch_polylap.kernels.aw11.polygon_entries`), so that no
quantity of order ``s^4`` is formed and faces far from the origin lose no precision. The
``3 x 3`` and ``2 x 2`` systems are solved in closed form (adjugates): no SVD, no batched LAPACK
call, and derivatives everywhere except where a face becomes exactly planar. There a quad's
``L`` itself jumps: the unique weights of a non-planar quad do not tend to the planar quad's
minimum-norm ones (2.3 % of the largest entry on a generic quad lifted by ``1e-12``), as in
the reference implementations (docs/math/properties.md, "Finite precision").
"""

from __future__ import annotations

from typing import NamedTuple

import torch

from .entries import BlockEntries
from .frames import face_frame

__all__ = ["virtual_vertex_weights", "virtual_vertices", "plms_entries", "error_factor"]


# A vector field over corners or faces as its three coordinate rows: ``(k, F)`` or ``(F,)``
# each. Component arithmetic fuses what stacked ``(3, k, F)`` arithmetic does in several passes
# (products, sums over the coordinate axis, stacks), and the kernel is memory bound.
Vec = tuple[torch.Tensor, torch.Tensor, torch.Tensor]


def _dot(a: Vec, b: Vec) -> torch.Tensor:
    return torch.addcmul(torch.addcmul(a[0] * b[0], a[1], b[1]), a[2], b[2])


def _cross(a: Vec, b: Vec) -> Vec:
    ax, ay, az = a
    bx, by, bz = b
    return (
        torch.addcmul(ay * bz, az, by, value=-1),
        torch.addcmul(az * bx, ax, bz, value=-1),
        torch.addcmul(ax * by, ay, bx, value=-1),
    )


def _sub(a: Vec, b: Vec) -> Vec:
    return (a[0] - b[0], a[1] - b[1], a[2] - b[2])


def _next(a: Vec, shift: int = -1) -> Vec:
    """Each corner's successor: row ``i`` holds corner ``i + 1`` (cyclically); ``shift=1``:
    its predecessor."""
    return (torch.roll(a[0], shift, 0), torch.roll(a[1], shift, 0), torch.roll(a[2], shift, 0))


def _fan_minimizer(y: torch.Tensor) -> torch.Tensor:
    """``(3, F)`` point ``z`` minimizing ``sum_i |(y_i - z) x (y_{i+1} - z)|^2`` (PLMS sec. 3).

    Args:
        y: ``(3, k, F)`` corners in the face's centered, scaled frame.
    """
    Y = (y[0], y[1], y[2])
    Q = _next(Y)
    return torch.stack(_fan_point(Y, _sub(Q, Y), _cross(Y, Q)))


def _fan_point(Y: Vec, E: Vec, C: Vec) -> Vec:
    """:func:`_fan_minimizer` from the corners ``Y``, the edges ``E = y_{i+1} - y_i`` and the
    cross products ``C = y_i x y_{i+1}``.

    ``(y_i - z) x (y_{i+1} - z) = y_i x y_{i+1} - z x e_i`` is affine in ``z``, so the minimizer
    solves ``A z = b`` with ``A = sum_i (|e_i|^2 I - e_i e_i^T)`` (positive definite unless every
    edge is parallel) and ``b = sum_i e_i x (y_i x y_{i+1})``; solved by the adjugate.
    """
    bx, by, bz = (c.sum(0) for c in _cross(E, C))
    ex, ey, ez = E
    sxx, syy, szz = (ex * ex).sum(0), (ey * ey).sum(0), (ez * ez).sum(0)
    sxy, sxz, syz = (ex * ey).sum(0), (ex * ez).sum(0), (ey * ez).sum(0)
    # A = tr(ee^T) I - ee^T, symmetric
    a00, a11, a22 = syy + szz, sxx + szz, sxx + syy
    a01, a02, a12 = -sxy, -sxz, -syz
    # adjugate of the symmetric 3 x 3 matrix: z = adj(A) b / det(A)
    c00 = a11 * a22 - a12 * a12
    c01 = a02 * a12 - a01 * a22
    c02 = a01 * a12 - a02 * a11
    c11 = a00 * a22 - a02 * a02
    c12 = a01 * a02 - a00 * a12
    c22 = a00 * a11 - a01 * a01
    det = a00 * c00 + a01 * c01 + a02 * c02
    inv_det = 1.0 / det.clamp_min(torch.finfo(det.dtype).tiny)
    return (
        (c00 * bx + c01 * by + c02 * bz) * inv_det,
        (c01 * bx + c11 * by + c12 * bz) * inv_det,
        (c02 * bx + c12 * by + c22 * bz) * inv_det,
    )


def virtual_vertex_weights(Y: Vec, z: Vec, n: Vec) -> torch.Tensor:
    """``(k, F)`` minimum-norm affine weights ``w`` with ``sum_i w_i y_i = z`` (PLMS sec. 3).

    See :func:`_weights_and_heights`, which also returns the heights that condition them.
    """
    return _weights_and_heights(Y, z, n)[0]


def _weights_and_heights(Y: Vec, z: Vec, n: Vec) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`virtual_vertex_weights` and ``(F,)`` the squared height of each face relative to
    its in-plane spread (``sum_i h_i^2 / sum_i |u_i|^2``), zero for a face judged planar.

    With centered corners (``sum_i y_i = 0``), ``w = 1/k + v`` where ``v`` is the minimum-norm
    solution of ``Y^T v = z``, i.e. ``v`` in the span of the corners' coordinate columns. In the
    face frame ``(t1, t2, n)`` these are the in-plane coordinates ``U = (u1, u2)`` and the heights
    ``h``; ``v = U G^-1 p + h' (q - h . U G^-1 p) / |h'|^2`` with ``G = U^T U``, ``p``, ``q`` the
    in-plane and normal parts of ``z`` and ``h' = h - U G^-1 U^T h`` the heights' part outside
    the plane's columns. A face whose ``h'`` is at round-off level is planar: its weights live
    in the plane (the rank decision libigl's complete orthogonal decomposition makes).

    Args:
        Y: coordinate rows ``(k, F)`` of the centered, scaled corners.
        z: coordinate rows ``(F,)`` of the virtual vertex.
        n: coordinate rows ``(F,)`` of the unit normals of the faces' maximal projections.
    """
    k = Y[0].shape[0]
    t1, t2 = face_frame(torch.stack(n))
    T1, T2 = (t1[0], t1[1], t1[2]), (t2[0], t2[1], t2[2])
    # Re-centered: the centroid's round-off leaves a constant offset of order eps in the
    # heights of a planar face, which the min-norm solve would read as a genuine height.
    u1, u2, h = (c - c.mean(0) for c in (_dot(Y, T1), _dot(Y, T2), _dot(Y, n)))
    g11, g12, g22 = (u1 * u1).sum(0), (u1 * u2).sum(0), (u2 * u2).sum(0)
    inv_det = 1.0 / (g11 * g22 - g12 * g12).clamp_min(torch.finfo(u1.dtype).tiny)

    def in_plane(r1: torch.Tensor, r2: torch.Tensor) -> torch.Tensor:
        """``U G^-1 r`` for a right-hand side ``r = (r1, r2)`` of shape ``(F,)`` each."""
        a1 = (g22 * r1 - g12 * r2) * inv_det
        a2 = (g11 * r2 - g12 * r1) * inv_det
        return torch.addcmul(u1 * a1, u2, a2)

    v = in_plane(_dot(z, T1), _dot(z, T2))
    h_out = h - in_plane((u1 * h).sum(0), (u2 * h).sum(0))
    hh = (h_out * h_out).sum(0)
    q = _dot(z, n) - (h * v).sum(0)
    # Heights below ~k eps of the (unit-order) in-plane spread are round-off of a planar face.
    planar = hh <= (k * torch.finfo(u1.dtype).eps) ** 2 * (g11 + g22)
    factor = torch.where(planar, torch.zeros_like(q), q / torch.where(planar, 1.0, hh))
    height2 = torch.where(planar, 0.0, (h * h).sum(0) / (g11 + g22))
    return torch.addcmul(v + 1.0 / k, factor, h_out), height2


class _VirtualVertex(NamedTuple):
    """The face's virtual vertex and what its frame computed on the way (see
    :func:`_virtual_vertex`)."""

    size2: torch.Tensor
    Y: Vec
    Q: Vec
    E: Vec
    z: Vec
    w: torch.Tensor
    height2: torch.Tensor
    area_scaled: torch.Tensor


def _virtual_vertex(x: torch.Tensor) -> _VirtualVertex:
    """The virtual vertex of every face of ``x`` ``(3, k, F)`` in its centered, scaled frame.

    Returns ``s^2`` ``(F,)``; the scaled corners ``Y``, their successors ``Q`` and the edges
    ``E`` (coordinate rows ``(k, F)``); the virtual vertex ``z`` (rows ``(F,)``, scaled frame);
    the affine weights ``w`` ``(k, F)``; the relative squared heights ``(F,)`` and ``|f| / s^2``.
    """
    tiny = torch.finfo(x.dtype).tiny
    X = (x[0], x[1], x[2])
    # s^2 = sum_i |g_i|^2 with g_i = (x_{i+1} - x_{i-1}) / 2
    G = _sub(_next(X), _next(X, 1))
    size2 = 0.25 * _dot(G, G).sum(0)
    inv_s = torch.rsqrt(size2.clamp_min(tiny))
    yx, yy, yz = ((c - c.mean(0)) * inv_s for c in X)
    Y = (yx, yy, yz)
    Q = _next(Y)
    E = _sub(Q, Y)
    C = _cross(Y, Q)
    # vector area 1/2 sum_i y_i x y_{i+1} (AW11 eq. 8): exact enough on the centered, scaled
    # corners (the fan from a corner is for faces far from the origin)
    a = (0.5 * C[0].sum(0), 0.5 * C[1].sum(0), 0.5 * C[2].sum(0))
    area_scaled = torch.sqrt(_dot(a, a).clamp_min(tiny))
    z = _fan_point(Y, E, C)
    w, height2 = _weights_and_heights(
        Y, z, (a[0] / area_scaled, a[1] / area_scaled, a[2] / area_scaled)
    )
    return _VirtualVertex(size2, Y, Q, E, z, w, height2, area_scaled)


def virtual_vertices(x: torch.Tensor) -> torch.Tensor:
    """``(k, F)`` the affine weights of the virtual vertex of every face (PLMS sec. 3), the
    minimizer of the sum of squared fan-triangle areas, for corners ``x`` ``(3, k, F)``."""
    return _virtual_vertex(x).w


def plms_entries(x: torch.Tensor, pair_i: torch.Tensor, pair_j: torch.Tensor) -> BlockEntries:
    """Off-diagonal entries of ``L_f = P^T L_fan P`` and the lumped corner masses (PLMS sec. 3).

    The fan triangle ``i`` is ``(y_i, y_{i+1}, z)``. Its cotangents give ``L_fan``'s entries
    (this package's positive semi-definite sign): ``(i, i+1)``: ``-cot_z / 2``;
    ``(i, f)``: ``l_i = -(cot at y_{i+1} in triangle i + cot at y_{i-1} in triangle i-1) / 2``;
    ``(f, f)``: ``-sum_i l_i``. Then
    ``(L_f)_ij = (L_fan)_ij + l_i w_j + w_i l_j + (L_fan)_ff w_i w_j`` and the lumped mass of
    corner ``i`` is ``m_i + m_f w_i`` (``P 1 = 1``; ``m`` the fan's lumped Galerkin masses, a
    third of each fan triangle's area at each of its corners).

    Args:
        x: ``(3, k, F)`` corner positions.
        pair_i, pair_j: ``(P,)`` local corner pairs ``i < j``.

    Returns:
        ``off`` ``(P, F)``; ``mass`` ``(k, F)``: lumped mass of each corner; ``area`` ``(F,)``:
        ``|f|`` (norm of the vector area, for the zero-area check); ``size2`` ``(F,)``: ``s^2``;
        ``error`` ``(F,)``: :func:`error_factor`, the expected relative error in units of eps.
    """
    k = x.shape[1]
    tiny = torch.finfo(x.dtype).tiny
    size2, Y, Q, E, z, w, height2, area_scaled = _virtual_vertex(x)

    # fan triangle i: p = y_i, q = y_{i+1}, z; cotangents by dot / |cross|
    zp, zq = _sub(Y, z), _sub(Q, z)
    cr = _cross(zp, zq)
    dbl = torch.sqrt(_dot(cr, cr).clamp_min(tiny))  # twice the areas, (k, F)
    cot_z = _dot(zp, zq) / dbl
    cot_q = _dot(E, zq) / dbl
    cot_p = -_dot(E, zp) / dbl
    ell = -0.5 * (cot_q + torch.roll(cot_p, 1, dims=0))  # (L_fan)_{i f}
    l_ff = -ell.sum(0)

    # (L_fan)_{ij} on the cycle: pair (i, i+1) is fan edge i, pair (0, k-1) is fan edge k-1
    step = pair_j - pair_i
    edge = torch.where(step == 1, pair_i, pair_j)
    on_cycle = ((step == 1) | (step == k - 1)).to(x.dtype)
    off = (-0.5 * on_cycle)[:, None] * cot_z.index_select(0, edge)
    # l_i w_j + w_i l_j + l_ff w_i w_j = r_i w_j + w_i r_j with r = l + l_ff w / 2
    r = torch.addcmul(ell, 0.5 * l_ff, w)
    off = torch.addcmul(off, r.index_select(0, pair_i), w.index_select(0, pair_j))
    off = torch.addcmul(off, w.index_select(0, pair_i), r.index_select(0, pair_j))

    # lumped Galerkin fan mass: a third of fan triangle i's area at y_i, y_{i+1} and z
    third = dbl / 6.0
    m_corner = third + torch.roll(third, 1, dims=0)
    mass = (m_corner + third.sum(0) * w) * size2
    error = error_factor(area_scaled.detach(), height2.detach())
    return BlockEntries(off, mass, area_scaled * size2, size2, error)


def error_factor(thinness: torch.Tensor, height2: torch.Tensor) -> torch.Tensor:
    """``(F,)`` bound on the relative error of a face's block and its gradient, in units of the
    working precision's epsilon.

    Measured in float32 against float64 on random convex, concave, thin, planar and bumpy
    faces (docs/math/properties.md, "Finite precision"): ``16 / t`` for planar faces, with
    ``t = |f| / s^2``; for faces with relative height ``h`` (``height2 = h^2``) the weights
    ``w`` carry terms ``q h' / |h'|^2`` whose rounding grows as ``1 / (t h)`` on thin faces and
    ``1 / h^2`` on nearly planar ones (float32 gradients off by 2.5 at ``h = 1e-4``).
    """
    rel = height2.clamp_min(torch.finfo(height2.dtype).tiny)
    bumpy = (32.0 * torch.rsqrt(rel) + 1.0 / rel) * (height2 > 0)
    return (16.0 + bumpy) / thinness

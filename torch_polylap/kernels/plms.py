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
call, and derivatives everywhere except where a face becomes exactly planar.
"""

from __future__ import annotations

import torch

from .frames import corner_terms, face_frame

__all__ = ["virtual_vertex_weights", "plms_entries"]


def _cross(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Cross products along the leading axis of two ``(3, ...)`` tensors."""
    ax, ay, az = a
    bx, by, bz = b
    return torch.stack((ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx))


def _fan_minimizer(y: torch.Tensor) -> torch.Tensor:
    """``(3, F)`` point ``z`` minimizing ``sum_i |(y_i - z) x (y_{i+1} - z)|^2`` (PLMS sec. 3).

    ``(y_i - z) x (y_{i+1} - z) = y_i x y_{i+1} - z x e_i`` is affine in ``z``, so the minimizer
    solves ``A z = b`` with ``A = sum_i (|e_i|^2 I - e_i e_i^T)`` (positive definite unless every
    edge is parallel) and ``b = sum_i e_i x (y_i x y_{i+1})``; solved by the adjugate.

    Args:
        y: ``(3, k, F)`` corners in the face's centered, scaled frame.
    """
    e = torch.roll(y, -1, dims=1) - y
    c = _cross(y, torch.roll(y, -1, dims=1))
    b = _cross(e, c).sum(1)  # (3, F)
    ee = torch.einsum("akf,bkf->abf", e, e)  # (3, 3, F) sum_i e_i e_i^T
    a = torch.eye(3, dtype=y.dtype, device=y.device)[:, :, None] * (ee[0, 0] + ee[1, 1] + ee[2, 2])
    a = a - ee
    # adjugate of the symmetric 3 x 3 matrix: z = adj(A) b / det(A)
    c00 = a[1, 1] * a[2, 2] - a[1, 2] * a[1, 2]
    c01 = a[0, 2] * a[1, 2] - a[0, 1] * a[2, 2]
    c02 = a[0, 1] * a[1, 2] - a[0, 2] * a[1, 1]
    c11 = a[0, 0] * a[2, 2] - a[0, 2] * a[0, 2]
    c12 = a[0, 1] * a[0, 2] - a[0, 0] * a[1, 2]
    c22 = a[0, 0] * a[1, 1] - a[0, 1] * a[0, 1]
    det = a[0, 0] * c00 + a[0, 1] * c01 + a[0, 2] * c02
    inv_det = 1.0 / det.clamp_min(torch.finfo(y.dtype).tiny)
    return (
        torch.stack(
            (
                c00 * b[0] + c01 * b[1] + c02 * b[2],
                c01 * b[0] + c11 * b[1] + c12 * b[2],
                c02 * b[0] + c12 * b[1] + c22 * b[2],
            )
        )
        * inv_det
    )


def virtual_vertex_weights(y: torch.Tensor, z: torch.Tensor, normal: torch.Tensor) -> torch.Tensor:
    """``(k, F)`` minimum-norm affine weights ``w`` with ``sum_i w_i y_i = z`` (PLMS sec. 3).

    With centered corners (``sum_i y_i = 0``), ``w = 1/k + v`` where ``v`` is the minimum-norm
    solution of ``Y^T v = z``, i.e. ``v`` in the span of the corners' coordinate columns. In the
    face frame ``(t1, t2, n)`` these are the in-plane coordinates ``U = (u1, u2)`` and the heights
    ``h``; ``v = U G^-1 p + h' (q - h . U G^-1 p) / |h'|^2`` with ``G = U^T U``, ``p``, ``q`` the
    in-plane and normal parts of ``z`` and ``h' = h - U G^-1 U^T h`` the heights' part outside
    the plane's columns. A face whose ``h'`` is at round-off level is planar: its weights live
    in the plane (the rank decision libigl's complete orthogonal decomposition makes).

    Args:
        y: ``(3, k, F)`` centered, scaled corners; ``z``: ``(3, F)`` the virtual vertex;
        normal: ``(3, F)`` unit normals of the faces' maximal projections.
    """
    k = y.shape[1]
    t1, t2 = face_frame(normal)
    # Re-centered: the centroid's round-off leaves a constant offset of order eps in the
    # heights of a planar face, which the min-norm solve would read as a genuine height.
    u1, u2, h = (((y * t[:, None]).sum(0)) for t in (t1, t2, normal))  # (k, F) each
    u1, u2, h = (c - c.mean(0) for c in (u1, u2, h))
    g11, g12, g22 = (u1 * u1).sum(0), (u1 * u2).sum(0), (u2 * u2).sum(0)
    inv_det = 1.0 / (g11 * g22 - g12 * g12).clamp_min(torch.finfo(y.dtype).tiny)

    def in_plane(r1: torch.Tensor, r2: torch.Tensor) -> torch.Tensor:
        """``U G^-1 r`` for a right-hand side ``r = (r1, r2)`` of shape ``(F,)`` each."""
        a1 = (g22 * r1 - g12 * r2) * inv_det
        a2 = (g11 * r2 - g12 * r1) * inv_det
        return u1 * a1 + u2 * a2

    v = in_plane((z * t1).sum(0), (z * t2).sum(0))
    h_out = h - in_plane((u1 * h).sum(0), (u2 * h).sum(0))
    hh = (h_out * h_out).sum(0)
    q = (z * normal).sum(0) - (h * v).sum(0)
    # Heights below ~k eps of the (unit-order) in-plane spread are round-off of a planar face.
    planar = hh <= (k * torch.finfo(y.dtype).eps) ** 2 * (g11 + g22)
    factor = torch.where(planar, torch.zeros_like(q), q / torch.where(planar, 1.0, hh))
    return (1.0 / k) + v + factor * h_out


def plms_entries(
    x: torch.Tensor, pair_i: torch.Tensor, pair_j: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
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
        ``|f|`` (norm of the vector area, for the zero-area check); ``size2`` ``(F,)``: ``s^2``.
    """
    k = x.shape[1]
    tiny = torch.finfo(x.dtype).tiny
    _, g, _ = corner_terms(x)
    size2 = (g * g).sum((0, 1))
    y = (x - x.mean(1, keepdim=True)) * torch.rsqrt(size2.clamp_min(tiny))
    _, _, a = corner_terms(y)
    area_scaled = torch.sqrt((a * a).sum(0).clamp_min(tiny))
    z = _fan_minimizer(y)
    w = virtual_vertex_weights(y, z, a / area_scaled)

    # fan triangle i: p = y_i, q = y_{i+1}, z; cotangents by dot / |cross|
    q = torch.roll(y, -1, dims=1)
    zp, zq, e = y - z[:, None], q - z[:, None], q - y
    dbl = torch.sqrt((_cross(zp, zq) ** 2).sum(0).clamp_min(tiny))  # twice the areas, (k, F)
    cot_z = (zp * zq).sum(0) / dbl
    cot_q = (e * zq).sum(0) / dbl
    cot_p = -(e * zp).sum(0) / dbl
    ell = -0.5 * (cot_q + torch.roll(cot_p, 1, dims=0))  # (L_fan)_{i f}
    l_ff = -ell.sum(0)

    # (L_fan)_{ij} on the cycle: pair (i, i+1) is fan edge i, pair (0, k-1) is fan edge k-1
    step = pair_j - pair_i
    edge = torch.where(step == 1, pair_i, pair_j)
    on_cycle = ((step == 1) | (step == k - 1)).to(x.dtype)
    off = (-0.5 * on_cycle)[:, None] * cot_z.index_select(0, edge)
    wi, wj = w.index_select(0, pair_i), w.index_select(0, pair_j)
    off = off + ell.index_select(0, pair_i) * wj + wi * ell.index_select(0, pair_j)
    off = off + l_ff * wi * wj

    # lumped Galerkin fan mass: a third of fan triangle i's area at y_i, y_{i+1} and z
    third = dbl / 6.0
    m_corner = third + torch.roll(third, 1, dims=0)
    mass = (m_corner + third.sum(0) * w) * size2
    return off, mass, area_scaled * size2, size2

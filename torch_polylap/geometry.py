"""Per-face geometry of polygons: vector area, normal, maximal projection, planarity.

Every function works on one *degree group* at a time, in structure-of-arrays layout: corner
positions are a ``(3, k, F)`` tensor (coordinate, corner, face), so each per-corner quantity is
a contiguous ``(F,)`` row and every operation is one vectorized pass over all faces of that
degree.  This is several times faster than batched ``(F, k, k)`` matrix calls, whose cost is
per-op overhead on tiny matrices (see ``docs`` in the repository), and it differentiates
cleanly: no SVD, no eigen-decomposition, no data-dependent Python branches.

Notation follows Alexa & Wardetzky 2011 (AW11) and ``MATH.md``: for a face with corners
``x_0 .. x_{k-1}``, edges ``e_i = x_{i+1} - x_i``, midpoints ``b_i``,
``g_i = (x_{i+1} - x_{i-1}) / 2``,
vector area ``a = 1/2 sum_i x_i x x_{i+1}`` (AW11 Lemma 1, eq. 8), area ``|f| = |a|``.
"""

from __future__ import annotations

import torch

__all__ = [
    "gather_corners",
    "face_frame",
    "corner_terms",
    "stabilizer_factors",
    "plane_basis",
]


def gather_corners(verts_t: torch.Tensor, corners_t: torch.Tensor) -> torch.Tensor:
    """Corner positions of a degree group.

    Args:
        verts_t: ``(3, V)`` vertex positions, transposed and contiguous.
        corners_t: ``(k, F)`` vertex index of each corner.

    Returns:
        ``(3, k, F)`` positions.
    """
    k, f = corners_t.shape
    return verts_t.index_select(1, corners_t.reshape(-1)).view(3, k, f)


def corner_terms(x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Edges, the vectors ``g_i`` and the vector area of each face.

    Args:
        x: ``(3, k, F)`` corner positions.

    Returns:
        ``e`` ``(3, k, F)``: edges ``x_{i+1} - x_i``;
        ``g`` ``(3, k, F)``: ``(x_{i+1} - x_{i-1}) / 2 = (e_i + e_{i-1}) / 2``, rows of ``d^T B``
        whose Gram matrix divided by ``|f|`` is the geometric part ``d^T (B B^T / |f|) d``
        (MATH.md; origin-free, unlike ``B``);
        ``a`` ``(3, F)``: vector area ``1/2 sum_i x_i x x_{i+1}`` (AW11 eq. 8), summed as the fan
        ``1/2 sum_i (x_i - x_0) x (x_{i+1} - x_0)`` so that a mesh far from the origin loses no
        precision.
    """
    e = torch.roll(x, -1, dims=1) - x
    g = 0.5 * (e + torch.roll(e, 1, dims=1))
    r = x[:, 1:] - x[:, :1]  # (3, k-1, F)
    a = 0.5 * torch.linalg.cross(r[:, :-1], r[:, 1:], dim=0).sum(1)
    return e, g, a


def face_frame(n: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """An orthonormal basis ``(t1, t2)`` of the plane orthogonal to each unit normal.

    Uses the branch-free construction of Duff et al., "Building an Orthonormal Basis,
    Revisited" (JCGT 2017), which is smooth everywhere except where ``n_z`` changes sign.  The
    stabilizer only depends on the plane, not on the basis chosen in it, so that seam changes
    neither values nor gradients.

    Args:
        n: ``(3, F)`` unit normals.

    Returns:
        ``t1, t2``: ``(3, F)`` each.
    """
    nx, ny, nz = n
    s = torch.copysign(torch.ones_like(nz), nz)
    a = -1.0 / (s + nz)
    b = nx * ny * a
    t1 = torch.stack((1.0 + s * nx * nx * a, s * b, -s * nx))
    t2 = torch.stack((b, s + ny * ny * a, -ny))
    return t1, t2


def stabilizer_factors(e: torch.Tensor, n: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Factors of the stabilizer ``d^T Pi d = d^T d - alpha alpha^T - beta beta^T`` of one face.

    ``Pi = C C^T`` projects onto ``ker(Ebar^T)``, where ``Ebar`` holds the edges of the maximal
    projection (AW11 Theorem 1, eq. 9, with the lambda-simple choice ``U = lambda Id``).  Its
    complement is the 2-dimensional column space of ``Ebar``, spanned by the in-plane edge
    coordinates ``u_i = e_i . t1`` and ``w_i = e_i . t2`` (``e_i . t = ebar_i . t`` for ``t`` in the
    plane, so the edges need not be projected).  Gram-Schmidt turns ``(u, w)`` into an
    orthonormal pair ``(q1, q2)``, so ``Pi = I - q1 q1^T - q2 q2^T`` without any SVD
    (MATH.md: SVD gradients divide by differences of the ``k - 2`` equal singular values).

    Args:
        e: ``(3, k, F)`` edges.
        n: ``(3, F)`` unit normals (of the maximal projection).

    Returns:
        ``alpha = d^T q1`` and ``beta = d^T q2``, each ``(k, F)``;
        ``(d^T y)_i = y_{i-1} - y_i``.
    """
    q1, q2 = plane_basis(e, n)
    return torch.roll(q1, 1, dims=0) - q1, torch.roll(q2, 1, dims=0) - q2


def plane_basis(e: torch.Tensor, n: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Orthonormal ``(k, F)`` vectors ``q1, q2`` spanning the column space of ``Ebar``.

    ``Pi = I - q1 q1^T - q2 q2^T`` (see :func:`stabilizer_factors`). The squared norms are
    clamped at the smallest normal number so that a degenerate face (zero area, only reachable
    with validation switched off) yields zeros instead of ``0 * inf = nan``.
    """
    t1, t2 = face_frame(n)
    tiny = torch.finfo(e.dtype).tiny
    u = (e * t1[:, None]).sum(0)  # (k, F)
    w = (e * t2[:, None]).sum(0)
    q1 = u * torch.rsqrt((u * u).sum(0).clamp_min(tiny))
    w = w - (q1 * w).sum(0) * q1
    q2 = w * torch.rsqrt((w * w).sum(0).clamp_min(tiny))
    return q1, q2

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
    "quad_entries",
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


def quad_entries(
    x: torch.Tensor, lam: float | torch.Tensor, geometric: bool = True
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Off-diagonal entries of ``L_f`` for quadrilaterals in closed form (fewer passes than the
    general path; quads dominate real meshes).

    For a quad ``g_2 = -g_0`` and ``g_3 = -g_1``, so ``G G^T`` needs three dot products, and the
    vector area is ``a = 2 g_0 x g_1``. ``ker(Ebar^T)`` is spanned by ``1`` and one vector ``c``;
    since ``d^T 1 = 0`` the stabilizer is the rank-one term ``(d^T c)(d^T c)^T / |c|^2``
    (AW11 eq. 9). With ``t_i = n . (e_i x e_{i+1})``, twice the projected area of the corner
    triangle ``(x_i, x_{i+1}, x_{i+2})``, ``t_0 + t_2 = t_1 + t_3 = 2 |f|`` and, solving
    ``Ebar^T c = 0, 1^T c = 0`` by minors,

        c   = (-t0 + 2 t1 + t2, -t0 + 2 t1 - 3 t2, 3 t0 - 2 t1 + t2, -t0 - 2 t1 + t2),
        d^T c = 4 (-t1, t2, -t3, t0).

    Args:
        x: ``(3, 4, F)`` corner positions.
        lam: stabilizer weight; ``geometric=False`` keeps only the stabilizer.

    Returns:
        ``off`` ``(6, F)`` in the pair order ``(0,1), (0,2), (0,3), (1,2), (1,3), (2,3)``;
        ``area`` ``(F,)``; ``size2`` ``(F,)``, the sum of the squared diagonals.
    """
    x0, x1, x2, x3 = x.unbind(1)
    g0 = x1 - x3  # 2 g_0
    g1 = x2 - x0  # 2 g_1
    a2 = torch.linalg.cross(g0, g1, dim=0)  # 2 a
    tiny = torch.finfo(x.dtype).tiny
    a2_norm = torch.sqrt((a2 * a2).sum(0).clamp_min(tiny))  # 2 |f|
    d00 = (g0 * g0).sum(0)
    d11 = (g1 * g1).sum(0)
    size2 = d00 + d11  # squared diagonals: the length scale of the zero-area test
    rows = []
    if geometric:
        scale = 0.5 / a2_norm  # (g_i . g_j) / |f| with the factors 2 of g0, g1 folded in
        d01 = (g0 * g1).sum(0) * scale
        d00 = d00 * scale
        d11 = d11 * scale
        rows = [d01, -d00, -d01, -d01, -d11, d01]
    if not (isinstance(lam, (int, float)) and lam == 0):
        n = a2 / a2_norm
        e1 = x2 - x1
        t0 = (torch.linalg.cross(x1 - x0, e1, dim=0) * n).sum(0)
        t1 = (torch.linalg.cross(e1, x3 - x2, dim=0) * n).sum(0)
        t2 = a2_norm - t0
        t3 = a2_norm - t1
        c0 = -t0 + 2 * t1 + t2
        c1 = -t0 + 2 * t1 - 3 * t2
        c2 = 3 * t0 - 2 * t1 + t2
        c3 = -t0 - 2 * t1 + t2
        w = (16 * lam) / (c0 * c0 + c1 * c1 + c2 * c2 + c3 * c3).clamp_min(tiny)
        dc = (-t1, t2, -t3, t0)
        pairs = ((0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3))
        stab = [w * dc[i] * dc[j] for i, j in pairs]
        rows = stab if not rows else [r + s for r, s in zip(rows, stab)]
    if not rows:
        rows = [x.new_zeros(x.shape[2])] * 6
    return torch.stack(rows), 0.5 * a2_norm, size2

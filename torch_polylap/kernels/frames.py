"""Per-face frames shared by every kernel: corner gathers, vector area, normal, plane basis.

Every function works on one *degree group* at a time, in structure-of-arrays layout: corner
positions are a ``(3, k, F)`` tensor (coordinate, corner, face), so each per-corner quantity is
a contiguous ``(F,)`` row and every operation is one vectorized pass over all faces of that
degree.  This is several times faster than batched ``(F, k, k)`` matrix calls, whose cost is
per-op overhead on tiny matrices, and it differentiates cleanly: no SVD, no
eigen-decomposition, no data-dependent Python branches.

Notation follows Alexa & Wardetzky 2011 (AW11; ``docs/math/aw11.md``): for a face with corners
``x_0 .. x_{k-1}``, edges ``e_i = x_{i+1} - x_i``, midpoints ``b_i``,
``g_i = (x_{i+1} - x_{i-1}) / 2``,
vector area ``a = 1/2 sum_i x_i x x_{i+1}`` (AW11 Lemma 1, eq. 8), area ``|f| = |a|``.
"""

from __future__ import annotations

import torch

__all__ = [
    "gather_corners",
    "gather_coordinates",
    "face_frame",
    "corner_terms",
    "stabilizer_factors",
    "plane_basis",
    "stable_norm",
]


def stable_norm(a: torch.Tensor, dim: int, *, keepdim: bool = False) -> torch.Tensor:
    """Euclidean norm along ``dim`` without under- or overflow: ``s |a / s|`` with ``s`` the
    largest magnitude.  The vector area of a face at scale ``1e-150`` has components near
    ``1e-300``, whose squares underflow to zero in a plain norm (``1e150``: overflow)."""
    scale = a.abs().amax(dim, keepdim=True).clamp_min(torch.finfo(a.dtype).tiny)
    norm = scale * torch.linalg.vector_norm(a / scale, dim=dim, keepdim=True)
    return norm if keepdim else norm.squeeze(dim)


def component_norm(x: torch.Tensor, y: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
    """``|(x, y, z)|`` elementwise from three component tensors of one shape, as
    :func:`stable_norm` (no under- or overflow) but without a reduction over a leading
    dimension (slow in torch: a fifth of a heat solver's build on a 27k-face mesh).

    Its gradient is finite wherever the vector is not zero, also where some components are
    exactly zero (a face in a coordinate plane), which ``hypot`` nested twice is not
    (``hypot(0, 0)`` has a 0/0 derivative); a zero vector gets norm ``tiny`` and gradient 0.
    """
    scale = torch.maximum(torch.maximum(x.abs(), y.abs()), z.abs())
    scale = scale.clamp_min(torch.finfo(scale.dtype).tiny)
    squares = (x / scale).square() + (y / scale).square() + (z / scale).square()
    # >= 1 for every non-zero vector (its largest component over itself is exactly 1)
    return scale * torch.where(squares > 0, squares, 1.0).sqrt()


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
        (``docs/math/aw11.md``, "The geometric part"; origin-free, unlike ``B``);
        ``a`` ``(3, F)``: vector area ``1/2 sum_i x_i x x_{i+1}`` (AW11 eq. 8), summed as the fan
        ``1/2 sum_i (x_i - x_0) x (x_{i+1} - x_0)`` so that a mesh far from the origin loses no
        precision.
    """
    e = torch.roll(x, -1, dims=1) - x
    g = 0.5 * (e + torch.roll(e, 1, dims=1))
    rx, ry, rz = (x[:, 1:] - x[:, :1]).unbind(0)  # (k-1, F) each
    a = (
        0.5
        * torch.stack(  # fan cross products by coordinate: cheaper than linalg.cross
            (
                torch.addcmul(ry[:-1] * rz[1:], rz[:-1], ry[1:], value=-1).sum(0),
                torch.addcmul(rz[:-1] * rx[1:], rx[:-1], rz[1:], value=-1).sum(0),
                torch.addcmul(rx[:-1] * ry[1:], ry[:-1], rx[1:], value=-1).sum(0),
            )
        )
    )
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
    (``docs/math/aw11.md``, "How the code forms Pi": SVD gradients divide by differences of
    the ``k - 2`` equal singular values).

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


def gather_coordinates(
    verts_t: torch.Tensor, corners_t: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Corner coordinates of a degree group as three ``(k, F)`` tensors ``(X, Y, Z)``.

    One 1-D ``index_select`` per coordinate row over the flattened corners: faster on the CPU
    than ``take`` (forward and backward), and unlike ``take``, whose backward is ``put``, it
    has batching rules both ways, so torch.func's transforms run it without a slow fallback.
    """
    flat = corners_t.reshape(-1)
    X, Y, Z = (torch.index_select(verts_t[i], 0, flat).view(corners_t.shape) for i in range(3))
    return X, Y, Z

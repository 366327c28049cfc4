"""AW11's per-face blocks: the quadrilateral closed form and the general ``k``-gon form.

For a face with ``k`` corners (AW11 sec. 3.3; ``docs/math/aw11.md``):

    L_f = d^T M_f d = G G^T / |f| + lambda d^T Pi d                 (AW11 eq. 3 and 9)

with ``G`` the rows ``g_i = (x_{i+1} - x_{i-1}) / 2`` and ``Pi`` the projector onto the kernel of
the maximal projection's edge matrix. Only the ``k (k - 1) / 2`` off-diagonal entries are
evaluated; the diagonal follows from ``L_f 1 = 0`` (``d 1 = 0``), which holds exactly.
:func:`aw11_entries` is the one entry: quads take the closed form of :func:`quad_entries`,
every other degree the general :func:`polygon_entries`.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch

from ..checks import Lam
from ..topology import DegreeGroup
from .entries import FaceEntries
from .frames import corner_terms, stabilizer_factors

__all__ = ["aw11_entries", "quad_entries", "polygon_entries", "row_sums"]


def aw11_entries(
    x: torch.Tensor | tuple[torch.Tensor, torch.Tensor, torch.Tensor],
    grp: DegreeGroup,
    lam: Lam,
    *,
    geometric: bool = True,
) -> FaceEntries:
    """Off-diagonal entries ``(L_f)_ij``, ``i < j``, of every face of one degree group.

    Args:
        x: ``(3, k, F)`` corner positions, or for quads the three ``(k, F)`` coordinate
            tensors of :func:`~torch_polylap.kernels.frames.gather_coordinates` (the faster
            gather for the closed form).
        grp: the faces' :class:`~torch_polylap.topology.DegreeGroup` (degree and corner pairs).
        lam: weight of the stabilizer; ``geometric=False`` keeps only ``lam d^T Pi d`` (the
            planarity operator's blocks, AW11 sec. 5.3).

    Returns:
        ``off`` ``(P, F)``: entry ``(pair_i[p], pair_j[p])`` of each face's block;
        ``area`` ``(F,)``: ``|f|``; ``size2`` ``(F,)``: a squared length of the face (sum of
        ``|g_i|^2``), against which a zero area is judged.
    """
    if grp.k == 4:
        xyz = x if isinstance(x, tuple) else x.unbind(0)
        return quad_entries((xyz[0], xyz[1], xyz[2]), lam, geometric=geometric)
    assert isinstance(x, torch.Tensor)
    return polygon_entries(x, grp.pair_i, grp.pair_j, lam, geometric=geometric)


def row_sums(off: torch.Tensor, grp: DegreeGroup) -> torch.Tensor:
    """``(k, F)`` sums of the off-diagonal entries in each row of every block.

    ``L_f 1 = 0`` makes the diagonal their negative. Accumulated row by row (a small BLAS
    matmul would cost milliseconds of threading overhead per call on small meshes).
    """
    # the first sum out of place: under vmap `off` is batched and the zeros are not
    sums = off.new_zeros(grp.k, off.shape[1]).index_add(0, grp.pair_i, off)
    return sums.index_add_(0, grp.pair_j, off)


def _cross_dot(
    n: Sequence[torch.Tensor], u: Sequence[torch.Tensor], v: Sequence[torch.Tensor]
) -> torch.Tensor:
    """``n . (u x v)`` for 3-vectors given as tuples of ``(F,)`` rows."""
    cx = torch.addcmul(u[1] * v[2], u[2], v[1], value=-1)
    cy = torch.addcmul(u[2] * v[0], u[0], v[2], value=-1)
    cz = torch.addcmul(u[0] * v[1], u[1], v[0], value=-1)
    return torch.addcmul(torch.addcmul(n[0] * cx, n[1], cy), n[2], cz)


def quad_entries(
    xyz: tuple[torch.Tensor, torch.Tensor, torch.Tensor],
    lam: float | torch.Tensor,
    *,
    geometric: bool = True,
) -> FaceEntries:
    """Off-diagonal entries of ``L_f`` for quadrilaterals in closed form.

    Quads dominate real meshes, so they get a scalar kernel: every quantity is an ``(F,)`` row
    and every step one vectorized pass (fused multiply-adds where possible).

    For a quad ``g_2 = -g_0`` and ``g_3 = -g_1``, so ``G G^T`` needs three dot products, and the
    vector area is ``a = 2 g_0 x g_1``. ``ker(Ebar^T)`` is spanned by ``1`` and one vector ``c``;
    since ``d^T 1 = 0`` the stabilizer is the rank-one term ``(d^T c)(d^T c)^T / |c|^2``
    (AW11 eq. 9). With ``t_i = n . (e_i x e_{i+1})``, twice the projected area of the corner
    triangle ``(x_i, x_{i+1}, x_{i+2})``, one has ``t_0 + t_2 = t_1 + t_3 = 2 |f|``, and solving
    ``Ebar^T c = 0, 1^T c = 0`` by minors gives

        c     = (-t0 + 2 t1 + t2, -t0 + 2 t1 - 3 t2, 3 t0 - 2 t1 + t2, -t0 - 2 t1 + t2),
        d^T c = 4 (-t1, t2, -t3, t0),
        |c|^2 = 4 (t0^2 + t1^2 + t2^2 + t3^2 + (t0 - t1)^2 + (t1 - t2)^2).

    Args:
        xyz: corner coordinates ``(X, Y, Z)``, each ``(4, F)``.
        lam: stabilizer weight; ``geometric=False`` keeps only the stabilizer.

    Returns:
        ``off`` ``(6, F)`` in the pair order ``(0,1), (0,2), (0,3), (1,2), (1,3), (2,3)``;
        ``area`` ``(F,)``; ``size2`` ``(F,)``, the sum of the squared diagonals.
    """
    # rows by unbind, not X[c]: the backward of four selects zero-fills four (4, F) arrays and
    # adds them up, that of one unbind stacks the four row gradients
    x0, x1, x2, x3 = zip(*(c.unbind(0) for c in xyz), strict=True)
    g0 = tuple(a - b for a, b in zip(x1, x3, strict=True))  # 2 g_0
    g1 = tuple(a - b for a, b in zip(x2, x0, strict=True))  # 2 g_1
    tiny = torch.finfo(xyz[0].dtype).tiny
    d00 = torch.addcmul(torch.addcmul(g0[0] * g0[0], g0[1], g0[1]), g0[2], g0[2])
    d11 = torch.addcmul(torch.addcmul(g1[0] * g1[0], g1[1], g1[1]), g1[2], g1[2])
    size2 = d00 + d11  # squared diagonals: the length scale s^2 of the face
    # Per-face scaled frame: quantities of order s^2 (a, d_ij, t_i) are divided by s^2 before
    # they are squared, so nothing of order s^4 is ever formed (it underflows below s ~ 1e-77
    # in float64 and 1e-10 in float32, and overflows above the reciprocals). L_f is scale
    # invariant; only the area is rescaled by s^2 at the end.
    r2 = 1.0 / size2.clamp_min(tiny)
    a2 = (  # (g0 x g1) / s^2 = 2 a / s^2
        torch.addcmul(g0[1] * g1[2], g0[2], g1[1], value=-1) * r2,
        torch.addcmul(g0[2] * g1[0], g0[0], g1[2], value=-1) * r2,
        torch.addcmul(g0[0] * g1[1], g0[1], g1[0], value=-1) * r2,
    )
    a2_sq = torch.addcmul(torch.addcmul(a2[0] * a2[0], a2[1], a2[1]), a2[2], a2[2])
    a2_norm = a2_sq.clamp_min(tiny).sqrt()  # 2 |f| / s^2
    inv = 1.0 / a2_norm
    if geometric:
        scale = (0.5 * r2) * inv  # (g_i . g_j) / |f| with the factors 2 of g0, g1 folded in
        d01 = torch.addcmul(torch.addcmul(g0[0] * g1[0], g0[1], g1[1]), g0[2], g1[2]) * scale
        neg = -scale
        d00n, d11n, d01n = d00 * neg, d11 * neg, -d01
        rows = [d01, d00n, d01n, d01n, d11n, d01]
    else:
        zero = torch.zeros_like(a2_norm)
        rows = [zero] * 6
    if not (isinstance(lam, (int, float)) and lam == 0):
        n = tuple(c * inv for c in a2)
        e0 = tuple(a - b for a, b in zip(x1, x0, strict=True))
        e1 = tuple(a - b for a, b in zip(x2, x1, strict=True))
        e2 = tuple(a - b for a, b in zip(x3, x2, strict=True))
        t0 = _cross_dot(n, e0, e1) * r2  # t_i / s^2
        t1 = _cross_dot(n, e1, e2) * r2
        t2 = a2_norm - t0
        t3 = a2_norm - t1
        p, r = t0 - t1, t1 - t2
        c_sq = torch.addcmul(torch.addcmul(t0 * t0, t1, t1), t2, t2)
        c_sq = torch.addcmul(torch.addcmul(torch.addcmul(c_sq, t3, t3), p, p), r, r)
        w = (4 * lam) / c_sq.clamp_min(tiny)  # 16 lam / |c|^2
        wt0, wt1, wt3 = w * t0, w * t1, w * t3
        # (d^T c)_i (d^T c)_j / |c|^2 with d^T c = 4 (-t1, t2, -t3, t0)
        rows = [
            torch.addcmul(rows[0], wt1, t2, value=-1),
            torch.addcmul(rows[1], wt1, t3),
            torch.addcmul(rows[2], wt1, t0, value=-1),
            torch.addcmul(rows[3], wt3, t2, value=-1),
            torch.addcmul(rows[4], wt0, t2),
            torch.addcmul(rows[5], wt3, t0, value=-1),
        ]
    return FaceEntries(torch.stack(rows), (0.5 * a2_norm) * size2, size2)


def polygon_entries(
    x: torch.Tensor,
    pair_i: torch.Tensor,
    pair_j: torch.Tensor,
    lam: float | torch.Tensor,
    *,
    geometric: bool = True,
) -> FaceEntries:
    """Off-diagonal entries ``(L_f)_ij``, ``i < j``, of every face of one degree ``k``.

    ``L_f = G G^T / |f| + lambda d^T Pi d`` (AW11 eq. 3 and 9), evaluated in a per-face scaled
    frame: with ``s^2 = sum_i |g_i|^2``, the vector area is divided by ``s^2`` before its norm
    is taken, so no quantity of order ``s^4`` is formed. ``L_f`` is scale invariant, so the
    entries are those of the unscaled face to round-off for any ``s`` with ``s^2`` at least
    ``tiny / eps`` and ``1 / s^2`` below the largest number (float64: about ``1e-146 .. 1e154``;
    float32: ``1e-15 .. 1e19``; the assembly divides the coordinates by a power of two near
    their largest magnitude, which brings every face it accepts into that range); the area is
    rescaled by ``s^2``. Triangles carry no stabilizer (AW11 Theorem 2).

    Args:
        x: ``(3, k, F)`` corner positions.
        pair_i, pair_j: ``(P,)`` local corner pairs ``i < j``.
        lam: stabilizer weight; ``geometric=False`` keeps only ``lam d^T Pi d`` (the planarity
            operator's blocks).

    Returns:
        ``off`` ``(P, F)``; ``area`` ``(F,)``: ``|f|``; ``size2`` ``(F,)``: ``s^2``, against which
        a zero area is judged.
    """
    k = x.shape[1]
    e, g, a = corner_terms(x)
    size2 = (g * g).sum((0, 1))
    tiny = torch.finfo(x.dtype).tiny
    r2 = 1.0 / size2.clamp_min(tiny)
    a_scaled = a * r2  # a / s^2, of order 1
    area_scaled = torch.sqrt((a_scaled * a_scaled).sum(0).clamp_min(tiny))  # |f| / s^2
    off = None
    if geometric:
        # g_i . g_j one coordinate at a time: row gathers of (k, F) blocks and fused
        # multiply-adds beat a (3, P, F) product reduced over its leading axis.
        gx, gy, gz = g.unbind(0)
        off = gx.index_select(0, pair_i) * gx.index_select(0, pair_j)
        off = torch.addcmul(off, gy.index_select(0, pair_i), gy.index_select(0, pair_j))
        off = torch.addcmul(off, gz.index_select(0, pair_i), gz.index_select(0, pair_j))
        off = off * (r2 / area_scaled)
    if k > 3 and not (isinstance(lam, (int, float)) and lam == 0):
        alpha, beta = stabilizer_factors(e, a_scaled / area_scaled)
        stab = torch.addcmul(
            alpha.index_select(0, pair_i) * alpha.index_select(0, pair_j),
            beta.index_select(0, pair_i),
            beta.index_select(0, pair_j),
        )
        # (d^T d)_ij for i < j: -1 for neighbours on the cycle (including the pair (0, k-1)).
        dtd = -((pair_j - pair_i == 1) | (pair_j - pair_i == k - 1)).to(x.dtype)
        stab = dtd[:, None] - stab
        off = lam * stab if off is None else off + lam * stab
    elif off is None:
        off = x.new_zeros(pair_i.numel(), x.shape[2])
    return FaceEntries(off, area_scaled * size2, size2)

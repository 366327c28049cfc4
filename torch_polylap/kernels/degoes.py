"""Per-face kernel of the de Goes-Butts-Desbrun polygon Laplacian (dGBD20).

de Goes, Butts and Desbrun 2020, "Discrete Differential Operators on Polygonal Meshes" (ACM
Trans. Graph. 39(4)), sec. 4 (the local operators of a face): for a face with vector area
``a_f``, area ``A = |a_f|`` and unit normal ``n = a_f / A``,

    gradient   G_f = [n]_x (B_f - c_f)^T D_f / A   columns  grad_i = n x g_i / A     (their eq. 8)
    flat       V_f = E_f (I - n n^T)                rows the edges projected
    sharp      U_f = [n]_x (B_f - c_f)^T / A
    projection P_f = I - V_f U_f
    1-forms    M_f = A U_f^T U_f + lambda P_f^T P_f
    Laplacian  L_f = D_f^T M_f D_f

with ``D_f`` the face's coboundary (``(D u)_h = u_{h+1} - u_h``), ``E_f`` its edge vectors,
``B_f`` its edge midpoints and ``g_i = (x_{i+1} - x_{i-1}) / 2 = -(D_f^T B_f)_i``. Hence

    L_f = G' G'^T / A + lambda Q^T Q,   G' = G (I - n n^T),   Q = D_f - E_f [n]_x G^T / A,

i.e. ``Q_hi = D_hi + e_h . (n x g_i) / A``. The consistency term equals AW11's ``G G^T / |f|``
on planar faces; the stabilizer uses the oblique projector ``P_f`` (idempotent, not symmetric)
where AW11 uses the orthogonal projector onto ``ker(Ebar^T)``, so the two agree where ``V_f U_f``
is symmetric (triangles, rectangles, regular polygons). Their 0-form inner product is the
lumped ``A / k`` per corner, as AW11 eq. 10. ``lambda`` is their ``beta`` (adobe-lagrange's
``polyddg.DifferentialOperators.laplacian(beta=...)``, against which the tests compare).
"""

from __future__ import annotations

import torch

from .entries import FaceEntries
from .frames import corner_terms

__all__ = ["degoes_entries"]


def degoes_entries(
    x: torch.Tensor,
    pair_i: torch.Tensor,
    pair_j: torch.Tensor,
    lam: float | torch.Tensor,
) -> FaceEntries:
    """Off-diagonal entries ``(L_f)_ij``, ``i < j``, of dGBD20's ``D^T M_f D`` for one degree group.

    Evaluated in the scaled frame of :func:`~torch_polylap.kernels.aw11.polygon_entries` (edges and
    ``g_i`` divided by ``s``, the area by ``s^2``): ``L_f`` is scale invariant, so no quantity of
    order ``s^4`` is formed. Triangles carry no stabilizer (``P_f D_f = 0``: every 1-form on a
    triangle is the flat of its gradient), as in AW11 Theorem 2.

    Args:
        x: ``(3, k, F)`` corner positions.
        pair_i, pair_j: ``(P,)`` local corner pairs ``i < j``.
        lam: stabilizer weight (their ``beta``).

    Returns:
        ``off`` ``(P, F)``; ``area`` ``(F,)``: ``A = |a_f|``; ``size2`` ``(F,)``: ``s^2``.
    """
    k = x.shape[1]
    tiny = torch.finfo(x.dtype).tiny
    e, g, a = corner_terms(x)
    size2 = (g * g).sum((0, 1))
    r = torch.rsqrt(size2.clamp_min(tiny))
    e, g, a = e * r, g * r, a * (r * r)
    area = torch.sqrt((a * a).sum(0).clamp_min(tiny))  # A / s^2
    n = a / area
    # consistency: g_i . g_j minus the normal parts (the sharp sees only in-plane midpoints)
    gn = (g * n[:, None]).sum(0)  # (k, F)
    gi, gj = g.index_select(1, pair_i), g.index_select(1, pair_j)
    off = ((gi * gj).sum(0) - gn.index_select(0, pair_i) * gn.index_select(0, pair_j)) / area
    if k > 3 and not (isinstance(lam, (int, float)) and lam == 0):
        ng = torch.stack(  # n x g_i, (3, k, F)
            (
                n[1, None] * g[2] - n[2, None] * g[1],
                n[2, None] * g[0] - n[0, None] * g[2],
                n[0, None] * g[1] - n[1, None] * g[0],
            )
        )
        q = torch.einsum("chf,cif->hif", e, ng) / area  # (k, k, F): e_h . (n x g_i) / A
        h = torch.arange(k, device=x.device)
        q = q.index_put((h, h), q[h, h] - 1.0).index_put((h, (h + 1) % k), q[h, (h + 1) % k] + 1.0)
        stab = (q.index_select(1, pair_i) * q.index_select(1, pair_j)).sum(0)
        off = off + lam * stab
    return FaceEntries(off, area * size2, size2)

"""The assembly of ``method="diamond"``: rescaling, validation and batches around its kernel.

The Diamond Laplacian has no per-face blocks (:mod:`torch_polylap.kernels.diamond`), so it does
not go through the shared block assembly; this module gives it the same frame: the exact
power-of-two rescaling of the coordinates, one device sync for every check (an in-graph
assertion when traced), errors that name the vertex or edge, and ``(B, V, 3)`` batches by
``torch.func.vmap``.
"""

from __future__ import annotations

import torch

from ..kernels.diamond import DiamondPlan, diamond_plan, diamond_values
from ..sparse.pattern import SparsityPattern
from ..topology import Topology
from ..tracing import require
from .scaling import normalizer

__all__ = ["diamond_laplacian", "diamond_flagged"]


def diamond_laplacian(
    verts: torch.Tensor, topo: Topology, *, validate: bool
) -> tuple[SparsityPattern, torch.Tensor, torch.Tensor]:
    """The Diamond ``L`` and ``M0`` of ``verts`` ``(V, 3)`` or ``(B, V, 3)`` on ``topo``.

    The coordinates are rescaled by a power of two first (exact; ``L`` is scale invariant and
    the masses are scaled back), as in the shared assembly. With ``validate`` (one device
    sync): finite coordinates and every diamond flattened with a positive area, else a
    ``ValueError`` naming the edge.

    Returns:
        the pattern, and the values of ``L`` and ``M0`` on it, ``(nnz,)`` or ``(B, nnz)``.
    """
    plan = diamond_plan(topo, verts.device)
    L, M, ok, c = diamond_flagged(verts, plan)
    # traced: an in-graph assertion with the general message
    if validate and not require(ok, _INVALID):
        _raise_invalid(verts, plan, c)
    return plan.pattern, L, M


def diamond_flagged(
    verts: torch.Tensor, plan: DiamondPlan
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """:func:`diamond_values` of ``verts`` ``(V, 3)`` or ``(B, V, 3)`` in the caller's units,
    without raising: ``L``, ``M0``, ``ok`` (0-dim bool: every check of
    :func:`diamond_laplacian` passed) and the diamonds' ``c``; what compiled code runs."""
    norm = normalizer(verts)
    scaled = verts * norm.scale
    with torch.autocast(verts.device.type, enabled=False):
        if verts.dim() == 3:
            L, M, c = torch.func.vmap(lambda v: diamond_values(v, plan))(scaled)
        else:
            L, M, c = diamond_values(scaled, plan)
    ok = norm.finite & (c > 0).all() & torch.isfinite(L).all() & torch.isfinite(M).all()
    return L, M * norm.unscale * norm.unscale, ok, c


def _raise_invalid(verts: torch.Tensor, plan: DiamondPlan, c: torch.Tensor) -> None:
    """The ``ValueError`` of :func:`diamond_laplacian`'s validation, naming the culprit."""
    finite = torch.isfinite(verts).reshape(-1, verts.shape[-2], 3).all(-1).all(0)
    if not bool(finite.all()):
        v = int(torch.nonzero(~finite)[0, 0])
        raise ValueError(f"vertex {v} has a non-finite coordinate; fix or drop it.")
    bad = ~(c.reshape(-1, c.shape[-1]) > 0).all(0)
    if bool(bad.any()):
        e = int(torch.nonzero(bad)[0, 0])
        i, j = int(plan.edge_i[e]), int(plan.edge_j[e])
        raise ValueError(
            f"method='diamond': the diamond of edge ({i}, {j}) has no positive area: its face "
            "points do not lie on either side of the edge (a degenerate edge or face, a fold, "
            "or a strongly non-convex face), so the Diamond Laplacian is not positive "
            "semidefinite there. Repair that region, use another method, or pass "
            "validate=False to get the indefinite operator."
        )
    raise ValueError(_INVALID)


_INVALID = (
    "torch_polylap: method='diamond' needs finite coordinates and diamonds of positive area "
    "(no degenerate edge or face, no fold); the Laplacian or mass is not finite or a diamond "
    "is folded. Repair the mesh there, or use another method."
)

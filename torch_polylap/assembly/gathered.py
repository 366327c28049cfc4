"""The assembly as gathers, the form that torch.compile traces.

Every stored value of ``L`` is gathered from the per-face entries that sum to it, as the
topology's :class:`~torch_polylap.assembly.gather_plan.GatherPlan` lists them; a compiler fuses
gathers far better than the eager form's scatters.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Protocol

import torch

from ..kernels import BlockKernel
from ..kernels.aw11 import row_sums
from ..topology import DegreeGroup, Topology, TopologyView
from ..tracing import outside_transforms
from .checks import FLOAT32_TOLERANCE, FlaggedAssembly, any_degenerate, input_ok, output_ok
from .gather_plan import GatherPlan, gather_plan
from .scaling import normalizer, unscaled

__all__ = ["assemble_gathered", "gather_plan_of"]


class HasGroups(Protocol):
    """What the gathered assembly reads of a :class:`~torch_polylap.topology.TopologyView`."""

    @property
    def groups(self) -> Sequence[DegreeGroup]: ...


def gather_plan_of(topo: Topology, view: TopologyView) -> GatherPlan:
    """``topo``'s :class:`~torch_polylap.assembly.gather_plan.GatherPlan` on ``view``'s device,
    computed once per topology and device."""
    key = ("gather_plan", view.col.device)
    plan = topo.derived.get(key)
    if plan is None:
        with outside_transforms():
            wholes = [view.whole(i) for i in range(len(view.groups))]
            shapes = [(g.pair_i.numel(), g.face_ids.numel()) for g in view.groups]
            cpu = gather_plan(
                [w.pos_upper.cpu().numpy().reshape(s) for w, s in zip(wholes, shapes, strict=True)],
                [w.pos_lower.cpu().numpy().reshape(s) for w, s in zip(wholes, shapes, strict=True)],
                [g.corners_t.cpu().numpy() for g in view.groups],
                view.pattern.diagonal_positions().cpu().numpy(),
                topo.nnz,
            )
            plan = cpu.to(view.col.device)
        topo.derived[key] = plan
    assert isinstance(plan, GatherPlan)
    return plan


def assemble_gathered(
    verts: torch.Tensor,
    view: HasGroups,
    kernel: BlockKernel,
    plan: GatherPlan,
    *,
    want_mass: bool,
) -> FlaggedAssembly:
    """:func:`assemble_flagged` with gathers instead of scatters (``plan``, from
    :func:`gather_plan_of`): every group's blocks at once, then each stored value as the sum
    of its (mostly two) per-face entries and each diagonal as minus the sum of the row sums
    of its vertex's blocks. Written for torch.compile, which fuses the kernels and the
    gathers; eagerly the chunked :func:`assemble` is faster."""
    scale, unscale, finite = normalizer(verts)
    verts_t = verts.t() * scale
    eps = torch.finfo(verts.dtype).eps
    offs, sums, corner_masses, degenerate, accurate, stretch = [], [], [], [], [], []
    corners = plan.vertex.corners(verts_t)
    start = 0
    for grp in view.groups:
        k, count = grp.corners_t.shape
        x = corners[:, start : start + k * count].view(3, k, count)
        start += k * count
        off, corner_mass, area, size2, error = kernel.on_corners(x, grp)
        offs.append(off.reshape(-1))
        sums.append(row_sums(off, grp).reshape(-1))
        corner_masses.append(corner_mass.reshape(-1))
        degenerate.append(any_degenerate(area, size2, eps))
        if verts.dtype == torch.float32:
            accurate.append(error.amax() * eps <= FLOAT32_TOLERANCE)
            if kernel.geometric:
                stretch.append(kernel.stretch(area, size2, grp).amax())
    # an empty piece each, for a mesh without faces
    none = verts_t.new_zeros(0)
    diagonal = -plan.vertex.total(torch.cat([*sums, none]))
    values = plan.values(torch.cat([*offs, none]), diagonal)
    masses_n = plan.vertex.total(torch.cat([*corner_masses, none])) if want_mass else None
    masses = unscaled(masses_n, unscale)
    ok = input_ok(finite, degenerate) & output_ok(values, masses_n, masses, plan.symbolic)
    all_accurate = torch.stack(accurate).all() if accurate else torch.ones_like(ok)
    top = torch.stack(stretch).amax() if stretch else torch.zeros_like(unscale)
    return FlaggedAssembly(values, masses, ok, all_accurate, top)

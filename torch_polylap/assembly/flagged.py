"""The assembly out of place, for traced code and torch.func transforms.

In place updates of a value array fail under vmap and a loop over chunks would unroll into a
traced graph, so these forms make one pass per degree group and return their checks as flags
(:class:`~torch_polylap.assembly.checks.FlaggedAssembly`) instead of reading them.
"""

from __future__ import annotations

import torch

from ..kernels import BlockKernel
from ..kernels.aw11 import row_sums
from ..topology import Topology, TopologyView
from ..tracing import require, run_eagerly, tracing
from .checks import (
    BAD_INPUT,
    FLOAT32_INACCURATE,
    FLOAT32_TOLERANCE,
    FlaggedAssembly,
    any_degenerate,
    input_ok,
    output_ok,
    raise_bad_input,
)
from .gathered import assemble_gathered, gather_plan_of
from .scaling import normalizer, unscaled

__all__ = ["assemble_flagged", "assemble_functional"]


def assemble_functional(
    verts: torch.Tensor,
    view: TopologyView,
    topo: Topology,
    kernel: BlockKernel,
    *,
    want_mass: bool,
    validate: bool,
) -> tuple[torch.Tensor, torch.Tensor | None]:
    """:func:`assemble` for traced and transformed code (see :func:`assemble_flagged`); the
    checks are an in-graph assertion when traced, a batch-wide check under vmap, and under
    the other torch.func transforms the eager error that names the vertex or face."""
    if tracing():
        # compiled: the gather form, which inductor fuses far better than scatters
        plan = run_eagerly(gather_plan_of, topo, view)
        flagged = assemble_gathered(verts, view, kernel, plan, want_mass=want_mass)
    else:
        flagged = assemble_flagged(verts, view, topo, kernel, want_mass=want_mass)
    values, masses, ok, accurate, _ = flagged
    if validate:
        if not require(ok, BAD_INPUT):
            raise_bad_input(verts, topo, kernel)
        if not require(accurate, FLOAT32_INACCURATE):
            raise ValueError(FLOAT32_INACCURATE)
    return values, masses


def assemble_flagged(
    verts: torch.Tensor,
    view: TopologyView,
    topo: Topology,
    kernel: BlockKernel,
    *,
    want_mass: bool,
) -> FlaggedAssembly:
    """The assembly out of place, one pass per group, with its checks as 0-dim flags (see
    :class:`FlaggedAssembly`). No error is raised here: batches check theirs together.

    In place updates of a value array from batched blocks fail under vmap, and a loop over
    chunks would unroll into the traced graph (thousands of nodes at a million faces, which
    the C++ compiler behind inductor then fails on); torch.compile fuses the whole group
    instead, so the chunking that keeps eager temporaries small is not needed there. Faces
    that float32 evaluates poorly are not re-evaluated in float64 here (that needs their
    number on the host): such faces make ``accurate`` false, and the callers refuse them
    rather than return a silently inaccurate result.
    """
    scale, unscale, finite = normalizer(verts)
    verts_t = verts.t().contiguous() * scale
    values = verts.new_zeros(topo.nnz)
    masses = verts.new_zeros(topo.num_verts) if want_mass else None
    eps = torch.finfo(verts.dtype).eps
    degenerate, accurate, stretch = [], [], []
    for i, grp in enumerate(view.groups):
        whole = view.whole(i)
        off, corner_mass, area, size2, error = kernel(verts_t, grp, whole.corners_t)
        if verts.dtype == torch.float32:
            accurate.append(error.amax() * eps <= FLOAT32_TOLERANCE)
            if kernel.geometric:
                stretch.append(kernel.stretch(area, size2, grp).amax())
        flat = off.reshape(-1)
        positions = torch.cat((whole.pos_upper, whole.pos_lower, whole.pos_diag))
        entries = torch.cat((flat, flat, -row_sums(off, grp).reshape(-1)))
        values = values.index_add(0, positions, entries)
        if masses is not None:
            masses = masses.index_add(0, whole.corners_t.reshape(-1), corner_mass.reshape(-1))
        degenerate.append(any_degenerate(area, size2, eps))
    masses_n, masses = masses, unscaled(masses, unscale)
    ok = input_ok(finite, degenerate) & output_ok(values, masses_n, masses)
    all_accurate = torch.stack(accurate).all() if accurate else torch.ones_like(ok)
    top = torch.stack(stretch).amax() if stretch else torch.zeros_like(unscale)
    return FlaggedAssembly(values, masses, ok, all_accurate, top)

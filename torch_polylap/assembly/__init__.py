"""The one assembly of every Laplacian in the package: per-face blocks scattered onto a pattern.

``L = sum_f P_f^T L_f P_f`` (AW11 eq. 3): a block kernel (:mod:`torch_polylap.kernels`)
evaluates the off-diagonal entries of the blocks of a chunk of faces of one degree, and
:func:`assemble` adds them, their mirrors and the diagonal ``-row sums`` (``L_f 1 = 0``) into
the CSR value array at the positions the :class:`~torch_polylap.topology.Topology` cached.
Validation costs one device sync per call: the checks of all chunks are reduced on the device
and read once.

The forms, one module each: :mod:`.scatter` (eager, chunked, in place), :mod:`.flagged`
(out of place, for traced and transformed code), :mod:`.gathered` (gathers instead of scatters,
what torch.compile runs) with its :mod:`.gather_plan`; :mod:`.checks` holds their validation,
:mod:`.scaling` the exact rescaling they start from and :mod:`.corners` the corner gathers.
:mod:`.diamond` assembles ``method="diamond"``, which has no per-face blocks, in the same frame.
"""

from __future__ import annotations

import torch

from ..kernels import BlockKernel
from ..topology import Topology, TopologyView
from ..tracing import functional
from .checks import (
    BAD_INPUT,
    FLOAT32_INACCURATE,
    FLOAT32_STRETCH_LIMIT,
    FLOAT32_TOLERANCE,
    FlaggedAssembly,
    raise_bad_input,
    warn_float32_products,
)
from .corners import face_groups
from .flagged import assemble_flagged, assemble_functional
from .gathered import assemble_gathered, gather_plan_of
from .scatter import assemble_chunked

__all__ = [
    "BAD_INPUT",
    "FLOAT32_INACCURATE",
    "FLOAT32_STRETCH_LIMIT",
    "FLOAT32_TOLERANCE",
    "FlaggedAssembly",
    "assemble",
    "assemble_flagged",
    "assemble_gathered",
    "face_groups",
    "gather_plan_of",
    "raise_bad_input",
    "warn_float32_products",
]


def assemble(
    verts: torch.Tensor,
    view: TopologyView,
    topo: Topology,
    kernel: BlockKernel,
    *,
    want_mass: bool,
    validate: bool,
    warn: bool = True,
) -> tuple[torch.Tensor, torch.Tensor | None]:
    """CSR values of ``sum_f P_f^T L_f P_f`` and, optionally, the lumped masses (AW11 eq. 10).

    ``kernel`` (see :func:`~torch_polylap.kernels.block_kernel`) evaluates the blocks of each
    chunk of faces of one degree; each block's off-diagonal entries are scattered to their two
    mirrored positions and minus their row sums to the diagonal. ``view`` is ``topo.on(device)``,
    taken once by the caller.

    The kernels see the coordinates divided by a power of two near their largest magnitude
    (exact: ``L`` is scale invariant and the masses are scaled back by its square), so no
    intermediate under- or overflows whatever the mesh's scale. With ``validate``, one device
    sync reads every check: finite coordinates, no zero-area face, finite ``L`` and masses
    that the dtype represents. For float32 input the same sync reads whether a face's kernel
    expects a relative error above :data:`FLOAT32_TOLERANCE` (thin or nearly degenerate
    faces; PLMS on nearly planar ones); if one does, the values are assembled again with
    those faces evaluated in float64. A float32 face so thin that products with ``L`` lose
    more than that (``s^2 / |f|`` above :data:`FLOAT32_STRETCH_LIMIT`) gives one
    :class:`~torch_polylap.checks.Float32PrecisionWarning` naming it (``warn=False``: left to
    the caller). Traced or under torch.func transforms there is no such warning: a Python
    warning cannot depend on traced values.

    Autocast is off inside: the kernels form products of coordinates that half precision
    cannot hold, and some (dGBD20's einsum) would otherwise be cast to it.

    Returns:
        ``values`` ``(nnz,)`` on ``view``'s pattern and ``masses`` ``(V,)`` (or ``None``).
    """
    with torch.autocast(verts.device.type, enabled=False):
        if functional():
            return assemble_functional(
                verts, view, topo, kernel, want_mass=want_mass, validate=validate
            )
        return assemble_chunked(
            verts, view, topo, kernel, want_mass=want_mass, validate=validate, warn=warn
        )

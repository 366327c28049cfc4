"""Assembly of the alternative polygon Laplacians selected by ``tp.laplacian(method=...)``.

``"aw11"`` (Alexa and Wardetzky 2011) is assembled in :mod:`torch_polylap.operators`. The others
are evaluated here, per degree group, by their per-face kernels and scattered onto the same
cached CSR pattern with the same scatter maps (``chunk.pos_upper/pos_lower/pos_diag``):

- ``"plms"``: Bunge, Herholz, Kazhdan and Botsch 2020, "Polygon Laplacian Made Simple"
  (:mod:`torch_polylap.kernels_plms`); ``lam`` is ignored (the method has no stabilizer).
- ``"degoes"``: de Goes, Butts and Desbrun 2020, "Discrete Differential Operators on Polygonal
  Meshes" (:mod:`torch_polylap.kernels_degoes`); ``lam`` weights their projection term.

Every block satisfies ``L_f 1 = 0``, so only the off-diagonal entries are evaluated and the
diagonal is minus their row sums, as for AW11.
"""

from __future__ import annotations

import torch

from .geometry import gather_corners
from .kernels_degoes import degoes_entries
from .kernels_plms import plms_entries
from .topology import Topology

__all__ = ["METHODS", "check_method", "assemble_method"]

METHODS = ("aw11", "plms", "degoes")


def check_method(method: object) -> str:
    """``method`` must name one of :data:`METHODS`."""
    if method not in METHODS:
        raise ValueError(f"method must be one of {', '.join(map(repr, METHODS))}, got {method!r}.")
    return method


def assemble_method(
    verts: torch.Tensor,
    topo: Topology,
    lam: float | torch.Tensor,
    method: str,
    validate: bool,
) -> tuple[torch.Tensor, torch.Tensor]:
    """CSR values ``(nnz,)`` of ``L`` and ``(V,)`` lumped masses for ``method`` ``"plms"`` or
    ``"degoes"``, on ``topo``'s cached pattern.

    Raises:
        ValueError: non-finite coordinates or a zero-area face (with ``validate``), with the
            same message as AW11 assembly.
    """
    groups, _, _ = topo.on(verts.device)
    verts_t = verts.t().contiguous()
    values = verts.new_zeros(topo.nnz)
    masses = verts.new_zeros(topo.num_verts)
    eps = torch.finfo(verts.dtype).eps
    degenerate = []
    for grp in groups:
        for chunk in grp.chunks:
            x = gather_corners(verts_t, chunk.corners_t)
            if method == "plms":
                off, mass, area, size2 = plms_entries(x, grp.pair_i, grp.pair_j)
            else:
                off, area, size2 = degoes_entries(x, grp.pair_i, grp.pair_j, lam)
                mass = (area / grp.k).expand(grp.k, -1)
            flat = off.reshape(-1)
            values.index_add_(0, chunk.pos_upper, flat)
            values.index_add_(0, chunk.pos_lower, flat)
            sums = off.new_zeros(grp.k, off.shape[1])
            sums.index_add_(0, grp.pair_i, off).index_add_(0, grp.pair_j, off)
            values.index_add_(0, chunk.pos_diag, sums.reshape(-1), alpha=-1)
            masses.index_add_(0, chunk.corners_t.reshape(-1), mass.reshape(-1))
            if validate:
                degenerate.append((area <= eps * size2).any())
    if validate:
        ok = torch.isfinite(verts).all()
        if degenerate:
            ok = ok & ~torch.stack(degenerate).any()
        if not bool(ok):
            # imported here: operators imports this module at load time
            from .operators import _raise_bad_input

            _raise_bad_input(verts, topo)
    return values, masses

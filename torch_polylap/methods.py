"""The per-face block kernels of the polygon Laplacians selected by ``tp.laplacian(method=...)``.

All methods share one assembly (:func:`torch_polylap.operators.laplacian`): a kernel evaluates
the blocks of a chunk of faces of one degree, and the assembly scatters them onto the topology's
cached CSR pattern with its scatter maps.  ``"aw11"`` (Alexa and Wardetzky 2011) has its kernel
in :mod:`torch_polylap.operators`; the others are here:

- ``"plms"``: Bunge, Herholz, Kazhdan and Botsch 2020, "Polygon Laplacian Made Simple"
  (:mod:`torch_polylap.kernels_plms`); ``lam`` is ignored (the method has no stabilizer).
- ``"degoes"``: de Goes, Butts and Desbrun 2020, "Discrete Differential Operators on Polygonal
  Meshes" (:mod:`torch_polylap.kernels_degoes`); ``lam`` weights their projection term.

Every block satisfies ``L_f 1 = 0``, so only the off-diagonal entries are evaluated and the
diagonal is minus their row sums, as for AW11.
"""

from __future__ import annotations

from collections.abc import Callable

import torch

from .geometry import gather_corners
from .kernels_degoes import degoes_entries
from .kernels_plms import plms_entries
from .topology import DegreeGroup

__all__ = ["METHODS", "BlockEntries", "BlockKernel", "check_method", "method_kernel"]

# (off-diagonal entries (P, F), corner masses (k, F), areas (F,), squared sizes (F,))
BlockEntries = tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]
BlockKernel = Callable[[torch.Tensor, DegreeGroup, torch.Tensor], BlockEntries]

METHODS = ("aw11", "plms", "degoes")


def check_method(method: object) -> str:
    """``method`` must name one of :data:`METHODS`."""
    if method not in METHODS:
        raise ValueError(f"method must be one of {', '.join(map(repr, METHODS))}, got {method!r}.")
    return method


def method_kernel(method: str, lam: float | torch.Tensor) -> BlockKernel:
    """The per-chunk block kernel of ``method`` (``"plms"`` or ``"degoes"``) for the shared
    assembly in :mod:`torch_polylap.operators`: ``(verts_t (3, V), group, corners_t (k, F))`` to
    off-diagonal entries ``(P, F)``, corner masses ``(k, F)``, areas ``(F,)`` and squared sizes
    ``(F,)`` (against which a zero area is judged)."""

    def kernel(verts_t: torch.Tensor, grp: DegreeGroup, corners_t: torch.Tensor) -> BlockEntries:
        x = gather_corners(verts_t, corners_t)
        if method == "plms":
            off, corner_mass, area, size2 = plms_entries(x, grp.pair_i, grp.pair_j)
            return off, corner_mass, area, size2
        off, area, size2 = degoes_entries(x, grp.pair_i, grp.pair_j, lam)
        return off, (area / grp.k).expand(grp.k, -1), area, size2

    return kernel

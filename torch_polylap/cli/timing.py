"""The first-assembly timing that ``polylap info`` and ``polylap spectrum`` both report.

The timing helpers themselves (median timing, thread pinning, Markdown tables) are the
library's :mod:`torch_polylap.timing`, shared with the repository's ``benchmarks/``.
"""

from __future__ import annotations

from collections.abc import Callable

import torch

from .._typing import MeshFaces
from ..operators import laplacian
from ..timing import timed
from ..topology import Topology, build_topology

__all__ = ["FIRST_ASSEMBLY", "first_assembly"]

# what first_assembly measures, as the commands label it
FIRST_ASSEMBLY = "first assembly (topology + values)"


def first_assembly(
    verts: torch.Tensor,
    faces: MeshFaces,
    lam: float,
    method: str,
    *,
    warn: bool = True,
    sync: Callable[[], None] | None = None,
) -> tuple[float, Topology, tuple[torch.Tensor, torch.Tensor]]:
    """Seconds of assembling ``(L, M0)`` from scratch, the topology and the operators.

    The quantity that ``polylap info`` and ``polylap spectrum`` both report as
    :data:`FIRST_ASSEMBLY`: :func:`~torch_polylap.topology.build_topology` of ``faces`` (never
    the topology cache) plus the first :func:`~torch_polylap.laplacian` on it, one sample each,
    at the thread count in effect. In a fresh process it includes first-call costs (lazy
    imports, allocator warm-up); the re-assembly on a cached topology is much cheaper (``info``
    reports both).

    Args:
        verts: ``(V, 3)`` positions.
        faces: the faces (a ``Topology`` is rebuilt from its faces).
        lam: stabilizer weight.
        method: the Laplacian.
        warn: let :func:`build_topology` warn about topology defects.
        sync: see :func:`timed` (CUDA).

    Returns:
        ``(seconds, topology, (L, M0))``.
    """
    if isinstance(faces, Topology):
        faces = faces.faces
    t_topo, topo = timed(lambda: build_topology(faces, verts.shape[0], warn=warn), 1, sync=sync)
    t_values, operators = timed(lambda: laplacian(verts, topo, lam, method=method), 1, sync=sync)
    return t_topo + t_values, topo, operators

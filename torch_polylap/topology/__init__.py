"""Everything about a polygon mesh that depends only on its faces, computed once and cached.

:class:`Topology` checks the connectivity and precomputes what every later assembly of ``L``
reuses: faces grouped by degree, the half-edges and undirected edges, the boundary, the CSR
sparsity pattern of ``L`` and, for each per-face matrix entry, its position in ``L``'s value
array.  Assembling ``L`` for new vertex positions is then pure arithmetic plus one scatter onto
this fixed pattern.

``L = sum_f P_f^T L_f P_f`` and ``M0`` are sums of per-face blocks (AW11 eq. 3, 10) that depend
neither on the face's orientation (reversing the corner order leaves ``L_f`` unchanged) nor on
how faces meet, so the pattern and the scatter map are built for *any* set of simple polygons:
non-manifold edges and vertices, inconsistent or impossible orientation (a Moebius band),
duplicated faces and several components are recorded in :attr:`Topology.report` and announced
by one ``UserWarning``, not refused.  Only what needs a manifold or an orientation (half-edge
twins, boundary loops) checks at its own entry, through :meth:`Topology.require_manifold` and
:meth:`Topology.require_oriented`, and says which repair to run (:mod:`torch_polylap.repair`).
Hard errors remain for what no polygon mesh can have: an index out of range, a face that visits
a vertex twice, a face too large to index.

:func:`get_topology` caches topologies in one bounded, weakly keyed cache, shared by the
functional API and :class:`~torch_polylap.PolygonLaplacian`.

Modules: :mod:`.groups` (faces by degree, scatter positions), :mod:`.build` (the pair sort),
:mod:`.structure` (the :class:`Topology` object and its per-device views), :mod:`.analysis`
(twins, fans, orientation, duplicates), :mod:`.report` (the findings), :mod:`.cache`.

The index work runs in numpy on the CPU (its ``argsort`` is several times faster than
``torch.sort`` there); the resulting index tensors are copied to each device once, on demand.
"""

from .analysis import (
    EdgeIncidence,
    OrientationFlips,
    duplicate_faces,
    edge_incidence,
    half_edge_vertices,
    orientation_flips,
)
from .build import build_topology
from .cache import clear_topology_cache, get_topology, set_topology_cache_limits, topology_of
from .groups import DegreeGroup, GroupChunk
from .report import TopologyReport
from .structure import Topology, TopologyView

__all__ = [
    "Topology",
    "TopologyView",
    "TopologyReport",
    "DegreeGroup",
    "GroupChunk",
    "build_topology",
    "get_topology",
    "clear_topology_cache",
    "topology_of",
    "set_topology_cache_limits",
    "duplicate_faces",
    "orientation_flips",
    "OrientationFlips",
    "edge_incidence",
    "EdgeIncidence",
    "half_edge_vertices",
]

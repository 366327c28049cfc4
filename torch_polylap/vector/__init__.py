"""Tangent vector fields on polygon meshes: connection, transport, log map, curvature.

- :func:`connection_laplacian`: the ``(2V, 2V)`` connection Laplacian of tangent vectors (and of
  ``n``-direction fields), built from any of the package's polygon Laplacians by inserting the
  discrete Levi-Civita transport through each face into its blocks; symmetric positive
  semi-definite, a :class:`~torch_polylap.sparse.SparseOperator` with O(nnz) gradients
  (:mod:`.connection`).
- :class:`VectorHeatSolver`: parallel transport and the logarithmic map by the vector heat
  method of Sharp, Soliman and Crane 2019, prefactored (:mod:`.heat`).
- :func:`shape_operator`, :func:`principal_curvatures`: the derivative of the vertex normals
  through the polygon face gradient, with second-order normals from a jet fit
  (:func:`fitted_frames`, :mod:`.curvature`).
- :class:`HodgeDecomposition`: exact, co-exact and harmonic parts of a tangent field,
  orthogonal to round-off, on the virtual refinement of the polygons (:mod:`.hodge`).
- :func:`smoothest_field`: the globally smoothest ``n``-direction field of Knoeppel et al. 2013
  (:mod:`.fields`).

Tangent vectors at the vertices are stored as two coordinates in per-vertex frames
(:class:`TangentFrames`, :mod:`.transport`); :func:`to_ambient` and :func:`to_tangent` convert
between those and 3D vectors.  Everything is differentiable with respect to the vertex
positions.  ``docs/vector.md`` has the mathematics and the measurements.
"""

from ..tangent import TangentFrames, tangent_frames
from .connection import connection_laplacian, vector_mass
from .curvature import face_shape_operator, fitted_frames, principal_curvatures, shape_operator
from .fields import smoothest_field
from .heat import VectorHeatSolver
from .hodge import HodgeDecomposition, HodgeParts, virtual_refinement
from .transport import minimal_rotation, to_ambient, to_tangent

__all__ = [
    "HodgeDecomposition",
    "HodgeParts",
    "TangentFrames",
    "VectorHeatSolver",
    "connection_laplacian",
    "face_shape_operator",
    "fitted_frames",
    "minimal_rotation",
    "principal_curvatures",
    "shape_operator",
    "smoothest_field",
    "tangent_frames",
    "to_ambient",
    "to_tangent",
    "vector_mass",
    "virtual_refinement",
]

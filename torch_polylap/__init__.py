"""torch_polylap: the Alexa-Wardetzky discrete Laplacian on general polygon meshes, in PyTorch.

Differentiable with respect to vertex positions, on CPU and CUDA, for faces of any degree
(non-planar, non-convex, mixed).  See ``docs/conventions.md`` for the conventions and
``docs/math/`` for the mathematics.

The API has two tiers, in the manner of pytorch3d and kornia:

- the core, at the top level: faces and topology, the operators (``laplacian``, ``mass``,
  ``PolygonLaplacian``, ...), face measures, the polygon calculus (gradient, divergence, heat
  geodesics), solves and spectra, I/O and interop (trimesh, pytorch3d, PyG) and batches;
- subpackages for what is built on it: :mod:`~torch_polylap.losses`,
  :mod:`~torch_polylap.apps` (the paper's applications), :mod:`~torch_polylap.nn` (layers),
  :mod:`~torch_polylap.vector` (tangent vector fields: connection, transport, curvature),
  :mod:`~torch_polylap.fitting`, :mod:`~torch_polylap.datasets`, :mod:`~torch_polylap.plot`,
  and the building blocks :mod:`~torch_polylap.sparse` (the operator type and its algebra),
  :mod:`~torch_polylap.io`, :mod:`~torch_polylap.triangulate` (polygons cut into triangles
  for libraries that take only those), :mod:`~torch_polylap.topology`,
  :mod:`~torch_polylap.kernels`, :mod:`~torch_polylap.dec` (AW11's ``d`` and ``M1``),
  :mod:`~torch_polylap.checks` and :mod:`~torch_polylap.repair`, :mod:`~torch_polylap.tangent`
  (vertex frames and tangent gradients), and :mod:`~torch_polylap.shapes` (generated grids,
  cube spheres, tori and the Schwarz lantern).

``__all__`` is derived from the core modules' own ``__all__`` lists plus the subpackage names.
"""

from types import ModuleType as _ModuleType

from . import (
    apps,
    checks,
    datasets,
    dec,
    fitting,
    interop,
    io,
    kernels,
    losses,
    nn,
    plot,
    repair,
    shapes,
    sparse,
    tangent,
    topology,
    vector,
)
from .batch import PolygonMeshes
from .calculus import *
from .compiled import *
from .faces import PolygonFaces, as_faces
from .geodesics import *
from .interop import from_pyg, from_pytorch3d, from_trimesh, to_pyg, to_pytorch3d, to_trimesh
from .io import read_mesh, write_mesh
from .linalg import *
from .measures import *
from .operators import *
from .spectral import (
    cached_eigs,
    heat_kernel_signature,
    implicit_heat_diffusion,
    spectral_heat_diffusion,
    wave_kernel_signature,
)
from .topology import Topology, TopologyReport, build_topology, get_topology

__version__ = "0.1.0"

# The building blocks dec and kernels stay importable (torch_polylap.dec, torch_polylap.kernels)
# but are not exported: they are for extending the package, not for using it.
_SUBPACKAGES = (
    "apps",
    "checks",
    "datasets",
    "fitting",
    "interop",
    "io",
    "losses",
    "nn",
    "plot",
    "repair",
    "shapes",
    "sparse",
    "tangent",
    "topology",
    "vector",
)

__all__ = sorted(
    name
    for name, value in list(globals().items())
    if not name.startswith("_") and (not isinstance(value, _ModuleType) or name in _SUBPACKAGES)
)

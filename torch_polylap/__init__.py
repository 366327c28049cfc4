"""torch_polylap: the Alexa-Wardetzky discrete Laplacian on general polygon meshes, in PyTorch.

Differentiable with respect to vertex positions, on CPU and CUDA, for faces of any degree
(non-planar, non-convex, mixed).  See README.md for the conventions.
"""

from . import apps, checks, datasets, fitting, losses, nn, repair, sparse
from .apps import (
    PlanarizeResult,
    angle_distortion,
    conformal_energy,
    conformal_parameterization,
    mean_curvature_flow,
    navier_deflection,
    planarize,
    plate_bending,
)
from .batch import PolygonMeshes, per_mesh_mean, per_mesh_sum
from .calculus import (
    HeatGeodesicSolver,
    divergence,
    face_gradient,
    gradient_operator,
    heat_geodesic_distance,
)
from .datasets import PolygonMeshDataset, collate_meshes
from .dec import coboundary, local_laplacians, one_form_inner_product
from .faces import PolygonFaces, as_faces
from .fitting import chamfer_distance, mesh_quality, nearest_neighbors, sample_points
from .io import from_trimesh, read_mesh, to_trimesh, write_mesh
from .linalg import dirichlet_solve, eigs, solve
from .losses import (
    BendingEnergy,
    DirichletEnergy,
    LaplacianSmoothingLoss,
    MeanCurvatureSmoothingLoss,
    NormalConsistencyLoss,
    PlanarityLoss,
    bending_energy,
    dirichlet_energy,
    laplacian_smoothing,
    mean_curvature_smoothing,
    normal_consistency,
    planarity_loss,
)
from .measures import (
    face_areas,
    face_nonplanarity,
    face_normals,
    face_planarity_energy,
    mass,
    planarity_energy,
    vector_area,
)
from .operators import (
    PolygonLaplacian,
    laplacian,
    mean_curvature_normal,
    planarity_laplacian,
    strong_laplacian,
)
from .sparse import from_scipy, spmm, to_scipy
from .spectral import (
    cached_eigs,
    heat_kernel_signature,
    implicit_heat_diffusion,
    spectral_heat_diffusion,
    wave_kernel_signature,
)
from .topology import Topology, build_topology, get_topology

__version__ = "0.1.0"

__all__ = [
    "PolygonFaces",
    "as_faces",
    "Topology",
    "build_topology",
    "get_topology",
    "laplacian",
    "mass",
    "PolygonLaplacian",
    "planarity_laplacian",
    "planarity_energy",
    "coboundary",
    "one_form_inner_product",
    "local_laplacians",
    "mean_curvature_normal",
    "strong_laplacian",
    "vector_area",
    "face_areas",
    "face_normals",
    "face_nonplanarity",
    "face_planarity_energy",
    "sparse",
    "checks",
    "repair",
    "spmm",
    "solve",
    "dirichlet_solve",
    "eigs",
    "heat_kernel_signature",
    "wave_kernel_signature",
    "spectral_heat_diffusion",
    "implicit_heat_diffusion",
    "cached_eigs",
    "to_scipy",
    "from_scipy",
    "read_mesh",
    "write_mesh",
    "from_trimesh",
    "to_trimesh",
    "PolygonMeshes",
    "per_mesh_sum",
    "per_mesh_mean",
    "losses",
    "laplacian_smoothing",
    "mean_curvature_smoothing",
    "dirichlet_energy",
    "planarity_loss",
    "bending_energy",
    "normal_consistency",
    "LaplacianSmoothingLoss",
    "MeanCurvatureSmoothingLoss",
    "DirichletEnergy",
    "PlanarityLoss",
    "BendingEnergy",
    "NormalConsistencyLoss",
    "apps",
    "mean_curvature_flow",
    "conformal_parameterization",
    "conformal_energy",
    "angle_distortion",
    "planarize",
    "PlanarizeResult",
    "plate_bending",
    "navier_deflection",
    "fitting",
    "chamfer_distance",
    "nearest_neighbors",
    "sample_points",
    "mesh_quality",
    "nn",
    "datasets",
    "PolygonMeshDataset",
    "collate_meshes",
    "face_gradient",
    "gradient_operator",
    "divergence",
    "HeatGeodesicSolver",
    "heat_geodesic_distance",
]

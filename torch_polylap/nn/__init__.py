"""Learning layers on polygon meshes: spectral features, learned diffusion, Chebyshev filters,
spatial gradient features, and rotation-equivariant layers on tangent vectors.

Kornia-style: each layer is a thin :class:`torch.nn.Module` over a plain function
(:meth:`Spectrum.heat_diffusion`, :func:`torch_polylap.implicit_heat_diffusion`,
:func:`chebyshev_operator`, :func:`chebyshev_filter`, and the library's
:func:`torch_polylap.heat_kernel_signature` / :func:`torch_polylap.wave_kernel_signature`).
Batches of heterogeneous meshes are packed (vertices of all meshes concatenated) with index
maps; per-mesh eigenpairs travel in a :class:`Spectrum`, and ``L, M0`` of a batch are
block-diagonal (``PolygonMeshes.laplacian`` or :func:`torch_polylap.sparse.block_diag`).
"""

from .chebyshev import ChebyshevFilter, chebyshev_filter, chebyshev_operator
from .diffusion import LearnedDiffusion
from .gradient_features import (
    SpatialGradientFeatures,
    VertexFrames,
    spatial_gradient_features,
    vertex_gradient_operators,
    vertex_tangent_frames,
)
from .models import DiffusionBlock, DiffusionNetLike
from .spectral_features import SpectralFeatures, hks_time_range, wks_energy_range
from .spectrum import Spectrum
from .vector_diffusion import LearnedVectorDiffusion, VectorGate, VectorLinear, rotate_vectors

__all__ = [
    "Spectrum",
    "SpectralFeatures",
    "hks_time_range",
    "wks_energy_range",
    "LearnedDiffusion",
    "ChebyshevFilter",
    "chebyshev_operator",
    "chebyshev_filter",
    "vertex_tangent_frames",
    "VertexFrames",
    "vertex_gradient_operators",
    "spatial_gradient_features",
    "SpatialGradientFeatures",
    "DiffusionBlock",
    "DiffusionNetLike",
    "LearnedVectorDiffusion",
    "VectorLinear",
    "VectorGate",
    "rotate_vectors",
]

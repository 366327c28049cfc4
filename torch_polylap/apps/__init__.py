"""Applications of the polygon Laplacian (AW11 sec. 5): flows, plates, parameterizations."""

from .conformal import (
    AngleDistortion,
    angle_distortion,
    conformal_energy,
    conformal_matrix,
    conformal_parameterization,
)
from .flow import (
    FlowOptions,
    FlowResult,
    enclosed_volume,
    mean_curvature_flow,
    scale_free_mean_curvature,
    schwarz_lantern,
)
from .planarize import PlanarizeOptions, PlanarizeResult, planarize
from .plate import navier_deflection, plate_bending, plate_error

__all__ = [
    "mean_curvature_flow",
    "FlowOptions",
    "FlowResult",
    "scale_free_mean_curvature",
    "enclosed_volume",
    "schwarz_lantern",
    "plate_bending",
    "navier_deflection",
    "plate_error",
    "conformal_parameterization",
    "conformal_energy",
    "conformal_matrix",
    "angle_distortion",
    "AngleDistortion",
    "planarize",
    "PlanarizeOptions",
    "PlanarizeResult",
]

"""Applications of the polygon Laplacian (AW11 sec. 5): flows, plates, parameterizations."""

from .flow import enclosed_volume, mean_curvature_flow
from .plate import navier_deflection, plate_bending, plate_error

__all__ = [
    "mean_curvature_flow",
    "enclosed_volume",
    "plate_bending",
    "navier_deflection",
    "plate_error",
]

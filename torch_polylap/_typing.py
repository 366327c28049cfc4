"""The type aliases shared across the package, each defined once.

``MeshFaces`` is what every mesh function takes for its connectivity; ``ArrayLike`` is what the
numpy-side entries (writers, figures) take for numbers.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

from .faces import FacesLike
from .topology.structure import Topology

__all__ = ["ArrayLike", "MeshFaces"]

MeshFaces = FacesLike | Topology
"""Faces in any form :func:`~torch_polylap.as_faces` accepts, or a prebuilt
:class:`~torch_polylap.topology.Topology`."""

ArrayLike = torch.Tensor | np.ndarray | Sequence[float] | Sequence[Sequence[float]]
"""Numbers as a tensor (detached and copied to the CPU where read), a numpy array or nested
Python sequences."""

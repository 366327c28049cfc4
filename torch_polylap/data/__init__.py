"""The meshes shipped with the package (their sources and licenses: ``README.md`` here).

Each is a path to a file inside the installed package, for :func:`torch_polylap.read_mesh`:

    >>> import torch_polylap as tp
    >>> from torch_polylap.data import DEFAULT_MESH
    >>> verts, faces = tp.read_mesh(DEFAULT_MESH)
    >>> faces.num_faces
    180
"""

from __future__ import annotations

from pathlib import Path

__all__ = ["DATA_DIR", "DEFAULT_MESH", "DISK_MESH", "PLATE_MESH"]

DATA_DIR = Path(__file__).resolve().parent
"""The folder of the embedded meshes."""

DEFAULT_MESH = DATA_DIR / "spot_control_mesh.obj"
"""Spot's Catmull-Clark control cage (closed, 180 faces of 3-5 sides, non-planar): the default
mesh of the ``polylap`` commands and the examples."""

DISK_MESH = DATA_DIR / "hex_hemisphere.obj"
"""A disk (one boundary loop) of 81 mostly hexagonal faces: the default of ``polylap param``,
which needs a boundary."""

PLATE_MESH = DATA_DIR / "grid_voronoi_1.obj"
"""Planar Voronoi cells covering the square ``[-1/2, 1/2]^2``: the plate of ``polylap demo``."""

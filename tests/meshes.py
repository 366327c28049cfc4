"""Where the test meshes live, and cached loading (shared by the test modules, not a test itself).

Two sources:

* ``tests/data/`` -- small copies inside the repository (see ``tests/data/LICENSES.md``); tests
  over them always run.
* ``../shared/data/meshes/`` next to the repository (override with ``POLYLAP_SHARED_MESHES``) --
  the full refinement families (levels 1..5) and the big real meshes. Tests that need it skip
  with :data:`SHARED_SKIP_REASON` when it is absent.
"""

from __future__ import annotations

import functools
import os
import warnings
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch

import torch_polylap as tp
from torch_polylap.io import SkippedContentWarning

DATA_DIR = Path(__file__).resolve().parent / "data"

SHARED_SKIP_REASON = (
    "../shared/data/meshes not found: the refinement families live outside the repository "
    "(set POLYLAP_SHARED_MESHES to its location to run this test)"
)


def shared_meshes_dir() -> Path | None:
    """``../shared/data/meshes`` (or ``$POLYLAP_SHARED_MESHES``), or ``None`` when absent."""
    env = os.environ.get("POLYLAP_SHARED_MESHES")
    root = (
        Path(env)
        if env
        else Path(__file__).resolve().parents[1].parent / "shared" / "data" / "meshes"
    )
    return root if root.is_dir() else None


def require_shared() -> Path:
    """The shared mesh directory; ``pytest.skip`` when it is absent."""
    root = shared_meshes_dir()
    if root is None:
        pytest.skip(SHARED_SKIP_REASON)
    return root


def shared_path(rel: str) -> Path:
    """``rel`` (e.g. ``"sphere/hex_5.obj"``) inside the shared directory, skipping when absent."""
    path = require_shared() / rel
    if not path.is_file():
        pytest.skip(f"{path} is missing from the shared mesh directory")
    return path


def read_mesh(path: str | Path, **kwargs: Any) -> tuple[torch.Tensor, tp.PolygonFaces]:
    """:func:`torch_polylap.read_mesh` of a test mesh, without its ``SkippedContentWarning``.

    The test meshes are copies of real files, with texture coordinates, normals, object names
    and smoothing groups that only the readers' own tests (``tests/io``) are about; everywhere
    else that warning is expected and says nothing, while every other warning stays an error.
    """
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", SkippedContentWarning)
        return tp.read_mesh(path, **kwargs)


@functools.cache
def load(path: str | Path) -> tuple[torch.Tensor, tp.PolygonFaces]:
    """``read_mesh`` in float64, cached per path (tests must not modify the returned tensors)."""
    return read_mesh(path, dtype=torch.float64)


def plms_galerkin_mass(verts: torch.Tensor, faces) -> np.ndarray:
    """PLMS lumped mass as polyLaplace computes it (``localMassMatrix`` + ``lump_matrix``).

    Per face: the virtual vertex ``z`` minimizing the sum of squared fan-triangle areas
    (normal equations ``sum_i (|e_i|^2 I - e_i e_i^T) z = sum_i e_i x (y_i x y_{i+1})``), the
    minimum-norm affine weights ``w`` with ``sum_i w_i y_i = z`` (what polyLaplace's complete
    orthogonal decomposition returns; unique for non-planar quads), fan areas ``A_i`` of
    ``(y_i, y_{i+1}, z)``. The fan's Galerkin mass has row sums ``A / 3`` at each triangle
    corner, so corner ``i`` gets ``(A_{i-1} + A_i) / 3 + w_i sum_j A_j / 3``. Written with
    numpy, independently of ``torch_polylap.kernels.plms``.
    """
    V = verts.numpy()
    m = np.zeros(V.shape[0])
    for group in tp.build_topology(faces, V.shape[0], warn=False).groups:
        corners = group.corners_t.numpy().T  # (F, k)
        Y = V[corners]
        Y = Y - Y.mean(1, keepdims=True)  # centered corners, (F, k, 3)
        nxt = np.roll(Y, -1, axis=1)
        e = nxt - Y
        b = np.cross(e, np.cross(Y, nxt)).sum(1)
        A = np.einsum("fk,ab->fab", (e * e).sum(2), np.eye(3)) - np.einsum("fka,fkb->fab", e, e)
        z = np.linalg.solve(A, b[..., None])[..., 0]
        C = np.concatenate([np.ones((len(Y), 1, group.k)), Y.transpose(0, 2, 1)], 1)  # (F, 4, k)
        rhs = np.concatenate([np.ones((len(Y), 1)), z], 1)
        w = np.einsum("fkr,fr->fk", np.linalg.pinv(C, rcond=1e-10), rhs)
        zp = Y - z[:, None]
        fan = 0.5 * np.linalg.norm(np.cross(zp, np.roll(zp, -1, axis=1)), axis=2)  # (F, k)
        corner = (fan + np.roll(fan, 1, axis=1)) / 3 + w * fan.sum(1, keepdims=True) / 3
        np.add.at(m, corners, corner)
    return m


def dumbbell(rings: int = 24, sides: int = 16) -> tuple[torch.Tensor, list[list[int]]]:
    """A closed surface of revolution about z with a thin neck at z = 0 (radius 0.15 of the
    bulbs'), quads between rings and triangle fans at the poles: ``(verts (V, 3) float64,
    faces)``. Mean-curvature flow pinches the neck in finite time."""
    z = np.linspace(-1, 1, rings + 2)[1:-1]
    rho = np.sqrt(1 - z**2) * (1 - 0.85 * np.exp(-((z / 0.2) ** 2)))
    phi = np.linspace(0, 2 * np.pi, sides, endpoint=False)
    ring = np.stack(
        [rho[:, None] * np.cos(phi), rho[:, None] * np.sin(phi), np.repeat(z[:, None], sides, 1)],
        -1,
    ).reshape(-1, 3)
    verts = np.concatenate([[[0, 0, -1.0]], ring, [[0, 0, 1.0]]])
    top = len(verts) - 1
    ids = 1 + np.arange(rings * sides).reshape(rings, sides)
    faces = [[0, int(ids[0, (j + 1) % sides]), int(ids[0, j])] for j in range(sides)]
    faces += [
        [
            int(ids[i, j]),
            int(ids[i, (j + 1) % sides]),
            int(ids[i + 1, (j + 1) % sides]),
            int(ids[i + 1, j]),
        ]
        for i in range(rings - 1)
        for j in range(sides)
    ]
    faces += [[top, int(ids[-1, j]), int(ids[-1, (j + 1) % sides])] for j in range(sides)]
    return torch.from_numpy(verts), faces


def bent_grid(n: int = 6, angle: float = 0.7) -> tuple[torch.Tensor, torch.Tensor]:
    """A regular grid folded along its middle grid line ``x = 1/2``: every quad stays planar,
    so the surface is developable, has parallel tangent fields (connection eigenvalue 0) and
    smoothest fields of energy ~1e-14."""
    from torch_polylap.shapes import quad_grid

    V, F = quad_grid(n)
    V = V.clone()
    x = V[:, 0] - 0.5
    fold = x > 0
    V[fold, 0] = 0.5 + x[fold] * np.cos(angle)
    V[fold, 2] = x[fold] * np.sin(angle)
    return V, F

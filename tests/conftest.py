"""Shared mesh generators and paths for the test suite."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

DATA = Path(__file__).resolve().parent / "data"


def quad_grid(n: int, m: int | None = None, bump: float = 0.0, seed: int | None = None):
    """``(n+1) x (m+1)`` vertices on the unit square, quads counter-clockwise seen from +z.

    ``bump`` lifts vertices by a smooth height field (non-planar quads); ``seed`` adds a random
    in-plane jitter so that the quads are irregular but still convex.
    """
    m = n if m is None else m
    xs, ys = np.meshgrid(np.linspace(0, 1, n + 1), np.linspace(0, 1, m + 1), indexing="ij")
    if seed is not None:
        rng = np.random.default_rng(seed)
        h = 0.25 / max(n, m)
        inner = (xs > 0) & (xs < 1) & (ys > 0) & (ys < 1)
        xs = xs + inner * rng.uniform(-h, h, xs.shape)
        ys = ys + inner * rng.uniform(-h, h, ys.shape)
    zs = bump * np.sin(3 * xs + 0.5) * np.cos(2 * ys - 0.3)
    verts = np.stack([xs.ravel(), ys.ravel(), zs.ravel()], 1)
    idx = np.arange((n + 1) * (m + 1)).reshape(n + 1, m + 1)
    faces = np.stack([idx[:-1, :-1], idx[1:, :-1], idx[1:, 1:], idx[:-1, 1:]], -1).reshape(-1, 4)
    return torch.from_numpy(verts), torch.from_numpy(faces)


def mixed_mesh():
    """A small non-planar mesh with a triangle, quads, a pentagon and a hexagon, with boundary."""
    verts = torch.tensor(
        [
            [0.0, 0.0, 0.0],
            [1.0, 0.0, 0.1],
            [2.0, 0.0, -0.1],
            [3.0, 0.1, 0.0],
            [0.0, 1.0, 0.2],
            [1.1, 1.0, 0.0],
            [2.0, 1.1, 0.3],
            [3.0, 1.0, -0.2],
            [0.5, 2.0, 0.0],
            [1.5, 2.1, 0.1],
            [2.5, 2.0, 0.0],
            [3.5, 1.6, 0.2],
        ],
        dtype=torch.float64,
    )
    faces = [
        [0, 1, 5, 4],  # quad
        [1, 2, 6, 5],  # quad
        [2, 3, 7, 6],  # quad
        [4, 5, 9, 8],  # quad
        [5, 6, 10, 9],  # quad
        [6, 7, 11, 10],  # quad
        [3, 11, 7],  # triangle
    ]
    return verts, faces


def hex_pent_mesh():
    """Degrees 3, 4 and 5 around a raised apex inside a ring of quads; non-planar, with boundary."""
    ang = np.linspace(0, 2 * np.pi, 7)[:-1]
    inner = np.stack([np.cos(ang), np.sin(ang), 0.15 * np.cos(3 * ang)], 1)
    outer = np.stack([2.2 * np.cos(ang + 0.3), 2.2 * np.sin(ang + 0.3), -0.2 * np.sin(2 * ang)], 1)
    verts = torch.from_numpy(np.concatenate([inner, outer, [[0.0, 0.0, 0.4]]]))
    faces = [[0, 1, 2, 3, 12], [3, 4, 12], [4, 5, 0, 12]]
    faces += [[i, 6 + i, 6 + (i + 1) % 6, (i + 1) % 6] for i in range(6)]
    return verts, faces


@pytest.fixture
def mixed():
    return mixed_mesh()


@pytest.fixture
def hexpent():
    return hex_pent_mesh()


def assert_directional_derivative(f, X: torch.Tensor, rtol: float, seed: int = 3) -> None:
    """Autograd's derivative of the scalar ``f`` at ``X`` along a random direction equals a
    central finite difference (step 1e-6, float64)."""
    Xg = X.clone().requires_grad_(True)
    (grad,) = torch.autograd.grad(f(Xg), Xg)
    d = torch.randn(X.shape, generator=torch.Generator().manual_seed(seed), dtype=X.dtype)
    h = 1e-6
    fd = (f(X + h * d) - f(X - h * d)) / (2 * h)
    assert torch.isclose((grad * d).sum(), fd, rtol=rtol), ((grad * d).sum(), fd)


@pytest.fixture
def one_thread():
    """Tiny meshes: when another process holds a core, torch's 2-thread CSR product waits
    ~25 ms per call for a descheduled worker thread; one thread takes microseconds."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)

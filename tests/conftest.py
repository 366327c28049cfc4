"""Fixtures, command-line options and small hand-made meshes shared by the test suite.

Generated meshes (grids, cube spheres, tori, the lantern) come from :mod:`torch_polylap.shapes`;
the two meshes here are fixed, hand-written inputs with mixed degrees.

* ``--runslow``: also run the tests marked ``slow`` (the examples re-run end to end, the
  two-process DDP training, inductor's C++ compile and the late-signal CLI cases); the default
  run skips them.
* ``device``, ``dtype``: parametrize a test over the CPU and, where one is available, a CUDA
  device; over float32 and float64.
* ``one_thread``: torch pinned to one intra-op thread for the test's duration.
"""

from __future__ import annotations

import os
from pathlib import Path

# One thread per library unless the environment says otherwise, set before numpy, scipy and
# torch load their thread pools: the test meshes are tiny, and on a machine whose cores are
# shared, every multi-threaded kernel waits for descheduled threads (measured: 76 s against
# 16 s for test_operator_algebra, test_linalg and test_lanczos under a load of 3.5 on 2 cores).
for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import numpy as np  # noqa: E402
import pytest  # noqa: E402
import torch  # noqa: E402

from torch_polylap.timing import pinned_threads  # noqa: E402

# the repository root and the in-repository test meshes, for the test modules in every subfolder
ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT / "tests" / "data"


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
    d = d.to(X.device)  # the same direction on every device
    h = 1e-6
    fd = (f(X + h * d) - f(X - h * d)) / (2 * h)
    assert torch.isclose((grad * d).sum(), fd, rtol=rtol), ((grad * d).sum(), fd)


def assert_second_order_derivative(f, X: torch.Tensor) -> None:
    """Central differences along a random direction converge to autograd's derivative at
    second order in the step (an error shrinking 100-fold per 10-fold smaller step, down to
    1e-7 relative) instead of jumping between eigenvectors as the step shrinks."""
    Xg = X.clone().requires_grad_(True)
    (grad,) = torch.autograd.grad(f(Xg), Xg)
    d = torch.randn(X.shape, dtype=torch.float64, generator=torch.Generator().manual_seed(3))
    exact = float((grad * d).sum())
    size = max(1.0, abs(exact))
    steps = (1e-3, 1e-4, 1e-5)
    errors = [abs(float((f(X + h * d) - f(X - h * d)) / (2 * h)) - exact) for h in steps]
    assert errors[0] < 0.1 * size, (errors, exact)
    for h, error in zip(steps[1:], errors[1:], strict=True):
        assert error <= 2 * errors[0] * (h / steps[0]) ** 2 + 1e-7 * size, (errors, exact)


@pytest.fixture
def one_thread():
    """Tiny meshes: when another process holds a core, torch's 2-thread CSR product waits
    ~25 ms per call for a descheduled worker thread; one thread takes microseconds."""
    with pinned_threads(1):
        yield


# ---------------------------------------------------------------------------- devices, dtypes

CUDA_SKIP = pytest.mark.skipif(
    not torch.cuda.is_available(), reason="no CUDA device here (CPU-only torch or no GPU)"
)


@pytest.fixture(params=["cpu", pytest.param("cuda", marks=CUDA_SKIP)])
def device(request) -> torch.device:
    """Each device a test should pass on: the CPU, and CUDA (skipped where there is none)."""
    return torch.device(request.param)


@pytest.fixture(params=[torch.float32, torch.float64], ids=["float32", "float64"])
def dtype(request) -> torch.dtype:
    """Both floating dtypes, for tests whose claims hold in either."""
    return request.param


def tolerances(dtype: torch.dtype) -> dict[str, float]:
    """``rtol``/``atol`` for comparing a result in ``dtype`` with a float64 reference."""
    return {"rtol": 1e-4, "atol": 1e-5} if dtype == torch.float32 else {"rtol": 1e-9, "atol": 1e-11}


# ------------------------------------------------------------------------------ slow tests


def pytest_addoption(parser):
    parser.addoption(
        "--runslow",
        action="store_true",
        default=False,
        help="also run the tests marked slow (the full run, as CI does)",
    )


def pytest_collection_modifyitems(config, items):
    if config.getoption("--runslow") or "slow" in (config.getoption("-m") or ""):
        return
    skip = pytest.mark.skip(reason="slow: run with --runslow (the full suite)")
    for item in items:
        if "slow" in item.keywords:
            item.add_marker(skip)


@pytest.fixture
def fresh_dynamo():
    """torch.compile's caches cleared around the test, with torch's ``trace_autograd_ops`` on
    (its switch for tracing ``.backward()`` and ``torch.autograd.grad`` into the graph, off by
    default in torch 2.13)."""
    torch._dynamo.reset()
    with torch._dynamo.config.patch(trace_autograd_ops=True):
        yield
    torch._dynamo.reset()


def on_device(
    mesh: tuple[torch.Tensor, object], device: torch.device
) -> tuple[torch.Tensor, object]:
    """A ``(verts, faces)`` pair with the vertices moved to ``device`` and the faces left as
    they are: the package takes faces on the CPU with vertices on any device."""
    verts, faces = mesh
    return verts.to(device), faces

"""Meshes without faces: ``0 x 0`` operators for no vertices, zero ``L`` and ``M0`` for isolated
ones (docs/conventions.md: an isolated vertex has zero mass and an empty row of ``L``).

The reference is the definition ``L = sum_f P_f^T L_f P_f``, ``M0 = diag(sum_f |f| / k_f)``:
an empty sum is the zero matrix, whatever the method and on every path that assembles it (eager,
batched, the module, the gather form that torch.compile runs).
"""

from __future__ import annotations

import pytest
import torch

import torch_polylap as tp
from torch_polylap.assembly import assemble_gathered, gather_plan_of
from torch_polylap.kernels import BLOCK_METHODS, METHODS, block_kernel

pytestmark = pytest.mark.filterwarnings("ignore:the mesh .* is not a consistently oriented")

DTYPES = (torch.float32, torch.float64)


def _assert_zero(A: torch.Tensor, shape: tuple[int, ...], dtype: torch.dtype) -> None:
    assert isinstance(A, tp.sparse.SparseOperator)
    assert tuple(A.shape) == shape and A.dtype == dtype
    assert torch.equal(A.to_dense(), torch.zeros(shape, dtype=dtype))


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("num_verts", [0, 3])
def test_laplacian_of_no_faces_is_zero(method, dtype, num_verts):
    verts = torch.zeros(num_verts, 3, dtype=dtype)
    L, M0 = tp.laplacian(verts, [], method=method)
    _assert_zero(L, (num_verts, num_verts), dtype)
    _assert_zero(M0, (num_verts, num_verts), dtype)
    assert tuple(M0.diagonal().shape) == (num_verts,)
    # products with the empty operator are empty (or zero) dense tensors
    assert torch.equal(
        L @ torch.ones(num_verts, 2, dtype=dtype), torch.zeros(num_verts, 2, dtype=dtype)
    )


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("num_verts", [0, 3])
def test_module_and_batch_of_no_faces(method, num_verts):
    verts = torch.zeros(num_verts, 3, dtype=torch.float64)
    L, M0 = tp.PolygonLaplacian(method=method)(verts, [])
    _assert_zero(L, (num_verts, num_verts), torch.float64)
    _assert_zero(M0, (num_verts, num_verts), torch.float64)
    Lb, Mb = tp.laplacian(verts.expand(2, num_verts, 3), [], method=method)
    _assert_zero(Lb, (2, num_verts, num_verts), torch.float64)
    _assert_zero(Mb, (2, num_verts, num_verts), torch.float64)


@pytest.mark.parametrize("num_verts", [0, 3])
def test_planarity_laplacian_of_no_faces(num_verts):
    verts = torch.zeros(num_verts, 3, dtype=torch.float64)
    _assert_zero(tp.planarity_laplacian(verts, []), (num_verts, num_verts), torch.float64)


@pytest.mark.parametrize("method", BLOCK_METHODS)
@pytest.mark.parametrize("num_verts", [0, 3])
def test_gathered_assembly_of_no_faces(method, num_verts):
    """The gather form (what torch.compile traces) on a topology without faces."""
    topo = tp.build_topology([], num_verts)
    view = topo.on("cpu")
    verts = torch.zeros(num_verts, 3, dtype=torch.float64)
    kernel = block_kernel(method, 1.0)
    values, masses, ok, accurate, stretch = assemble_gathered(
        verts, view, kernel, gather_plan_of(topo, view), want_mass=True
    )
    assert values.shape == (topo.nnz,) and not values.any()
    assert masses is not None and torch.equal(masses, torch.zeros(num_verts, dtype=torch.float64))
    assert bool(ok) and bool(accurate) and float(stretch) == 0.0


@pytest.mark.parametrize("num_verts", [0, 3])
def test_compiled_laplacian_of_no_faces(num_verts):
    topo = tp.build_topology([], num_verts)
    lap = tp.CompiledLaplacian(topo, options={"backend": "aot_eager"})
    L, M0 = lap(torch.zeros(num_verts, 3, dtype=torch.float64))
    _assert_zero(L, (num_verts, num_verts), torch.float64)
    _assert_zero(M0, (num_verts, num_verts), torch.float64)

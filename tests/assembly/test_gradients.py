"""Gradients: gradcheck in float64 (values, spmm), thin faces, CUDA.

Peak memory of the O(nnz) backward is tested in test_operator_algebra.py under an address-space cap.
"""

from __future__ import annotations

import pytest
import torch
from conftest import assert_directional_derivative, hex_pent_mesh, mixed_mesh, tolerances

import torch_polylap as tp
from torch_polylap.shapes import quad_grid
from torch_polylap.sparse import sparse_values

D64 = {"dtype": torch.float64}


@pytest.mark.parametrize("make", [mixed_mesh, hex_pent_mesh], ids=["mixed", "hexpent"])
@pytest.mark.parametrize("lam", [0.7, 2.0])
def test_gradcheck_laplacian_values(make, lam, device):
    V, F = make()
    V = V.to(device)
    topo = tp.build_topology(F, V.shape[0])

    def values(X):
        L, M0 = tp.laplacian(X, topo, lam)
        return sparse_values(L), sparse_values(M0)

    assert torch.autograd.gradcheck(values, (V.clone().requires_grad_(True),), eps=1e-6, atol=1e-6)


@pytest.mark.parametrize("split", [False, True], ids=["quads", "triangles"])
def test_gradients_of_chunked_assembly(split, monkeypatch, device):
    """With a degree group split into several chunks (gathered by one autograd node), first
    and second derivatives pass gradcheck/gradgradcheck, and forward mode equals reverse."""
    import torch_polylap.topology as topology

    monkeypatch.setattr(topology.groups, "CHUNK_ELEMENTS", 1)  # 256 faces per chunk
    V, F = quad_grid(17, bump=0.3, seed=5, device=device)
    V = V.double()
    if split:
        F = torch.cat((F[:, [0, 1, 2]], F[:, [0, 2, 3]]))
    topo = tp.build_topology(F, V.shape[0])
    assert len(topo.groups[0].chunks) > 1
    U = torch.randn(V.shape[0], 2, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    U = U.to(device)

    def values(X):
        L, M0 = tp.laplacian(X, topo, 1.3)
        return sparse_values(L), sparse_values(M0)

    def energy(X):
        L, M0 = tp.laplacian(X, topo, 1.3)
        return ((L @ U).square().sum(0) * (M0 @ U).sum(0)).sum()

    X = V.clone().requires_grad_(True)
    assert torch.autograd.gradcheck(values, (X,), eps=1e-6, atol=1e-6, fast_mode=True)
    assert torch.autograd.gradgradcheck(energy, (X,), eps=1e-6, atol=1e-5, fast_mode=True)
    T = torch.randn_like(V)
    (g,) = torch.autograd.grad(energy(X), X)
    with torch.autograd.forward_ad.dual_level():
        dual = torch.autograd.forward_ad.make_dual(V.clone(), T)
        tangent = torch.autograd.forward_ad.unpack_dual(energy(dual)).tangent
    torch.testing.assert_close(tangent, (g * T).sum())


def test_gradcheck_planarity_energy(device):
    V, F = hex_pent_mesh()
    X = V.to(device).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda X: tp.planarity_energy(X, F, 2.0), (X,))


def test_gradcheck_learnable_lambda(device):
    V, F = mixed_mesh()
    V = V.to(device)
    topo = tp.build_topology(F, V.shape[0])
    lam = torch.tensor(1.3, **D64, device=device, requires_grad=True)
    assert torch.autograd.gradcheck(
        lambda lam: sparse_values(tp.laplacian(V, topo, lam)[0]), (lam,)
    )


def random_sparse(n, m, density, seed):
    gen = torch.Generator().manual_seed(seed)
    dense = torch.rand(n, m, generator=gen, **D64) * (torch.rand(n, m, generator=gen) < density)
    return dense, dense.to_sparse_csr()


@pytest.mark.parametrize("symmetric", [False, True])
@pytest.mark.parametrize("layout", [torch.sparse_csr, torch.sparse_coo])
def test_gradcheck_spmm(symmetric, layout, device):
    dense, _ = random_sparse(7, 7 if symmetric else 5, 0.5, 0)
    if symmetric:
        dense = dense + dense.T
    dense = dense.to(device)
    pattern = (
        dense.to_sparse_coo().coalesce() if layout == torch.sparse_coo else dense.to_sparse_csr()
    )
    # a torch sparse tensor without grad is converted; its values then vary through the operator
    operator = tp.sparse.as_operator(pattern)
    values = pattern.values().clone().requires_grad_(True)
    X = torch.randn(dense.shape[1], 3, **D64, device=device, requires_grad=True)

    def product(v, X):
        A = operator.with_values(v, symmetric=symmetric)
        return tp.sparse.spmm(A, X)

    assert torch.autograd.gradcheck(product, (values, X))
    x1 = torch.randn(dense.shape[1], **D64, device=device, requires_grad=True)
    assert torch.autograd.gradcheck(product, (values, x1))
    assert torch.allclose(product(values, X), dense @ X)


def test_spmm_rejects_mismatches(device):
    _, A = random_sparse(4, 3, 0.6, 1)
    A = A.to(device)
    with pytest.raises(ValueError, match="dtype"):
        tp.sparse.spmm(A, torch.randn(3, 2, device=device))
    with pytest.raises(ValueError, match="cannot multiply"):
        tp.sparse.spmm(A, torch.randn(4, 2, **D64, device=device))
    with pytest.raises(TypeError, match="expected a sparse matrix"):
        tp.sparse.spmm(
            torch.randn(4, 3, **D64, device=device), torch.randn(3, 2, **D64, device=device)
        )


def test_gradient_of_dirichlet_energy_matches_finite_differences(device):
    V, F = quad_grid(4, bump=0.3, seed=9, device=device)
    u = torch.sin(3 * V[:, 0]) * V[:, 1]
    topo = tp.build_topology(F, V.shape[0])

    def energy(X):
        L, _ = tp.laplacian(X, topo, 1.5)
        return 0.5 * (u * tp.sparse.spmm(L, u)).sum()

    assert_directional_derivative(energy, V, rtol=1e-7)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("thinness", [1e-3, 1e-6])
def test_thin_faces_have_finite_values_and_gradients(dtype, thinness, device):
    """Valid but thin faces (aspect ratio up to 1e6) give finite L, M0 and gradients; in
    float32 (aspect ratio 1e3: products with L lose about 6e-2) with a warning that says so."""
    if dtype == torch.float32 and thinness < 1e-5:
        thinness = 1e-3  # float32 resolves aspect ratios to about 1e-4
    verts = torch.tensor(
        [
            [0.0, 0.0, 0.0],
            [1.0, 0.0, 0.0],
            [1.0, thinness, 0.01],
            [0.0, thinness, -0.01],
            [2.0, 0.0, 0.02],
            [2.0, thinness, 0.0],
            [0.5, 1.0, 0.0],
        ],
        dtype=dtype,
        device=device,
    )
    faces = [[0, 1, 2, 3], [1, 4, 5, 2], [3, 2, 5, 6]]
    X = verts.clone().requires_grad_(True)
    if dtype == torch.float32:
        with pytest.warns(tp.checks.Float32PrecisionWarning, match="face 0 "):
            L, M0 = tp.laplacian(X, faces)
    else:
        L, M0 = tp.laplacian(X, faces)
    assert torch.isfinite(sparse_values(L)).all() and torch.isfinite(sparse_values(M0)).all()
    loss = (tp.sparse.spmm(L, X) ** 2).sum() + tp.planarity_energy(X, faces)
    loss.backward()
    assert torch.isfinite(X.grad).all()


def test_laplacian_and_its_gradient_on_every_device_and_dtype(device, dtype):
    V, F = quad_grid(20, bump=0.3, seed=1)
    X = V.to(device, dtype).requires_grad_(True)
    L, M0 = tp.laplacian(X, F, 1.5)
    assert L.device.type == device.type and M0.device.type == device.type
    assert L.dtype == dtype and M0.dtype == dtype
    (tp.sparse.spmm(L, X) ** 2).sum().backward()
    assert X.grad.device.type == device.type and X.grad.dtype == dtype
    # float64 on the CPU: the gradient is checked against finite differences; every other
    # device and dtype against that float64 CPU result
    ref = V.clone().requires_grad_(True)
    L64, M64 = tp.laplacian(ref, F, 1.5)
    (tp.sparse.spmm(L64, ref) ** 2).sum().backward()
    if (device.type, dtype) == ("cpu", torch.float64):
        assert_directional_derivative(
            lambda Y: (tp.sparse.spmm(tp.laplacian(Y, F, 1.5)[0], Y) ** 2).sum(), V, rtol=1e-6
        )
    else:
        tol = tolerances(dtype)
        torch.testing.assert_close(L.detach().to_dense().cpu().double(), L64.to_dense(), **tol)
        torch.testing.assert_close(M0.diagonal().detach().cpu().double(), M64.diagonal(), **tol)
        scale = float(ref.grad.abs().max())
        torch.testing.assert_close(
            X.grad.cpu().double(), ref.grad, rtol=tol["rtol"], atol=tol["rtol"] * scale
        )

"""Differentiable solves and eigenpairs."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.linalg
import scipy.sparse as sp
import torch
from conftest import DATA, assert_directional_derivative, hex_pent_mesh, mixed_mesh
from meshes import read_mesh, require_shared

import torch_polylap as tp
from torch_polylap.shapes import quad_grid
from torch_polylap.sparse import operator_from_parts

D64 = {"dtype": torch.float64}


def implicit_matrix(V, F, h=0.1, lam=1.0):
    L, M0 = tp.laplacian(V, F, lam)
    return M0 + h * L


@pytest.mark.parametrize("backend", ["splu", "cg", "cholesky"])
def test_solve_matches_dense(backend, device):
    V, F = quad_grid(6, bump=0.3, seed=2)
    A = implicit_matrix(V.to(device), F)
    B = torch.randn(V.shape[0], 3, generator=torch.Generator().manual_seed(0), **D64).to(device)
    X = tp.solve(A, B, backend=backend, tol=1e-12)
    ref = torch.linalg.solve(A.to_dense(), B)
    assert X.device == B.device and torch.allclose(X, ref, rtol=1e-9, atol=1e-10)
    x = tp.solve(A, B[:, 0], backend=backend, tol=1e-12)
    assert x.shape == (V.shape[0],) and torch.allclose(x, ref[:, 0], rtol=1e-9, atol=1e-10)


@pytest.mark.parametrize("backend", ["splu", "cg", "cholesky"])
def test_gradcheck_solve_values_and_rhs(backend, device):
    V, F = mixed_mesh()
    A = implicit_matrix(V.to(device), F, h=0.3)
    crow, col = A.crow_indices(), A.col_indices()
    values = A.values().detach().clone().requires_grad_(True)
    B = torch.randn(V.shape[0], 2, generator=torch.Generator().manual_seed(1), **D64).to(device)
    B.requires_grad_(True)

    def f(v, B):
        # symmetrize so that perturbations keep A symmetric, as the adjoint for CG assumes
        A = operator_from_parts(crow, col, v, (V.shape[0],) * 2, symmetric=backend == "cholesky")
        return tp.solve(A, B, backend=backend, tol=1e-13)

    if backend in ("cg", "cholesky"):
        # CG and Cholesky assume symmetry: check the gradient with respect to B only (the
        # value gradient's formula is the same as splu's, checked there)
        Ad = A.to_dense()
        assert torch.equal(Ad, Ad.T)
        assert torch.autograd.gradcheck(lambda B: f(values.detach(), B), (B,))
    else:
        assert torch.autograd.gradcheck(f, (values, B))


def test_solve_gradient_reaches_vertex_positions(device):
    """d/dX of a loss through (M0 + h L)^{-1} b matches finite differences."""
    V, F = quad_grid(4, bump=0.3, seed=5)
    V, F = V.to(device), F.to(device)
    topo = tp.build_topology(F, V.shape[0])
    b = torch.sin(3 * V[:, 0]) + V[:, 1]

    def loss(X):
        return tp.solve(implicit_matrix(X, topo), b).square().sum()

    assert_directional_derivative(loss, V, rtol=1e-6)


@pytest.mark.parametrize(
    ("backend", "factor_class"), [("splu", "Factorization"), ("cholesky", "CholeskyFactorization")]
)
def test_factorization_is_cached_and_invalidated(monkeypatch, backend, factor_class, device):
    V, F = quad_grid(5, bump=0.2, device=device)
    A = implicit_matrix(V, F)
    B = torch.ones(V.shape[0], **D64, device=device)
    built = []
    original = getattr(tp.linalg.factor, factor_class)

    def counting(*args):
        built.append(1)
        return original(*args)

    monkeypatch.setattr(tp.linalg.factor, factor_class, counting)
    tp.solve(A, B, backend=backend)
    tp.solve(A, 2 * B, backend=backend)
    tp.solve(A.detach(), 3 * B, backend=backend)  # same value storage: same factorization
    assert len(built) == 1
    A.values().mul_(2.0)  # in-place change of the values: the cache must notice
    X = tp.solve(A, B, backend=backend)
    assert len(built) == 2
    assert torch.allclose(A.to_dense() @ X, B)
    # gradients through a solve reuse the forward's factorization in the backward solve
    Vg = V.clone().requires_grad_(True)
    tp.solve(implicit_matrix(Vg, F), B, backend=backend).sum().backward()
    assert len(built) == 3


def test_auto_backend_and_cholesky_requirements(device):
    V, F = quad_grid(4, bump=0.2, device=device)
    L, M0 = tp.laplacian(V, F)
    B = torch.ones(V.shape[0], **D64, device=device)
    A = M0 + 0.1 * L
    reference = torch.linalg.solve(A.to_dense(), B)
    # a symmetric system goes through CHOLMOD (cholespy is in the test extra)
    torch.testing.assert_close(tp.solve(A, B), reference, rtol=1e-10, atol=1e-12)
    assert "cholesky" in A._solver_cache
    unsymmetric = A.with_values(A.values(), symmetric=False)
    # not marked symmetric: SuperLU on the CPU, CG (to a 1e-10 residual) elsewhere
    tol = {"rtol": 1e-10, "atol": 1e-12} if device.type == "cpu" else {"rtol": 1e-7, "atol": 1e-9}
    torch.testing.assert_close(tp.solve(unsymmetric, B), reference, **tol)
    with pytest.raises(ValueError, match="symmetric operator"):
        tp.solve(unsymmetric, B, backend="cholesky")
    with pytest.raises(ValueError, match="singular.*M0 \\+ h L"):
        tp.solve(L, B, backend="cholesky")


def test_singular_system_is_a_clear_error(device):
    V, F = quad_grid(3, device=device)
    L, _ = tp.laplacian(V, F)
    with pytest.raises(ValueError, match="singular.*M0 \\+ h L.*dirichlet_solve"):
        tp.solve(L, torch.ones(V.shape[0], **D64, device=device))
    with pytest.raises(ValueError, match="dtype"):
        tp.solve(L, torch.ones(V.shape[0], device=device))


def test_dirichlet_solve_reproduces_linear_functions(device):
    """Linear precision: harmonic interpolation of linear boundary data is that linear function."""
    V, F = read_mesh(DATA / "grid" / "quad_3.obj", device=device)
    topo = tp.build_topology(F, V.shape[0])
    L, _ = tp.laplacian(V, topo, 2.0)
    boundary = topo.boundary_vertices
    u = 0.3 + 2.0 * V[:, 0] - 1.5 * V[:, 1]
    X = tp.dirichlet_solve(L, torch.zeros_like(u), boundary, u[boundary])
    assert torch.allclose(X, u, atol=1e-11)
    assert torch.equal(X[boundary], u[boundary])
    mask = torch.zeros(V.shape[0], dtype=torch.bool, device=device)
    mask[boundary] = True
    X2 = tp.dirichlet_solve(
        L, torch.zeros(V.shape[0], 2, **D64, device=device), mask, torch.stack([u, u], 1)[mask]
    )
    assert torch.allclose(X2[:, 1], u, atol=1e-11)


def test_gradcheck_dirichlet_solve(device):
    V, F = hex_pent_mesh()
    V = V.to(device)
    topo = tp.build_topology(F, V.shape[0])
    boundary = topo.boundary_vertices
    b = torch.randn(V.shape[0], generator=torch.Generator().manual_seed(4), **D64).to(device)
    g = torch.randn(boundary.numel(), generator=torch.Generator().manual_seed(5), **D64)
    g = g.to(device)

    def f(X, b, g):
        L, M0 = tp.laplacian(X, topo)
        return tp.dirichlet_solve(L, M0 @ b, boundary, g)

    args = (V.clone().requires_grad_(True), b.requires_grad_(True), g.requires_grad_(True))
    assert torch.autograd.gradcheck(f, args)


def test_eigs_match_dense_and_are_m_orthonormal(device):
    V, F = read_mesh(DATA / "spot_control_mesh.obj", device=device)
    L, M0 = tp.laplacian(V, F)
    evals, evecs = tp.eigs(L, M0, 10)
    assert evals.device == evecs.device == V.device
    ref = scipy.linalg.eigh(
        L.to_dense().cpu().numpy(), M0.to_dense().cpu().numpy(), eigvals_only=True
    )[:10]
    np.testing.assert_allclose(evals.cpu().numpy(), ref, rtol=1e-8, atol=1e-10)
    gram = evecs.T @ (M0.to_dense() @ evecs)
    assert torch.allclose(gram, torch.eye(10, **D64, device=device), atol=1e-10)
    residual = L.to_dense() @ evecs - (M0.to_dense() @ evecs) * evals
    assert residual.abs().max() < 1e-9 * evals.max()
    assert abs(evals[0]) < 1e-10  # constants


def test_eigs_counts_components(device):
    V1, F1 = quad_grid(4, bump=0.2)
    V2, F2 = mixed_mesh()
    V = torch.cat([V1, V2 + 5.0]).to(device)
    F = [f.tolist() for f in F1] + [[i + V1.shape[0] for i in f] for f in F2]
    L, M0 = tp.laplacian(V, F)
    evals, _ = tp.eigs(L, M0, 4)
    assert (evals[:2].abs() < 1e-9).all() and evals[2] > 1e-3


def test_eigenvalue_gradient_matches_finite_differences(device):
    V, F = quad_grid(5, bump=0.3, seed=11)  # irregular: simple eigenvalues
    V = V.to(device)
    topo = tp.build_topology(F, V.shape[0])
    weights = torch.tensor([0.0, 1.0, -0.5, 2.0], **D64, device=device)

    def spectrum(X):
        L, M0 = tp.laplacian(X, topo, 1.5)
        return (tp.eigs(L, M0, 4)[0] * weights).sum()

    assert_directional_derivative(spectrum, V, rtol=1e-5, seed=7)


def test_eigs_rejects_bad_k(device):
    V, F = mixed_mesh()
    L, M0 = tp.laplacian(V.to(device), F)
    with pytest.raises(ValueError, match="1 <= k < n"):
        tp.eigs(L, M0, V.shape[0])


@pytest.mark.parametrize("family", ["hex", "quad"])
def test_sphere_spectrum_converges_at_second_order(family, device):
    """First 16 eigenvalues on the unit sphere against l(l+1), multiplicities 1, 3, 5, 7."""
    shared = require_shared()
    exact = torch.tensor([ell * (ell + 1) for ell in range(4) for _ in range(2 * ell + 1)], **D64)
    errors, sizes = [], []
    for level in (2, 3, 4):
        V, F = read_mesh(shared / "sphere" / f"{family}_{level}.obj", device=device)
        V = V / V.norm(dim=1, keepdim=True)
        evals, _ = tp.eigs(*tp.laplacian(V, F, 1.0), 16)
        evals = evals.cpu()
        errors.append(float(((evals[1:] - exact[1:]).abs() / exact[1:]).max()))
        sizes.append(V.shape[0])
    for i in (1, 2):
        order = np.log(errors[i - 1] / errors[i]) / np.log(np.sqrt(sizes[i] / sizes[i - 1]))
        assert order > 1.7, (family, errors)


def test_eigs_names_a_vertex_without_mass(device):
    V, F = quad_grid(5, bump=0.2, device=device)
    isolated = torch.cat([V, torch.zeros(1, 3, **D64, device=device)])  # a vertex in no face
    with pytest.warns(UserWarning):
        L, M0 = tp.laplacian(isolated, F)
    with pytest.raises(ValueError, match=f"vertex {V.shape[0]} has mass 0.*remove_unreferenced"):
        tp.eigs(L, M0, 5)
    with pytest.raises(TypeError, match="k must be an integer"):
        tp.eigs(*tp.laplacian(V, F), 2.0)


def test_dirichlet_solve_refuses_bad_fixed_rows(device):
    V, F = quad_grid(3, device=device)
    L, _ = tp.laplacian(V, F)
    b = torch.zeros(V.shape[0], **D64, device=device)

    def zeros(n: int) -> torch.Tensor:
        return torch.zeros(n, **D64, device=device)

    def index(*values: float) -> torch.Tensor:
        return torch.tensor(values, device=device)

    with pytest.raises(ValueError, match=r"fixed\[1\] = 99 is out of range"):
        tp.dirichlet_solve(L, b, index(0, 99), zeros(2))
    with pytest.raises(ValueError, match="repeats an earlier index"):
        tp.dirichlet_solve(L, b, index(0, 0), zeros(2))
    with pytest.raises(TypeError, match="integer indices or be a boolean mask"):
        tp.dirichlet_solve(L, b, index(0.5), zeros(1))
    with pytest.raises(ValueError, match="do not fit"):
        tp.dirichlet_solve(L, b, index(0, 1), zeros(3))


def test_preconditioned_cg_with_the_exact_inverse_takes_one_step(device):
    from torch_polylap.linalg.cg import preconditioned_cg

    A = torch.tensor([[4.0, 1, 0], [1, 3, 1], [0, 1, 2]], dtype=torch.float64, device=device)
    B = torch.tensor([[1.0, 0], [2, 1], [3, -1]], dtype=torch.float64, device=device)
    calls = []

    def exact(R: torch.Tensor) -> torch.Tensor:
        calls.append(1)
        return torch.linalg.solve(A, R)

    X, ok = preconditioned_cg(A, B, exact, 1e-12, 10)
    assert ok and len(calls) == 2  # the initial residual and the one after the exact step
    assert torch.allclose(X, torch.linalg.solve(A, B), atol=1e-14)
    _, ok = preconditioned_cg(A, B, lambda R: R, 1e-12, 1)
    assert not ok  # one unpreconditioned step does not solve a 3 x 3 system


def test_factorization_check_can_be_skipped(device):
    from torch_polylap.linalg.factor import spd_factorization

    A = tp.sparse.from_scipy(sp.diags([1.0, 1e-17, 2.0]).tocsr()).to(device)
    with pytest.raises(ValueError, match="singular"):
        spd_factorization(A)
    ones = torch.ones(3, 1, dtype=torch.float64, device=device)
    X = spd_factorization(A, check=False).solve(ones).cpu()
    assert torch.allclose(X[[0, 2], 0], torch.tensor([1.0, 0.5], dtype=torch.float64))
    assert X[1, 0] > 1e16  # what the check would have refused: the caller asked for it

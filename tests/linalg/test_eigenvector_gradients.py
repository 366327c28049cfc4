"""Eigenvector derivatives through ``tp.eigs`` (simple eigenvalues, adjoint / Nelson's method)."""

from __future__ import annotations

import subprocess
import sys

import pytest
import torch
from conftest import ROOT, assert_directional_derivative, hex_pent_mesh, mixed_mesh

import torch_polylap as tp
from torch_polylap.shapes import quad_grid

D64 = {"dtype": torch.float64}
MESHES = {
    "quad_grid": lambda: quad_grid(4, bump=0.3, seed=2),
    "mixed": mixed_mesh,
    "hex_pent": hex_pent_mesh,
}


def _weights(n: int, k: int, seed: int = 1) -> torch.Tensor:
    return torch.randn(n, k, **D64, generator=torch.Generator().manual_seed(seed))


def _sign_dependent(evecs: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    """Uses the package's sign convention (largest-magnitude entry positive) and every column."""
    return (evecs * w).sum() + (evecs[:, 1:] ** 3 * w[:, 1:]).sum()


def _sign_invariant(evecs: torch.Tensor, M0: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    """|phi_i^T M phi_target_i| and squared entries: unchanged when a column flips sign."""
    return (evecs * (M0 @ w)).sum(0).abs().sum() + (evecs**2 * w).sum()


@pytest.mark.parametrize("mesh", sorted(MESHES))
def test_gradcheck_to_vertices(mesh, one_thread, device):
    V, F = MESHES[mesh]()
    V = V.to(device, torch.float64)
    k = 5
    w = _weights(V.shape[0], k).to(device)

    def dependent(X):
        return _sign_dependent(tp.eigs(*tp.laplacian(X, F), k)[1], w)

    def invariant(X):
        L, M0 = tp.laplacian(X, F)
        evals, evecs = tp.eigs(L, M0, k)
        return _sign_invariant(evecs, M0, w) + evals.sum()

    X = V.clone().requires_grad_(True)
    for f in (dependent, invariant):
        assert torch.autograd.gradcheck(f, (X,), eps=1e-6, atol=1e-6, rtol=1e-5)


def test_gradcheck_to_operator_values(one_thread, device):
    """Gradients with respect to L's values (kept symmetric: L = B + B^T) and M's diagonal."""
    V, F = quad_grid(3, bump=0.3, seed=5)
    L0, M0 = tp.laplacian(V.to(device, torch.float64), F)
    k = 4
    w = _weights(V.shape[0], k, seed=2).to(device)
    half = (0.5 * tp.sparse.sparse_values(L0)).clone().requires_grad_(True)
    mass = tp.sparse.sparse_values(M0).clone().requires_grad_(True)

    def f(half, mass):
        B = L0.with_values(half, symmetric=False)
        evals, evecs = tp.eigs(B + B.T, M0.with_values(mass), k)
        return evecs * w + evecs**2, evals

    assert torch.autograd.gradcheck(f, (half, mass), eps=1e-6, atol=1e-6, rtol=1e-5)


def test_operator_from_parts_and_m_orthonormality_are_consistent(one_thread, device):
    """The gradient of phi^T M phi (identically 1) is zero; of phi_i^T M phi_j zero as well."""
    V, F = mixed_mesh()
    X = V.to(device).requires_grad_(True)
    L, M0 = tp.laplacian(X, F)
    _, evecs = tp.eigs(L, M0, 4)
    gram = evecs.T @ (M0 @ evecs)
    torch.testing.assert_close(gram.detach().cpu(), torch.eye(4, **D64), atol=1e-12, rtol=0)
    (grad,) = torch.autograd.grad((gram * _weights(4, 4).to(device)).sum(), X)
    assert grad.abs().max() < 1e-9


def test_matches_finite_differences_on_the_sparse_route(one_thread, device):
    """500 vertices: eigs runs block Lanczos, not LAPACK; central differences agree."""
    V, F = quad_grid(21, bump=0.3, seed=7)
    w = _weights(V.shape[0], 6, seed=4).to(device)

    def f(X):
        L, M0 = tp.laplacian(X, F)
        return _sign_invariant(tp.eigs(L, M0, 6)[1], M0, w)

    assert_directional_derivative(f, V.to(device, torch.float64), rtol=1e-5)


def test_heat_kernel_signature_gradient_reaches_the_vertices(one_thread, device):
    V, F = hex_pent_mesh()
    times = torch.tensor([0.1, 1.0], **D64, device=device)

    def f(X):
        evals, evecs = tp.eigs(*tp.laplacian(X, F), 6)
        return tp.heat_kernel_signature(evals, evecs, times).square().sum()

    assert_directional_derivative(f, V.to(device, torch.float64), rtol=1e-6)


def test_repeated_eigenvalue_names_the_cluster(one_thread, device):
    V, F = quad_grid(4)  # regular grid: mu_1 = mu_2 exactly (x <-> y symmetry)
    X = V.to(device, torch.float64).clone().requires_grad_(True)
    evals, evecs = tp.eigs(*tp.laplacian(X, F), 4)
    assert torch.isclose(evals[1], evals[2], rtol=1e-10)
    with pytest.raises(RuntimeError, match=r"evecs\[:, 1\].*eigenvalues 1\.\.2.*mu_1 = .*mu_2 = "):
        evecs[:, 1].abs().sum().backward()
    # the simple pairs (the constant and mu_3) still have gradients
    evals, evecs = tp.eigs(*tp.laplacian(X, F), 4)
    (grad,) = torch.autograd.grad(evecs[:, 3].abs().sum() + evecs[:, 0].sum() + evals.sum(), X)
    assert torch.isfinite(grad).all()


def test_repeated_eigenvalue_beyond_the_computed_ones(one_thread, device):
    """k = 2 on a regular grid: mu_1's twin mu_2 was not computed, inverse iteration finds it."""
    V, F = quad_grid(4)
    X = V.to(device, torch.float64).clone().requires_grad_(True)
    evals, evecs = tp.eigs(*tp.laplacian(X, F), 2)
    mu = f"{evals[1].item():.8f}"[:-1]
    with pytest.raises(RuntimeError, match=rf"evecs\[:, 1\].*mu_1 = {mu}.*not computed, near {mu}"):
        evecs[:, 1].square().mul(X[:, 0]).sum().backward()


def test_subspace_invariant_loss_on_a_repeated_eigenvalue(one_thread, device):
    """A loss that sees the cluster mu_1 = mu_2 of a regular grid only through its projector
    Phi_C Phi_C^T M0 has a gradient, also at the symmetric mesh itself."""
    V, F = quad_grid(4, bump=0.0)
    V = V.to(device, torch.float64)
    u = torch.cos(3 * V[:, 0]) + V[:, 1] ** 2
    w = _weights(V.shape[0], 1, seed=6)[:, 0].to(device)

    def f(X):
        L, M0 = tp.laplacian(X, F)
        evals, evecs = tp.eigs(L, M0, 4)
        C = evecs[:, 1:3]
        projected = C @ (C.T @ (M0 @ u))  # depends on span(phi_1, phi_2) only
        # phi_3 is simple, but its largest entries tie in magnitude: a sign-invariant term
        return (projected * w).sum() + (C.T @ (M0 @ u)).square().sum() + (evecs[:, 3] ** 2 @ w)

    L, M0 = tp.laplacian(V, F)
    evals, _ = tp.eigs(L, M0, 4)
    assert abs(evals[1] - evals[2]) < 1e-12 * evals[3]
    X = V.clone().requires_grad_(True)
    assert torch.autograd.gradcheck(f, (X,), eps=1e-6, atol=1e-6, rtol=1e-5)


def test_second_derivatives_refuse(one_thread, device):
    V, F = mixed_mesh()
    X = V.to(device).requires_grad_(True)
    _, evecs = tp.eigs(*tp.laplacian(X, F), 3)
    with pytest.raises(RuntimeError, match="second derivatives"):
        torch.autograd.grad(evecs[:, 1].sum(), X, create_graph=True)


@pytest.mark.slow  # runs the example in a subprocess
def test_example_runs_and_its_loss_decreases(tmp_path):
    run = subprocess.run(
        [
            sys.executable,
            str(ROOT / "examples" / "fit_eigenvectors.py"),
            "--steps",
            "12",
            "--n",
            "6",
            "--out",
            str(tmp_path),
        ],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=ROOT,
    )
    assert run.returncode == 0, run.stderr
    losses = [
        float(line.split("loss")[1].split()[0])
        for line in run.stdout.splitlines()
        if line.startswith("step")
    ]
    assert len(losses) >= 2 and losses[-1] < 0.5 * losses[0], run.stdout
    assert "| 12 |" in (tmp_path / "fit_eigenvectors.md").read_text()  # the last step's row
    assert (tmp_path / "fit_eigenvectors.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"

"""Spectral features and heat diffusion against dense matrix exponentials."""

from __future__ import annotations

import math

import pytest
import scipy.linalg
import torch
from conftest import DATA, mixed_mesh
from meshes import read_mesh

import torch_polylap as tp
from torch_polylap.shapes import quad_grid

D64 = {"dtype": torch.float64}


@pytest.fixture(scope="module")
def spot():
    V, F = read_mesh(DATA / "spot_control_mesh.obj")
    L, M0 = tp.laplacian(V, F)
    evals, evecs = tp.eigs(L, M0, V.shape[0] - 1)  # all but the largest eigenpair
    return V, F, L, M0, evals, evecs


def heat_operator(L, M0, t):
    """exp(-t M0^{-1} L), dense, computed independently of the eigensolver."""
    Linv = torch.diag(1.0 / M0.to_dense().diagonal()) @ L.to_dense()
    return torch.from_numpy(scipy.linalg.expm(-t * Linv.numpy()))


def test_heat_kernel_signature_is_the_heat_kernel_diagonal(spot, device):
    _, _, L, M0, evals, evecs = spot
    times = torch.tensor([0.05, 0.2, 1.0], **D64)
    hks = tp.heat_kernel_signature(evals.to(device), evecs.to(device), times.to(device))
    assert hks.device.type == device.type
    hks = hks.cpu()  # the dense references on the CPU
    m = M0.to_dense().diagonal()
    for j, t in enumerate(times.tolist()):
        kernel = heat_operator(L, M0, t) / m[None, :]  # K_t = exp(-t M^-1 L) M^-1
        assert torch.allclose(hks[:, j], kernel.diagonal(), rtol=1e-6)


def test_spectral_and_implicit_diffusion_agree_with_expm(spot, device):
    V, _, L, M0, evals, evecs = spot
    u0 = torch.stack([V[:, 0], torch.cos(3 * V[:, 1])], 1)
    t = 0.1
    exact = heat_operator(L, M0, t) @ u0  # the dense references on the CPU
    on = [x.to(device) for x in (u0, evals, evecs, M0, L)]
    u0_d, evals_d, evecs_d, M0_d, L_d = on
    spectral = tp.spectral_heat_diffusion(u0_d, evals_d, evecs_d, M0_d, t)
    assert spectral.device.type == device.type
    assert torch.allclose(spectral.cpu(), exact, atol=1e-8)
    times = torch.tensor([t, 2 * t], **D64, device=device)
    per_channel = tp.spectral_heat_diffusion(u0_d, evals_d, evecs_d, M0_d, times).cpu()
    assert torch.allclose(per_channel[:, 1], (heat_operator(L, M0, 2 * t) @ u0)[:, 1], atol=1e-8)
    # one implicit Euler step: (M0 + tL) u = M0 u0, first-order accurate in t
    implicit = tp.implicit_heat_diffusion(L_d, M0_d, u0_d, t).cpu()
    ref = torch.linalg.solve(M0.to_dense() + t * L.to_dense(), M0.to_dense() @ u0)
    assert torch.allclose(implicit, ref, atol=1e-10)
    # one step's error is O(t^2) once t |mu_max| is small; on this coarse cage the stiff
    # modes still damp part of it at these steps, so ask for more than first order only
    errors = [
        (tp.implicit_heat_diffusion(L_d, M0_d, u0_d, s).cpu() - heat_operator(L, M0, s) @ u0)
        .abs()
        .max()
        for s in (1e-3, 1e-4, 1e-5)
    ]
    assert errors[1] < errors[0] / 15 and errors[2] < errors[1] / 15


def test_wave_kernel_signature_is_mass_normalized(spot, device):
    _, _, _, M0, evals, evecs = spot
    energies = torch.linspace(0.0, 4.0, 12, **D64)
    wks = tp.wave_kernel_signature(evals.to(device), evecs.to(device), energies.to(device))
    assert wks.device.type == device.type
    wks = wks.cpu()  # the reference column on the CPU
    assert wks.shape == (evecs.shape[0], 12)
    # one column from the definition (Aubry et al.), a loop over the non-constant pairs with
    # the bandwidth 7 times the energy spacing: sum_k w_k phi_k^2 / sum_k w_k
    sigma = 7 * float(energies[1] - energies[0])
    w = [math.exp(-((4.0 - math.log(float(mu))) ** 2) / (2 * sigma**2)) for mu in evals[1:]]
    column = sum(wk * evecs[:, k + 1] ** 2 for k, wk in enumerate(w)) / sum(w)
    torch.testing.assert_close(wks[:, -1], column, rtol=1e-12, atol=1e-15)
    mass = M0.to_dense().diagonal()
    assert torch.allclose(mass @ wks, torch.ones(12, **D64), atol=1e-10)


def test_learnable_times_and_diffusion_gradients(device):
    V, F = quad_grid(5, bump=0.3, seed=3)
    V = V.to(device)
    L, M0 = tp.laplacian(V, F)
    evals, evecs = tp.eigs(L, M0, 12)
    times = torch.tensor([0.01, 0.1], **D64, device=device, requires_grad=True)
    assert torch.autograd.gradcheck(lambda t: tp.heat_kernel_signature(evals, evecs, t), (times,))
    u0 = V[:, :2].clone().requires_grad_(True)
    t = torch.tensor(0.05, **D64, device=device, requires_grad=True)
    assert torch.autograd.gradcheck(lambda u, t: tp.implicit_heat_diffusion(L, M0, u, t), (u0, t))


def test_eigenvector_gradients_reach_the_vertices(device):
    """Through evecs as well as evals (formerly refused;
    tests/linalg/test_eigenvector_gradients.py)."""
    V, F = mixed_mesh()
    V = V.to(device)
    times = torch.tensor([0.1], **D64, device=device)

    def hks(X, detach):
        evals, evecs = tp.eigs(*tp.laplacian(X, F), 4)
        return tp.heat_kernel_signature(evals, evecs.detach() if detach else evecs, times).sum()

    X = V.clone().requires_grad_(True)
    assert torch.autograd.gradcheck(lambda X: hks(X, False), (X,), eps=1e-6, atol=1e-6)
    full = torch.autograd.grad(hks(X, False), X)[0]
    evals_only = torch.autograd.grad(hks(X, True), X)[0]  # gradient through the eigenvalues only
    assert torch.isfinite(evals_only).all() and not torch.allclose(full, evals_only)


def test_cached_eigs_round_trip(tmp_path, device):
    V, F = quad_grid(4, bump=0.2, seed=1, device=device)
    F = tp.as_faces(F)
    evals, evecs = tp.cached_eigs(V, F, 5, tmp_path)
    files = list(tmp_path.glob("eigs-*.npz"))
    assert len(files) == 1
    again = tp.cached_eigs(V, F, 5, tmp_path)
    assert torch.equal(again[0], evals) and torch.equal(again[1], evecs)
    assert len(list(tmp_path.glob("eigs-*.npz"))) == 1
    moved = tp.cached_eigs(V * 2.0, F, 5, tmp_path)  # new geometry: new entry
    assert len(list(tmp_path.glob("eigs-*.npz"))) == 2
    assert torch.allclose(moved[0], evals / 4.0, rtol=1e-8, atol=1e-12)  # mu scales as 1/s^2
    assert tp.cached_eigs(V.float(), F, 5, tmp_path)[0].dtype == torch.float32

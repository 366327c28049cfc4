"""Block Lanczos (torch_polylap.lanczos) and the sparse eigensolver route of eigs that uses it."""

from __future__ import annotations

import sys

import numpy as np
import pytest
import scipy.linalg
import scipy.sparse as sp
import scipy.sparse.linalg as spla
import torch
from conftest import DATA
from meshes import read_mesh

import torch_polylap as tp
import torch_polylap.linalg as linalg
from torch_polylap.linalg.lanczos import block_lanczos


def test_block_lanczos_finds_a_known_spectrum_with_multiplicities():
    """A symmetric matrix with prescribed eigenvalues, the top one repeated 12 times (more
    than the block of 8): every copy must be found, with orthonormal vectors."""
    rng = np.random.default_rng(3)
    n = 600
    values = np.concatenate([np.full(12, 50.0), np.linspace(40.0, 30.0, 20), rng.random(n - 32)])
    basis = np.linalg.qr(rng.standard_normal((n, n)))[0]
    C = (basis * values) @ basis.T
    theta, Y, converged = block_lanczos(lambda X: C @ X, n, 32, max_dim=300)
    assert converged
    np.testing.assert_allclose(theta, np.sort(values)[::-1][:32], rtol=1e-12)
    np.testing.assert_allclose(Y.T @ Y, np.eye(32), atol=1e-12)
    residual = C @ Y - Y * theta
    assert np.abs(residual).max() < 1e-9 * theta.max()


def test_block_lanczos_reports_failure_when_the_basis_is_too_small():
    rng = np.random.default_rng(4)
    n = 400
    values = 1.0 + 1e-6 * rng.random(n)  # no gap: Lanczos cannot separate the top 20
    basis = np.linalg.qr(rng.standard_normal((n, n)))[0]
    C = (basis * values) @ basis.T
    _, _, converged = block_lanczos(lambda X: C @ X, n, 20, max_dim=40)
    assert not converged


def _mesh_operators(name: str, device: torch.device | str = "cpu"):
    V, F = read_mesh(DATA / name, dtype=torch.float64, device=device)
    return tp.laplacian(V, F)


@pytest.mark.parametrize("cholmod", [True, False], ids=["cholmod", "superlu"])
def test_sparse_eigs_match_arpack(cholmod, monkeypatch, device):
    """2310 vertices: above the dense threshold, so eigs runs block Lanczos; it must agree with
    scipy's ARPACK to round-off, with M0-orthonormal vectors spanning the same subspaces."""
    if cholmod:
        pytest.importorskip(
            "cholespy", reason='cholespy not installed: pip install -e ".[cholmod]"'
        )
    else:
        monkeypatch.setitem(sys.modules, "cholespy", None)  # import fails: SuperLU route
    L, M0 = _mesh_operators("mixedFaring.off", device)
    k = 40
    # the route rule sends this size to ARPACK: force block Lanczos, which must not fall back
    monkeypatch.setattr(linalg.eigenpairs, "eigs_route", lambda *a, **kw: "lanczos")
    calls = []
    # ARPACK must not be used
    monkeypatch.setattr(linalg.eigenpairs, "_eigs_arpack", lambda *a, **kw: calls.append(a))
    evals, evecs = tp.eigs(L, M0, k)
    assert not calls
    assert evals.device.type == evecs.device.type == device.type
    evals, evecs = evals.cpu(), evecs.cpu()  # against ARPACK on the CPU
    Ls, Ms = tp.sparse.to_scipy(L), tp.sparse.to_scipy(M0)
    ref_vals, ref_vecs = spla.eigsh(Ls, k=k, M=Ms, sigma=-1e-6, which="LM", tol=0)
    np.testing.assert_allclose(evals.numpy(), np.sort(ref_vals), rtol=1e-9, atol=1e-11)
    phi = evecs.numpy()
    np.testing.assert_allclose(phi.T @ (Ms @ phi), np.eye(k), atol=1e-9)
    residual = Ls @ phi - (Ms @ phi) * evals.numpy()
    assert np.abs(residual).max() < 1e-7 * evals.max().item() * np.abs(Ms @ phi).max()
    # same invariant subspaces, up to round-off, whatever the basis within a cluster
    overlap = phi.T @ (Ms @ ref_vecs[:, np.argsort(ref_vals)])
    singular = np.linalg.svd(overlap[:-4, :], compute_uv=False)  # last ones may cut a cluster
    assert singular.min() > 1 - 1e-8


@pytest.mark.parametrize("route", ["arpack", "lanczos"])
def test_sparse_eigs_count_components(route, monkeypatch, device):
    """Three copies of a 2310-vertex mesh: three zero eigenvalues, found by each sparse route."""
    monkeypatch.setattr(linalg.eigenpairs, "eigs_route", lambda *a, **kw: route)
    V, F = read_mesh(DATA / "mixedFaring.off", dtype=torch.float64)
    n = V.shape[0]
    blocks = [tp.laplacian(V + 10.0 * i, F) for i in range(3)]
    L = tp.sparse.from_scipy(
        sp.block_diag([tp.sparse.to_scipy(b[0]) for b in blocks], format="csr")
    )
    M0 = tp.sparse.from_scipy(
        sp.block_diag([tp.sparse.to_scipy(b[1]) for b in blocks], format="csr")
    )
    evals, evecs = tp.eigs(L.to(device), M0.to(device), 6)
    assert evals.device.type == device.type
    evals, evecs = evals.cpu(), evecs.cpu()
    assert (evals[:3].abs() < 1e-9).all() and evals[3] > 1e-4
    # the kernel is spanned by the indicator functions of the three copies
    indicator = np.kron(np.eye(3), np.ones((n, 1)))
    kernel = evecs[:, :3].numpy()
    projection = kernel @ (kernel.T @ (tp.sparse.to_scipy(M0) @ indicator))
    np.testing.assert_allclose(projection, indicator, atol=1e-8)


def test_sparse_eigs_are_accurate_to_round_off_on_a_sphere(device):
    """Near-multiple eigenvalues (the cube-sphere's l(l+1) clusters) against LAPACK: a shift
    too close to zero once made the shifted solves lose digits (1e-9 relative error here)."""
    L, M0 = _mesh_operators("sphere/quad_3.obj", device)
    evals, _ = tp.eigs(L, M0, 64)
    assert evals.device == L.device
    L, M0 = L.to_dense().cpu().numpy(), M0.to_dense().cpu().numpy()
    ref = scipy.linalg.eigh(L, M0, eigvals_only=True)[:64]
    np.testing.assert_allclose(evals.cpu().numpy(), ref, rtol=0, atol=1e-11 * ref.max())


@pytest.mark.parametrize(
    ("n", "k", "cholmod", "route"),
    [
        (150, 16, True, "dense"),
        (200, 16, True, "dense"),
        (640, 128, True, "dense"),
        (320, 64, True, "dense"),
        (321, 64, True, "arpack"),
        (641, 128, True, "arpack"),
        (1_000, 16, True, "arpack"),
        (10_000, 16, True, "arpack"),
        (1_000, 64, True, "arpack"),
        (1_000, 128, True, "arpack"),
        (100_000, 16, True, "arpack"),  # block Lanczos never won for k = 16
        (200_000, 31, True, "arpack"),
        (linalg.eigenpairs._LANCZOS_SIZE[32] + 1, 32, True, "lanczos"),
        (linalg.eigenpairs._LANCZOS_SIZE[64], 64, True, "arpack"),
        (linalg.eigenpairs._LANCZOS_SIZE[64] + 1, 64, True, "lanczos"),
        (linalg.eigenpairs._LANCZOS_SIZE[128] + 1, 128, True, "lanczos"),
        (linalg.eigenpairs._LANCZOS_SIZE[128] + 1, 512, True, "lanczos"),
        (30_000, 96, True, "lanczos"),
        (100_000, 64, True, "lanczos"),
        (1_000_000, 64, True, "lanczos"),
        (1_000_000, 128, True, "arpack"),  # the Lanczos basis of 6 k vectors: over 4 GiB
        (linalg.eigenpairs._LANCZOS_SIZE[128] + 1, 128, False, "arpack"),  # SuperLU: twice the size
        (2 * linalg.eigenpairs._LANCZOS_SIZE[128] + 1, 128, False, "lanczos"),
    ],
)
def test_eigs_route_picks_each_route_in_its_range(n, k, cholmod, route):
    assert linalg.eigs_route(n, k, diagonal_mass=True, cholmod=cholmod) == route


def test_eigs_route_needs_a_diagonal_mass_for_lanczos():
    assert linalg.eigs_route(100_000, 64, diagonal_mass=False) == "arpack"
    assert linalg.eigs_route(300, 64, diagonal_mass=False) == "dense"


@pytest.mark.parametrize("route", ["dense", "arpack", "lanczos", "arpack-generalized"])
@pytest.mark.parametrize("cholmod", [True, False], ids=["cholmod", "superlu"])
def test_every_route_matches_lapack(route, cholmod, monkeypatch, device):
    """Each route, forced, on the 1538-vertex cube sphere (near-multiple l(l+1) clusters):
    eigenvalues within 1e-10 relative of dense LAPACK, M0-orthonormal vectors with small
    residuals."""
    if cholmod:
        pytest.importorskip("cholespy", reason='pip install -e ".[cholmod]"')
    else:
        monkeypatch.setitem(sys.modules, "cholespy", None)
    L, M0 = _mesh_operators("sphere/quad_3.obj", device)
    k = 64
    if route == "arpack-generalized":  # a non-diagonal M goes through ARPACK's generalized mode
        monkeypatch.setattr(linalg.eigenpairs, "_is_diagonal", lambda S: False)
    monkeypatch.setattr(linalg.eigenpairs, "eigs_route", lambda *a, **kw: route.split("-")[0])
    evals, evecs = tp.eigs(L, M0, k)
    assert evals.device.type == device.type
    evals, evecs = evals.cpu(), evecs.cpu()  # against LAPACK on the CPU
    Ld, Md = L.to_dense().cpu().numpy(), M0.to_dense().cpu().numpy()
    ref = scipy.linalg.eigh(Ld, Md, eigvals_only=True, subset_by_index=(0, k - 1))
    np.testing.assert_allclose(evals.numpy(), ref, rtol=1e-10, atol=1e-10 * ref.max())
    phi = evecs.numpy()
    np.testing.assert_allclose(phi.T @ Md @ phi, np.eye(k), atol=1e-9)
    assert np.abs(Ld @ phi - (Md @ phi) * evals.numpy()).max() < 1e-7 * ref.max()

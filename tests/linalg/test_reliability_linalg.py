"""Reliability of ``eigs`` and ``solve``: a correct answer or a clear error, never a silent one.

References are independent of the routes under test: LAPACK (``scipy.linalg.eigh``) on the dense
generalized problem; for disjoint copies of one mesh, the spectrum of one copy (dense) repeated
once per copy, since the operators of a disjoint union are block diagonal; ``numpy.linalg``
for the small linear systems.
"""

from __future__ import annotations

import re
import warnings

import numpy as np
import pytest
import scipy.linalg
import scipy.sparse as sp
import torch
from conftest import DATA
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st
from meshes import read_mesh

import torch_polylap as tp
import torch_polylap.linalg as linalg
from torch_polylap.linalg.lanczos import block_lanczos
from torch_polylap.shapes import quad_cube, quad_sphere

D64 = {"dtype": torch.float64}
SLOW = settings(
    max_examples=6, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
FAST = settings(max_examples=40, deadline=None)


def _spot():
    V, F = read_mesh(DATA / "spot_control_mesh.obj", dtype=torch.float64)
    return V, F.tolist()


def _copies(V: torch.Tensor, F: list, count: int):
    """``count`` disjoint, translated copies of one mesh: every eigenvalue ``count`` times."""
    n = V.shape[0]
    verts = torch.cat([V + 4.0 * i for i in range(count)])
    faces = [[v + i * n for v in face] for i in range(count) for face in F]
    return verts, faces


def _spectrum(V: torch.Tensor, F: list) -> np.ndarray:
    L, M0 = tp.laplacian(V, F)
    return scipy.linalg.eigh(L.to_dense().numpy(), M0.to_dense().numpy(), eigvals_only=True)


def _assert_eigenpairs(evals, evecs, L, M, reference) -> None:
    """The k smallest eigenvalues with their multiplicities, M-orthonormal vectors, and small
    residuals (each computed pair is an eigenpair)."""
    Ls, Ms = tp.sparse.to_scipy(L), tp.sparse.to_scipy(M)
    mu, phi = evals.cpu().numpy(), evecs.cpu().numpy()
    k = mu.size
    top = max(abs(reference[k - 1]), 1.0)
    np.testing.assert_allclose(mu, reference[:k], rtol=0, atol=1e-9 * top)
    np.testing.assert_allclose(phi.T @ (Ms @ phi), np.eye(k), atol=1e-8)
    residual = Ls @ phi - (Ms @ phi) * mu
    assert np.abs(residual).max() < 1e-7 * top * np.abs(Ms @ phi).max()


def test_eigs_finds_every_copy_of_forty_disjoint_spots(device):
    """The case found by fuzzing: k = 128 on 40 copies of the Spot cage (7520 vertices, the
    block Lanczos route) returned an eigenvalue of multiplicity 40 only 32 times and went on
    to the next one (max error 1.4), each returned pair having a tiny residual."""
    V, F = _spot()
    verts, faces = _copies(V, F, 40)
    L, M0 = tp.laplacian(verts.to(device), faces)
    reference = np.sort(np.repeat(_spectrum(V, F), 40))
    assert linalg.eigs_route(L.shape[0], 128, diagonal_mass=True, cholmod=True) == "lanczos"
    evals, evecs = tp.eigs(L, M0, 128)
    assert evals.device.type == device.type
    _assert_eigenpairs(evals, evecs, L, M0, reference)


@pytest.mark.parametrize("route", ["arpack", "lanczos"])
@SLOW
@given(count=st.integers(9, 16), k=st.integers(40, 72), seed=st.integers(0, 2**16))
def test_eigs_on_disjoint_copies_has_full_multiplicities(route, count, k, seed, monkeypatch):
    """Multiplicities above the Lanczos block of 8 on either sparse route (forced), against
    one copy's dense spectrum repeated ``count`` times."""
    monkeypatch.setattr(linalg.eigenpairs, "eigs_route", lambda *a, **kw: route)
    V, F = _spot()
    V = V * (1.0 + 0.1 * np.random.default_rng(seed).random())  # scale: another spectrum
    L, M0 = tp.laplacian(*_copies(V, F, count))
    reference = np.sort(np.repeat(_spectrum(V, F), count))
    evals, evecs = tp.eigs(L, M0, k)
    _assert_eigenpairs(evals, evecs, L, M0, reference)


@pytest.mark.parametrize("route", ["dense", "arpack", "lanczos"])
@pytest.mark.parametrize("shape", ["cube", "sphere"])
def test_eigs_on_symmetric_shapes_match_lapack(route, shape, monkeypatch, device):
    """The cube's and the cube sphere's octahedral symmetry gives eigenvalues of multiplicity
    2, 3 and 6 (and near-multiplicities on the sphere); each route against dense LAPACK."""
    monkeypatch.setattr(linalg.eigenpairs, "eigs_route", lambda *a, **kw: route)
    V, F = quad_cube(6) if shape == "cube" else quad_sphere(6)
    L, M0 = tp.laplacian(V.to(device), F)
    Ld, Md = L.to_dense().cpu().numpy(), M0.to_dense().cpu().numpy()
    reference = scipy.linalg.eigh(Ld, Md, eigvals_only=True)
    evals, evecs = tp.eigs(L, M0, 40)
    assert evals.device.type == device.type
    _assert_eigenpairs(evals, evecs, L, M0, reference)


def _dropping(original, drop: int):
    """A route that misses ``drop`` eigenpairs from the middle of its answer (as a Krylov
    method can miss directions of a repeated eigenvalue) and returns later ones instead."""

    def route(Ls, Ms, k, *args, **kwargs):
        evals, evecs = original(Ls, Ms, k + drop, *args, **kwargs)
        order = np.argsort(evals)
        keep = np.delete(order, np.arange(k // 2, k // 2 + drop))
        return evals[keep], evecs[:, keep]

    return route


@pytest.mark.parametrize("mass", ["diagonal", "consistent"])
def test_eigs_completes_a_route_that_missed_eigenpairs(mass, monkeypatch, device):
    """The inertia count catches missing eigenpairs whatever the route and the mass matrix:
    ARPACK made to drop three from the middle of its answer (on 5 copies of Spot, so that the
    dropped ones are copies of a repeated eigenvalue), with a diagonal mass and with a
    non-diagonal SPD one (scipy's generalized shift-invert path)."""
    monkeypatch.setattr(linalg.eigenpairs, "eigs_route", lambda *a, **kw: "arpack")
    monkeypatch.setattr(
        linalg.eigenpairs, "_eigs_arpack", _dropping(linalg.eigenpairs._eigs_arpack, 3)
    )
    V, F = _spot()
    verts, faces = _copies(V, F, 5)
    L, M0 = tp.laplacian(verts.to(device), faces)
    M = M0
    if mass == "consistent":
        # M0 plus a small multiple of L: symmetric positive definite, not diagonal
        Ms = tp.sparse.to_scipy(M0) + 1e-3 * tp.sparse.to_scipy(L)
        M = tp.sparse.from_scipy(sp.csr_matrix(Ms)).to(device)
    Ld, Md = L.to_dense().cpu().numpy(), M.to_dense().cpu().numpy()
    reference = scipy.linalg.eigh(Ld, Md, eigvals_only=True)
    evals, evecs = tp.eigs(L, M, 24)
    assert evals.device.type == device.type
    _assert_eigenpairs(evals, evecs, L, M, reference)


@FAST
@given(
    shape=st.sampled_from(["cube", "sphere", "spot"]),
    copies=st.integers(1, 3),
    where=st.floats(0.0, 1.0),
)
def test_inertia_count_matches_lapack(shape, copies, where):
    """The Sylvester inertia count behind the check, at shifts across the spectrum and just
    off an eigenvalue, against the dense eigenvalues."""
    from torch_polylap.linalg.eigenpairs import _count_below

    V, F = quad_cube(3) if shape == "cube" else quad_sphere(3) if shape == "sphere" else _spot()
    F = F.tolist() if isinstance(F, torch.Tensor) else F
    L, M0 = tp.laplacian(*_copies(V, F, copies))
    Ls, Ms = tp.sparse.to_scipy(L).tocsr(), tp.sparse.to_scipy(M0).tocsr()
    mu = scipy.linalg.eigh(Ls.toarray(), Ms.toarray(), eigvals_only=True)
    j = int(where * (mu.size - 2))
    for sigma in (0.5 * (mu[j] + mu[j + 1]), mu[j] + 1e-7 * mu.max()):
        if np.abs(mu - sigma).min() < 1e-9 * mu.max():
            continue  # sigma on an eigenvalue (within round-off): the count is ambiguous
        count = _count_below(Ls, Ms, sigma)
        assert count is None or count == int((mu < sigma).sum())


def test_block_lanczos_stops_at_a_max_dim_that_is_not_a_multiple_of_the_block():
    """A basis that fills up at 222 vectors (blocks of 8) without converging: reported as not
    converged, where the last block once overflowed the work arrays."""
    rng = np.random.default_rng(4)
    n = 400
    values = 1.0 + 1e-6 * rng.random(n)  # no gap: no convergence
    basis = np.linalg.qr(rng.standard_normal((n, n)))[0]
    C = (basis * values) @ basis.T
    _, _, converged = block_lanczos(lambda X: C @ X, n, 37, max_dim=222)
    assert not converged


# ---- eigs refuses non-symmetric matrices ----


@st.composite
def _nonsymmetric(draw):
    n = draw(st.integers(6, 30))
    seed = draw(st.integers(0, 2**16))
    rng = np.random.default_rng(seed)
    B = sp.random(n, n, density=0.3, random_state=rng)
    A = B @ B.T + sp.eye(n) * n  # symmetric positive definite
    i, j = draw(
        st.tuples(st.integers(0, n - 1), st.integers(0, n - 1)).filter(lambda p: p[0] != p[1])
    )
    A = sp.lil_matrix(A)
    A[i, j] = A[i, j] + draw(st.sampled_from([1e-6, 1e-3, 1.0, -5.0])) * (1 + abs(A[i, j]))
    return sp.csr_matrix(A), (i, j)


@FAST
@given(data=_nonsymmetric(), which=st.sampled_from(["L", "M"]))
def test_eigs_refuses_a_non_symmetric_matrix(data, which):
    A, (i, j) = data
    n = A.shape[0]
    S = tp.sparse.from_scipy(sp.csr_matrix(0.5 * (A + A.T)))
    I = tp.sparse.from_scipy(sp.identity(n, format="csr"))
    L, M = (tp.sparse.from_scipy(A), I) if which == "L" else (S, tp.sparse.from_scipy(A))
    with pytest.raises(ValueError, match=f"{which} is not symmetric: {which}\\[") as err:
        tp.eigs(L, M, 2)
    assert f"{which}[{i}, {j}]" in str(err.value) and f"{which}[{j}, {i}]" in str(err.value)


@FAST
@given(data=_nonsymmetric())
def test_eigs_accepts_an_unmarked_symmetric_matrix(data):
    """Symmetric matrices that do not declare it (built from scipy) pass the check and match
    LAPACK."""
    A, _ = data
    S = sp.csr_matrix(0.5 * (A + A.T))
    n = S.shape[0]
    evals, _ = tp.eigs(
        tp.sparse.from_scipy(S), tp.sparse.from_scipy(sp.identity(n, format="csr")), 3
    )
    np.testing.assert_allclose(evals.numpy(), np.linalg.eigvalsh(S.toarray())[:3], rtol=1e-10)


# ---- solve: singular, indefinite, non-convergent ----


def test_cg_on_a_singular_laplacian_raises_a_convergence_error(device):
    """Found by fuzzing: CG's updated residual met the tolerance while |b - L x| / |b| was 5.7
    and |x| 6e14, and the result came back without a word."""
    V, F = _spot()
    L, _ = tp.laplacian(V.to(device), F)
    b = torch.randn(V.shape[0], generator=torch.Generator().manual_seed(0), **D64).to(device)
    with pytest.raises(ValueError, match="did not converge: relative residual") as err:
        tp.solve(L, b, backend="cg")
    assert isinstance(err.value, linalg.solves.ConvergenceError)
    assert err.value.residual > 1e-3 and err.value.iterations > 0
    # b in L's range (orthogonal to the constants): a consistent system CG does solve
    b0 = b - b.mean()
    x = tp.solve(L, b0, backend="cg")
    assert torch.linalg.vector_norm(L @ x - b0) <= 1e-9 * torch.linalg.vector_norm(b0)


def _system(n: int, seed: int, negative: int):
    """A symmetric matrix with ``negative`` negative eigenvalues, the others positive, all of
    magnitude in [1, 10]: ``Q diag(d) Q^T`` for a random orthogonal ``Q``."""
    rng = np.random.default_rng(seed)
    d = rng.uniform(1.0, 10.0, n)
    d[:negative] *= -1
    Q = np.linalg.qr(rng.standard_normal((n, n)))[0]
    A = (Q * d) @ Q.T
    A = 0.5 * (A + A.T)
    return tp.sparse.from_scipy(sp.csr_matrix(A), symmetric=True), A, rng.standard_normal(n)


@FAST
@given(
    n=st.integers(3, 25),
    seed=st.integers(0, 2**16),
    backend=st.sampled_from(["splu", "cg", "cholesky"]),
)
def test_solve_spd_systems_match_numpy(n, seed, backend):
    A, dense, b = _system(n, seed, 0)
    x = tp.solve(A, torch.from_numpy(b), backend=backend, tol=1e-12)
    np.testing.assert_allclose(x.numpy(), np.linalg.solve(dense, b), rtol=1e-8, atol=1e-9)


def _graph_laplacian(n: int, seed: int, components: int):
    """The weighted graph Laplacian of ``components`` connected random graphs (a path plus
    random chords, weights in [1, 10]): positive semi-definite, singular, its kernel the
    constants on each component, like a mesh Laplacian without a mass term."""
    rng = np.random.default_rng(seed)
    parts = np.array_split(np.arange(n), components)
    rows, cols = [], []
    for part in parts:
        rows += list(part[:-1])
        cols += list(part[1:])
        for _ in range(part.size):
            i, j = rng.choice(part, 2)
            if i != j:
                rows.append(i)
                cols.append(j)
    W = sp.coo_matrix((rng.uniform(1.0, 10.0, len(rows)), (rows, cols)), shape=(n, n))
    W = (W + W.T).tocsr()
    L = sp.diags(np.asarray(W.sum(1)).ravel()) - W
    return tp.sparse.from_scipy(sp.csr_matrix(L), symmetric=True), rng.standard_normal(n)


@FAST
@given(
    n=st.integers(4, 40),
    seed=st.integers(0, 2**16),
    components=st.integers(1, 2),
    backend=st.sampled_from(["splu", "cholesky", "cg"]),
)
# CHOLMOD's last pivot of this one is 11 eps |S|: the solve grows b by only 0.1 / eps
@example(n=5, seed=753, components=1, backend="cholesky")
def test_solve_refuses_singular_systems(n, seed, components, backend):
    """Every backend refuses a singular matrix with a right-hand side outside its range, and
    calls it singular (CG: by the residual it could not reduce)."""
    A, b = _graph_laplacian(n, seed, components)
    with pytest.raises(ValueError, match="singular") as err:
        tp.solve(A, torch.from_numpy(b), backend=backend)
    if backend == "cg":
        # either the residual CG could not reduce, or a direction of zero curvature
        error = err.value
        assert isinstance(error, linalg.solves.ConvergenceError) or "p^T A p" in str(error)
        if isinstance(error, linalg.solves.ConvergenceError):
            assert error.residual > 1e-10 and f"{error.residual:.3g}" in str(error)


def _shifted_solution(L: torch.Tensor, M0: torch.Tensor, shift: float, b: np.ndarray):
    """``(L + shift M0)^-1 b`` for a Laplacian ``L`` of a closed connected mesh, to float64
    accuracy however small ``shift``: the constants are the kernel of ``L`` and
    ``(L + shift M0) 1 = shift M0 1``, so the part of ``b`` along ``M0 1`` solves in closed
    form, and the rest with ``L + shift M0 + w w^T`` (``w = M0 1`` scaled like ``L``), which
    acts alike on the rest and is well-conditioned."""
    Ld, Md = L.to_dense().numpy(), M0.to_dense().numpy()
    w = Md @ np.ones(b.size)
    along = w * (b.sum() / w.sum())  # 1^T (b - along) = 0
    constant = b.sum() / (shift * w.sum())
    fixed = Ld + shift * Md + np.outer(w, w) * (np.abs(Ld).max() / (w @ w))
    return constant + np.linalg.solve(fixed, b - along)


# the direct solvers, each skipped where its optional package is missing
DIRECT_BACKENDS = [
    "splu",
    pytest.param(
        "cholesky",
        marks=pytest.mark.skipif(not linalg.cholespy_available(), reason="needs cholespy"),
    ),
    pytest.param(
        "ldl", marks=pytest.mark.skipif(not linalg.qdldl_available(), reason="needs qdldl")
    ),
]


@pytest.mark.parametrize("backend", DIRECT_BACKENDS)
def test_ill_conditioned_positive_definite_solve_warns_and_solves(backend):
    """``L + 1e-12 M0`` is positive definite with condition number about 8e12 on spot: it was
    refused as singular by its solution growth alone. Solved now, to the digits the warning
    promises, against a reference that needs no ill-conditioned solve."""
    V, F = _spot()
    L, M0 = tp.laplacian(V, F)
    b = np.random.default_rng(3).standard_normal(V.shape[0])
    with pytest.warns(tp.IllConditionedWarning, match=r"ill-conditioned .* correct digits") as w:
        x = tp.solve(L + 1e-12 * M0, torch.from_numpy(b), backend=backend).numpy()
    digits = int(re.search(r"about (\d+) correct digits", str(w[0].message))[1])
    reference = _shifted_solution(L, M0, 1e-12, b)
    assert digits >= 2
    assert np.abs(x - reference).max() <= 10.0**-digits * np.abs(reference).max()
    # a shift 100x larger is well enough conditioned to pass without a word
    with warnings.catch_warnings():
        warnings.simplefilter("error", tp.IllConditionedWarning)
        x = tp.solve(L + 1e-10 * M0, torch.from_numpy(b), backend=backend).numpy()
    reference = _shifted_solution(L, M0, 1e-10, b)
    assert np.abs(x - reference).max() <= 1e-4 * np.abs(reference).max()


@pytest.mark.parametrize("backend", DIRECT_BACKENDS)
def test_laplacian_alone_stays_singular(backend):
    """``L`` of a closed mesh with a right-hand side outside its range (``M0 1``): no
    refinement converges, so the error names the singular matrix and the remedy."""
    V, F = _spot()
    L, M0 = tp.laplacian(V, F)
    with pytest.raises(ValueError, match=r"is singular .*M0 \+ h L"):
        tp.solve(L, M0 @ torch.ones(V.shape[0], **D64), backend=backend)


def _with_entry(A: torch.Tensor, k: int, value: float):
    """``A`` with its ``k``-th stored entry (CSR order) set to ``value``, and that entry's
    ``(row, col)`` as scipy reads the same matrix."""
    values = tp.sparse.sparse_values(A).detach().clone()
    values[k] = value
    S = tp.sparse.to_scipy(A).tocoo()
    return A.with_values(values), (int(S.row[k]), int(S.col[k]))


@pytest.mark.parametrize("value", [float("nan"), float("inf")])
def test_non_finite_operands_are_named_before_anything_else(value):
    """A NaN in L was reported by eigs as an asymmetry ("L[0, 0] = nan but L[0, 0] = nan")
    and by solve as a singular matrix; both now name the first non-finite entry."""
    V, F = _spot()
    L, M0 = tp.laplacian(V, F)
    n = V.shape[0]
    k = tp.sparse.sparse_values(L).numel() // 3
    bad_L, (i, j) = _with_entry(L, k, value)
    pattern = rf"eigs: L holds non-finite values: L\[{i}, {j}\] = {value} \(1 such entries\)"
    with pytest.raises(ValueError, match=pattern):
        tp.eigs(bad_L, M0, k=3)
    with pytest.raises(ValueError, match=r"eigs: L holds non-finite values: L\[0, 0\] = nan"):
        tp.eigs(L * float("nan"), M0, k=3)
    bad_M, (i, j) = _with_entry(M0, 7, value)
    assert i == j == 7  # M0 is diagonal
    with pytest.raises(ValueError, match=rf"eigs: M holds non-finite values: M\[7, 7\] = {value}"):
        tp.eigs(L, bad_M, k=3)
    A = M0 + 0.1 * L
    bad_A, (i, j) = _with_entry(A, k, value)
    b = torch.ones(n, **D64)
    with pytest.raises(ValueError, match=rf"solve: A holds non-finite values: A\[{i}, {j}\]"):
        tp.solve(bad_A, b)
    B = torch.ones(n, 2, **D64)
    B[11, 1] = value
    with pytest.raises(
        ValueError, match=rf"solve: B holds non-finite values: B\[11, 1\] = {value}"
    ):
        tp.solve(A, B)
    with pytest.raises(ValueError, match=r"solve: B holds non-finite values: B\[11\]"):
        tp.solve(A, B[:, 1].contiguous())


@FAST
@given(n=st.integers(3, 25), seed=st.integers(0, 2**16), negative=st.integers(1, 2))
def test_indefinite_systems_are_named_indefinite(n, seed, negative):
    """A symmetric indefinite non-singular matrix: SuperLU solves it; Cholesky and CG refuse it
    as indefinite (not as singular) and point to backend='splu'."""
    negative = min(negative, n - 1)
    A, dense, b = _system(n, seed, negative)
    x = tp.solve(A, torch.from_numpy(b), backend="splu")
    np.testing.assert_allclose(x.numpy(), np.linalg.solve(dense, b), rtol=1e-8, atol=1e-9)
    for backend in ("cholesky", "cg"):
        with pytest.raises(ValueError, match="indefinite") as err:
            tp.solve(A, torch.from_numpy(b), backend=backend)
        assert "is singular" not in str(err.value) and "backend='splu'" in str(err.value)

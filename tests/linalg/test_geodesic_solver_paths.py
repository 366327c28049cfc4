"""The heat geodesic solver's fast paths against the algorithm written out with public operators.

``HeatGeodesicSolver`` factors its systems with QDLDL (``backend="ldl"``) and forms the Poisson
right-hand side in one pass over the faces; the reference here is Crane et al.'s Algorithm 1
spelled out with ``tp.laplacian``, ``tp.face_gradient``, ``tp.divergence`` and SuperLU solves,
which share neither the factorization nor the per-face code. Exact distances (Euclidean on a
plane) check the far field, where the heat underflows.
"""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp
import torch
from conftest import DATA, hex_pent_mesh
from meshes import load, shared_path

import torch_polylap as tp
from torch_polylap.linalg.factor import LDLFactorization, _upper_parts, cholespy_available
from torch_polylap.measures import mean_edge_length

pytest.importorskip("qdldl", reason="the 'ldl' backend needs the optional qdldl")


def _reference_distance(verts, faces, source: int, t: float) -> torch.Tensor:
    """Algorithm 1 on a connected mesh: heat, unit field, Poisson with vertex 0 pinned, shift."""
    L, M0 = tp.laplacian(verts, faces, 1.0)
    L_poisson, _ = tp.laplacian(verts, faces, 0.1)
    delta = torch.zeros(verts.shape[0], dtype=verts.dtype)
    delta[source] = 1.0
    u = tp.solve(M0 + t * L, M0 @ delta, backend="splu")
    grad = tp.face_gradient(verts, faces, u)
    field = -grad / grad.norm(dim=1, keepdim=True)
    rhs = -tp.divergence(verts, faces, field)
    diagonal = L_poisson.diagonal()
    pin = torch.zeros_like(diagonal)
    pin[0] = diagonal[diagonal > 0].mean()
    phi = tp.solve(L_poisson + tp.sparse.diag(pin), rhs, backend="splu")
    return phi - phi[source]


def _sphere_quad():
    verts, faces = load(DATA / "sphere" / "quad_3.obj")
    return verts / verts.norm(dim=1, keepdim=True), faces


MESHES = {
    "sphere quad_3": _sphere_quad,
    "grid voronoi_3": lambda: load(DATA / "grid" / "voronoi_3.obj"),
    "grid concave_3": lambda: load(DATA / "grid" / "concave_3.obj"),
    "hex_pent": hex_pent_mesh,
    "mixedFaring": lambda: load(DATA / "mixedFaring.off"),
    "rockerArm": lambda: load(shared_path("real/rockerArm.obj")),
}


@pytest.mark.parametrize("name", sorted(MESHES))
def test_solver_equals_the_algorithm_written_out(name):
    verts, faces = MESHES[name]()
    topo = tp.get_topology(faces, verts.shape[0])
    source = verts.shape[0] // 3
    t = 4.0 * float(mean_edge_length(verts, topo)) ** 2
    reference = _reference_distance(verts, faces, source, t)
    solver = tp.HeatGeodesicSolver(verts, topo)
    assert solver.backend == "ldl"
    dist = solver.distance([source])
    scale = float(reference.abs().max())
    assert float((dist - reference).abs().max()) <= 1e-12 * scale


def test_backends_give_the_same_distances():
    verts, faces = _sphere_quad()
    sources = [[0], [5, 40]]
    dist = {b: tp.heat_geodesic_distance(verts, faces, sources, backend=b) for b in ("ldl", "splu")}
    torch.testing.assert_close(dist["ldl"], dist["splu"], rtol=0, atol=1e-12)
    # the public steps still compose to the distance
    solver = tp.HeatGeodesicSolver(verts, faces)
    ind = solver._indicator([0])
    phi = solver.potential(solver.normalized_field(solver.heat(ind)))
    torch.testing.assert_close(solver.shift_to_sources(phi, ind)[:, 0], dist["ldl"][:, 0])


def _two_components():
    """A quad grid and a copy of it 100x larger, lifted off its plane: two connected
    components. The copy's faces have areas above 1e2, whose ratio to the smallest normal
    float overflows (a component without a source has ``grad u = 0`` on every face)."""
    verts, faces = tp.shapes.quad_grid(9, 8)
    verts = verts.double()
    lifted = 100.0 * verts + torch.tensor([0.0, 0.0, 2.0], dtype=torch.float64)
    return torch.cat([verts, lifted]), torch.cat([faces, faces + verts.shape[0]])


_BACKENDS = ["ldl", "splu"] + (["cholesky"] if cholespy_available() else [])


@pytest.mark.parametrize("backend", _BACKENDS)
def test_query_without_gradients_equals_the_differentiable_path(backend, device):
    """A query that needs no gradient runs on float64 arrays (the gradient as one sparse
    matrix, the solves straight through the factorizations); with ``verts`` requiring grad it
    takes the torch path (per degree group, through ``solve``'s autograd Function). Both must
    agree, batches, several sources and a component without a source (``inf``) included.
    Off the CPU both queries take the torch path."""
    if backend == "ldl" and device.type != "cpu":
        pytest.skip("backend='ldl' factors on the CPU only")
    verts, faces = _two_components()
    verts = verts.to(device)
    n = verts.shape[0] // 2
    sources = [[0], [5, 40], [n + 3], [7, n + 9]]
    plain = tp.HeatGeodesicSolver(verts, faces, backend=backend)
    fast = plain.distance(sources)
    tracked = verts.clone().requires_grad_(True)
    slow = tp.HeatGeodesicSolver(tracked, faces, backend=backend).distance(sources)
    assert slow.requires_grad and not fast.requires_grad
    torch.testing.assert_close(fast, slow.detach(), rtol=1e-12, atol=1e-12)
    assert bool(torch.isinf(fast[n:, 0]).all()) and bool(torch.isinf(fast[:n, 2]).all())
    # one query gives a vector; no_grad on tracked vertices takes the array path too
    with torch.no_grad():
        single = tp.HeatGeodesicSolver(tracked, faces, backend=backend).distance([5, 40])
    torch.testing.assert_close(single, fast[:, 1], rtol=1e-12, atol=1e-12)


def test_float32_query_without_gradients_matches_float64(device):
    verts, faces = _sphere_quad()
    verts = verts.to(device)
    d64 = tp.HeatGeodesicSolver(verts, faces).distance([0])
    d32 = tp.HeatGeodesicSolver(verts.float(), faces).distance([0])
    assert d32.dtype == torch.float32
    torch.testing.assert_close(d32.double(), d64, rtol=1e-4, atol=1e-5)


def _strip(n: int) -> tuple[torch.Tensor, torch.Tensor]:
    """``n`` unit squares in a row, ``2 (n + 1)`` vertices."""
    x = torch.arange(n + 1, dtype=torch.float64)
    zero = torch.zeros_like(x)
    verts = torch.cat([torch.stack([x, zero, zero], 1), torch.stack([x, zero + 1, zero], 1)])
    i = torch.arange(n)
    return verts, torch.stack([i, i + 1, i + n + 2, i + n + 1], 1)


def test_far_field_where_the_heat_gradient_squared_underflows():
    # At t = 4 h^2 the heat falls like exp(-d / 2): below 1e-154 (whose square underflows)
    # some 700 squares from the source, to 1e-195 at the end of this strip. A norm of the heat
    # gradient that squares it was 0 there, and the clamped division blew the field up to
    # 1e146 everywhere. The error must stay that of a short strip (the heat method's offset
    # next to the source).
    errors = []
    for n in (100, 900):
        verts, faces = _strip(n)
        dist = tp.heat_geodesic_distance(verts, faces, [0])
        exact = (verts - verts[0]).norm(dim=1)
        assert bool(torch.isfinite(dist).all())
        errors.append(float((dist - exact).abs().max()))
        keep = exact > 0
        assert float(((dist - exact).abs() / exact)[keep].mean()) < 1e-2
    assert errors[1] <= 1.01 * errors[0]


def test_unknown_backend_is_refused(device):
    verts, faces = _strip(3)
    with pytest.raises(ValueError, match="backend must be 'auto', 'ldl'"):
        tp.HeatGeodesicSolver(verts.to(device), faces, backend="qr")
    if device.type != "cpu":
        with pytest.raises(ValueError, match="backend='ldl' factors on the CPU"):
            tp.HeatGeodesicSolver(verts.to(device), faces, backend="ldl")


# --- the factorization itself --------------------------------------------------------------


def _random_spd(n: int, seed: int) -> sp.csr_matrix:
    rng = np.random.default_rng(seed)
    A = sp.random(n, n, density=0.1, random_state=rng)
    return sp.csr_matrix(A @ A.T + sp.eye(n))


def test_ldl_factorization_solves_against_dense_solve():
    S = _random_spd(40, 0)
    B = torch.from_numpy(np.random.default_rng(1).standard_normal((40, 3)))
    X = LDLFactorization(tp.sparse.from_scipy(S, symmetric=True)).solve(B)
    np.testing.assert_allclose(X.numpy(), np.linalg.solve(S.toarray(), B.numpy()), rtol=1e-10)


def test_ldl_factorization_refuses_singular_and_indefinite_matrices():
    verts, faces = _strip(4)
    L, _ = tp.laplacian(verts, faces)  # the constants are in its kernel
    with pytest.raises(ValueError, match="singular"):
        LDLFactorization(L)
    indefinite = tp.sparse.from_scipy(_random_spd(30, 2) - 3.0 * sp.eye(30), symmetric=True)
    with pytest.raises(ValueError, match="not positive definite|singular"):
        LDLFactorization(indefinite)


def test_solve_takes_the_ldl_backend_with_gradients():
    """tp.solve(backend="ldl") equals SuperLU's answer and keeps the solve's derivatives."""
    pytest.importorskip("qdldl", reason="the ldl backend needs qdldl: pip install qdldl")
    verts, faces = tp.shapes.quad_grid(6, 5)
    X = verts.double().requires_grad_(True)
    L, M0 = tp.laplacian(X, faces)
    B = torch.randn(X.shape[0], 2, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    got = tp.solve(M0 + 0.1 * L, B, backend="ldl")
    want = tp.solve(M0 + 0.1 * L, B, backend="splu")
    torch.testing.assert_close(got, want, rtol=1e-10, atol=1e-12)
    (g1,) = torch.autograd.grad(got.square().sum(), X)
    L, M0 = tp.laplacian(X, faces)
    (g2,) = torch.autograd.grad(tp.solve(M0 + 0.1 * L, B, backend="splu").square().sum(), X)
    torch.testing.assert_close(g1, g2, rtol=1e-9, atol=1e-12)
    with pytest.raises(ValueError, match="backend='ldl' factors a symmetric operator"):
        tp.solve(
            (M0 + 0.1 * L) * torch.arange(1.0, X.shape[0] + 1)[:, None].double(), B, backend="ldl"
        )


def test_upper_triangle_equals_scipy_triu():
    """The upper triangle handed to qdldl (one mask over a symmetric CSR matrix's entries)."""
    S = _random_spd(60, 3)
    U = _upper_parts(S)[0]
    assert U.format == "csc"
    np.testing.assert_array_equal(U.toarray(), sp.triu(S).toarray())
    assert U.nnz == sp.triu(S, format="csc").nnz


def test_unit_field_of_huge_tiny_and_zero_gradients():
    """The array path's unit field: a face whose squared gradient over- or underflows takes
    the scaled norm, a zero gradient stays 0; reference: each row divided by its norm computed
    after scaling by its largest entry."""
    from torch_polylap.geodesics import _unit_rows

    rng = np.random.default_rng(4)
    rows = rng.standard_normal((6, 3, 2))
    rows[1] *= 1e200  # the square overflows
    rows[2] *= 1e-170  # the square underflows
    rows[3, :, 0] = 0.0  # a face where the heat is constant
    rows[4, 2] = 0.0
    scale = np.abs(rows).max(axis=1, keepdims=True)
    scaled = rows / np.where(scale > 0, scale, 1.0)
    want = scaled / np.maximum(np.linalg.norm(scaled, axis=1, keepdims=True), 1e-300)
    got = _unit_rows(rows.reshape(18, 2).copy())
    np.testing.assert_allclose(got.reshape(6, 3, 2), want, rtol=1e-14, atol=0)
    assert np.all(got.reshape(6, 3, 2)[3, :, 0] == 0.0)


@pytest.mark.parametrize("kind", ["ldl", "splu"] + (["cholesky"] if cholespy_available() else []))
def test_solve_array_against_dense_solve(kind):
    from torch_polylap.linalg.factor import CholeskyFactorization, Factorization

    S = _random_spd(50, 5)
    A = tp.sparse.from_scipy(S, symmetric=True)
    factor = {"ldl": LDLFactorization, "splu": Factorization, "cholesky": CholeskyFactorization}
    F = factor[kind](A)
    B = np.random.default_rng(6).standard_normal((50, 3))
    dense = np.linalg.solve(S.toarray(), B)
    if kind == "ldl":  # through the 32-bit copies of the factor, not QDLDL's solve
        assert F._triangle_solves() is not None
    np.testing.assert_allclose(F.solve_array(B), dense, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(F.solve_array(B[:, 1]), dense[:, 1], rtol=1e-10, atol=1e-12)


# --- heat solves from a few sources over elimination-tree paths ----------------------------


def _two_component_heat():
    """The heat system ``M0 + t L`` of two grids (two trees in the factor's elimination
    forest), as an operator and as a dense matrix."""
    verts, faces = _two_components()
    L, M0 = tp.laplacian(verts, faces)
    A = M0 + 0.05 * L
    return A, tp.sparse.to_scipy(A).toarray()


# vertex 0 and 71 are corners of the first grid, 5 and 40 share most of their tree path,
# 72 + 3 lies on the second grid's boundary
_QUERIES = [[0], [71], [5, 40], [72 + 3], [7, 72 + 9], [0, 8, 63, 71, 30, 31, 32]]


def test_path_solve_equals_dense_solve(monkeypatch):
    """Right-hand sides nonzero at a few rows (corners, boundary vertices, sources whose tree
    paths overlap, sources on two components) against a dense solve and QDLDL's full one. On
    this small mesh the paths of several sources hold most of the factor: the path solve is
    made to take them all."""
    from torch_polylap.linalg import etree_solve

    monkeypatch.setattr(etree_solve, "PATH_SHARE", 10.0)
    A, dense = _two_component_heat()
    F = LDLFactorization(A)
    paths = F._path_solver()
    assert paths is not None
    rng = np.random.default_rng(7)
    rows = [np.array(q) for q in _QUERIES]
    values = [rng.uniform(0.5, 2.0, len(q)) for q in _QUERIES]
    assert all(paths.pays(r) for r in rows)
    B = np.zeros((dense.shape[0], len(rows)))
    for q, (r, v) in enumerate(zip(rows, values, strict=True)):
        B[r, q] = v
    want = np.linalg.solve(dense, B)
    got = F.solve_sparse_array(rows, values)
    np.testing.assert_allclose(got, want, rtol=1e-10, atol=1e-13 * np.abs(want).max())
    qdldl = np.stack([F.factor.solve(np.ascontiguousarray(b)) for b in B.T], axis=1)
    np.testing.assert_allclose(got, qdldl, rtol=1e-12, atol=1e-15)


def test_forward_solve_is_supported_on_the_tree_path():
    """The forward solve from one row is nonzero only on the columns its path walks, and
    equals the dense triangular solve with QDLDL's factor there."""
    import scipy.linalg as sla

    A, _ = _two_component_heat()
    F = LDLFactorization(A)
    paths = F._path_solver()
    assert paths is not None
    L, d, p = F.factor.factors()
    unit = np.eye(L.shape[0]) + L.toarray()
    inverse = np.argsort(p)
    for row in (0, 40, 71, 75, 143):
        e = np.zeros(L.shape[0])
        e[inverse[row]] = 1.0  # P^T e_row
        y = sla.solve_triangular(unit, e, lower=True, unit_diagonal=True) / d
        columns, values = paths.forward(row, 1.0)
        assert np.all(np.diff(columns) > 0)
        np.testing.assert_allclose(values, y[columns], rtol=1e-12, atol=1e-15)
        outside = np.ones(y.size, dtype=bool)
        outside[columns] = False
        assert np.all(y[outside] == 0.0)


def test_path_solve_falls_back_to_full_solves(monkeypatch):
    """Columns whose paths are too long (here: all, then every second) or that have more
    than MAX_SOURCES sources take the full solve; the result is the same."""
    from torch_polylap.linalg import etree_solve

    A, dense = _two_component_heat()
    n = dense.shape[0]
    many = np.arange(0, n, 2)
    assert many.size > etree_solve.MAX_SOURCES
    rows = [np.array([3]), many, np.array([5, 40])]
    values = [np.ones(r.size) for r in rows]
    B = np.zeros((n, 3))
    for q, r in enumerate(rows):
        B[r, q] = 1.0
    want = np.linalg.solve(dense, B)
    F = LDLFactorization(A)
    paths = F._path_solver()
    assert paths is not None and not paths.pays(many)
    np.testing.assert_allclose(F.solve_sparse_array(rows, values), want, rtol=1e-10, atol=1e-15)
    monkeypatch.setattr(etree_solve, "PATH_SHARE", 0.0)
    np.testing.assert_allclose(F.solve_sparse_array(rows, values), want, rtol=1e-10, atol=1e-15)


class _MisreadFactor:
    """A qdldl solver whose ``factors()`` are wrong: transposed, or with a scaled ``D``."""

    def __init__(self, inner, how: str) -> None:
        self.inner, self.how = inner, how

    def solve(self, b):
        return self.inner.solve(b)

    def factors(self):
        L, d, p = self.inner.factors()
        return (L.T.tocsc(), d, p) if self.how == "transposed" else (L, 2.0 * d, p)


@pytest.mark.parametrize("how", ["transposed", "scaled"])
def test_unreadable_factors_take_the_full_solve(how):
    """A factor whose structure is not a lower triangle is refused when read, one whose
    values are off by the check against a full solve; the solves stay right."""
    A, dense = _two_component_heat()
    F = LDLFactorization(A)
    F.factor = _MisreadFactor(F.factor, how)
    assert F._path_solver() is None and F._triangle_solves() is None
    rows, values = [np.array([5, 40])], [np.array([1.0, 2.0])]
    B = np.zeros((dense.shape[0], 1))
    B[[5, 40], 0] = [1.0, 2.0]
    want = np.linalg.solve(dense, B)
    np.testing.assert_allclose(F.solve_sparse_array(rows, values), want, rtol=1e-10, atol=1e-15)
    np.testing.assert_allclose(F.solve_array(B), want, rtol=1e-10, atol=1e-15)


def test_tree_depths_against_a_walk():
    from torch_polylap.linalg.etree_solve import _depths

    rng = np.random.default_rng(8)
    n = 500
    parent = np.array(
        [rng.integers(j + 1, n) if rng.random() < 0.97 and j < n - 1 else -1 for j in range(n)]
    )
    want = np.zeros(n, dtype=np.int64)
    for j in range(n):
        k = j
        while parent[k] >= 0:
            k = parent[k]
            want[j] += 1
    np.testing.assert_array_equal(_depths(parent), want)


def test_distances_from_boundary_sources_equal_the_splu_backend():
    """Heat geodesics from boundary vertices and overlapping source sets: the path solve
    (``"ldl"``) against SuperLU's full solves."""
    verts, faces = tp.shapes.quad_grid(14, 11)
    verts = verts.double()
    sources = [[0], [14], [0, 1, 2], [3, 100], [int(verts.shape[0]) - 1]]
    ldl = tp.HeatGeodesicSolver(verts, faces, backend="ldl").distance(sources)
    splu = tp.HeatGeodesicSolver(verts, faces, backend="splu").distance(sources)
    torch.testing.assert_close(ldl, splu, rtol=1e-12, atol=1e-12)


def test_triangle_solves_of_a_mesh_system_against_dense_solve():
    """The full solves through the 32-bit copies of QDLDL's factor (forward with ``D`` on
    the diagonal, backward as a lower solve with the reversed transpose) on a sparse system
    with a branching elimination forest (two components), one and several columns."""
    A, dense = _two_component_heat()
    F = LDLFactorization(A)
    assert F._triangle_solves() is not None
    B = np.random.default_rng(9).standard_normal((dense.shape[0], 4))
    want = np.linalg.solve(dense, B)
    np.testing.assert_allclose(F.solve_array(B), want, rtol=1e-10, atol=1e-13)
    np.testing.assert_allclose(F.solve_array(B[:, 2]), want[:, 2], rtol=1e-10, atol=1e-13)


def test_factor_copies_are_made_by_the_second_query(monkeypatch):
    """A first query (heat_geodesic_distance's only one, a solver's first) solves with QDLDL
    itself: the 32-bit copies of the factors and the path solver would cost more than they
    save. The second query makes them (the heat factor's path solver, the Poisson factor's
    triangles), later ones reuse them; every query gives SuperLU's distances."""
    import torch_polylap.linalg.factor as factor
    from torch_polylap.linalg.etree_solve import EtreePathSolver, LDLTriangles

    verts, faces = _sphere_quad()
    sources = [[3, 50], [7]]
    want = tp.HeatGeodesicSolver(verts, faces, backend="splu").distance(sources)
    made = []
    checked_solves = factor._checked_solves

    def counted(factors, S, kind):
        made.append(kind)
        return checked_solves(factors, S, kind)

    monkeypatch.setattr(factor, "_checked_solves", counted)
    got = tp.heat_geodesic_distance(verts, faces, sources)
    torch.testing.assert_close(got, want, rtol=1e-12, atol=1e-12)
    solver = tp.HeatGeodesicSolver(verts, faces)
    torch.testing.assert_close(solver.distance(sources), want, rtol=1e-12, atol=1e-12)
    assert made == []
    torch.testing.assert_close(solver.distance(sources), want, rtol=1e-12, atol=1e-12)
    assert sorted(k.__name__ for k in made) == ["EtreePathSolver", "LDLTriangles"]
    assert made.count(EtreePathSolver) == 1 and made.count(LDLTriangles) == 1
    torch.testing.assert_close(solver.distance(sources[1]), want[:, 1], rtol=1e-12, atol=1e-12)
    assert len(made) == 2


def _heat_and_poisson():
    """``M0 + t L`` and ``L' + pin`` of the two-component grids (one pattern: the heat
    solver's pair of systems), as operators and dense matrices."""
    verts, faces = _two_components()
    L, M0 = tp.laplacian(verts, faces, 1.0)
    L2, _ = tp.laplacian(verts, faces, 0.1)
    pin = torch.zeros(verts.shape[0], dtype=torch.float64)
    pin[[0, verts.shape[0] // 2]] = 1.0
    A, B = M0 + 0.05 * L, L2 + tp.sparse.diag(pin)
    return A, B, tp.sparse.to_scipy(A).toarray(), tp.sparse.to_scipy(B).toarray()


@pytest.mark.parametrize("keep", [True, False])
def test_refactored_solves_both_systems_against_dense_solves(keep):
    """QDLDL's numeric refactorization of a second matrix of the same pattern (reusing the
    first's ordering and tree) solves it; the first factorization, whose solver was handed
    on, still solves its own matrix: through the factor read out beforehand (``keep``), or by
    factoring again. Reference: dense solves; the refactored factor equals a fresh one."""
    A, B, dense_a, dense_b = _heat_and_poisson()
    rhs = np.random.default_rng(10).standard_normal((dense_a.shape[0], 2))
    first = LDLFactorization(A)
    second = first.refactored(B, keep=keep)
    assert second.factor is not None and first.factor is None
    fresh = LDLFactorization(B)
    np.testing.assert_array_equal(second.factor.solve(rhs[:, 0]), fresh.factor.solve(rhs[:, 0]))
    want_b = np.linalg.solve(dense_b, rhs)
    want_a = np.linalg.solve(dense_a, rhs)
    np.testing.assert_allclose(second.solve_array(rhs, copy_factor=False), want_b, rtol=1e-10)
    np.testing.assert_allclose(second.solve_array(rhs), want_b, rtol=1e-10)
    np.testing.assert_allclose(first.solve_array(rhs, copy_factor=False), want_a, rtol=1e-10)
    # with the factor kept, first's solves ran through copies made from it; without, QDLDL
    # factored the matrix again
    assert (first._triangles is not None) == keep and (first.factor is None) == keep
    rows, values = [np.array([5, 40])], [np.array([1.0, 2.0])]
    sparse_rhs = np.zeros((dense_a.shape[0], 1))
    sparse_rhs[[5, 40], 0] = [1.0, 2.0]
    np.testing.assert_allclose(
        first.solve_sparse_array(rows, values),
        np.linalg.solve(dense_a, sparse_rhs),
        rtol=1e-10,
        atol=1e-15,
    )


def test_refactored_with_another_pattern_factors_afresh():
    """A matrix whose pattern differs (here: a diagonal) cannot reuse the symbolic analysis:
    it gets a fresh factorization, and the first keeps its solver."""
    A, _, dense_a, _ = _heat_and_poisson()
    n = dense_a.shape[0]
    first = LDLFactorization(A)
    solver = first.factor
    D = tp.sparse.diag(torch.arange(1.0, n + 1, dtype=torch.float64))
    second = first.refactored(D)
    assert first.factor is solver and second.factor is not solver
    b = np.ones(n)
    np.testing.assert_allclose(second.solve_array(b), b / np.arange(1.0, n + 1), rtol=1e-14)
    np.testing.assert_allclose(first.solve_array(b), np.linalg.solve(dense_a, b), rtol=1e-10)


def test_refactored_refuses_an_indefinite_matrix():
    """The refactored matrix is checked as a fresh one: ``-B`` (same pattern, negative
    definite) is refused, and the first factorization still solves its matrix."""
    A, B, dense_a, _ = _heat_and_poisson()
    first = LDLFactorization(A)
    with pytest.raises(ValueError, match="not positive definite|singular"):
        first.refactored(-1.0 * B)
    b = np.ones(dense_a.shape[0])
    np.testing.assert_allclose(first.solve_array(b), np.linalg.solve(dense_a, b), rtol=1e-10)

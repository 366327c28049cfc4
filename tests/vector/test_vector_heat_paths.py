"""The vector heat method's query path outside autograd (the complex ``L D L^H`` of
``M + t A``, the scalar heat over elimination-tree paths) against its differentiable torch path
and against dense solves."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp
import torch
from conftest import DATA
from meshes import read_mesh, shared_path

import torch_polylap as tp
import torch_polylap.vector as tv
from torch_polylap.linalg import HermitianLDL
from torch_polylap.sparse import to_scipy
from torch_polylap.vector.heat import _complex_form


def sphere(name: str) -> tuple[torch.Tensor, tp.PolygonFaces]:
    verts, faces = read_mesh(DATA / "sphere" / f"{name}.obj", dtype=torch.float64)
    return verts / verts.norm(dim=1, keepdim=True), faces


def tangent(verts: torch.Tensor, s: int, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    v = torch.randn(3, generator=g, dtype=verts.dtype)
    return torch.linalg.cross(verts[s], v)


def both_paths(solver: tv.VectorHeatSolver, query) -> tuple[torch.Tensor, torch.Tensor]:
    """``query(solver)`` outside autograd (the array path) and with ``verts`` requiring grad
    (the torch path, whose solves go through :func:`torch_polylap.solve`)."""
    fast = query(solver)
    verts = solver.verts.detach().clone().requires_grad_(True)
    faces = solver.topology
    slow = query(tv.VectorHeatSolver(verts, faces, method=solver.method))
    return fast, slow.detach()


@pytest.mark.parametrize("name", ["hex_3", "concave_3", "voronoi_3"])
def test_transport_equals_the_differentiable_path(name, device):
    """One source, and two sources of different lengths (two scalar heat solves); to
    round-off amplified where |Y| is small (measured up to 5e-10 relative on concave_3)."""
    verts, faces = sphere(name)
    verts = verts.to(device)
    solver = tv.VectorHeatSolver(verts, faces)
    s, r = 0, verts.shape[0] // 2
    vec = tangent(verts.cpu(), s).to(device)
    fast, slow = both_paths(solver, lambda x: x.transport(s, vec))
    torch.testing.assert_close(fast, slow, rtol=1e-8, atol=1e-10)
    vecs = torch.stack((vec, 3.0 * tangent(verts.cpu(), r, 1).to(device)))
    fast, slow = both_paths(solver, lambda x: x.transport([s, r], vecs))
    torch.testing.assert_close(fast, slow, rtol=1e-8, atol=1e-10)


def test_log_map_equals_the_differentiable_path(device):
    verts, faces = sphere("hex_3")
    solver = tv.VectorHeatSolver(verts.to(device), faces)
    fast, slow = both_paths(solver, lambda x: x.log_map([0, 7]))
    torch.testing.assert_close(fast, slow, rtol=1e-9, atol=1e-11)


def test_transport_is_zero_on_a_component_without_source(device):
    """Two spheres: the second, without a source, gets 0 on both paths; the first matches."""
    verts, faces = tp.shapes.quad_sphere(4)
    n = verts.shape[0]
    both = torch.cat((verts, verts + 3.0)).to(device)
    polys = torch.cat((faces, faces + n))
    solver = tv.VectorHeatSolver(both, polys)
    vec = tangent(verts, 5).to(device)
    fast, slow = both_paths(solver, lambda x: x.transport(5, vec))
    assert bool((fast[n:] == 0).all())
    torch.testing.assert_close(fast, slow, rtol=1e-8, atol=1e-10)


def test_complex_form_is_the_real_operator():
    """The complex matrix's real form ``[[a, -b], [b, a]]`` per entry is the ``(2V, 2V)``
    operator, entry for entry."""
    verts, faces = sphere("concave_3")
    solver = tv.VectorHeatSolver(verts, faces)
    S = to_scipy(solver.vector_operator).tocsr()
    C = _complex_form(S)
    real = sp.bmat([[C.real, -C.imag], [C.imag, C.real]]).tocsr()
    n = C.shape[0]
    interleave = np.arange(2 * n).reshape(2, n).T.reshape(-1)  # x_0, y_0, x_1, ...
    assert abs(real[interleave][:, interleave] - S).max() == 0.0
    assert abs(C - C.conj().T).max() == 0.0
    # entries given twice, halved (not canonical): the general route, the same matrix
    twice = sp.csr_matrix(
        (np.repeat(S.data / 2, 2), np.repeat(S.indices, 2), 2 * S.indptr), shape=S.shape
    )
    assert not twice.has_canonical_format
    assert abs(_complex_form(twice) - C).max() <= 1e-15 * abs(C).max()


def random_hermitian(n: int, seed: int) -> sp.csr_matrix:
    """A sparse Hermitian positive definite matrix: a random complex pattern, made diagonally
    dominant."""
    rng = np.random.default_rng(seed)
    B = sp.random(n, n, density=0.05, random_state=rng, format="csr")
    B = B + 1j * sp.random(n, n, density=0.05, random_state=rng, format="csr")
    H = B + B.conj().T
    return sp.csr_matrix(H + sp.diags(abs(H).sum(1).A1 + 1.0))


@pytest.mark.parametrize("ordered", [False, True])
def test_hermitian_ldl_solves_as_a_dense_solve(ordered):
    A = random_hermitian(60, 0)
    ordering = np.random.default_rng(1).permutation(60) if ordered else None
    factor = HermitianLDL(A, ordering)
    b = np.random.default_rng(2).standard_normal((60, 3)) * (1 + 2j)
    np.testing.assert_allclose(factor.solve(b), np.linalg.solve(A.toarray(), b), rtol=1e-10)


def test_hermitian_ldl_solves_a_sparse_right_hand_side():
    """Few nonzero rows (the forward pass over their tree paths, where it pays) and many (a
    full solve): both as a dense solve."""
    A = random_hermitian(80, 4)
    factor = HermitianLDL(A, np.arange(80))
    dense = A.toarray()
    for rows in (np.array([3]), np.array([0, 41]), np.arange(0, 80, 2)):
        values = (1.0 + 0.5j) * np.arange(1, rows.size + 1)
        b = np.zeros(80, dtype=complex)
        b[rows] = values
        np.testing.assert_allclose(factor.solve_sparse(rows, values), np.linalg.solve(dense, b))


def test_hermitian_ldl_refuses_an_indefinite_matrix():
    A = random_hermitian(40, 3)
    A = sp.csr_matrix(A - 2 * sp.diags(A.diagonal().real))
    with pytest.raises(ValueError, match="not positive definite"):
        HermitianLDL(A)


@pytest.mark.slow
@pytest.mark.parametrize("name", ["loki.obj", "rockerArm.obj"])
def test_transport_on_real_meshes_equals_the_differentiable_path(name):
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # OBJ groups the reader skips
        verts, faces = read_mesh(shared_path(f"real/{name}"), dtype=torch.float64)
    solver = tv.VectorHeatSolver(verts, faces)
    vec = tangent(verts, 0)
    fast, slow = both_paths(solver, lambda x: x.transport(0, vec))
    torch.testing.assert_close(fast, slow, rtol=1e-8, atol=1e-10)
    # one source: every vertex gets its tangent length (to the 1e-6 within which the far
    # field's u / phi is kept), also where the scalar heat falls to round-off far away (on
    # loki the quotient was once inf or NaN at 15 vertices)
    frames = tp.tangent.vertex_tangent_frames(verts, faces)
    length = (vec - (vec @ frames.normal[0]) * frames.normal[0]).norm()
    torch.testing.assert_close(fast.norm(dim=1), length.expand(len(verts)), rtol=2e-6, atol=0)

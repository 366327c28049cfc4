"""Properties of L and M0 (AW11; docs/math/properties.md) against independent formulas."""

from __future__ import annotations

import math

import numpy as np
import pytest
import scipy.linalg
import torch
from conftest import DATA, hex_pent_mesh, mixed_mesh, tolerances
from meshes import read_mesh

import torch_polylap as tp
from torch_polylap.shapes import quad_grid

D64 = {"dtype": torch.float64}


def dense(A: torch.Tensor) -> torch.Tensor:
    return A.detach().to_dense()


def meshes():
    """(name, verts, faces) of small meshes covering degrees 3..10, planar and not."""
    out = [("mixed", *mixed_mesh()), ("hexpent", *hex_pent_mesh())]
    out.append(("grid", *quad_grid(4, 3, bump=0.3, seed=1)))
    for name in ("tetris.obj", "spot_control_mesh.obj", "dodecahedron_poly.obj"):
        v, f = read_mesh(DATA / name)
        out.append((name, v, f))
    return out


MESHES = meshes()
IDS = [m[0] for m in MESHES]


def cotan_laplacian(V: np.ndarray, F: np.ndarray) -> np.ndarray:
    """Textbook cotan Laplacian (PSD sign), L_ij = -(cot a_ij + cot b_ij) / 2, written anew."""
    n = len(V)
    L = np.zeros((n, n))
    for tri in F:
        for c in range(3):
            i, j, k = tri[c], tri[(c + 1) % 3], tri[(c + 2) % 3]
            u, w = V[i] - V[k], V[j] - V[k]
            cot = np.dot(u, w) / np.linalg.norm(np.cross(u, w))
            L[i, j] -= cot / 2
            L[j, i] -= cot / 2
            L[i, i] += cot / 2
            L[j, j] += cot / 2
    return L


def polygon_blocks_svd(X: torch.Tensor, lam: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Independent M_f and L_f of one face, straight from AW11 sec. 4 pseudo-code (SVD kernel)."""
    k = X.shape[0]
    E = torch.roll(X, -1, 0) - X
    B = 0.5 * (torch.roll(X, -1, 0) + X)
    A = E.T @ B
    a = torch.stack((-A[1, 2], A[0, 2], -A[0, 1]))  # Darboux vector (Lemma 1, eq. 8)
    area = torch.linalg.norm(a)
    n = a / area
    Ebar = E - (E @ n)[:, None] * n
    _, _, vh = torch.linalg.svd(Ebar.T)
    C = vh[2:].T  # orthonormal kernel of Ebar^T, k x (k-2)
    Mf = B @ B.T / area + lam * C @ C.T
    d = torch.roll(torch.eye(k, **D64), 1, 1) - torch.eye(k, **D64)  # (d u)_i = u_{i+1} - u_i
    return Mf, d.T @ Mf @ d


@pytest.mark.parametrize("lam", [0.5, 1.0, 2.0])
def test_triangles_give_cotan(lam, device, dtype):
    """Theorem 2: on triangles L is the cotan Laplacian for every lambda."""
    V, F = quad_grid(5, 4, bump=0.4, seed=3, dtype=dtype, device=device)
    T = torch.cat([F[:, [0, 1, 2]], F[:, [0, 2, 3]]])
    L, M0 = tp.laplacian(V, T, lam)
    assert L.device.type == M0.device.type == device.type and L.dtype == M0.dtype == dtype
    V = V.cpu().double()  # the references from the same (rounded) coordinates, in float64
    ref = cotan_laplacian(V.numpy(), T.numpy())
    tol = 1e-12 if dtype == torch.float64 else tolerances(dtype)["atol"]
    np.testing.assert_allclose(dense(L).cpu().numpy(), ref, atol=tol * np.abs(ref).max())
    # M0 = barycentric lumped mass: a third of each incident triangle's area
    areas = 0.5 * np.linalg.norm(np.cross(V[T[:, 1]] - V[T[:, 0]], V[T[:, 2]] - V[T[:, 0]]), axis=1)
    m = np.zeros(len(V))
    np.add.at(m, T.numpy().ravel(), np.repeat(areas / 3, 3))
    rtol = 1e-13 if dtype == torch.float64 else tolerances(dtype)["rtol"]
    np.testing.assert_allclose(torch.diagonal(dense(M0)).cpu().numpy(), m, rtol=rtol)


def test_triangles_match_libigl(device):
    igl = pytest.importorskip("igl", reason="libigl not installed (pip install libigl)")
    V, F = quad_grid(6, 6, bump=0.3, seed=2)
    T = torch.cat([F[:, [0, 1, 2]], F[:, [0, 2, 3]]])
    L, _ = tp.laplacian(V.to(device), T)
    C = igl.cotmatrix(V.numpy(), T.numpy()).toarray()
    np.testing.assert_allclose(dense(L).cpu().numpy(), -C, atol=1e-12 * np.abs(C).max())


@pytest.mark.parametrize("name,V,F", MESHES, ids=IDS)
@pytest.mark.parametrize("lam", [0.5, 2.0])
def test_blocks_match_svd_construction(name, V, F, lam, device):
    """Our closed-form blocks equal the paper's construction with an SVD kernel basis."""
    faces = tp.as_faces(F)
    for ids, blocks in tp.dec.local_laplacians(V.to(device), faces, lam):
        assert blocks.device.type == device.type
        for local, f in enumerate(ids.tolist()[:25]):
            _, ref = polygon_blocks_svd(V[faces[f]], lam)  # the reference on the CPU
            scale = ref.abs().max()
            assert torch.allclose(blocks[local].cpu(), ref, atol=1e-12 * scale), (name, f)


@pytest.mark.parametrize("name,V,F", MESHES, ids=IDS)
def test_symmetric_psd_constant_kernel(name, V, F, device):
    V = V.to(device)
    L, M0 = tp.laplacian(V, F)
    assert L.device == V.device and M0.device == V.device
    D = dense(L)
    scale = D.abs().max()
    # exact on the CPU; CUDA sums the shared entries of (i, j) and (j, i) in a parallel order
    assert torch.allclose(D, D.T, atol=0 if device.type == "cpu" else 1e-15 * scale, rtol=0)
    assert D.sum(1).abs().max() <= 1e-13 * scale
    ev = torch.linalg.eigvalsh(D)
    assert ev[0] >= -1e-12 * ev[-1]
    # kernel = constants (these meshes are connected): exactly one ~zero eigenvalue
    assert ev[1] > 1e-8 * ev[-1]
    m = torch.diagonal(dense(M0))
    assert (m > 0).all()
    assert torch.isclose(m.sum(), tp.face_areas(V, F).sum(), rtol=1e-13)


def test_kernel_counts_components(device):
    V1, F1 = quad_grid(3, bump=0.2)
    V2, F2 = mixed_mesh()
    V = torch.cat([V1, V2 + 5.0]).to(device)
    F = [f.tolist() for f in F1] + [[i + V1.shape[0] for i in f] for f in F2]
    ev = torch.linalg.eigvalsh(dense(tp.laplacian(V, F)[0]))
    assert int((ev < 1e-10 * ev[-1]).sum()) == 2


def test_linear_precision_on_planar_mesh(device):
    """(L X)_p = 0 at interior vertices of a planar mesh (AW11 sec. 3.1), for any lambda."""
    V, F = quad_grid(6, 5, seed=4)  # irregular convex quads in the plane z = 0
    V = (V @ random_rotation(0).T).to(device)
    topo = tp.build_topology(F, V.shape[0])
    interior = torch.ones(V.shape[0], dtype=torch.bool, device=device)
    interior[topo.boundary_vertices] = False
    for lam in (0.5, 1.0, 3.0):
        L, _ = tp.laplacian(V, topo, lam)
        LX = tp.sparse.spmm(L, V)
        assert LX[interior].abs().max() <= 1e-13 * dense(L).abs().max()
        assert LX[~interior].abs().max() > 1e-3  # boundary rows are not zero: the test can fail


def test_linear_precision_nonconvex_polygons(device):
    V, F = read_mesh(DATA / "tetris.obj", device=device)  # planar, non-convex 4- to 10-gons
    topo = tp.build_topology(F, V.shape[0])
    interior = torch.ones(V.shape[0], dtype=torch.bool, device=device)
    interior[topo.boundary_vertices] = False
    L, _ = tp.laplacian(V, topo)
    assert interior.any()
    assert tp.sparse.spmm(L, V)[interior].abs().max() <= 1e-12 * dense(L).abs().max()


def random_rotation(seed: int) -> torch.Tensor:
    q, r = torch.linalg.qr(torch.randn(3, 3, generator=torch.Generator().manual_seed(seed), **D64))
    q = q * torch.sign(torch.diagonal(r))
    return q if torch.det(q) > 0 else -q


@pytest.mark.parametrize("name,V,F", MESHES, ids=IDS)
def test_invariances(name, V, F, device):
    V = V.to(device)
    L, M0 = tp.laplacian(V, F)
    D, m = dense(L), torch.diagonal(dense(M0))
    scale = D.abs().max()
    # uniform scaling: L invariant (scale invariance), M0 scales with area
    L2, M2 = tp.laplacian(3.7 * V, F)
    assert torch.allclose(dense(L2), D, atol=1e-12 * scale)
    assert torch.allclose(torch.diagonal(dense(M2)), 3.7**2 * m, rtol=1e-12)
    # rigid motion, far from the origin (origin independence)
    R = random_rotation(7).to(device)
    L3, M3 = tp.laplacian(V @ R.T + torch.tensor([1e3, -2e3, 5e2], **D64, device=device), F)
    assert torch.allclose(dense(L3), D, atol=1e-9 * scale)
    assert torch.allclose(torch.diagonal(dense(M3)), m, rtol=1e-8)
    # cyclic relabelling of every face's corners, and reversing all orientations
    faces = tp.as_faces(F)
    rolled = [f[1:] + f[:1] for f in faces.tolist()]
    assert torch.allclose(dense(tp.laplacian(V, rolled)[0]), D, atol=1e-13 * scale)
    assert torch.allclose(dense(tp.laplacian(V, faces.flipped())[0]), D, atol=1e-13 * scale)
    # permuting vertex indices permutes L
    perm = torch.randperm(V.shape[0], generator=torch.Generator().manual_seed(1))
    inv = torch.argsort(perm)
    relabelled = [[int(inv[v]) for v in f] for f in faces.tolist()]
    perm = perm.to(device)
    Lp = dense(tp.laplacian(V[perm], relabelled)[0])
    assert torch.allclose(Lp, D[perm][:, perm], atol=1e-13 * scale)


@pytest.mark.parametrize("name,V,F", MESHES, ids=IDS)
def test_lemma3_area_gradient(name, V, F, device):
    """Lemma 3: grad of sum_f |f| equals (sum_f P_f^T (G G^T / |f|) P_f) X = L(lam = 0) X."""
    V = V.to(device)
    X = V.clone().requires_grad_(True)
    (grad,) = torch.autograd.grad(tp.face_areas(X, F).sum(), X)
    L0, _ = tp.laplacian(V, F, lam=0.0)
    assert torch.allclose(grad, tp.sparse.spmm(L0, V), atol=1e-13 * grad.abs().max())


def test_lemma5_nonplanar_face(device):
    """Lemma 5: Htilde_f = H_fbar, and H_f - Htilde_f = lam (d^T hbar_e) n^T."""
    gen = torch.Generator().manual_seed(5)
    for k in (4, 5, 7):
        ang = torch.linspace(0, 2 * math.pi, k + 1, **D64)[:-1] + 0.2 * torch.rand(
            k, generator=gen, **D64
        )
        X = torch.stack(
            [torch.cos(ang), 1.3 * torch.sin(ang), 0.3 * torch.randn(k, generator=gen, **D64)], 1
        ).to(device)
        face = [list(range(k))]
        lam = 1.7
        ((_, (Lf,)),) = [(i, b) for i, b in tp.dec.local_laplacians(X, face, lam)]
        ((_, (Lg,)),) = [(i, b) for i, b in tp.dec.local_laplacians(X, face, 0.0)]
        n = tp.face_normals(X, face)[0]
        h = (X - X.mean(0)) @ n
        Xbar = X - h[:, None] * n
        ((_, (Lbar,)),) = [(i, b) for i, b in tp.dec.local_laplacians(Xbar, face, 0.0)]
        assert torch.allclose(Lg @ X, Lbar @ Xbar, atol=1e-13)
        # hbar_e: projection of h_e = d h onto ker(Ebar^T), from an independent SVD
        eye = torch.eye(k, **D64, device=device)
        d = torch.roll(eye, 1, 1) - eye
        Ebar = d @ Xbar
        C = torch.linalg.svd(Ebar.T)[2][2:].T
        hbar_e = C @ (C.T @ (d @ h))
        assert torch.allclose(Lf @ X - Lg @ X, lam * torch.outer(d.T @ hbar_e, n), atol=1e-13)


@pytest.mark.parametrize("name,V,F", MESHES, ids=IDS)
def test_inner_product_definiteness(name, V, F, device):
    """Theorem 1: M_f positive definite for lam > 0; the geometric part alone is rank deficient."""
    V = V.to(device)
    faces = tp.as_faces(F)
    M1 = dense(tp.dec.one_form_inner_product(V, faces, 1.0))
    M1g = dense(tp.dec.one_form_inner_product(V, faces, 0.0))
    start = faces.offsets.tolist()
    nonplanarity = tp.face_nonplanarity(V, faces)
    for f in range(min(faces.num_faces, 40)):
        a, b = start[f], start[f + 1]
        ev = torch.linalg.eigvalsh(M1[a:b, a:b])
        assert ev[0] > 1e-6 * ev[-1]
        k = b - a
        # The geometric part is B B^T / |f| with B the edge midpoints about the centroid. They
        # lie in a plane for triangles, for planar faces and (Varignon's parallelogram) for
        # every quad: rank 2. Around a non-planar face of degree >= 5 they span space: rank 3.
        rank_geo = int(torch.linalg.matrix_rank(M1g[a:b, a:b], rtol=1e-10))
        if k <= 4 or nonplanarity[f] < 1e-12:
            assert rank_geo == 2, (f, k, float(nonplanarity[f]))
        elif nonplanarity[f] > 1e-6:
            assert rank_geo == 3, (f, k, float(nonplanarity[f]))
        if k > 3:
            # for quads and planar faces G = d^T B has rank 2
            Lg = tp.dec.local_laplacians(V[faces[f]], [list(range(k))], 0.0)[0][1][0]
            if k == 4 or name in ("tetris.obj",):
                assert int(torch.linalg.matrix_rank(Lg, rtol=1e-10)) == 2


@pytest.mark.parametrize("name,V,F", MESHES, ids=IDS)
def test_half_edge_factorization(name, V, F, device):
    """L = d^T M1 d (AW11 eq. 3) with the half-edge coboundary of eq. 2."""
    V = V.to(device)
    d = dense(tp.dec.coboundary(F, V.shape[0])).to(device)  # index-only: built on the CPU
    for lam in (0.0, 1.0):
        M1 = dense(tp.dec.one_form_inner_product(V, F, lam))
        L = dense(tp.laplacian(V, F, lam)[0])
        assert torch.allclose(d.T @ M1 @ d, L, atol=1e-12 * L.abs().max())
    assert torch.all(d.sum(1) == 0) and torch.all(d.abs().sum(1) == 2)


def test_planarity_operator_and_energy(hexpent, device):
    V, F = hexpent
    V = V.to(device)
    P = tp.planarity_laplacian(V, F, lam=2.0)
    energy = tp.planarity_energy(V, F, lam=2.0)
    quad = 0.5 * (V * tp.sparse.spmm(P, V)).sum()
    assert energy > 1e-3
    assert torch.isclose(energy, quad, rtol=1e-12)
    # L = geometric part + planarity operator
    L = dense(tp.laplacian(V, F, 2.0)[0])
    L0 = dense(tp.laplacian(V, F, 0.0)[0])
    assert torch.allclose(L, L0 + dense(P), atol=1e-13 * L.abs().max())
    # zero exactly when all faces are planar
    Vf = V.clone()
    Vf[:, 2] = 0.0
    assert tp.planarity_energy(Vf, F, 2.0).abs() < 1e-26
    Pf = tp.planarity_laplacian(Vf, F)
    assert (
        tp.sparse.spmm(Pf, Vf).abs().max() < 1e-13 * dense(Pf).abs().max()
    )  # Lplan X = 0, Lplan != 0


def test_mean_curvature_on_sphere(device):
    V, F = read_mesh(DATA / "sphere" / "quad_3.obj", device=device)
    V = V / V.norm(dim=1, keepdim=True)
    H = tp.mean_curvature_normal(V, F)
    err = ((H.norm(dim=1) / 2 - 1) ** 2).mean().sqrt()
    assert err < 0.05
    # H points along the outward normal for counter-clockwise faces, so H . x > 0 ...
    # ... or inward for the opposite convention; either way it is parallel to x.
    cos = (H * V).sum(1) / H.norm(dim=1)
    assert cos.abs().min() > 0.99


def test_mass_matches_face_areas(mixed, device):
    V, F = mixed
    V = V.to(device)
    m = tp.mass(V, F)
    faces = tp.as_faces(F)
    areas = tp.face_areas(V, F).cpu()
    ref = torch.zeros(V.shape[0], **D64)
    for f, face in enumerate(faces.tolist()):
        for v in face:
            ref[v] += areas[f] / len(face)
    assert m.device == V.device and torch.allclose(m.cpu(), ref, rtol=1e-14)
    # the vector area of a planar polygon is its shoelace area
    sq = torch.tensor([[0.0, 0, 0], [2, 0, 0], [2, 1, 0], [0, 1, 0]], **D64, device=device)
    assert torch.allclose(
        tp.vector_area(sq, [[0, 1, 2, 3]]), torch.tensor([[0.0, 0, 2]], **D64, device=device)
    )


def test_float32_matches_float64(device):
    V, F = quad_grid(5, bump=0.3, seed=6, device=device)
    L64, M64 = tp.laplacian(V, F)
    L32, M32 = tp.laplacian(V.float(), F)
    assert L32.dtype == torch.float32 and M32.dtype == torch.float32
    assert torch.allclose(dense(L32).double(), dense(L64), atol=1e-5 * dense(L64).abs().max())


def test_operators_report_the_csr_layout_they_store(mixed, device):
    V, F = mixed
    V = V.to(device)
    L, M = tp.laplacian(V, F)
    P = tp.planarity_laplacian(V, F)
    lap = tp.PolygonLaplacian()
    for A in (L, M, P, lap(V, F)[0]):
        assert A.layout == torch.sparse_csr and A.is_sparse_csr and not A.is_sparse
        # the reported layout is the storage: scipy's CSR arrays of the same matrix
        ref = tp.sparse.to_scipy(A).tocsr()
        ref.sort_indices()
        assert A.device.type == device.type
        assert torch.equal(A.crow_indices().cpu(), torch.from_numpy(ref.indptr).long())
        assert torch.equal(A.col_indices().cpu(), torch.from_numpy(ref.indices).long())


def test_layout_is_no_argument(mixed):
    """The operators store and report sorted CSR; there is no label to choose."""
    V, F = mixed
    with pytest.raises(TypeError, match="layout"):
        tp.laplacian(V, F, layout=torch.sparse_coo)
    with pytest.raises(TypeError, match="layout"):
        tp.PolygonLaplacian(layout=torch.sparse_coo)


def test_scipy_roundtrip(mixed, device):
    V, F = mixed
    L, _ = tp.laplacian(V.to(device), F)
    S = tp.sparse.to_scipy(L)
    assert np.allclose(S.toarray(), dense(L).cpu().numpy())
    back = tp.sparse.from_scipy(S)
    assert torch.equal(dense(back), dense(L).cpu())


def test_module_caches_topology(device):
    V, F = quad_grid(4, bump=0.2, device=device)
    module = tp.PolygonLaplacian(lam=2.0)
    L1, _ = module(V, F)
    topo = module.topology
    L2, _ = module(V * 1.5 + 1.0, F)
    assert module.topology is topo
    assert torch.allclose(dense(L1), dense(L2), atol=1e-12)
    L3, _ = module(V)  # faces omitted: reuse
    assert module.topology is topo and torch.allclose(dense(L3), dense(L1))
    F2 = F.clone()
    module(V, F2)
    assert module.topology is not topo
    rebuilt = module.topology
    F2[0] = F2[0].flip(0).roll(1)  # in-place edit: must be noticed (a new, flipped topology)
    with pytest.warns(UserWarning, match="inconsistent orientation"):
        L4, _ = module(V, F2)
    assert module.topology is not rebuilt and rebuilt.is_oriented
    assert not module.topology.is_oriented and module.topology.is_manifold
    # L_f does not depend on the corner order: flipping a face leaves L unchanged
    assert torch.allclose(dense(L4), dense(L1), atol=1e-12)
    assert torch.allclose(dense(tp.laplacian(V, F, 2.0)[0]), dense(L1))


def test_learnable_lambda_gets_gradient(device):
    V, F = quad_grid(3, bump=0.4, seed=2)
    V, F = V.to(device), F.to(device)
    module = tp.PolygonLaplacian(lam=1.0, learn_lam=True).to(device)
    L, _ = module(V, F)
    (tp.sparse.spmm(L, V) ** 2).sum().backward()
    assert module.lam.grad is not None and module.lam.grad.abs() > 0
    # d/dlam of sum (L X)^2 = 2 <L X, Lplan X>, with Lplan the planarity operator at lam = 1
    P = tp.planarity_laplacian(V, F, 1.0)
    ref = 2 * (tp.sparse.spmm(L, V).detach() * tp.sparse.spmm(P, V)).sum()
    assert torch.isclose(module.lam.grad.double(), ref, rtol=1e-6)  # the parameter is float32


def test_generalized_eigenvalues_of_dodecahedron(device):
    """On a regular polyhedron the spectrum has the icosahedral multiplicities 1, 3, 5..."""
    V, F = read_mesh(DATA / "dodecahedron_poly.obj", device=device)
    L, M0 = tp.laplacian(V, F)
    ev = scipy.linalg.eigh(dense(L).cpu().numpy(), dense(M0).cpu().numpy(), eigvals_only=True)
    ev = ev / ev[1]
    assert abs(ev[0]) < 1e-10
    np.testing.assert_allclose(ev[1:4], 1.0, rtol=1e-8)  # threefold first eigenvalue
    assert ev[4] > 1.5


def test_fitted_plane_nonplanarity_against_svd(device):
    """plane="fit": the least-squares plane of the corners (independent per-face SVD here), and
    the projection plane never fits the corners better in the least-squares sense."""
    V, F = read_mesh(DATA / "mixedFaring.off", device=device)
    fit = tp.face_nonplanarity(V, F, plane="fit").cpu()
    projection = tp.face_nonplanarity(V, F).cpu()
    normals = tp.face_normals(V, F).cpu()
    for f, face in enumerate(F.tolist()[:300]):
        x = V[face].cpu().numpy()
        centered = x - x.mean(0)
        normal = np.linalg.svd(centered)[2][-1]
        diameter = max(np.linalg.norm(a - b) for a in x for b in x)
        assert fit[f].item() == pytest.approx(np.abs(centered @ normal).max() / diameter, abs=1e-12)
        squares_fit = ((centered @ normal) ** 2).sum()
        squares_projection = ((centered @ normals[f].numpy()) ** 2).sum()
        assert squares_fit <= squares_projection + 1e-15
    assert (projection[F.sizes == 3] < 1e-14).all() and (fit[F.sizes == 3] < 1e-14).all()
    X = V.clone().requires_grad_(True)
    assert not tp.face_nonplanarity(X, F, plane="fit").requires_grad
    assert tp.face_nonplanarity(X, F).requires_grad
    with pytest.raises(ValueError, match="plane must be"):
        tp.face_nonplanarity(V, F, plane="best")

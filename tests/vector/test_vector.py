"""``tp.vector``: the connection Laplacian, vector heat transport and log map, curvature and
smoothest direction fields, against closed forms on the sphere, the torus and the plane,
against adobe-lagrange's ``polyddg`` and potpourri3d, and by gradcheck."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.linalg as sl
import torch
from conftest import DATA
from meshes import load, read_mesh, shared_path

import torch_polylap as tp
import torch_polylap.vector as tv
from torch_polylap.sparse import to_scipy

METHODS = ("aw11", "plms", "degoes")
SPHERES = ("quad_3", "hex_3", "voronoi_3", "concave_3", "hex_cos_3")


def sphere(name: str) -> tuple[torch.Tensor, tp.PolygonFaces]:
    """A polyLaplace unit-sphere mesh from ``tests/data/sphere``, projected onto the sphere."""
    verts, faces = read_mesh(DATA / "sphere" / f"{name}.obj", dtype=torch.float64)
    return verts / verts.norm(dim=1, keepdim=True), faces


def generalized_spectrum(A: torch.Tensor, M: torch.Tensor) -> np.ndarray:
    """All eigenvalues of ``A x = mu M x`` by a dense LAPACK solve (an independent route)."""
    return sl.eigh(to_scipy(A).toarray(), to_scipy(M).toarray(), eigvals_only=True)


def triangulated(verts: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """Quads split along a diagonal (a triangle mesh for the comparison with lagrange)."""
    return torch.cat((faces[:, [0, 1, 2]], faces[:, [0, 2, 3]]))


# ---------------------------------------------------------------- the connection Laplacian


@pytest.mark.parametrize("method", METHODS)
def test_sphere_spectrum_is_l_l_plus_1_minus_1(method, device):
    """The Bochner Laplacian of the unit sphere has eigenvalues l (l + 1) - 1 with multiplicity
    2 (2 l + 1): 1 six times, 5 ten times (Weitzenboeck: the Hodge Laplacian's l (l + 1) minus
    the Ricci curvature 1). Measured on the 6 x 6 cube sphere: within 1.5% for all methods."""
    verts, faces = tp.shapes.quad_sphere(6)
    A, M, _ = tv.connection_laplacian(verts.to(device), faces, method=method)
    assert A.device.type == M.device.type == device.type
    mu = generalized_spectrum(A, M)
    np.testing.assert_allclose(mu[:6], 1.0, rtol=0.03)
    np.testing.assert_allclose(mu[6:16], 5.0, rtol=0.03)
    assert mu[16] > 10.0  # then l = 3: 11


@pytest.mark.parametrize("n, first, second", [(2, 2.0, 8.0), (4, 4.0, 14.0)])
def test_sphere_spectrum_of_n_fold_connection(n, first, second, device):
    """With the n-fold connection the operator is the Bochner Laplacian of spin-n fields on the
    sphere: eigenvalues l (l + 1) - n^2 for l >= n, multiplicity 2 (2 l + 1) (for n = 2: 2 ten
    times, then 8; for n = 4: 4 eighteen times, then 14). Measured within 6% on 6 x 6."""
    verts, faces = tp.shapes.quad_sphere(6)
    A, M, _ = tv.connection_laplacian(verts.to(device), faces, symmetry=n)
    assert A.device.type == device.type
    mu = generalized_spectrum(A, M)
    m1, m2 = 2 * (2 * n + 1), 2 * (2 * n + 3)
    np.testing.assert_allclose(mu[:m1], first, rtol=0.07)
    np.testing.assert_allclose(mu[m1 : m1 + m2], second, rtol=0.07)


@pytest.mark.parametrize("name", SPHERES)
def test_symmetric_positive_semidefinite_on_polygon_spheres(name, device):
    """Symmetric, and positive definite on the sphere (no parallel field): every face term is
    the scalar block seen through a unitary change of frame, whatever the weights' signs
    (concave and anisotropic polygons included)."""
    verts, faces = sphere(name)
    verts = verts.to(device)
    for method in METHODS:
        A, M, _ = tv.connection_laplacian(verts, faces, method=method)
        S = to_scipy(A)
        assert abs(S - S.T).max() <= 1e-14 * abs(S).max()
        mu, _ = tp.eigs(A, M, k=1)
        assert float(mu[0]) > 0.5, (method, mu)


@pytest.mark.parametrize("method", METHODS)
def test_planar_mesh_gives_scalar_laplacian_on_each_component(method, device):
    """On a plane every transport is the identity in a common frame: A = L (x) I_2. In the
    default frames (each vertex's own reference edge) the same operator is seen through the
    block rotation R of each vertex's angle to the common frame: A = R^T (L (x) I_2) R."""
    verts, faces = read_mesh(DATA / "grid" / "irr_poly_2.obj", dtype=torch.float64)
    verts = verts.to(device)
    A, M, frames = tv.connection_laplacian(verts, faces, method=method)
    L, M0 = tp.laplacian(verts, faces, method=method)
    assert torch.allclose(frames.normal.abs()[:, 2], torch.ones_like(verts[:, 0]))
    common_x = torch.zeros_like(verts)
    common_x[:, 0] = 1.0
    common_y = torch.linalg.cross(frames.normal, common_x, dim=1)
    common, _, _ = tv.connection_laplacian(
        verts, faces, method=method, frames=(frames.normal, common_x, common_y)
    )
    scalar = np.kron(to_scipy(L).toarray(), np.eye(2))
    np.testing.assert_allclose(to_scipy(common).toarray(), scalar, atol=1e-12)
    c = (frames.e_x * common_x).sum(1).cpu().numpy()
    s = (frames.e_x * common_y).sum(1).cpu().numpy()
    R = sl.block_diag(*[[[ci, -si], [si, ci]] for ci, si in zip(c, s, strict=True)])
    np.testing.assert_allclose(to_scipy(A).toarray(), R.T @ scalar @ R, atol=1e-12)
    np.testing.assert_allclose(to_scipy(M).diagonal(), np.repeat(M0.diagonal().cpu().numpy(), 2))


def test_change_of_frames_conjugates_the_operator(device):
    """Rotating vertex v's frame by alpha_v turns A into R^T A R with R the block rotation."""
    verts, faces = sphere("hex_2")
    verts = verts.to(device)
    A, _, frames = tv.connection_laplacian(verts, faces)
    alpha = torch.linspace(0, 5, verts.shape[0], dtype=torch.float64, device=device)
    c, s = torch.cos(alpha)[:, None], torch.sin(alpha)[:, None]
    rotated = (frames.normal, c * frames.e_x + s * frames.e_y, -s * frames.e_x + c * frames.e_y)
    B, _, _ = tv.connection_laplacian(verts, faces, frames=rotated)
    cos, sin = c[:, 0].cpu().numpy(), s[:, 0].cpu().numpy()
    R = sl.block_diag(*[[[ci, -si], [si, ci]] for ci, si in zip(cos, sin, strict=True)])
    np.testing.assert_allclose(to_scipy(B).toarray(), R.T @ to_scipy(A).toarray() @ R, atol=1e-12)


def lagrange_modules() -> tuple:
    """adobe-lagrange and its ``polyddg`` module; skips the test where it is not installed."""
    lagrange = pytest.importorskip(
        "lagrange", reason="adobe-lagrange not installed: pip install adobe-lagrange"
    )
    from lagrange import polyddg

    return lagrange, polyddg


def lagrange_curvatures(verts: torch.Tensor, faces: torch.Tensor) -> tuple:
    """``(kmin, kmax)``, each ``(V,)``, of the quad mesh by adobe-lagrange's
    ``compute_principal_curvatures`` (de Goes et al. 2020's adjoint shape operator)."""
    lagrange, polyddg = lagrange_modules()
    mesh = lagrange.SurfaceMesh()
    mesh.add_vertices(verts.numpy())
    mesh.add_quads(faces.numpy().astype(np.uint32))
    ids = polyddg.compute_principal_curvatures(mesh)
    return tuple(torch.from_numpy(mesh.attribute(i).data.copy()) for i in ids[:2])


@pytest.mark.parametrize("n", [1, 2, 4])
def test_equals_adobe_lagrange_on_triangles(n, device):
    """On triangles every polygon method is the cotangent Laplacian and our connection
    Laplacian is de Goes et al. 2020's vertex-based one: the spectra of adobe-lagrange's
    ``connection_laplacian_nrosy`` and ours agree to rounding (measured 6e-13 relative)."""
    lagrange, polyddg = lagrange_modules()
    verts, quads = tp.shapes.quad_sphere(4, noise=0.02, seed=1)
    faces = triangulated(verts, quads)
    mesh = lagrange.SurfaceMesh()
    mesh.add_vertices(verts.numpy())
    mesh.add_triangles(faces.numpy().astype(np.uint32))
    ops = polyddg.DifferentialOperators(mesh)
    peer = ops.connection_laplacian_nrosy(n=n).toarray()
    mass = np.repeat(ops.star0().diagonal(), 2)
    A, M, _ = tv.connection_laplacian(verts.to(device), faces, symmetry=n, method="degoes")
    np.testing.assert_allclose(to_scipy(M).diagonal(), mass, rtol=1e-12)
    ours = generalized_spectrum(A, M)
    theirs = sl.eigh(peer, np.diag(mass), eigvals_only=True)
    np.testing.assert_allclose(ours, theirs, atol=1e-9 * theirs.max())


@pytest.mark.parametrize("method", METHODS)
def test_gradcheck_connection_laplacian(method, device):
    """Values and mass differentiable in verts in the default frames (float64 gradcheck,
    non-planar mixed polygons with boundary), for vector and cross fields."""
    from conftest import hex_pent_mesh

    verts, faces = hex_pent_mesh()
    verts = verts.to(device)

    def values(v: torch.Tensor) -> torch.Tensor:
        A1, M, _ = tv.connection_laplacian(v, faces, method=method)
        A4, _, _ = tv.connection_laplacian(v, faces, method=method, symmetry=4)
        return torch.cat((A1.values(), A4.values(), M.diagonal()))

    assert torch.autograd.gradcheck(values, verts.clone().requires_grad_(True), fast_mode=True)


def test_folded_vertex_is_refused_by_name(device):
    verts = torch.tensor(
        [[0.0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [2, 0, 0], [2, 1, 0]],
        dtype=torch.float64,
        device=device,
    )
    faces = [[0, 1, 2, 3], [1, 4, 5, 2]]
    frames = list(tv.connection_laplacian(verts, faces)[2])
    frames[0] = frames[0].clone()
    frames[0][1] = -frames[0][1]  # vertex 1's normal against both its faces
    with pytest.raises(ValueError, match=r"face 0: the normal at its vertex 1"):
        tv.connection_laplacian(verts, faces, frames=frames)
    with pytest.raises(ValueError, match="symmetry must be a positive integer"):
        tv.connection_laplacian(verts, faces, symmetry=0)
    with pytest.raises(ValueError, match=r"frames.e_x must be a \(6, 3\)"):
        tv.connection_laplacian(verts, faces, frames=(frames[0], frames[1][:3], frames[2]))


# ---------------------------------------------------------------- vector heat method


def exact_transport(verts: torch.Tensor, s: int, vector: torch.Tensor) -> torch.Tensor:
    """Parallel transport on the unit sphere along the great circle from x_s: the rotation
    about x_s x x_v taking x_s to x_v."""
    return tv.minimal_rotation(verts[s].expand_as(verts), verts, vector.expand_as(verts))


def angle_errors(X: torch.Tensor, Y: torch.Tensor, verts: torch.Tensor) -> torch.Tensor:
    """Angles between the tangent parts (to the exact sphere) of two vector fields."""
    X = X - (X * verts).sum(1, keepdim=True) * verts
    Y = Y - (Y * verts).sum(1, keepdim=True) * verts
    cos = (X * Y).sum(1) / (X.norm(dim=1) * Y.norm(dim=1))
    return torch.arccos(cos.clamp(-1, 1))


def tangent_at(verts: torch.Tensor, s: int) -> torch.Tensor:
    v = torch.linalg.cross(verts[s], torch.tensor([0.3, 0.5, 0.8], dtype=verts.dtype))
    return v / v.norm()


def away_from_antipode(verts: torch.Tensor, s: int) -> torch.Tensor:
    return torch.arccos((verts @ verts[s]).clamp(-1, 1)) < 0.9 * np.pi


@pytest.mark.parametrize("name", SPHERES)
def test_transport_on_sphere_beats_potpourri3d(name):
    """Transport from three sources against the exact great-circle transport, beside
    potpourri3d's PolygonMeshHeatSolver: ours is at least as accurate in mean and max angle
    (measured ratios 0.3 to 0.03 on these meshes at the default t = 4 h^2)."""
    pp3d = pytest.importorskip(
        "potpourri3d", reason="potpourri3d not installed: pip install potpourri3d"
    )
    verts, faces = sphere(name)
    solver = tv.VectorHeatSolver(verts, faces)
    peer = pp3d.PolygonMeshHeatSolver(verts.numpy(), faces.tolist())
    bx, by, _ = peer.get_tangent_frames()
    ours, theirs = [], []
    for s in (0, verts.shape[0] // 3, verts.shape[0] // 2):
        vec = tangent_at(verts, s)
        keep = away_from_antipode(verts, s)
        exact = exact_transport(verts, s, vec)
        X = solver.transport(s, vec)
        # the length of the vector's part tangent at the source, everywhere
        assert torch.allclose(X.norm(dim=1), X[s].norm(), atol=1e-9)
        ours.append(angle_errors(X, exact, verts)[keep])
        c = peer.transport_tangent_vectors([s], [[vec.numpy() @ bx[s], vec.numpy() @ by[s]]])
        Xp = torch.from_numpy(c[:, :1] * bx + c[:, 1:] * by)
        theirs.append(angle_errors(Xp, exact, verts)[keep])
    ours_, theirs_ = torch.cat(ours), torch.cat(theirs)
    assert ours_.mean() <= theirs_.mean() and ours_.max() <= theirs_.max()
    assert ours_.mean() < 0.03


def test_transport_on_cube_sphere_is_close_to_exact(device):
    """In-repo mesh: mean angle error below 0.02 rad (measured 0.012 on the 10 x 10 cube
    sphere), and the transported vector at the source is the given one."""
    verts, faces = tp.shapes.quad_sphere(10)
    solver = tv.VectorHeatSolver(verts.to(device), faces)
    s = 7
    vec = 2.5 * tangent_at(verts, s)
    X = solver.transport(s, vec.to(device))
    assert X.device.type == device.type
    X = X.cpu()
    err = angle_errors(X, exact_transport(verts, s, vec), verts)[away_from_antipode(verts, s)]
    assert err.mean() < 0.02
    n = solver.frames.normal[s].cpu()
    tangent = vec - (vec @ n) * n  # the part of vec tangent at the source
    torch.testing.assert_close(X.norm(dim=1), tangent.norm().expand(len(X)))
    torch.testing.assert_close(X[s], tangent, atol=1e-3, rtol=0)


def test_transport_from_two_sources_follows_the_nearest(device):
    """Each vertex receives the transport of the nearer source's vector (SSC19 sec. 5), away
    from the border where the two diffused fields blend (measured mean angle error 0.010 for
    |z| > 0.5 with the poles as sources; 0.0006 from one source alone). Lengths blend too:
    with lengths 1 and 3 the length stays within 6% of the nearer source's for |z| > 0.5."""
    verts, faces = tp.shapes.quad_sphere(10)
    north = int(torch.argmax(verts[:, 2]))
    south = int(torch.argmin(verts[:, 2]))
    vecs = torch.stack((tangent_at(verts, north), -tangent_at(verts, south)))
    vecs[1] = 3 * vecs[1]
    X = tv.VectorHeatSolver(verts.to(device), faces).transport([north, south], vecs.to(device))
    X = X.cpu()
    for s, vec, side in ((north, vecs[0], verts[:, 2] > 0.5), (south, vecs[1], verts[:, 2] < -0.5)):
        exact = exact_transport(verts, s, vec)
        assert angle_errors(X, exact, verts)[side].mean() < 0.02
        assert torch.allclose(X[side].norm(dim=1), X[s].norm(), rtol=0.07)
    assert abs(float(X[south].norm()) - 3.0) < 1e-3 and abs(float(X[north].norm()) - 1.0) < 1e-3


@pytest.mark.parametrize("name, bound", [("quad_3", 0.06), ("hex_3", 0.03), ("voronoi_3", 0.12)])
def test_log_map_on_sphere(name, bound, device):
    """The log map at s on the unit sphere is arccos(x_s . x) times the unit tangent at x_s
    of the great circle towards x: mean error over the vertices (away from the antipode)
    within the bound (measured 0.045, 0.012, 0.095 over six sources)."""
    verts, faces = sphere(name)
    solver = tv.VectorHeatSolver(verts.to(device), faces)
    sources = [0, verts.shape[0] // 3, verts.shape[0] // 2]
    logs = solver.log_map(sources)
    assert logs.shape == (verts.shape[0], 3, 2) and logs.device.type == device.type
    logs = logs.cpu()
    for q, s in enumerate(sources):
        e_x, e_y = solver.frames.e_x[s].cpu(), solver.frames.e_y[s].cpu()
        ours = logs[:, q, :1] * e_x + logs[:, q, 1:] * e_y
        d = torch.arccos((verts @ verts[s]).clamp(-1, 1))
        towards = verts - (verts @ verts[s])[:, None] * verts[s]
        exact = towards / towards.norm(dim=1, keepdim=True).clamp_min(1e-300) * d[:, None]
        keep = away_from_antipode(verts, s)
        assert (ours - exact).norm(dim=1)[keep].mean() < bound
        assert logs[s, q].abs().max() == 0
    torch.testing.assert_close(solver.log_map(sources[1]).cpu(), logs[:, 1])


@pytest.mark.parametrize("method", METHODS)
def test_vector_heat_method_builds_every_system_with_that_laplacian(method, device):
    """``method=`` reaches both systems: ``M + t A`` is built from
    ``connection_laplacian(method=...)`` and the scalar ``M0 + t L`` from
    ``laplacian(method=...)`` (dense comparison); and with every method transport, log map and
    the radius are accurate on three unit spheres against the great-circle closed forms (mean
    transport angle measured 0.002-0.023 rad, log map 0.016-0.11, distance 1.3%-4.9%)."""
    verts, faces = sphere("hex_3")
    verts = verts.to(device)
    solver = tv.VectorHeatSolver(verts, faces, method=method)
    assert solver.method == method and solver.geodesic.method == method
    A, M, _ = tv.connection_laplacian(verts, faces, method=method)
    L, M0 = tp.laplacian(verts, faces, method=method)
    t = solver.t
    np.testing.assert_allclose(
        to_scipy(solver.vector_operator).toarray(), to_scipy(M + t * A).toarray(), atol=1e-12
    )
    np.testing.assert_allclose(
        to_scipy(solver.geodesic.heat_operator).toarray(),
        to_scipy(M0 + t * L).toarray(),
        atol=1e-12,
    )
    for name in ("quad_3", "voronoi_3", "concave_3"):
        verts, faces = sphere(name)
        solver = tv.VectorHeatSolver(verts.to(device), faces, method=method)
        s = verts.shape[0] // 3
        vec, keep = tangent_at(verts, s), away_from_antipode(verts, s)
        X = solver.transport(s, vec.to(device)).cpu()
        assert angle_errors(X, exact_transport(verts, s, vec), verts)[keep].mean() < 0.04
        log = solver.log_map(s).cpu()
        e_x, e_y = solver.frames.e_x[s].cpu(), solver.frames.e_y[s].cpu()
        ours = log[:, :1] * e_x + log[:, 1:] * e_y
        d = torch.arccos((verts @ verts[s]).clamp(-1, 1))
        towards = verts - (verts @ verts[s])[:, None] * verts[s]
        exact = towards / towards.norm(dim=1, keepdim=True).clamp_min(1e-300) * d[:, None]
        assert (ours - exact).norm(dim=1)[keep].mean() < 0.15
        radius = solver.geodesic.distance([s]).cpu()
        assert ((radius - d).abs() / d.clamp_min(1e-12))[d > 0].mean() < 0.07
        torch.testing.assert_close(
            tp.heat_geodesic_distance(verts.to(device), faces, [s], method=method).cpu(), radius
        )


def test_vector_heat_unknown_method_is_refused():
    verts, faces = tp.shapes.quad_sphere(2)
    with pytest.raises(ValueError, match="method must be one of 'aw11', 'plms', 'degoes'"):
        tv.VectorHeatSolver(verts, faces, method="cotan")


def test_vector_heat_gradcheck(device):
    """Transport and log map are differentiable in verts (float64 gradcheck, 26 vertices)."""
    verts, faces = tp.shapes.quad_sphere(2, noise=0.05, seed=2)
    vec = tangent_at(verts, 3).to(device)
    verts = verts.to(device)

    def transport(v: torch.Tensor) -> torch.Tensor:
        return tv.VectorHeatSolver(v, faces).transport(3, vec)

    def log_map(v: torch.Tensor) -> torch.Tensor:
        return tv.VectorHeatSolver(v, faces).log_map(3)[torch.arange(26, device=device) != 3]

    x = verts.clone().requires_grad_(True)
    assert torch.autograd.gradcheck(transport, x, atol=1e-7, fast_mode=True)
    assert torch.autograd.gradcheck(log_map, x, atol=1e-7, fast_mode=True)


def test_vector_heat_errors_name_the_problem(device):
    verts, faces = tp.shapes.quad_sphere(2, device=device)
    solver = tv.VectorHeatSolver(verts, faces)
    with pytest.raises(ValueError, match="no part tangent"):
        solver.transport(0, verts[0])
    with pytest.raises(ValueError, match=r"vectors must have shape \(3,\) or \(2, 3\)"):
        solver.transport([0, 1], torch.ones(3, 3, dtype=verts.dtype, device=device))
    with pytest.raises(ValueError, match="out of range|outside"):
        solver.log_map(26)
    with pytest.raises(ValueError, match="empty"):
        solver.transport([], torch.zeros(0, 3, device=device))


# ---------------------------------------------------------------- curvature


def torus_curvatures(verts: torch.Tensor, major: float, minor: float) -> tuple:
    """Closed form: 1 / minor around the tube, cos v / (major + minor cos v) along it."""
    cos_v = (verts[:, :2].norm(dim=1) - major) / minor
    k1 = torch.full_like(cos_v, 1 / minor)
    k2 = cos_v / (major + minor * cos_v)
    return torch.minimum(k1, k2), torch.maximum(k1, k2)


def test_principal_curvatures_of_the_torus_converge(device):
    """Against the closed form on tori of quads: the max error falls about 4x per halving of
    h (measured 0.191, 0.048, 0.012), and the directions follow the parameter lines."""
    errors = []
    for n in (24, 48):
        verts, faces = tp.shapes.torus(n, n // 2, major=1.0, minor=0.4)
        curvatures = tv.principal_curvatures(verts.to(device), faces)
        assert curvatures[0].device.type == device.type
        kmin, kmax, dmin, dmax = (c.cpu() for c in curvatures)
        emin, emax = torus_curvatures(verts, 1.0, 0.4)
        errors.append(max(float((kmin - emin).abs().max()), float((kmax - emax).abs().max())))
        # kmax = 1 / minor: its direction goes around the tube, orthogonal to the azimuth
        azimuth = torch.stack((-verts[:, 1], verts[:, 0], 0 * verts[:, 0]), 1)
        azimuth = azimuth / azimuth.norm(dim=1, keepdim=True)
        assert (dmax * azimuth).sum(1).abs().max() < 0.05
        assert (dmin * azimuth).sum(1).abs().min() > 0.99
    assert errors[0] < 0.2 and errors[1] < errors[0] / 3.5


def test_principal_curvatures_close_to_lagrange_on_torus(device):
    """adobe-lagrange's ``compute_principal_curvatures`` (de Goes et al. 2020's adjoint shape
    operator) on the same torus: both within 2x of each other's error (measured 0.048 ours,
    0.027 lagrange at 48 x 24), and the curvatures agree to 0.05 on average (measured 0.012
    and 0.027)."""
    verts, faces = tp.shapes.torus(48, 24, major=1.0, minor=0.4)
    lmin, lmax = lagrange_curvatures(verts, faces)
    kmin, kmax, _, _ = (c.cpu() for c in tv.principal_curvatures(verts.to(device), faces))
    emin, emax = torus_curvatures(verts, 1.0, 0.4)
    ours = max(float((kmin - emin).abs().max()), float((kmax - emax).abs().max()))
    theirs = max(float((lmin - emin).abs().max()), float((lmax - emax).abs().max()))
    assert ours < 2 * theirs
    assert float((kmin - lmin).abs().mean()) < 0.05 and float((kmax - lmax).abs().mean()) < 0.05


def jittered_torus(n: int, major: float = 1.0, minor: float = 0.4) -> tuple:
    """The ``n x n/2`` torus of quads with every vertex moved by up to a fifth of the tube's edge
    length along each axis, then put back on the torus (closest point): irregular, non-planar
    quads on an exactly known surface."""
    verts, faces = tp.shapes.torus(n, n // 2, major=major, minor=minor)
    h = 2 * np.pi * minor / (n // 2)
    g = torch.Generator().manual_seed(0)
    x = verts + 0.2 * h * (2 * torch.rand(verts.shape, generator=g, dtype=verts.dtype) - 1)
    rho = x[:, :2].norm(dim=1)
    tube = torch.stack((rho - major, x[:, 2]), 1)
    tube = minor * tube / tube.norm(dim=1, keepdim=True)
    return torch.cat((x[:, :2] * ((major + tube[:, :1]) / rho[:, None]), tube[:, 1:]), 1), faces


def torus_error(kmin: torch.Tensor, kmax: torch.Tensor, verts: torch.Tensor) -> torch.Tensor:
    emin, emax = torus_curvatures(verts, 1.0, 0.4)
    return torch.cat(((kmin - emin).abs(), (kmax - emax).abs()))


def test_principal_curvatures_converge_on_an_irregular_torus(device):
    """Irregular quads on a non-umbilic surface: the curvatures converge (mean error measured
    0.053 at 32 x 16 and 0.017 at 64 x 32, max 0.23 and 0.14), while those from the
    area-weighted normals do not (mean 0.086 and 0.078): the first-order normals' error does not
    shrink under refinement, and differentiating them leaves an O(1) error."""
    mean, worst, area_normals = [], [], []
    for n in (32, 64):
        verts, faces = jittered_torus(n)
        on = verts.to(device)
        kmin, kmax, _, _ = (c.cpu() for c in tv.principal_curvatures(on, faces))
        error = torus_error(kmin, kmax, verts)
        mean.append(float(error.mean()))
        worst.append(float(error.max()))
        frames = tv.tangent_frames(on, tp.build_topology(faces, verts.shape[0]))
        kmin0, kmax0, _, _ = (c.cpu() for c in tv.principal_curvatures(on, faces, frames))
        area_normals.append(float(torus_error(kmin0, kmax0, verts).mean()))
    assert mean[1] < mean[0] / 2.5 and mean[1] < 0.025
    assert worst[1] < worst[0] and worst[1] < 0.2
    assert area_normals[1] > 0.8 * area_normals[0] and area_normals[1] > 3 * mean[1]


def test_principal_curvatures_beside_lagrange_on_an_irregular_torus(device):
    """adobe-lagrange's polygon shape operator uses first-order vertex normals too and does not
    converge on irregular quads (mean error measured 0.096 at 32 x 16 and 0.095 at 64 x 32);
    ours is below a third of it at 64 x 32 (measured 0.017)."""
    verts, faces = jittered_torus(64)
    lmin, lmax = lagrange_curvatures(verts, faces)
    kmin, kmax, _, _ = (c.cpu() for c in tv.principal_curvatures(verts.to(device), faces))
    ours = float(torus_error(kmin, kmax, verts).mean())
    assert ours < float(torus_error(lmin, lmax, verts).mean()) / 3


def test_fitted_normals_are_second_order(device):
    """On the irregular tori the fitted normals' mean angle error falls about 4x per halving
    of h (second order; measured 0.0195 and 0.0051 rad), the area-weighted normals' about 2x
    (first order; 0.046 and 0.024)."""
    fitted, area = [], []
    for n in (32, 64):
        verts, faces = jittered_torus(n)
        rho = verts[:, :2].norm(dim=1, keepdim=True)
        exact = torch.cat((verts[:, :2] * (1 - 1.0 / rho), verts[:, 2:]), 1) / 0.4
        on = verts.to(device)
        for out, on_device in (
            (fitted, tv.fitted_frames(on, faces)),
            (area, tv.tangent_frames(on, tp.build_topology(faces, verts.shape[0]))),
        ):
            assert on_device.normal.device.type == device.type
            frames = tv.TangentFrames(*(f.cpu() for f in on_device))
            out.append(float(torch.arccos((frames.normal * exact).sum(1).clamp(-1, 1)).mean()))
            torch.testing.assert_close(frames.e_y, torch.linalg.cross(frames.normal, frames.e_x))
            torch.testing.assert_close(
                (frames.normal * frames.e_x).sum(1), torch.zeros_like(rho[:, 0])
            )
    assert fitted[1] < fitted[0] / 3.2 and fitted[1] < area[1] / 3
    assert area[1] > area[0] / 2.8


def test_fitted_normals_on_a_plane_and_on_boundaries(device):
    """A tilted planar grid of irregular polygons: the fitted normals are the plane's at every
    vertex, boundary corners included (rings too small or too one-sided for a quadric), and the
    curvatures vanish."""
    verts, faces = read_mesh(DATA / "grid" / "irr_poly_3.obj", dtype=torch.float64)
    tilt = torch.tensor([[1.0, 0.3, -0.2], [0.1, 0.9, 0.4], [-0.3, 0.2, 1.1]], dtype=verts.dtype)
    q, _ = torch.linalg.qr(tilt)
    verts = (verts @ q.T).to(device)
    frames = tv.fitted_frames(verts, faces)
    plane = q[:, 2].to(device)
    assert float((frames.normal @ plane).abs().min()) > 1 - 1e-12
    kmin, kmax, _, _ = tv.principal_curvatures(verts, faces)
    assert float(torch.cat((kmin, kmax)).abs().max()) < 1e-9


SPHERE_FAMILIES = ("concave", "hex", "hex_cos", "hex_noise", "quad", "triangle", "voronoi")


@pytest.mark.parametrize("family", SPHERE_FAMILIES)
def test_principal_curvatures_on_every_sphere_family_at_level_4(family, device):
    """Within 2% of 1 on average at level 4 of every unit-sphere family (measured below 0.2%
    everywhere; with the area-weighted normals 5.2% on hex_noise and 12.8% on voronoi). The
    sign follows the orientation (hex_cos is oriented inwards), found from the signed volume."""
    verts, faces = load(shared_path(f"sphere/{family}_4.obj"))
    verts = verts / verts.norm(dim=1, keepdim=True)
    topo = tp.build_topology(faces, verts.shape[0], warn=False)
    # signed volume: sum over faces of (vector area . centroid) / 3
    face = torch.repeat_interleave(torch.arange(topo.num_faces), topo.faces.sizes)
    centroid = (
        torch.zeros(topo.num_faces, 3, dtype=verts.dtype).index_add(
            0, face, verts[topo.faces.indices]
        )
        / topo.faces.sizes[:, None]
    )
    sign = float(torch.sign((tp.vector_area(verts, topo) * centroid).sum()))
    kmin, kmax, _, _ = (c.cpu() for c in tv.principal_curvatures(verts.to(device), topo))
    error = (sign * torch.cat((kmin, kmax)) - 1).abs()
    assert float(error.mean()) < 0.02
    assert float(error.max()) < 0.1


def test_principal_curvatures_of_the_sphere(device):
    """About 1 on the unit sphere (outward normals), the sign flipping with the orientation; scale
    1 / R on a sphere of radius R."""
    verts, faces = tp.shapes.quad_sphere(12, device=device)
    kmin, kmax, _, _ = tv.principal_curvatures(verts, faces)
    # measured mean |k - 1|: 0.020 (the cube corners, valence 3, are worst: 0.11)
    assert (kmin - 1).abs().mean() < 0.03 and (kmax - 1).abs().mean() < 0.03
    kmin3, kmax3, _, _ = tv.principal_curvatures(3 * verts, faces)
    torch.testing.assert_close(kmax3, kmax / 3)
    kmin_f, kmax_f, _, _ = tv.principal_curvatures(verts, faces.flip(1))
    torch.testing.assert_close(kmax_f, -kmin)
    S, frames = tv.shape_operator(verts, faces)
    torch.testing.assert_close(S, S.transpose(1, 2))
    assert S.shape == (verts.shape[0], 2, 2)


def test_curvature_gradcheck(device):
    verts, faces = tp.shapes.torus(6, 4, major=1.0, minor=0.4)
    verts = verts + 0.02 * torch.randn(
        verts.shape, generator=torch.Generator().manual_seed(0), dtype=verts.dtype
    )
    verts = verts.to(device)

    def curvatures(v: torch.Tensor) -> torch.Tensor:
        kmin, kmax, dmin, dmax = tv.principal_curvatures(v, faces)
        return torch.cat((kmin, kmax, dmax.abs().sum(1)))

    x = verts.clone().requires_grad_(True)
    assert torch.autograd.gradcheck(curvatures, x, fast_mode=True)


# ---------------------------------------------------------------- direction fields


@pytest.mark.parametrize("n", [1, 2, 4])
def test_smoothest_field_on_a_plane_is_constant(n, device):
    """A planar grid of irregular polygons carries parallel fields: the smoothest n-direction
    field has zero energy and one direction everywhere (mod 2 pi / n)."""
    verts, faces = read_mesh(DATA / "grid" / "voronoi_3.obj", dtype=torch.float64, device=device)
    directions, magnitude, energy = tv.smoothest_field(verts, faces, n)
    assert directions.device.type == device.type
    assert abs(float(energy)) < 1e-8
    angle = torch.atan2(directions[:, 1], directions[:, 0]) * n
    assert float(torch.cos(angle - angle[0]).min()) > 1 - 1e-8
    torch.testing.assert_close(magnitude, magnitude.mean().expand_as(magnitude))


def test_polar_matches_atan2_and_hypot_with_finite_gradients_at_the_origin(device):
    """The field's angle and length are atan2 and hypot (values, and gradients by gradcheck
    away from the origin); at an exact zero, where both have 0/0 derivatives that autograd
    makes NaN, the angle and length are 0 with a zero gradient, in plain autograd and in
    torch.func alike."""
    from torch_polylap.vector.fields import polar

    g = torch.Generator().manual_seed(3)
    x, y = torch.randn(2, 50, generator=g, dtype=torch.float64).to(device)
    x[:3], y[:3] = torch.tensor([0.0, 0.0, 1e-300]), torch.tensor([0.0, -0.0, 0.0])
    angle, length = polar(x, y)
    away = slice(3, None)
    torch.testing.assert_close(angle[away], torch.atan2(y, x)[away], rtol=0, atol=0)
    torch.testing.assert_close(length[away], torch.hypot(x, y)[away], rtol=0, atol=0)
    assert angle[:2].eq(0).all() and length[:2].eq(0).all()
    inputs = (x[away].clone().requires_grad_(), y[away].clone().requires_grad_())
    assert torch.autograd.gradcheck(polar, inputs)
    xg, yg = x.clone().requires_grad_(), y.clone().requires_grad_()
    angle, length = polar(xg, yg)
    (angle.sum() + length.sum()).backward()
    assert xg.grad is not None and yg.grad is not None
    assert torch.isfinite(xg.grad).all() and torch.isfinite(yg.grad).all()
    assert xg.grad[:2].eq(0).all() and yg.grad[:2].eq(0).all()
    gx, gy = torch.func.grad(lambda a, b: sum(t.sum() for t in polar(a, b)), argnums=(0, 1))(x, y)
    torch.testing.assert_close((gx, gy), (xg.grad, yg.grad))


def test_smoothest_field_energy_on_sphere(device):
    """On the sphere no field is parallel: the energy is the spectrum's bottom, l (l + 1) - n^2
    at l = n (cross fields: 4, measured 4.19 on 6 x 6)."""
    verts, faces = tp.shapes.quad_sphere(6, device=device)
    _, magnitude, energy = tv.smoothest_field(verts, faces, 4)
    assert magnitude.device.type == device.type
    assert abs(float(energy) - 4.0) < 0.3

"""The default vertex frames (``torch_polylap.tangent``) are smooth functions of the positions.

Every frame-dependent result (the connection Laplacian, parallel transport, the log map, the
vector layers, the tangent gradient operators) must have the derivative autograd reports: a
frame that switched its tangent axis with the data (the coordinate axis least aligned with the
normal, as the frames once did) makes central differences grow like ``1 / h`` at vertices in
symmetric positions (normal components that tie), while autograd sees a smooth function. The
meshes here are full of such vertices: cube and icosahedral spheres, a planar and a bent grid,
a torus, the Schwarz lantern and a CAD-like part.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import pytest
import torch
from conftest import DATA
from meshes import read_mesh

import torch_polylap as tp
import torch_polylap.vector as tv

D64 = torch.float64
STEPS = (1e-3, 1e-4, 1e-5)


def icosphere() -> tuple[torch.Tensor, torch.Tensor]:
    import trimesh  # a dependency of the package

    mesh = trimesh.creation.icosphere(subdivisions=1)
    return torch.tensor(mesh.vertices, dtype=D64), torch.tensor(mesh.faces, dtype=torch.int64)


def tetris() -> tuple[torch.Tensor, tp.PolygonFaces]:
    return read_mesh(DATA / "tetris.obj", dtype=D64)


MESHES: dict[str, Callable[[], tuple[torch.Tensor, object]]] = {
    "quad sphere level 2": lambda: read_mesh(DATA / "sphere" / "quad_2.obj", dtype=D64),
    "cube sphere": lambda: tp.shapes.quad_sphere(3),
    "icosphere": icosphere,
    "planar grid": lambda: tp.shapes.quad_grid(4),
    "bent grid": lambda: tp.shapes.quad_grid(4, height=lambda x, y: 0.6 * x * x - 0.3 * y),
    "torus": lambda: tp.shapes.torus(8, 6),
    "lantern": lambda: tp.shapes.schwarz_lantern(8, 4),
    "tetris (CAD-like)": tetris,
}
# the heat solvers take a few solves per evaluation: a subset with every kind of symmetry
HEAT_MESHES = ("cube sphere", "icosphere", "bent grid", "torus")


def assert_smooth(f: Callable[[torch.Tensor], torch.Tensor], verts: torch.Tensor) -> None:
    """Autograd's directional derivative of ``f`` along a random unit direction agrees with
    central differences at every step of :data:`STEPS` (relative to the gradient's norm), and
    the agreement does not degrade as the step shrinks (a jump would grow like ``1 / h``)."""
    g = torch.Generator().manual_seed(7)
    x = verts.detach().clone().requires_grad_(True)
    (grad,) = torch.autograd.grad(f(x), x)
    direction = torch.randn(verts.shape, generator=g, dtype=D64)
    direction = direction / direction.norm()
    exact = float((grad * direction).sum())
    scale = max(float(grad.norm()), 1e-12)
    errors = []
    with torch.no_grad():
        for h in STEPS:
            fd = (f(verts + h * direction) - f(verts - h * direction)) / (2 * h)
            errors.append(abs(float(fd) - exact) / scale)
    assert max(errors) < 1e-5, dict(zip(STEPS, errors, strict=True))
    assert errors[-1] <= 10 * errors[0] + 1e-8, dict(zip(STEPS, errors, strict=True))


def weights(shape: tuple[int, ...], seed: int = 3) -> torch.Tensor:
    return torch.randn(shape, generator=torch.Generator().manual_seed(seed), dtype=D64)


@pytest.fixture(params=list(MESHES))
def mesh(request) -> tuple[str, torch.Tensor, tp.Topology]:
    verts, faces = MESHES[request.param]()
    verts = verts.to(D64)
    return request.param, verts, tp.get_topology(faces, verts.shape[0])


def test_frames_are_smooth(mesh):
    _, verts, topo = mesh
    w = weights((verts.shape[0], 3, 3))
    assert_smooth(lambda v: (torch.stack(tv.tangent_frames(v, topo), 1) * w).sum(), verts)


def test_connection_laplacian_is_smooth(mesh):
    _, verts, topo = mesh
    y = weights((2 * verts.shape[0],))
    assert_smooth(lambda v: (y * (tv.connection_laplacian(v, topo)[0] @ y)).sum(), verts)


def test_tangent_gradient_operators_are_smooth(mesh):
    _, verts, topo = mesh
    u, w = weights((verts.shape[0],)), weights((verts.shape[0],), seed=4)
    assert_smooth(
        lambda v: sum((w * (g @ u)).sum() for g in tp.tangent.vertex_gradient_operators(v, topo)),
        verts,
    )


def test_vector_diffusion_layer_is_smooth(mesh):
    _, verts, topo = mesh
    n = verts.shape[0]
    layer = tp.nn.LearnedVectorDiffusion(3).double()
    x, w = weights((n, 3, 2)), weights((n, 3, 2), seed=5)

    def f(v: torch.Tensor) -> torch.Tensor:
        A, M, _ = tv.connection_laplacian(v, topo)
        return (w * layer(x, A, M)).sum()

    assert_smooth(f, verts)


@pytest.mark.parametrize("name", HEAT_MESHES)
def test_parallel_transport_and_log_map_are_smooth(name):
    """Weighted near the source and off the cut locus only: towards the cut locus the diffused
    field decays to round-off (1e-19 of its peak at the antipode of a sphere), and where the
    distance has a critical point (the far side of the torus' tube) the log map's direction is
    undefined: noise for central differences and autograd alike."""
    verts, faces = MESHES[name]()
    verts = verts.to(D64)
    topo = tp.get_topology(faces, verts.shape[0])
    n = verts.shape[0]
    dist = tp.heat_geodesic_distance(verts, topo, [0])
    gx, gy = tp.tangent.vertex_gradient_operators(verts, topo)
    slope = torch.hypot(gx @ dist, gy @ dist)  # frame-invariant
    near = (dist > 0) & (dist < 0.35 * float(dist.max())) & (slope > 0.1)
    near = near.to(D64)[:, None]
    w = weights((n, 3)) * near
    assert_smooth(
        lambda v: (w * tv.VectorHeatSolver(v, topo).transport(0, [0.3, -0.2, 0.5])).sum(), verts
    )
    w2 = weights((n, 2), seed=6) * near
    assert_smooth(lambda v: (w2 * tv.VectorHeatSolver(v, topo).log_map(0)).sum(), verts)


def test_frames_turn_with_the_mesh(mesh):
    """The frames come from the mesh alone (no coordinate axis): rotating the mesh rotates
    them."""
    _, verts, topo = mesh
    a, b = 0.7, -1.1
    ca, sa, cb, sb = math.cos(a), math.sin(a), math.cos(b), math.sin(b)
    Rz = torch.tensor([[ca, -sa, 0], [sa, ca, 0], [0, 0, 1]], dtype=D64)
    Rx = torch.tensor([[1, 0, 0], [0, cb, -sb], [0, sb, cb]], dtype=D64)
    R = Rz @ Rx
    frames = tv.tangent_frames(verts, topo)
    turned = tv.tangent_frames(verts @ R.T, topo)
    for ours, theirs in zip(frames, turned, strict=True):
        torch.testing.assert_close(theirs, ours @ R.T, atol=1e-12, rtol=0)


def test_frames_are_orthonormal_with_the_area_weighted_normal(mesh):
    _, verts, topo = mesh
    normal, e_x, e_y = tv.tangent_frames(verts, topo)
    stack = torch.stack((e_x, e_y, normal), 1)  # (V, 3, 3)
    eye = torch.eye(3, dtype=D64).expand_as(stack)
    torch.testing.assert_close(stack @ stack.transpose(1, 2), eye, atol=1e-12, rtol=0)
    torch.testing.assert_close(torch.linalg.cross(normal, e_x, dim=1), e_y, atol=1e-12, rtol=0)
    # the normal: the normalized sum of the vector areas of the faces around each vertex
    area = tp.vector_area(verts, topo)
    summed = torch.zeros_like(verts).index_add(0, topo.faces.indices, area[topo.faces.corner_face])
    torch.testing.assert_close(normal, summed / summed.norm(dim=1, keepdim=True))


def test_e_x_is_the_first_outgoing_edge_projected():
    """On a grid, vertex v's first corner is in the first face that holds it, and e_x is the
    tangent part of the edge to the next corner of that face, normalized."""
    verts, faces = tp.shapes.quad_grid(3, height=lambda x, y: 0.4 * x * y)
    faces_t = torch.as_tensor(faces)
    normal, e_x, _ = tp.tangent.vertex_tangent_frames(verts, faces)
    for v in range(verts.shape[0]):
        f, i = (int(k) for k in torch.nonzero(faces_t == v)[0])
        w = int(faces_t[f, (i + 1) % faces_t.shape[1]])
        edge = verts[w] - verts[v]
        tangent = edge - (edge @ normal[v]) * normal[v]
        torch.testing.assert_close(e_x[v], tangent / tangent.norm(), atol=1e-14, rtol=0)


def test_a_degenerate_reference_edge_falls_back_to_the_other_edge_of_the_corner():
    """A zero-length first outgoing edge (two vertices at one point) has no tangent direction:
    e_x comes from the other edge of the same corner."""
    verts = torch.tensor(
        [[0.0, 0, 0], [0, 0, 0], [1, 1, 0.1], [0, 1, 0], [1, -0.2, 0.2]], dtype=D64
    )
    faces = [[0, 1, 2, 3], [1, 4, 2]]  # vertex 0's first edge runs to vertex 1, at its position
    normal, e_x, e_y = tp.tangent.vertex_tangent_frames(verts, faces)
    assert torch.isfinite(torch.stack((normal, e_x, e_y))).all()
    edge = verts[3] - verts[0]  # the previous corner of vertex 0's first face
    tangent = edge - (edge @ normal[0]) * normal[0]
    torch.testing.assert_close(e_x[0], tangent / tangent.norm(), atol=1e-14, rtol=0)
    # the choice is the one left to the positions: where the edge has a length again (the
    # two vertices apart) it is the reference, so there is no derivative across; but the
    # gradient here is that of the fallback, finite
    x = verts.clone().requires_grad_(True)
    (tp.tangent.vertex_tangent_frames(x, faces).e_x * weights((5, 3))).sum().backward()
    assert x.grad is not None and torch.isfinite(x.grad).all()


@pytest.mark.filterwarnings("ignore:the mesh .* is not a consistently oriented")  # on purpose
def test_isolated_vertices_keep_the_fixed_frame():
    verts = torch.tensor([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [5, 5, 5]], dtype=D64)
    normal, e_x, e_y = tp.tangent.vertex_tangent_frames(verts, [[0, 1, 2]])
    torch.testing.assert_close(normal[3], torch.tensor([0.0, 0, 1], dtype=D64))
    torch.testing.assert_close(e_x[3], torch.tensor([1.0, 0, 0], dtype=D64))
    torch.testing.assert_close(e_y[3], torch.tensor([0.0, 1, 0], dtype=D64))

"""The generated meshes of torch_polylap.shapes: counts, topology, orientation and geometry.

Edges, Euler characteristics and boundaries are counted here from the face lists with numpy,
independently of torch_polylap.topology, and then compared with what the Topology reports.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

import torch_polylap as tp
from torch_polylap.shapes import quad_cube, quad_grid, quad_sphere, schwarz_lantern, torus


def face_lists(faces) -> list[list[int]]:
    return faces.tolist() if isinstance(faces, torch.Tensor) else [list(f) for f in faces]


def counts(verts: torch.Tensor, faces) -> dict:
    """V, E, F, the Euler characteristic and the boundary edges, from the face lists alone."""
    polys = face_lists(faces)
    half = [(f[i], f[(i + 1) % len(f)]) for f in polys for i in range(len(f))]
    undirected: dict[tuple[int, int], int] = {}
    for a, b in half:
        key = (min(a, b), max(a, b))
        undirected[key] = undirected.get(key, 0) + 1
    boundary = sorted(e for e, uses in undirected.items() if uses == 1)
    V, E, F = verts.shape[0], len(undirected), len(polys)
    return {
        "V": V,
        "E": E,
        "F": F,
        "chi": V - E + F,
        "boundary": boundary,
        "max_uses": max(undirected.values()),
        "oriented": len(set(half)) == len(half),  # no directed edge twice
    }


def check_topology(verts: torch.Tensor, faces, chi: int, boundary_edges: int) -> None:
    c = counts(verts, faces)
    assert c["chi"] == chi and len(c["boundary"]) == boundary_edges
    assert c["max_uses"] <= 2 and c["oriented"]
    topo = tp.build_topology(faces, verts.shape[0])
    assert topo.euler_characteristic() == chi and topo.num_edges == c["E"]
    assert topo.boundary_edges.shape[0] == boundary_edges
    assert topo.is_manifold and topo.is_oriented
    assert topo.connected_components()[0] == 1
    used = np.unique(np.concatenate([np.asarray(f) for f in face_lists(faces)]))
    assert np.array_equal(used, np.arange(verts.shape[0]))  # no unused vertex


# ------------------------------------------------------------------------------- quad_grid


@pytest.mark.parametrize("n, m", [(1, 1), (3, 3), (4, 2), (2, 5)])
def test_quad_grid_is_a_disk_with_the_expected_counts(n, m, device):
    verts, faces = quad_grid(n, m, device=device)
    assert verts.shape == ((n + 1) * (m + 1), 3) and faces.shape == (n * m, 4)
    assert faces.dtype == torch.int64 and verts.dtype == torch.float64
    assert verts.device.type == device.type
    check_topology(verts, faces, chi=1, boundary_edges=2 * (n + m))
    # flat, covering the unit square once, counter-clockwise seen from +z
    assert torch.equal(verts[:, 2], torch.zeros_like(verts[:, 2]))
    assert float(tp.face_areas(verts, faces).sum()) == pytest.approx(1.0, rel=1e-14)
    assert bool((tp.face_normals(verts, faces)[:, 2] > 0.999).all())
    # vertex (i, j) at index i (m + 1) + j, on the lattice
    i, j = 1, m - 1
    assert verts[i * (m + 1) + j, :2].tolist() == pytest.approx([i / n, j / m], abs=1e-15)


def test_quad_grid_extent_bump_height_and_dtype(device):
    verts, faces = quad_grid(4, 3, extent=(-1.0, 3.0, 2.0, 2.5), device=device)
    assert verts[:, 0].min() == -1.0 and verts[:, 0].max() == 3.0
    assert verts[:, 1].min() == 2.0 and verts[:, 1].max() == 2.5
    assert float(tp.face_areas(verts, faces).sum()) == pytest.approx(4.0 * 0.5, rel=1e-14)

    bumped, _ = quad_grid(4, 3, bump=0.2, device=device)
    x, y = bumped[:, 0], bumped[:, 1]
    torch.testing.assert_close(bumped[:, 2], 0.2 * torch.sin(3 * x + 0.5) * torch.cos(2 * y - 0.3))
    assert float(tp.face_nonplanarity(bumped, faces).max()) > 1e-3  # non-planar quads

    lifted, _ = quad_grid(4, 3, bump=0.2, height=lambda x, y: x * y, device=device)
    torch.testing.assert_close(lifted[:, 2] - bumped[:, 2], x * y, rtol=0, atol=1e-15)

    v32, f32 = quad_grid(4, 3, bump=0.2, seed=1, dtype=torch.float32, device=device)
    v64, f64 = quad_grid(4, 3, bump=0.2, seed=1, device=device)
    assert (
        v32.dtype == torch.float32
        and v32.device.type == device.type
        and torch.equal(v32, v64.float())
        and torch.equal(f32, f64)
    )


def test_quad_grid_jitter_is_seeded_interior_and_keeps_quads_convex(device):
    n, m = 6, 5
    plain, faces = quad_grid(n, m, device=device)
    a, _ = quad_grid(n, m, seed=3, device=device)
    b, _ = quad_grid(n, m, seed=3, device=device)
    c, _ = quad_grid(n, m, seed=4, device=device)
    assert torch.equal(a, b) and not torch.equal(a, c)  # deterministic, seed-dependent
    moved = (a - plain).norm(dim=1) > 0
    boundary = tp.build_topology(faces, a.shape[0]).boundary_vertices
    assert not bool(moved[boundary].any())
    assert int(moved.sum()) == (n - 1) * (m - 1)
    # at most jitter * the smaller cell side along each axis
    assert float((a - plain).abs().max()) <= 0.25 / max(n, m)
    # every corner still turns left: convex quads
    p = a[faces][..., :2]
    e = torch.roll(p, -1, 1) - p
    cross = e[..., 0] * torch.roll(e, -1, 1)[..., 1] - e[..., 1] * torch.roll(e, -1, 1)[..., 0]
    assert bool((cross > 0).all())
    # the total area of a planar jittered grid with a fixed boundary is unchanged
    assert float(tp.face_areas(a, faces).sum()) == pytest.approx(1.0, rel=1e-13)


# ----------------------------------------------------------------------- quad_cube, sphere


@pytest.mark.parametrize("n", [1, 2, 5])
def test_quad_cube_is_a_closed_outward_cube(n, device):
    verts, faces = quad_cube(n, device=device)
    assert verts.device.type == device.type
    assert verts.shape == (6 * n * n + 2, 3) and faces.shape == (6 * n * n, 4)
    check_topology(verts, faces, chi=2, boundary_edges=0)
    assert float(verts.abs().max(dim=1).values.min()) == 1.0  # every vertex on the surface
    assert float(tp.face_areas(verts, faces).sum()) == pytest.approx(24.0, rel=1e-14)
    assert float(tp.apps.enclosed_volume(verts, faces)) == pytest.approx(8.0, rel=1e-14)
    # side s is a grid: quad (i, j)'s edge to (i + 1, j) is the latter's first edge reversed
    grid = faces.reshape(6, n, n, 4)
    normals = tp.face_normals(verts, faces).reshape(6, n, n, 3)
    for s in range(6):
        assert torch.allclose(normals[s], normals[s, 0, 0].expand(n, n, 3), atol=1e-15)
        if n > 1:
            assert torch.equal(grid[s, 1:, :, 0], grid[s, :-1, :, 1])
            assert torch.equal(grid[s, :, 1:, 0], grid[s, :, :-1, 3])
    sides = normals[:, 0, 0]
    expected = torch.tensor([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]])
    assert torch.allclose(sides, expected.double().to(device), atol=1e-15)


@pytest.mark.parametrize("n", [1, 3, 8])
def test_quad_sphere_lies_on_the_sphere_and_is_closed(n, device):
    verts, faces = quad_sphere(n, radius=2.5, device=device)
    assert verts.shape == (6 * n * n + 2, 3) and faces.shape == (6 * n * n, 4)
    assert verts.device.type == device.type
    check_topology(verts, faces, chi=2, boundary_edges=0)
    torch.testing.assert_close(verts.norm(dim=1), torch.full_like(verts[:, 0], 2.5))
    # outward: the enclosed volume is positive and below the ball's (an inscribed polyhedron)
    volume = float(tp.apps.enclosed_volume(verts, faces))
    assert 0 < volume < 4 / 3 * math.pi * 2.5**3
    assert torch.equal(faces, quad_cube(n)[1])  # the cube's connectivity


def test_quad_sphere_refines_towards_the_sphere_with_balanced_quads(device):
    volumes, ratios = [], []
    for n in (4, 8, 16):
        verts, faces = quad_sphere(n, device=device)
        volumes.append(float(tp.apps.enclosed_volume(verts, faces)))
        areas = tp.face_areas(verts, faces)
        ratios.append(float(areas.max() / areas.min()))
    ball = 4 / 3 * math.pi
    errors = [ball - v for v in volumes]
    assert errors[0] > errors[1] > errors[2] > 0
    assert errors[1] / errors[2] == pytest.approx(4.0, rel=0.1)  # second order in 1/n
    # the equi-angular warp keeps the largest to smallest quad area ratio below 1.5 (the plain
    # projection of the cube's quads onto the sphere tends to 3 sqrt(3) = 5.2)
    assert max(ratios) < 1.5


def test_quad_sphere_noise_is_radial_seeded_and_scaled(device):
    plain, faces = quad_sphere(6, device=device)
    a, fa = quad_sphere(6, noise=0.05, seed=1, device=device)
    b, _ = quad_sphere(6, noise=0.05, seed=1, device=device)
    c, _ = quad_sphere(6, noise=0.05, seed=2, device=device)
    assert torch.equal(a, b) and not torch.equal(a, c) and torch.equal(fa, faces)
    r = a.norm(dim=1)
    torch.testing.assert_close(a / r[:, None], plain)  # moved along the radius only
    assert 0.03 < float((r - 1).std()) < 0.07
    assert float(tp.face_nonplanarity(a, faces).max()) > 1e-3
    v32, _ = quad_sphere(6, noise=0.05, seed=1, dtype=torch.float32, device=device)
    assert v32.dtype == torch.float32 and torch.equal(v32, a.float())


# ----------------------------------------------------------------------------------- torus


@pytest.mark.parametrize("n_u, n_v", [(3, 3), (8, 4), (12, 6)])
def test_torus_is_closed_with_genus_one(n_u, n_v, device):
    verts, faces = torus(n_u, n_v, major=2.0, minor=0.5, device=device)
    assert verts.device.type == device.type
    assert verts.shape == (n_u * n_v, 3) and faces.shape == (n_u * n_v, 4)
    check_topology(verts, faces, chi=0, boundary_edges=0)
    # every vertex at distance 0.5 from the centre circle of radius 2 in the xy plane
    ring = verts[:, :2].norm(dim=1)
    torch.testing.assert_close(
        (ring - 2.0) ** 2 + verts[:, 2] ** 2, torch.full_like(ring, 0.25), rtol=0, atol=1e-14
    )
    assert float(tp.apps.enclosed_volume(verts, faces)) > 0  # outward


def test_torus_volume_converges_to_the_solid_torus(device):
    exact = 2 * math.pi**2 * 2.0 * 0.5**2
    errors = []
    for n in (8, 16, 32):
        verts, faces = torus(2 * n, n, major=2.0, minor=0.5, device=device)
        errors.append(exact - float(tp.apps.enclosed_volume(verts, faces)))
    assert errors[0] > errors[1] > errors[2] > 0
    assert errors[1] / errors[2] == pytest.approx(4.0, rel=0.1)


def test_torus_rejects_a_self_intersecting_tube():
    with pytest.raises(ValueError, match="minor < major"):
        torus(8, 4, major=1.0, minor=1.0)


# --------------------------------------------------------------------------------- lantern


@pytest.mark.parametrize("triangulation", ["quad", "horizontal", "vertical", "alternating"])
def test_lantern_is_an_open_cylinder(triangulation, device):
    sides, rings = 6, 5
    verts, faces = schwarz_lantern(
        sides, rings, radius=1.5, triangulation=triangulation, device=device
    )
    assert verts.device.type == device.type
    degrees = sorted(len(f) for f in faces)
    diamonds = (rings - 2) * sides
    if triangulation == "quad":
        assert degrees == [3] * (2 * sides) + [4] * diamonds
    else:
        assert degrees == [3] * (2 * sides + 2 * diamonds)
    # an annulus: chi = 0, two boundary loops of `sides` edges (the first and last rings)
    check_topology(verts, faces, chi=0, boundary_edges=2 * sides)
    loops = tp.build_topology(faces, verts.shape[0]).boundary_loops()
    assert sorted(len(loop) for loop in loops) == [sides, sides]
    torch.testing.assert_close(verts[:, :2].norm(dim=1), torch.full_like(verts[:, 0], 1.5))
    # the rotation by 2 pi / sides maps vertex (i, j) to (i, j + 1)
    c, s = math.cos(2 * math.pi / sides), math.sin(2 * math.pi / sides)
    rot = torch.tensor(
        [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64, device=device
    )
    grid = torch.arange(sides * rings).reshape(rings, sides)
    torch.testing.assert_close(verts @ rot.T, verts[torch.roll(grid, -1, 1).reshape(-1)])
    # outward: the normals point away from the axis
    centroids = torch.stack([verts[f].mean(0) for f in faces])
    normals = tp.face_normals(verts, faces)
    assert bool(((normals[:, :2] * centroids[:, :2]).sum(1) > 0).all())


def test_generators_reject_bad_sizes():
    for call in (
        lambda: quad_grid(0),
        lambda: quad_grid(2, 0),
        lambda: quad_grid(2.5),
        lambda: quad_cube(0),
        lambda: quad_sphere(True),
        lambda: torus(2, 4),
        lambda: schwarz_lantern(2, 4),
        lambda: schwarz_lantern(4, 4, triangulation="diagonal"),
        lambda: quad_grid(2, extent=(1.0, 0.0, 0.0, 1.0)),
    ):
        with pytest.raises(ValueError):
            call()

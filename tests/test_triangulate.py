"""Tests for torch_polylap.triangulate: polygons cut into triangles that keep their orientation
and tile planar faces exactly, non-convex ones included."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from conftest import DATA
from meshes import shared_meshes_dir

from torch_polylap.interop import to_trimesh
from torch_polylap.io import SkippedContentWarning, read_mesh
from torch_polylap.triangulate import triangulate_faces


def _tiled_arrows(n: int, tilt: np.ndarray) -> tuple[np.ndarray, list[list[int]]]:
    """``n * n`` non-convex octagons (arrow heads pointing at +y), each with its own corners,
    on a plane through the origin spanned by ``tilt``'s columns."""
    arrow = np.array(
        [[0, 0], [1, 0.6], [2, 0], [2, 1], [1, 2], [0, 1], [0.4, 0.8], [0.2, 0.5]], dtype=float
    )
    verts, faces = [], []
    for i in range(n):
        for j in range(n):
            faces.append(list(range(len(verts), len(verts) + len(arrow))))
            verts += (arrow + [3 * i, 3 * j]).tolist()
    return np.array(verts) @ tilt.T, faces


def _polygon_area(points: np.ndarray) -> float:
    return 0.5 * np.linalg.norm(np.cross(points, np.roll(points, -1, axis=0)).sum(axis=0))


def _check_triangulation(verts: np.ndarray, faces: list[list[int]], tris: np.ndarray) -> None:
    sizes = np.array([len(f) for f in faces])
    owner = np.repeat(np.arange(len(faces)), sizes - 2)
    a, b, c = (verts[tris[:, i]] for i in range(3))
    tri_normal = 0.5 * np.cross(b - a, c - a)
    for f, face in enumerate(faces):
        pts = verts[face]
        normal = 0.5 * np.cross(pts, np.roll(pts, -1, axis=0)).sum(axis=0)
        mine = owner == f
        assert set(tris[mine].ravel()) <= set(face)
        dots = tri_normal[mine] @ normal / np.linalg.norm(normal)
        assert (dots > 1e-9 * _polygon_area(pts)).all(), f"face {f}: flipped or degenerate"
        assert dots.sum() == pytest.approx(_polygon_area(pts), rel=1e-12)


def test_non_convex_faces_are_ear_clipped_with_their_orientation():
    tilt = np.linalg.qr(np.random.default_rng(0).normal(size=(3, 3)))[0][:, :2]
    verts, faces = _tiled_arrows(4, tilt)
    tris = triangulate_faces(verts, faces)
    _check_triangulation(verts, faces, tris)
    flipped = [f[::-1] for f in faces]  # the other orientation is kept too
    _check_triangulation(verts, flipped, triangulate_faces(verts, flipped))
    mesh = to_trimesh(verts, faces)
    assert np.array_equal(mesh.faces, tris)
    assert mesh.area == pytest.approx(sum(_polygon_area(verts[f]) for f in faces), rel=1e-12)


def test_collinear_corners_give_no_degenerate_triangle():
    # a square with extra corners on its edges: convex but not strictly, so not fanned
    verts = np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0], [2, 1, 0], [2, 2, 0], [0, 2, 0], [0, 1, 0]])
    faces = [list(range(7))]
    _check_triangulation(verts.astype(float), faces, triangulate_faces(verts, faces))


@pytest.mark.parametrize("name", ["concave_3.obj"])
def test_triangulated_concave_grid(name):
    shared = shared_meshes_dir()
    paths = sorted((shared / "grid").glob("concave_*.obj"))[:3] if shared is not None else []
    paths.append(DATA / "grid" / name)
    for path in paths:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", SkippedContentWarning)
            verts, faces = read_mesh(path)
        v, face_lists = verts.numpy(), faces.tolist()
        _check_triangulation(v, face_lists, triangulate_faces(v, faces))

"""Faces in every form, connectivity validation with clear errors, and the cached pattern."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp
import torch
from conftest import DATA, mixed_mesh, quad_grid

import torch_polylap as tp


def test_face_forms_agree():
    V, F = quad_grid(3)
    as_list = F.tolist()
    packed = tp.PolygonFaces(F.reshape(-1), sizes=torch.full((F.shape[0],), 4))
    offsets = tp.PolygonFaces(F.reshape(-1).numpy(), offsets=np.arange(0, F.numel() + 1, 4))
    ref = tp.laplacian(V, F)[0].to_dense()
    for form in (as_list, F.numpy(), packed, offsets, F.int()):
        assert torch.equal(tp.laplacian(V, form)[0].to_dense(), ref)
    assert torch.equal(packed.as_uniform(), F)
    assert tp.as_faces([[0, 1, 2], [0, 2, 3, 4]]).as_uniform() is None


def test_polygon_faces_accessors():
    faces = tp.as_faces([[0, 1, 2], [2, 1, 3, 4]])
    assert faces.num_faces == 2 and faces.num_corners == 7 and len(faces) == 2
    assert faces[1].tolist() == [2, 1, 3, 4] and faces[-1].tolist() == [2, 1, 3, 4]
    assert faces.flipped().tolist() == [[2, 1, 0], [4, 3, 1, 2]]
    assert faces.face_ids().tolist() == [0, 0, 0, 1, 1, 1, 1]
    assert "degrees=[3, 4]" in repr(faces)
    with pytest.raises(IndexError):
        faces[2]


@pytest.mark.parametrize(
    "faces,num_verts,match",
    [
        ([[0, 1, 2], [0, 2, 7]], 4, r"face 1 refers to vertex 7, but the mesh has 4 vertices"),
        ([[0, 1, 2], [0, -1, 2]], 4, r"face 1 refers to vertex -1"),
        ([[0, 1, 2, 1]], 3, r"face 0 .* visits vertex 1 twice"),
        ([[0, 1, 2], [0, 2]], 3, r"face 1 has 2 vertices; a polygon needs at least 3"),
        ([[0, 1, 2], [1, 0, 3], [0, 1, 4]], 5, r"edge \(0, 1\) is shared by 3 faces \[0, 1, 2\]"),
        (
            [[0, 1, 2], [0, 1, 3]],
            4,
            r"faces 0 and 1 both traverse edge 0 -> 1 in the same direction",
        ),
    ],
)
def test_bad_connectivity_is_named(faces, num_verts, match):
    with pytest.raises(ValueError, match=match):
        tp.build_topology(faces, num_verts)


def test_bad_face_arrays():
    with pytest.raises(ValueError, match=r"shape \(F, k\)"):
        tp.as_faces(torch.arange(6))
    with pytest.raises(ValueError, match="integer vertex indices"):
        tp.as_faces(torch.rand(2, 3))
    with pytest.raises(ValueError, match="sequence of vertex indices"):
        tp.as_faces([[0, 1, 2], 5])
    with pytest.raises(ValueError, match="exactly one of"):
        tp.PolygonFaces([0, 1, 2])
    with pytest.raises(ValueError, match="add up to"):
        tp.PolygonFaces([0, 1, 2], sizes=[4])


def test_moebius_band_is_rejected():
    V, F = tp.read_mesh(DATA / "moebius.obj")
    with pytest.raises(ValueError, match="not consistently oriented .*Moebius"):
        tp.laplacian(V, F)


def test_bad_geometry_is_named():
    V, F = quad_grid(2)
    bad = V.clone()
    bad[4, 1] = float("nan")
    with pytest.raises(ValueError, match=r"vertex 4 has non-finite coordinates"):
        tp.laplacian(bad, F)
    collinear = V.clone()
    collinear[[0, 1, 3, 4], 1] = 0.0  # face 0 = (0, 1, 4, 3) collapses onto the x axis
    collinear[[0, 1, 3, 4], 0] = torch.tensor([0.0, 0.5, 0.25, 0.75], dtype=V.dtype)
    with pytest.raises(
        ValueError, match=r"face 0 \(vertices \[0, 3, 4, 1\]\) has zero vector area"
    ):
        tp.laplacian(collinear, F)
    with pytest.raises(ValueError, match=r"shape \(V, 3\)"):
        tp.laplacian(V[:, :2], F)
    with pytest.raises(ValueError, match="floating point"):
        tp.laplacian(V.long(), F)


def test_zero_area_without_validation_stays_finite():
    V, F = quad_grid(2)
    V = V.clone()
    V[[0, 1, 3, 4], 1] = 0.0
    L, M0 = tp.laplacian(V, F, validate=False)
    assert torch.isfinite(L.values()).all() and torch.isfinite(M0.values()).all()


def test_isolated_vertex_warns_and_gets_zero_mass():
    V, F = quad_grid(2)
    V = torch.cat([V, torch.tensor([[5.0, 5.0, 5.0]], dtype=V.dtype)])
    with pytest.warns(UserWarning, match=r"1 of 10 vertices belong to no face \(first: \[9\]\)"):
        L, M0 = tp.laplacian(V, F)
    assert M0.to_dense()[9, 9] == 0 and L.to_dense()[9].abs().sum() == 0
    H = tp.strong_laplacian(L, M0, V)
    assert torch.isfinite(H).all() and H[9].abs().sum() == 0


def test_pattern_matches_scipy_and_edges():
    V, F = mixed_mesh()
    topo = tp.build_topology(F, V.shape[0])
    rows, cols = [], []
    for face in F:
        for a in face:
            for b in face:
                rows.append(a)
                cols.append(b)
    ref = sp.csr_matrix((np.ones(len(rows)), (rows, cols)), shape=(12, 12))
    ref.sum_duplicates()
    ref.sort_indices()
    assert topo.crow.tolist() == ref.indptr.tolist()
    assert topo.col.tolist() == ref.indices.tolist()
    # edges: every consecutive corner pair, once; boundary edges are used by one face
    edges = {tuple(sorted((f[i], f[(i + 1) % len(f)]))) for f in F for i in range(len(f))}
    assert sorted(edges) == [tuple(e) for e in topo.edges.tolist()]
    uses = {e: 0 for e in edges}
    for f in F:
        for i in range(len(f)):
            uses[tuple(sorted((f[i], f[(i + 1) % len(f)])))] += 1
    assert topo.edge_faces.tolist() == [uses[tuple(e)] for e in topo.edges.tolist()]
    boundary = sorted({v for e, n in uses.items() if n == 1 for v in e})
    assert topo.boundary_vertices.tolist() == boundary
    assert topo.euler_characteristic() == 12 - len(edges) + len(F) == 1  # a disk
    faces = tp.as_faces(F)
    he = topo.half_edge_edge
    for h, (a, b) in enumerate(zip(faces.indices.tolist(), _next_corner(faces), strict=True)):
        assert tuple(topo.edges[he[h]].tolist()) == (min(a, b), max(a, b))


def _next_corner(faces):
    out = []
    for face in faces.tolist():
        out.extend(face[1:] + face[:1])
    return out


def test_chunked_groups_match_unchunked(monkeypatch):
    """Splitting a degree group into chunks must not change L (tiny chunks force many)."""
    import torch_polylap.topology as topology

    V, F = quad_grid(30, bump=0.2, seed=3)
    ref = tp.laplacian(V, tp.build_topology(F, V.shape[0]))[0].to_dense()
    monkeypatch.setattr(topology, "CHUNK_ELEMENTS", 1)
    topo = tp.build_topology(F, V.shape[0])
    assert len(topo.groups[0].chunks) > 1
    # identical up to the order of floating-point additions in the scatter
    assert torch.allclose(tp.laplacian(V, topo)[0].to_dense(), ref, rtol=0, atol=1e-14)


def test_functional_cache_follows_tensor_edits():
    V, F = quad_grid(3)
    F = F.clone()
    t1 = tp.get_topology(F, V.shape[0])
    assert tp.get_topology(F, V.shape[0]) is t1
    F[0] = F[0].roll(1)  # same face, relabelled corners: in-place edit invalidates the cache
    assert tp.get_topology(F, V.shape[0]) is not t1

"""Faces in every form, connectivity validation with clear errors, and the cached pattern."""

from __future__ import annotations

import dataclasses
import gc
import os
import time
import warnings
import weakref

import numpy as np
import pytest
import scipy.sparse as sp
import torch
from conftest import DATA, mixed_mesh
from hypothesis import given, settings
from hypothesis import strategies as st
from meshes import read_mesh

import torch_polylap as tp
from torch_polylap.assembly import gather_plan_of
from torch_polylap.shapes import quad_grid
from torch_polylap.topology.groups import moved


def test_face_forms_agree(device):
    V, F = quad_grid(3, device=device)
    as_list = F.tolist()
    packed = tp.PolygonFaces(F.reshape(-1), sizes=torch.full((F.shape[0],), 4))
    offsets = tp.PolygonFaces(F.reshape(-1).numpy(), offsets=np.arange(0, F.numel() + 1, 4))
    ref = tp.laplacian(V, F)[0].to_dense()
    # bitwise on the CPU; CUDA's parallel scatter may order the sums differently per call
    atol = 0.0 if device.type == "cpu" else 1e-15 * float(ref.abs().max())
    for form in (as_list, F.numpy(), packed, offsets, F.int(), F.to(device)):
        torch.testing.assert_close(tp.laplacian(V, form)[0].to_dense(), ref, rtol=0, atol=atol)
    assert torch.equal(packed.as_uniform(), F)
    assert tp.as_faces([[0, 1, 2], [0, 2, 3, 4]]).as_uniform() is None


def test_polygon_faces_accessors(device):
    faces = tp.as_faces([[0, 1, 2], [2, 1, 3, 4]]).to(device)
    assert faces.device.type == device.type and faces.corner_face.device.type == device.type
    assert faces.num_faces == 2 and faces.num_corners == 7 and len(faces) == 2
    assert faces[1].tolist() == [2, 1, 3, 4] and faces[-1].tolist() == [2, 1, 3, 4]
    assert faces.flipped().tolist() == [[2, 1, 0], [4, 3, 1, 2]]
    assert faces.corner_face.tolist() == [0, 0, 0, 1, 1, 1, 1]
    assert faces.next_corner.tolist() == [1, 2, 0, 4, 5, 6, 3]
    assert "degrees=[3, 4]" in repr(faces)
    with pytest.raises(IndexError):
        faces[2]


@settings(max_examples=60, deadline=None)
@given(st.lists(st.integers(3, 9), max_size=12))
def test_corner_maps_walk_each_face_cyclically(degrees):
    # faces with arbitrary vertex ids; the reference walks each face as a Python list
    faces = tp.PolygonFaces(torch.arange(sum(degrees)) * 7 % 101, sizes=degrees)
    nxt, prv, face = faces.next_corner, faces.prev_corner, faces.corner_face
    start = 0
    for f, k in enumerate(degrees):
        ring = list(range(start, start + k))
        assert nxt[ring].tolist() == ring[1:] + ring[:1]
        assert prv[ring].tolist() == ring[-1:] + ring[:-1]
        assert face[ring].tolist() == [f] * k
        start += k
    assert faces.next_corner is nxt  # computed once
    moved = faces.to("cpu")
    assert torch.equal(moved.next_corner, nxt) and torch.equal(moved.corner_face, face)


@pytest.mark.parametrize(
    "faces,num_verts,match",
    [
        ([[0, 1, 2], [0, 2, 7]], 4, r"face 1 refers to vertex 7, but the mesh has 4 vertices"),
        ([[0, 1, 2], [0, -1, 2]], 4, r"face 1 refers to vertex -1"),
        ([[0, 1, 2, 1]], 3, r"face 0 .* visits vertex 1 twice"),
        ([[0, 1, 2], [0, 2]], 3, r"face 1 has 2 vertices; a polygon needs at least 3"),
        ([[0, 1, 2], [0, 1.5, 2]], 3, r"face 1 holds the vertex index 1.5, which is not an int"),
    ],
)
def test_bad_connectivity_is_named(faces, num_verts, match):
    with pytest.raises(ValueError, match=match):
        tp.build_topology(faces, num_verts)


def test_bad_face_arrays(device):
    with pytest.raises(ValueError, match=r"shape \(F, k\)"):
        tp.as_faces(torch.arange(6, device=device))
    with pytest.raises(ValueError, match="integer vertex indices"):
        tp.as_faces(torch.rand(2, 3, device=device))
    with pytest.raises(ValueError, match="sequence of vertex indices"):
        tp.as_faces([[0, 1, 2], 5])
    with pytest.raises(ValueError, match="exactly one of"):
        tp.PolygonFaces([0, 1, 2])
    with pytest.raises(ValueError, match="add up to"):
        tp.PolygonFaces([0, 1, 2], sizes=[4])


def test_bad_geometry_is_named(device):
    V, F = quad_grid(2, device=device)
    bad = V.clone()
    bad[4, 1] = float("nan")
    with pytest.raises(ValueError, match=r"vertex 4 has non-finite coordinates"):
        tp.laplacian(bad, F)
    collinear = V.clone()
    collinear[[0, 1, 3, 4], 1] = 0.0  # face 0 = (0, 1, 4, 3) collapses onto the x axis
    collinear[[0, 1, 3, 4], 0] = torch.tensor([0.0, 0.5, 0.25, 0.75], dtype=V.dtype, device=device)
    with pytest.raises(
        ValueError, match=r"face 0 \(vertices \[0, 3, 4, 1\]\) has zero vector area"
    ):
        tp.laplacian(collinear, F)
    with pytest.raises(ValueError, match=r"shape \(V, 3\)"):
        tp.laplacian(V[:, :2], F)
    # the wrong kind of object is a TypeError (torch_polylap.checks.check_verts)
    with pytest.raises(TypeError, match=r"floating point \(float32 or float64\).*int64"):
        tp.laplacian(V.long(), F)
    with pytest.raises(TypeError, match=r"float16.*verts.float\(\)"):
        tp.laplacian(V.half(), F)
    with pytest.raises(TypeError, match=r"torch.Tensor of shape \(V, 3\), got ndarray"):
        tp.laplacian(V.cpu().numpy(), F)


def test_zero_area_without_validation_stays_finite(device):
    V, F = quad_grid(2, device=device)
    V = V.clone()
    V[[0, 1, 3, 4], 1] = 0.0
    L, M0 = tp.laplacian(V, F, validate=False)
    assert torch.isfinite(L.values()).all() and torch.isfinite(M0.values()).all()


def test_isolated_vertex_warns_and_gets_zero_mass(device):
    V, F = quad_grid(2, device=device)
    V = torch.cat([V, torch.tensor([[5.0, 5.0, 5.0]], dtype=V.dtype, device=device)])
    with pytest.warns(UserWarning, match=r"1 of 10 vertices belong to no face \(first: \[9\]\)"):
        L, M0 = tp.laplacian(V, F)
    assert M0.to_dense()[9, 9] == 0 and L.to_dense()[9].abs().sum() == 0
    H = tp.strong_laplacian(L, M0, V)
    assert torch.isfinite(H).all() and H[9].abs().sum() == 0


def _split_vertices_reference(faces: list[list[int]]) -> list[int]:
    """Vertices whose faces form two or more fans, by a union-find over each vertex's faces
    linked across the edges at that vertex (plain Python; edges used by at most two faces)."""
    at: dict[int, list[int]] = {}
    edge_faces: dict[tuple[int, int], list[int]] = {}
    for f, face in enumerate(faces):
        for i, v in enumerate(face):
            at.setdefault(v, []).append(f)
            w = face[(i + 1) % len(face)]
            edge_faces.setdefault((min(v, w), max(v, w)), []).append(f)
    parent = {(v, f): (v, f) for v, fs in at.items() for f in fs}

    def root(x):
        while parent[x] != x:
            x = parent[x]
        return x

    for (p, q), fs in edge_faces.items():
        if len(fs) == 2:
            for v in (p, q):
                parent[root((v, fs[0]))] = root((v, fs[1]))
    return sorted(v for v, fs in at.items() if len({root((v, f)) for f in fs}) > 1)


@settings(max_examples=40, deadline=None)
@given(
    st.integers(0, 2**32 - 1),
    st.sampled_from(["quads", "triangles", "mixed", "cones", "busy cones"]),
    st.floats(0.2, 1.0),
)
def test_split_vertices_match_a_union_find(seed, kind, keep):
    # Subsets of consistently oriented meshes: manifold edges, and pinched vertices wherever
    # the kept faces touch only at a corner. Cones share their apex, each whole (a closed fan),
    # missing one face (an open fan) or thinned; busy cones give the apex more corners than
    # the walk takes (MAX_WALK_VALENCE), so pointer doubling decides there.
    rng = np.random.default_rng(seed)
    if kind.endswith("cones"):
        faces, base = [], 1
        low, high = (3, 12) if kind == "cones" else (17, 40)
        for m in rng.integers(low, high, size=rng.integers(1, 4)).tolist():
            cone = [[0, base + i, base + (i + 1) % m] for i in range(m)]
            mode = rng.integers(3)
            if mode == 1:
                cone.pop(int(rng.integers(m)))
            elif mode == 2:
                cone = [f for f in cone if rng.random() < keep]
            faces += cone
            base += m
        faces = faces or [[0, 1, 2]]
    else:
        _, grid = quad_grid(6, 5)
        quads = grid.tolist()
        tris = [[a, b, c] for a, b, c, d in quads] + [[a, c, d] for a, b, c, d in quads]
        faces = {"quads": quads, "triangles": tris, "mixed": quads[:15] + tris[30:]}[kind]
        faces = [f for f in faces if rng.random() < keep] or faces[:1]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        topo = tp.build_topology(faces)
    assert topo.report.non_manifold_vertices.tolist() == _split_vertices_reference(faces)


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


def test_chunked_groups_match_unchunked(monkeypatch, device):
    """Splitting a degree group into chunks must not change L (tiny chunks force many)."""
    import torch_polylap.topology as topology

    V, F = quad_grid(30, bump=0.2, seed=3, device=device)
    ref = tp.laplacian(V, tp.build_topology(F, V.shape[0]))[0].to_dense()
    monkeypatch.setattr(topology.groups, "CHUNK_ELEMENTS", 1)
    topo = tp.build_topology(F, V.shape[0])
    assert len(topo.groups[0].chunks) > 1
    # identical up to the order of floating-point additions in the scatter
    assert torch.allclose(tp.laplacian(V, topo)[0].to_dense(), ref, rtol=0, atol=1e-14)


def test_functional_cache_follows_tensor_edits(device):
    V, F = quad_grid(3)
    F = F.to(device, copy=True)
    t1 = tp.get_topology(F, V.shape[0])
    assert tp.get_topology(F, V.shape[0]) is t1
    F[0] = F[0].roll(1)  # same face, relabelled corners: in-place edit invalidates the cache
    assert tp.get_topology(F, V.shape[0]) is not t1


# -- meshes as people download them: reported, not refused ------------------------------------


def _fin(n: int = 3):
    """A bumpy quad grid with a fin: a quad standing on an interior edge (3 faces on it)."""
    V, F = quad_grid(n, bump=0.2, seed=1)
    p, q = int(F[0, 2]), int(F[0, 3])  # an interior edge of the grid
    top = V[[p, q]] + torch.tensor([0.0, 0.1, 1.0], dtype=V.dtype)
    V = torch.cat([V, top])
    nv = V.shape[0]
    return V, F.tolist() + [[p, q, nv - 1, nv - 2]]


def _pyramid(apex: int, base: list[int]) -> list[list[int]]:
    k = len(base)
    return [[apex, base[i], base[(i + 1) % k]] for i in range(k)] + [base[::-1]]


def irregular_meshes():
    """(name, verts, faces, expected report) of meshes that are not oriented 2-manifolds."""
    out = []
    V, F = quad_grid(3, bump=0.2, seed=1)
    F = F.tolist()
    F[4] = F[4][::-1]
    out.append(("flipped_face", V, F, {"oriented": False, "manifold": True}))
    V, F = read_mesh(DATA / "moebius.obj")
    out.append(("moebius", V, F, {"oriented": False, "manifold": True, "non_orientable": 1}))
    V, F = _fin()
    out.append(("fin", V, F, {"oriented": True, "manifold": False}))
    V, F = quad_grid(3, bump=0.2, seed=2)
    F = F.tolist()
    F = F + [F[4], F[2][::-1], F[2][1:] + F[2][:1]]
    out.append(("duplicates", V, F, {"manifold": False, "duplicates": [9, 10, 11]}))
    V, F = quad_grid(2, bump=0.2, seed=3)
    V2 = V + torch.tensor([1.0, 1.0, 0.3], dtype=V.dtype)  # touches the first at vertex 8
    F2 = (F + V.shape[0]).tolist()
    F2 = [[8 if v == V.shape[0] else v for v in f] for f in F2]
    V = torch.cat([V, V2])
    out.append(("bowtie", V, F.tolist() + F2, {"oriented": True, "manifold": False, "isolated": 1}))
    cone = torch.tensor(
        [[0, 0, 0], [1, 0, 1], [0, 1, 1.2], [-1, 0, 1], [0, -1, 1.1]]
        + [[1, 0.1, -1], [0, 1, -1.1], [-1, 0, -1], [0, -1, -1.3]],
        dtype=torch.float64,
    )
    F = _pyramid(0, [1, 2, 3, 4]) + _pyramid(0, [8, 7, 6, 5])
    out.append(("double_cone", cone, F, {"oriented": True, "manifold": False}))
    Va, Fa = mixed_mesh()
    Vb, Fb = quad_grid(2, bump=0.1, seed=4)
    V = torch.cat([Va, Vb + 5.0, torch.tensor([[9.0, 9.0, 9.0]], dtype=Va.dtype)])
    F = [list(f) for f in Fa] + (Fb + Va.shape[0]).tolist()
    F[0] = F[0][::-1]
    out.append(("components_isolated", V, F, {"oriented": False, "isolated": 1}))
    tri = torch.tensor(
        [[0, 0, 0], [1, 0, 0], [0.4, 1, 0], [0.5, -1, 0.2], [0.6, 0.2, 1], [0.3, -0.3, -1]],
        dtype=torch.float64,
    )
    out.append(
        ("triangle_book", tri, [[0, 1, 2], [1, 0, 3], [0, 1, 4], [5, 1, 0]], {"manifold": False})
    )
    return out


IRREGULAR = irregular_meshes()


def _reference_laplacian(V: torch.Tensor, F: list[list[int]]) -> np.ndarray:
    """Dense L summed with numpy, face by face, from the blocks of tp.dec.local_laplacians."""
    n = V.shape[0]
    L = np.zeros((n, n))
    for face_ids, blocks in tp.dec.local_laplacians(V, F):
        for f, block in zip(face_ids.tolist(), blocks.numpy(), strict=True):
            c = np.asarray(F[f])
            np.add.at(L, (c[:, None], c[None, :]), block)
    return L


@pytest.mark.filterwarnings("ignore::UserWarning")
@pytest.mark.parametrize("name,V,F,expect", IRREGULAR, ids=[m[0] for m in IRREGULAR])
def test_laplacian_on_irregular_meshes(name, V, F, expect, device):
    F = F.tolist() if isinstance(F, tp.PolygonFaces) else F
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        topo = tp.build_topology(F, V.shape[0])
    assert len([w for w in caught if issubclass(w.category, UserWarning)]) == 1
    report = topo.report
    assert topo.is_oriented == expect.get("oriented", topo.is_oriented)
    assert topo.is_manifold == expect.get("manifold", topo.is_manifold)
    assert report.non_orientable_components == expect.get("non_orientable", 0)
    if "duplicates" in expect:
        assert report.duplicate_faces.tolist() == expect["duplicates"]
    assert report.isolated_vertices.size == expect.get("isolated", 0)

    L, M0 = tp.laplacian(V.to(device), topo)
    assert L.device.type == device.type
    Ld = L.to_dense().cpu().numpy()  # the references below on the CPU
    assert np.allclose(Ld, Ld.T, rtol=0, atol=1e-13 * np.abs(Ld).max())
    assert np.abs(Ld.sum(1)).max() <= 1e-12 * np.abs(Ld).max()
    eig = np.linalg.eigvalsh(Ld)
    assert eig[0] >= -1e-12 * eig[-1]
    n_comp, _ = topo.connected_components()
    assert int((eig < 1e-9 * eig[-1]).sum()) == n_comp
    assert np.allclose(Ld, _reference_laplacian(V, F), rtol=0, atol=1e-12 * np.abs(Ld).max())
    if all(len(f) == 3 for f in F):
        igl = pytest.importorskip("igl", reason="libigl not installed (pip install libigl)")
        C = igl.cotmatrix(V.numpy(), np.asarray(F, dtype=np.int64)).toarray()
        assert np.allclose(Ld, -C, rtol=0, atol=1e-12 * np.abs(Ld).max())
    assert float(M0.to_dense().diagonal().sum()) == pytest.approx(
        float(tp.face_areas(V.to(device), topo).sum()), rel=1e-12
    )


def test_flipping_faces_leaves_laplacian_unchanged(device):
    V, F = quad_grid(4, bump=0.3, seed=5, device=device)
    flipped = F.clone()
    flipped[::3] = flipped[::3].flip(1)
    with pytest.warns(UserWarning, match="inconsistent orientation"):
        L2 = tp.laplacian(V, flipped)[0].to_dense()
    assert torch.allclose(tp.laplacian(V, F)[0].to_dense(), L2, rtol=0, atol=1e-14)


def test_manifold_entry_points_say_what_to_run():
    V, F = quad_grid(3)
    clean = tp.build_topology(F, V.shape[0])
    assert clean.report.is_clean and clean.is_manifold and clean.is_oriented
    assert clean.boundary_loops()[0].tolist() == [0, 4, 8, 12, 13, 14, 15, 11, 7, 3, 2, 1]
    twin = clean.half_edge_twin
    src, dst = tp.topology.half_edge_vertices(clean.faces)
    inner = twin >= 0
    assert torch.equal(src[twin[inner]], dst[inner]) and torch.equal(dst[twin[inner]], src[inner])
    assert int(inner.sum()) == 2 * int((clean.edge_faces == 2).sum())
    flipped = F.clone()
    flipped[4] = flipped[4].flip(0)
    with pytest.warns(UserWarning):
        topo = tp.build_topology(flipped, V.shape[0])
    with pytest.raises(ValueError, match=r"boundary_loops needs .*repair.orient_faces"):
        topo.boundary_loops()
    with pytest.warns(UserWarning):
        fin = tp.build_topology(_fin()[1])
    with pytest.raises(
        ValueError, match=r"half_edge_twin needs a manifold mesh.*non-manifold edge"
    ):
        _ = fin.half_edge_twin
    V, F = read_mesh(DATA / "moebius.obj")
    moebius = tp.build_topology(F, V.shape[0], warn=False)
    with pytest.raises(ValueError, match=r"1 of its components cannot be oriented"):
        moebius.require_oriented("conformal_parameterization")


def test_zero_area_face_is_still_an_error_on_an_irregular_mesh(device):
    V, F = _fin()
    p, q = F[-1][:2]
    V = V.to(device, copy=True)
    t = torch.tensor([[0.3], [0.7]], dtype=V.dtype, device=device)
    V[-2:] = V[p] + t * (V[q] - V[p])  # the fin collapses onto its edge
    with pytest.warns(UserWarning), pytest.raises(ValueError, match=r"face 9 .* zero vector area"):
        tp.laplacian(V, F)


# -- high-degree faces ---------------------------------------------------------------------


def test_high_degree_face_is_vectorized(device):
    k = 1500
    t = np.linspace(0, 2 * np.pi, k, endpoint=False)
    V = torch.from_numpy(np.stack([np.cos(t), np.sin(t), 0.1 * np.sin(3 * t)], 1)).to(device)
    start = time.perf_counter()
    topo = tp.build_topology(torch.arange(k)[None], k)
    elapsed = time.perf_counter() - start
    assert elapsed < 1.5, elapsed  # about 0.2 s here; the old pair loop took 8 s
    assert topo.nnz == k * k
    L = tp.laplacian(V, topo)[0]
    assert float(L.to_dense().sum(1).abs().max()) < 1e-9


def test_oversized_face_is_refused_with_its_memory():
    with pytest.raises(ValueError, match=r"face 1 has degree 20000: .*199,990,000 corner pairs"):
        tp.build_topology(tp.PolygonFaces(torch.arange(20003), sizes=[3, 20000]), 20003)


# -- the topology cache ----------------------------------------------------------------------


def _rss_bytes() -> int:
    with open("/proc/self/statm") as fh:
        return int(fh.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")


@pytest.mark.skipif(not os.path.exists("/proc/self/statm"), reason="needs Linux /proc for RSS")
def test_fresh_faces_tensors_do_not_leak():
    """400 calls with new faces tensors of a 4.9k-face mesh grew RSS by 741 MB before (1.9 MB a
    call): 100 calls would grow by about 185 MB, three times the bound."""
    V, F = quad_grid(70)
    tp.laplacian(V, F.clone())
    gc.collect()
    before = _rss_bytes()
    cached_before = len(tp.topology.cache._CACHE)  # other tests' live faces tensors may be cached
    for _ in range(100):
        tp.laplacian(V, F.clone())
    gc.collect()
    grown = _rss_bytes() - before
    assert grown < 60 * 2**20, f"RSS grew by {grown / 2**20:.0f} MB"
    assert len(tp.topology.cache._CACHE) <= cached_before


def test_cache_holds_no_faces_and_is_shared_with_the_module(device):
    V, F = quad_grid(3, device=device)
    F = F.clone()
    ref = weakref.ref(F)
    module = tp.PolygonLaplacian()
    module(V, F)
    assert tp.get_topology(F, V.shape[0]) is module.topology
    del F
    gc.collect()
    assert ref() is None


@pytest.mark.filterwarnings("ignore:the mesh .* is not a consistently oriented")  # on purpose
def test_cache_sees_edits_through_shared_numpy_memory():
    V, F = quad_grid(3)
    arr = F.numpy().copy()
    faces = torch.from_numpy(arr)
    t1 = tp.get_topology(faces, V.shape[0])
    assert tp.get_topology(faces, V.shape[0]) is t1
    arr[0] = arr[0][::-1].copy()  # bypasses the tensor's version counter
    t2 = tp.get_topology(faces, V.shape[0])
    assert t2 is not t1 and not t2.is_oriented


def test_cache_is_bounded(monkeypatch):
    V, F = quad_grid(2)
    monkeypatch.setattr(tp.topology.cache._CACHE, "max_entries", 3)
    keep = [F.clone() for _ in range(6)]
    for f in keep:
        tp.get_topology(f, V.shape[0])
    assert len(tp.topology.cache._CACHE) == 3
    assert tp.get_topology(keep[-1], V.shape[0]) is tp.get_topology(keep[-1], V.shape[0])


# the topology's layouts reach another device whole, field by field
META = torch.device("meta")


def _tensors(obj: object) -> list[torch.Tensor]:
    """Every tensor reachable through dataclass fields and tuples."""
    if isinstance(obj, torch.Tensor):
        return [obj]
    if dataclasses.is_dataclass(obj):
        return [t for f in dataclasses.fields(obj) for t in _tensors(getattr(obj, f.name))]
    if isinstance(obj, tuple):
        return [t for v in obj for t in _tensors(v)]
    return []


def test_groups_and_plan_move_every_tensor_and_keep_the_rest() -> None:
    V, F = quad_grid(3, bump=0.1)
    topo = tp.build_topology(F, V.shape[0])
    view = topo.on(V.device)
    plan = gather_plan_of(topo, view)
    for layout in (*view.groups, *view.groups[0].chunks, plan, plan.vertex):
        out = layout.to(META)
        assert type(out) is type(layout)
        before, after = _tensors(layout), _tensors(out)
        assert len(after) == len(before) > 0
        for a, b in zip(before, after, strict=True):
            assert b.device == META and a.device.type == "cpu"
            assert (a.shape, a.dtype) == (b.shape, b.dtype)
        for f in dataclasses.fields(layout):
            value = getattr(layout, f.name)
            if isinstance(value, int):
                assert getattr(out, f.name) == value


def test_moved_leaves_the_original_alone() -> None:
    V, F = quad_grid(2)
    group = tp.build_topology(F, V.shape[0]).on(V.device).groups[0]
    out = moved(group, META)
    assert group.face_ids.device.type == "cpu" and out.face_ids.device == META

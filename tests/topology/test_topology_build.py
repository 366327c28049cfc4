"""The topology build against pure-Python references on small random meshes: pattern, scatter
positions, edges, the report's edge findings, and the key sort's two routes."""

from __future__ import annotations

import warnings
from collections import defaultdict

import numpy as np
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

import torch_polylap as tp
from torch_polylap.shapes import quad_grid
from torch_polylap.topology.build import _sort_keys, _unique_pairs


@st.composite
def polygon_soups(draw):
    """Arbitrary simple polygons on a few vertices: non-manifold and misoriented edges,
    duplicated faces and isolated vertices all occur."""
    n = draw(st.integers(3, 12))
    face = st.lists(st.integers(0, n - 1), min_size=3, max_size=min(n, 7), unique=True)
    return draw(st.lists(face, min_size=1, max_size=14)), n + draw(st.integers(0, 2))


@st.composite
def flipped_grid_subsets(draw):
    """Faces of an oriented quad/triangle grid, some dropped and some reversed: manifold
    edges, misoriented wherever a reversed face meets a kept one."""
    _, grid = quad_grid(4, 3)
    quads = grid.tolist()
    tris = [[a, b, c] for a, b, c, _ in quads] + [[a, c, d] for a, _, c, d in quads]
    faces = draw(st.sampled_from([quads, tris, quads[:6] + tris[12:]]))
    keep = draw(st.lists(st.booleans(), min_size=len(faces), max_size=len(faces)))
    flip = draw(st.lists(st.booleans(), min_size=len(faces), max_size=len(faces)))
    out = [f[::-1] if r else f for f, k, r in zip(faces, keep, flip, strict=True) if k]
    return out or faces[:1], 20


def _reference(faces: list[list[int]]) -> dict:
    """Edges, their uses and directions, walked face by face."""
    uses: dict[tuple[int, int], int] = defaultdict(int)
    forward: dict[tuple[int, int], int] = defaultdict(int)
    half_edges = []
    for f in faces:
        for i, a in enumerate(f):
            b = f[(i + 1) % len(f)]
            e = (min(a, b), max(a, b))
            uses[e] += 1
            forward[e] += a < b
            half_edges.append(e)
    edges = sorted(uses)
    # both faces of a misoriented edge run p -> q: stored as (p, q)
    mis = [e if forward[e] == 2 else e[::-1] for e in edges if uses[e] == 2 and forward[e] != 1]
    return {
        "edges": edges,
        "uses": [uses[e] for e in edges],
        "half_edges": half_edges,
        "heavy": [e for e in edges if uses[e] > 2],
        "misoriented": mis,
    }


def _build(faces: list[list[int]], num_verts: int) -> tp.Topology:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return tp.build_topology(faces, num_verts)


def _check_pattern_and_scatter(topo: tp.Topology, faces: list[list[int]], n: int) -> None:
    pairs = {(a, b) for f in faces for a in f for b in f} | {(v, v) for v in range(n)}
    crow, col = topo.crow.numpy(), topo.col.numpy()
    row = np.repeat(np.arange(n), np.diff(crow))
    assert sorted(pairs) == list(zip(row.tolist(), col.tolist(), strict=True))
    for grp in topo.groups:
        pi, pj = grp.pair_i.numpy(), grp.pair_j.numpy()
        for c in grp.chunks:
            corners = c.corners_t.numpy()
            up = c.pos_upper.numpy().reshape(pi.size, -1)
            low = c.pos_lower.numpy().reshape(pi.size, -1)
            diag = c.pos_diag.numpy().reshape(grp.k, -1)
            # a pair's two entries: (lo, hi) above the diagonal, (hi, lo) below (L is symmetric)
            lo = np.minimum(corners[pi], corners[pj])
            hi = np.maximum(corners[pi], corners[pj])
            assert np.array_equal(row[up], lo) and np.array_equal(col[up], hi)
            assert np.array_equal(row[low], hi) and np.array_equal(col[low], lo)
            assert np.array_equal(row[diag], corners) and np.array_equal(col[diag], corners)


def _check_edges(topo: tp.Topology, ref: dict) -> None:
    assert [tuple(e) for e in topo.edges.tolist()] == ref["edges"]
    assert topo.edge_faces.tolist() == ref["uses"]
    edges = topo.edges.numpy()
    assert [tuple(edges[e]) for e in topo.half_edge_edge.tolist()] == ref["half_edges"]
    for t in (topo.edges, topo.edge_faces, topo.half_edge_edge):
        assert t.dtype == torch.int64


@settings(max_examples=150, deadline=None)
@given(st.one_of(polygon_soups(), flipped_grid_subsets()))
def test_build_matches_python_reference(mesh):
    faces, n = mesh
    topo = _build(faces, n)
    ref = _reference(faces)
    _check_pattern_and_scatter(topo, faces, n)
    _check_edges(topo, ref)
    report = topo.report
    assert [tuple(e) for e in report.non_manifold_edges.tolist()] == ref["heavy"]
    assert [tuple(e) for e in report.misoriented_edges.tolist()] == ref["misoriented"]
    assert report.non_manifold_edges.dtype == report.misoriented_edges.dtype == np.int64
    used = {v for f in faces for v in f}
    assert report.isolated_vertices.tolist() == [v for v in range(n) if v not in used]
    if not ref["heavy"] and not ref["misoriented"]:
        assert report.is_oriented and topo.half_edge_twin.shape == (len(ref["half_edges"]),)


@settings(max_examples=100, deadline=None)
@given(
    st.lists(st.integers(0, 40), min_size=0, max_size=200),
    st.sampled_from([41, 2**20, 2**31]),
)
def test_key_sort_routes_agree_with_argsort(values, nv):
    # nv = 2**31: keys and positions do not fit one int64, so argsort sorts them; the others
    # take the packed in-place sort. Both must give the sorted keys and a stable permutation.
    keys = np.asarray(values, dtype=np.int64) * np.int64(nv) // 41
    perm, sk = _sort_keys(keys.copy(), np.int64(nv))
    ref = np.argsort(keys, kind="stable")
    assert np.array_equal(perm, ref) and np.array_equal(sk, keys[ref])
    ulo, uhi, inv = _unique_pairs(keys.copy(), np.int64(nv))
    uniq = np.unique(keys)
    assert np.array_equal(ulo * nv + uhi, uniq) and np.array_equal(uniq[inv], keys)

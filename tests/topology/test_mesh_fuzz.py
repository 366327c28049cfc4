"""Random polygon meshes as people download them: every input gives either a clear error that
names the offending element or a valid operator (finite, symmetric, PSD, L 1 = 0, kernel of
dimension the number of components).

Meshes are random grids of mixed-degree polygons (quads, triangle pairs, hexagons merged from
two cells), then randomly flipped, duplicated, glued non-manifoldly (fins on random edges),
scaled, or corrupted. Hypothesis draws the sizes, probabilities and a seed; numpy builds the
mesh from the seed. ``COUNTS`` records how many inputs each category tried.
"""

from __future__ import annotations

import re
import warnings
from collections import Counter

import numpy as np
import pytest
import torch
from fuzzing import fuzz_settings, tally_fixture
from hypothesis import given, settings
from hypothesis import strategies as st

import torch_polylap as tp
from torch_polylap import repair

# the fuzzed meshes are non-manifold and misoriented on purpose: the warning that says so is
# expected (tests/topology/test_topology.py checks its text)
pytestmark = pytest.mark.filterwarnings("ignore:the mesh .* is not a consistently oriented")

COUNTS: Counter = Counter()
FUZZ = fuzz_settings(60)
_print_counts = tally_fixture(COUNTS, "fuzz inputs")


def polygon_grid(rng: np.random.Generator, n: int, m: int) -> tuple[np.ndarray, list[list[int]]]:
    """A jittered, bumpy ``n x m`` grid whose cells are quads, triangle pairs or hexagons."""
    xs, ys = np.meshgrid(np.arange(n + 1.0), np.arange(m + 1.0), indexing="ij")
    xs = xs + rng.uniform(-0.2, 0.2, xs.shape)
    ys = ys + rng.uniform(-0.2, 0.2, ys.shape)
    zs = 0.3 * np.sin(xs) * np.cos(0.7 * ys)
    verts = np.stack([xs.ravel(), ys.ravel(), zs.ravel()], 1)
    v = np.arange((n + 1) * (m + 1)).reshape(n + 1, m + 1)
    faces, used = [], np.zeros((n, m), bool)
    for i in range(n):
        for j in range(m):
            if used[i, j]:
                continue
            r = rng.random()
            if r < 0.2 and j + 1 < m and not used[i, j + 1]:
                used[i, j + 1] = True
                faces.append(
                    [
                        v[i, j],
                        v[i + 1, j],
                        v[i + 1, j + 1],
                        v[i + 1, j + 2],
                        v[i, j + 2],
                        v[i, j + 1],
                    ]
                )
            elif r < 0.45:
                faces += [
                    [v[i, j], v[i + 1, j], v[i + 1, j + 1]],
                    [v[i, j], v[i + 1, j + 1], v[i, j + 1]],
                ]
            else:
                faces.append([v[i, j], v[i + 1, j], v[i + 1, j + 1], v[i, j + 1]])
    return verts, [[int(c) for c in f] for f in faces]


def flip_some(rng, faces, p):
    return [f[::-1] if rng.random() < p else f for f in faces]


def duplicate_some(rng, faces, count):
    extra = []
    for f in rng.choice(len(faces), size=count).tolist():
        face = faces[f]
        s = int(rng.integers(len(face)))
        face = face[s:] + face[:s]
        extra.append(face[::-1] if rng.random() < 0.5 else face)
    return faces + extra


def add_fins(rng, verts, faces, count):
    """Glue a quad onto ``count`` random edges, making them non-manifold where interior."""
    verts, faces = verts.copy(), list(faces)
    for f in rng.choice(len(faces), size=count).tolist():
        face = faces[f]
        c = int(rng.integers(len(face)))
        p, q = face[c], face[(c + 1) % len(face)]
        up = np.array([0.1, 0.2, 1.0]) * rng.uniform(0.5, 2)
        n = len(verts)
        verts = np.vstack([verts, verts[p] + up, verts[q] + up])
        faces.append([p, q, n + 1, n])
    return verts, faces


def assert_valid(V: torch.Tensor, faces) -> None:
    """L finite, symmetric, PSD, L 1 = 0, kernel = components; M0 finite and >= 0."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        topo = tp.build_topology(faces, V.shape[0])
    L, M0 = tp.laplacian(V, topo)
    Ld = L.to_dense().numpy()
    scale = np.abs(Ld).max()
    assert np.isfinite(Ld).all() and np.isfinite(M0.to_dense().numpy()).all()
    # lumped mass: |f| / k to each corner, so the masses add up to the total area and every
    # vertex of a face with positive area gets a positive mass
    m = M0.to_dense().diagonal()
    areas = tp.face_areas(V, topo.faces)
    assert float(m.sum()) == pytest.approx(float(areas.sum()), rel=1e-12, abs=1e-300)
    with_area = topo.faces.indices[torch.repeat_interleave(areas > 0, topo.faces.sizes)]
    assert bool((m[with_area] > 0).all())
    assert np.abs(Ld - Ld.T).max() <= 1e-13 * scale
    assert np.abs(Ld.sum(1)).max() <= 1e-11 * scale
    eig = np.linalg.eigvalsh(Ld / scale)
    assert eig[0] >= -1e-12 * eig[-1]
    n_comp, _ = topo.connected_components()
    assert int((eig < 1e-9 * eig[-1]).sum()) == n_comp


sizes = st.tuples(st.integers(1, 5), st.integers(1, 5), st.integers(0, 2**32 - 1))


def fuzzed_grid(nms: tuple[int, int, int], case: str) -> tuple:
    """``(rng, verts, faces)``: the mixed-degree grid of the drawn ``(n, m, seed)`` and the
    generator that goes on drawing from the same seed; counts one example of ``case``."""
    n, m, seed = nms
    COUNTS[case] += 1
    rng = np.random.default_rng(seed)
    return (rng, *polygon_grid(rng, n, m))


@FUZZ
@given(sizes)
def test_mixed_degree_grids(nms):
    _, verts, faces = fuzzed_grid(nms, "mixed-degree grid")
    assert_valid(torch.from_numpy(verts), faces)


@FUZZ
@given(sizes, st.floats(0.05, 0.9))
def test_random_flips(nms, p):
    rng, verts, faces = fuzzed_grid(nms, "random flips")
    flipped = flip_some(rng, faces, p)
    V = torch.from_numpy(verts)
    assert_valid(V, flipped)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        same = tp.laplacian(V, flipped)[0].to_dense()
    assert torch.allclose(same, tp.laplacian(V, faces)[0].to_dense(), rtol=0, atol=1e-13)


@FUZZ
@given(sizes, st.integers(1, 4))
def test_random_duplicates(nms, count):
    rng, verts, faces = fuzzed_grid(nms, "random duplicates")
    dup = duplicate_some(rng, faces, count)
    assert_valid(torch.from_numpy(verts), dup)
    _, cleaned, rep = repair.remove_duplicate_faces(verts, dup)
    assert cleaned.num_faces == len(faces) and rep.removed_faces.size == count


@FUZZ
@given(sizes, st.integers(1, 3), st.floats(0.0, 0.5))
def test_random_nonmanifold_gluing(nms, fins, p):
    rng, verts, faces = fuzzed_grid(nms, "non-manifold gluing")
    verts, faces = add_fins(rng, verts, flip_some(rng, faces, p), fins)
    assert_valid(torch.from_numpy(verts), faces)


@FUZZ
@given(sizes, st.floats(-150, 150), st.floats(0.0, 0.5))
def test_random_scales_on_quad_meshes(nms, log_scale, p):
    """float64 quads at scales 1e-150..1e150: the same L to round-off, M0 scaled by s^2."""
    n, m, seed = nms
    COUNTS["random scale (quads)"] += 1
    rng = np.random.default_rng(seed)
    xs, ys = np.meshgrid(np.arange(n + 1.0), np.arange(m + 1.0), indexing="ij")
    verts = np.stack([xs.ravel(), ys.ravel(), 0.3 * np.sin(xs.ravel() + ys.ravel())], 1)
    verts[:, :2] += rng.uniform(-0.2, 0.2, (len(verts), 2))
    v = np.arange(len(verts)).reshape(n + 1, m + 1)
    quads = np.stack([v[:-1, :-1], v[1:, :-1], v[1:, 1:], v[:-1, 1:]], -1).reshape(-1, 4).tolist()
    faces = flip_some(rng, quads, p)
    s = 10.0**log_scale
    V = torch.from_numpy(verts)
    assert_valid(V * s, faces)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        L1, M1 = tp.laplacian(V, faces)
        Ls, Ms = tp.laplacian(V * s, faces)
    ref = L1.to_dense()
    assert float((Ls.to_dense() - ref).abs().max() / ref.abs().max()) <= 1e-10
    m1 = M1.to_dense().diagonal()
    assert torch.allclose(Ms.to_dense().diagonal() / s**2, m1, rtol=1e-10, atol=0)


CORRUPTIONS = ["out_of_range", "repeat_vertex", "fractional", "nan_vertex", "collapse_face"]


@pytest.mark.parametrize("kind", CORRUPTIONS)
@settings(FUZZ, max_examples=25)
@given(nms=sizes, pick=st.integers(0, 10**6))
def test_corrupted_inputs_name_the_element(kind, nms, pick):
    n, m, seed = nms
    COUNTS[f"corrupted: {kind}"] += 1
    rng = np.random.default_rng(seed)
    verts, faces = polygon_grid(rng, n, m)
    f = pick % len(faces)
    faces = [list(face) for face in faces]
    expect = rf"face {f}\b"
    if kind == "out_of_range":
        faces[f][0] = len(verts) + pick % 7
    elif kind == "repeat_vertex":
        faces[f][-1] = faces[f][0] if len(faces[f]) > 3 else faces[f][1]
    elif kind == "fractional":
        faces[f] = [float(c) for c in faces[f]]
        faces[f][1] += 0.5
    elif kind == "nan_vertex":
        vert = faces[f][pick % len(faces[f])]
        verts[vert, pick % 3] = np.nan
        expect = rf"vertex {vert}\b"
    else:  # every corner of face f onto one line; the first face so degenerate is named
        corners = faces[f]
        # exactly collinear: a base on a 1/8 grid plus quarter steps along a dyadic direction,
        # so no sum rounds (rounded corners would leave a sliver of area ~eps, a valid face)
        t = 0.25 * np.arange(len(corners))[:, None]
        verts[corners] = np.round(8 * verts[corners[0]]) / 8 + t * np.array([1.0, 0.5, 0.25])
        expect = r"face \d+ .*zero vector area"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        with pytest.raises((ValueError, TypeError)) as err:
            tp.laplacian(torch.from_numpy(verts), faces)
    assert re.search(expect, str(err.value)), str(err.value)

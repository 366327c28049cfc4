"""Face and vertex measures and the planarity loss refuse non-finite vertex coordinates, as
``laplacian`` and the losses that assemble it do; ``validate=False`` is the escape hatch."""

from __future__ import annotations

import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

import torch_polylap as tp
from torch_polylap.losses import planarity_loss
from torch_polylap.shapes import quad_grid

MEASURES = {
    "mass": tp.mass,
    "vector_area": tp.vector_area,
    "face_areas": tp.face_areas,
    "face_normals": tp.face_normals,
    "edge_lengths": tp.edge_lengths,
    "mean_edge_length": tp.mean_edge_length,
    "face_nonplanarity": tp.face_nonplanarity,
    "face_planarity_energy": tp.face_planarity_energy,
    "planarity_energy": tp.planarity_energy,
}


@settings(max_examples=60, deadline=None)
@given(
    name=st.sampled_from(sorted(MEASURES)),
    vertex=st.integers(0, 15),
    coordinate=st.integers(0, 2),
    bad=st.sampled_from([math.nan, math.inf, -math.inf]),
    dtype=st.sampled_from([torch.float32, torch.float64]),
)
def test_measures_refuse_non_finite_coordinates(name, vertex, coordinate, bad, dtype):
    V, F = quad_grid(3, bump=0.2)  # 16 vertices, every one in a face
    V = V.to(dtype)
    V[vertex, coordinate] = bad
    with pytest.raises(ValueError, match=f"vertex {vertex} of verts is not finite"):
        MEASURES[name](V, F)
    # the escape hatch: no test, and the non-finite value reaches the result
    out = MEASURES[name](V, F, validate=False)
    assert not bool(torch.isfinite(out).all())


@settings(max_examples=30, deadline=None)
@given(
    mesh=st.integers(0, 1),
    vertex=st.integers(0, 15),
    bad=st.sampled_from([math.nan, math.inf, -math.inf]),
)
def test_planarity_loss_refuses_non_finite_coordinates(mesh, vertex, bad):
    """As the losses that assemble ``L`` do: the packed vertex is named."""
    (V0, F0), (V1, F1) = quad_grid(3, bump=0.2), quad_grid(3, bump=0.3)
    verts = [V0.clone(), V1.clone()]
    verts[mesh][vertex, 1] = bad
    meshes = tp.PolygonMeshes(verts, [F0, F1])
    with pytest.raises(ValueError, match=f"vertex {16 * mesh + vertex} of verts_packed"):
        planarity_loss(meshes)
    with pytest.raises(ValueError, match="non-finite"):
        tp.losses.bending_energy(meshes)  # the behaviour it now shares


def test_finite_inputs_are_unchanged_by_the_check(device):
    V, F = quad_grid(3, bump=0.2, device=device)
    for fn in MEASURES.values():
        torch.testing.assert_close(fn(V, F), fn(V, F, validate=False), rtol=0, atol=0)

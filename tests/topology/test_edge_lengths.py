"""Edge lengths against a reference that walks the face lists in Python: every undirected edge
once, whichever faces share it, and their mean as the mesh's length scale."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from conftest import mixed_mesh, tolerances

import torch_polylap as tp


def _reference_lengths(verts: np.ndarray, faces: list[list[int]]) -> dict[tuple[int, int], float]:
    out = {}
    for face in faces:
        for p, q in zip(face, face[1:] + face[:1], strict=True):
            out[min(p, q), max(p, q)] = float(np.linalg.norm(verts[q] - verts[p]))
    return out


def test_edge_lengths_match_a_walk_over_the_faces(device, dtype):
    verts, faces = mixed_mesh()
    faces = tp.as_faces(faces)
    verts = verts.to(device, dtype)
    # the reference from the same (rounded) coordinates, in float64 on the CPU
    ref = _reference_lengths(verts.cpu().double().numpy(), faces.tolist())
    edges = tp.get_topology(faces, verts.shape[0]).edges.tolist()
    lengths = tp.edge_lengths(verts, faces)
    assert lengths.device.type == device.type and lengths.dtype == dtype
    assert sorted(map(tuple, edges)) == sorted(ref)
    rtol = 1e-14 if dtype == torch.float64 else tolerances(dtype)["rtol"]
    assert np.allclose(lengths.cpu().numpy(), [ref[tuple(e)] for e in edges], rtol=rtol)
    mean = tp.mean_edge_length(verts, faces)
    assert mean.dim() == 0 and math.isclose(float(mean), np.mean(list(ref.values())), rel_tol=rtol)


def test_mean_edge_length_gradient(device, dtype):
    # a unit square scaled by s has four edges of length s: d h / d s = 1
    s = torch.tensor(1.5, dtype=dtype, device=device, requires_grad=True)
    square = torch.tensor(
        [[0.0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], dtype=dtype, device=device
    )
    h = tp.mean_edge_length(s * square, [[0, 1, 2, 3]])
    (grad,) = torch.autograd.grad(h, s)
    rtol = tolerances(dtype)["rtol"]
    assert h.dtype == grad.dtype == dtype
    assert math.isclose(float(h.detach()), 1.5, rel_tol=rtol) and math.isclose(
        float(grad), 1.0, rel_tol=rtol
    )


@pytest.mark.filterwarnings("ignore:the mesh .* is not a consistently oriented")  # on purpose
def test_mean_edge_length_of_a_mesh_without_faces_is_refused(device):
    """No edges: no length scale, an error rather than the NaN of an empty mean."""
    verts = torch.zeros(3, 3, dtype=torch.float64, device=device)
    with pytest.raises(ValueError, match="no faces"):
        tp.mean_edge_length(verts, torch.zeros(0, 3, dtype=torch.long))

"""The validation vocabulary (``torch_polylap.checks``) and its use at every public entry.

Property-based: whatever is accepted comes back normalized, whatever is refused raises a
TypeError (wrong kind of object) or a ValueError (bad content) whose message names the argument.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

import torch_polylap as tp
from torch_polylap import checks
from torch_polylap.shapes import quad_grid

SETTINGS = settings(max_examples=60, deadline=None)


@SETTINGS
@given(
    rows=st.integers(0, 6),
    cols=st.integers(1, 5),
    dtype=st.sampled_from([torch.float32, torch.float64, torch.int64, torch.float16]),
)
def test_check_verts_accepts_exactly_real_v_by_3_tensors(rows, cols, dtype):
    verts = torch.zeros(rows, cols, dtype=dtype)
    if cols == 3 and dtype in (torch.float32, torch.float64):
        assert checks.check_verts(verts) is verts
        return
    with pytest.raises((TypeError, ValueError), match="verts"):
        checks.check_verts(verts)


@SETTINGS
@given(row=st.integers(0, 4), value=st.sampled_from([float("nan"), float("inf"), -float("inf")]))
def test_check_verts_names_the_first_non_finite_vertex(row, value):
    verts = torch.zeros(5, 3, dtype=torch.float64)
    verts[row, 1] = value
    with pytest.raises(ValueError, match=f"vertex {row} of verts is not finite"):
        checks.check_verts(verts)
    assert checks.check_verts(verts, finite=False) is verts


@SETTINGS
@given(
    shape=st.tuples(st.integers(0, 5), st.integers(1, 4)),
    kind=st.sampled_from(["f8", "f4", "i8", "u1", "c16", "U3", "b1"]),
    as_tensor=st.booleans(),
)
def test_check_verts_array_returns_float64_v_by_3_or_refuses(shape, kind, as_tensor):
    arr = np.zeros(shape, dtype=kind)
    value: object = arr
    if as_tensor and kind not in ("U3",):
        value = torch.from_numpy(arr)
    if kind in ("c16", "U3", "b1"):
        with pytest.raises(TypeError, match="real coordinates"):
            checks.check_verts_array(value)
        return
    if shape[1] != 3:
        with pytest.raises(ValueError, match=r"shape \(V, 3\)"):
            checks.check_verts_array(value)
        return
    out = checks.check_verts_array(value)
    assert out.dtype == np.float64 and out.shape == shape


@SETTINGS
@given(st.lists(st.integers(-3, 12), max_size=8))
def test_check_index_or_mask_accepts_unique_in_range_indices(idx):
    n = 10
    ok = all(0 <= i < n for i in idx) and len(set(idx)) == len(idx)
    if ok:
        out = checks.check_index_or_mask(idx, n, "fixed")
        assert out.dtype == torch.int64 and out.tolist() == idx
    else:
        with pytest.raises(ValueError, match=r"fixed\[\d+\]"):
            checks.check_index_or_mask(idx, n, "fixed")


@SETTINGS
@given(st.lists(st.booleans(), min_size=1, max_size=12))
def test_check_index_or_mask_turns_a_mask_of_the_right_length_into_indices(mask):
    n = len(mask)
    out = checks.check_index_or_mask(torch.tensor(mask), n, "pins")
    assert out.tolist() == [i for i, m in enumerate(mask) if m]
    with pytest.raises(ValueError, match="boolean mask"):
        checks.check_index_or_mask(torch.tensor(mask + [True]), n, "pins")


@SETTINGS
@given(st.one_of(st.integers(-5, 5), st.floats(-5, 5), st.booleans(), st.text(max_size=2)))
def test_check_positive_int(value):
    if isinstance(value, int) and not isinstance(value, bool) and value >= 1:
        assert checks.check_positive_int(value, "k") == value
    else:
        with pytest.raises((TypeError, ValueError), match="k must be a positive integer"):
            checks.check_positive_int(value, "k")


@SETTINGS
@given(st.one_of(st.integers(-5, 5), st.floats(-5, 5), st.booleans(), st.text(max_size=2)))
def test_check_int_with_a_lower_bound(value):
    if isinstance(value, int) and not isinstance(value, bool) and value >= 0:
        assert checks.check_int(value, "n", least=0) == value
    elif isinstance(value, int) and not isinstance(value, bool):
        with pytest.raises(ValueError, match=f"n must be an integer >= 0, got {value}"):
            checks.check_int(value, "n", least=0)
    else:
        # a wrong kind of object is a TypeError, and a ValueError for the entries that once
        # raised that
        with pytest.raises(checks.NotAnIntegerError, match="n must be an integer >= 0") as err:
            checks.check_int(value, "n", least=0)
        assert isinstance(err.value, TypeError) and isinstance(err.value, ValueError)


def test_inverse_or_zero_is_zero_on_empty_rows_and_has_finite_gradients():
    d = torch.tensor([2.0, 0.0, 0.5, -0.0], dtype=torch.float64, requires_grad=True)
    inv = checks.inverse_or_zero(d)
    torch.testing.assert_close(inv, torch.tensor([0.5, 0.0, 2.0, 0.0], dtype=torch.float64))
    inv.sum().backward()
    # d(1/d) = -1/d^2 where d > 0, and no NaN from the masked branch
    torch.testing.assert_close(d.grad, torch.tensor([-0.25, 0.0, -4.0, 0.0], dtype=torch.float64))


# Every public entry that takes vertex positions refuses a (V, 2) array with the same words.
ENTRIES = {
    "laplacian": lambda v, f: tp.laplacian(v, f),
    "mass": lambda v, f: tp.mass(v, f),
    "vector_area": lambda v, f: tp.vector_area(v, f),
    "PolygonLaplacian": lambda v, f: tp.PolygonLaplacian()(v, f),
    "gradient_operator": lambda v, f: tp.gradient_operator(v, f),
    "mean_curvature_flow": lambda v, f: tp.apps.mean_curvature_flow(v, f, 1e-3, steps=1),
    "planarize": lambda v, f: tp.apps.planarize(v, f),
    "conformal_parameterization": lambda v, f: tp.apps.conformal_parameterization(v, f),
    "plate_bending": lambda v, f: tp.apps.plate_bending(v, f, torch.zeros(v.shape[0])),
    "sample_points": lambda v, f: tp.fitting.sample_points(v, f, 10),
    "PolygonMeshes": lambda v, f: tp.PolygonMeshes([v], [f]),
    "write_mesh": lambda v, f: tp.write_mesh("/nonexistent/never_written.obj", v, f),
    "orient_faces": lambda v, f: tp.repair.orient_faces(v, f),
}


@pytest.mark.parametrize("entry", sorted(ENTRIES))
def test_every_entry_refuses_flat_vertices_in_the_same_words(entry, device):
    verts, faces = quad_grid(2, device=device)
    with pytest.raises(ValueError, match=r"must have shape \(V, 3\), got \(9, 2\)"):
        ENTRIES[entry](verts[:, :2], faces)


def test_any_real_lam_is_accepted_as_the_float_it_equals(device):
    """A ``Fraction`` (or any numbers.Real) passes the check and gives the operator of its value."""
    from fractions import Fraction

    verts, faces = quad_grid(2, bump=0.3, device=device)
    L, _ = tp.laplacian(verts, faces, Fraction(3, 2))
    assert L.device.type == device.type
    torch.testing.assert_close(L.to_dense(), tp.laplacian(verts, faces, 1.5)[0].to_dense())


# One finiteness test (a reduction and a host sync) per call: entries built on other entries
# check the positions once, at the door, and hand them on unchecked.
ONE_CHECK = {
    "vertex_gradient_operators": lambda v, f: tp.tangent.vertex_gradient_operators(v, f),
    "vertex_tangent_frames": lambda v, f: tp.tangent.vertex_tangent_frames(v, f),
    "connection_laplacian": lambda v, f: tp.vector.connection_laplacian(v, f),
    "VectorHeatSolver": lambda v, f: tp.vector.VectorHeatSolver(v, f),
    "HeatGeodesicSolver": lambda v, f: tp.HeatGeodesicSolver(v, f),
    "principal_curvatures": lambda v, f: tp.vector.principal_curvatures(v, f),
    "HodgeDecomposition": lambda v, f: tp.vector.HodgeDecomposition(v, f),
}


@pytest.mark.parametrize("entry", sorted(ONE_CHECK))
def test_positions_are_checked_once_per_call(entry, monkeypatch):
    verts, faces = tp.shapes.quad_sphere(2)
    calls = []
    real = checks.check_finite

    def counted(x, name, what="row"):
        calls.append(name)
        real(x, name, what)

    monkeypatch.setattr(checks, "check_finite", counted)
    ONE_CHECK[entry](verts, faces)
    assert calls == ["verts"]

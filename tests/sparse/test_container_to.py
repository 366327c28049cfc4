"""``.to`` of the batch containers (``PolygonMeshes``, ``Spectrum``, ``MeshBatch``) takes the
arguments :meth:`torch.Tensor.to` takes, and moves every tensor as torch would move it.

The reference is torch itself: each container's floating tensors must end up exactly as
``tensor.to(*args, **kwargs)`` leaves them, and the argument parser must refuse what torch
refuses (checked on random argument lists with hypothesis).
"""

from __future__ import annotations

import pytest
import torch
from conftest import hex_pent_mesh, mixed_mesh
from hypothesis import example, given, settings
from hypothesis import strategies as st

from torch_polylap.batch import PolygonMeshes, to_arguments
from torch_polylap.datasets import PolygonMeshDataset, collate_meshes
from torch_polylap.shapes import quad_grid

F32, F64 = torch.float32, torch.float64


def _meshes() -> PolygonMeshes:
    v1, f1 = mixed_mesh()
    v2, f2 = hex_pent_mesh()
    v3, f3 = quad_grid(2, bump=0.1, seed=3)
    return PolygonMeshes([v1, v2, v3], [f1, f2, f3])


def _forms(device: torch.device) -> list[tuple[tuple, dict]]:
    """Every call form of torch's ``Tensor.to`` (``dtype``, ``device``, both, a tensor,
    keywords, ``non_blocking``/``copy`` positionally and as keywords)."""
    like = torch.zeros(1, dtype=F32, device=device)
    return [
        ((F32,), {}),
        ((device,), {}),
        ((str(device),), {}),
        ((device, F32), {}),
        ((like,), {}),
        ((), {"dtype": F32}),
        ((), {"device": device}),
        ((), {"device": device, "dtype": F32}),
        ((device,), {"dtype": F32}),
        ((F32, False, True), {}),
        ((F32,), {"non_blocking": True}),
        ((like, True), {"copy": True}),
        ((device, F32, False, True), {}),
        ((None, F32), {}),
        ((), {"dtype": F32, "copy": True, "memory_format": torch.preserve_format}),
    ]


def _torch_moves(t: torch.Tensor, args: tuple, kwargs: dict) -> torch.Tensor:
    return t.to(*args, **kwargs)


@pytest.mark.parametrize("form", range(15))
def test_polygon_meshes_to_takes_every_tensor_form(form, device):
    args, kwargs = _forms(device)[form]
    m = _meshes()
    expected = _torch_moves(m.verts_packed(), args, kwargs)
    moved = m.to(*args, **kwargs)
    assert isinstance(moved, PolygonMeshes)
    got = moved.verts_packed()
    assert got.dtype == expected.dtype and got.device == expected.device
    assert torch.equal(got.cpu(), expected.cpu())
    # the connectivity (and its caches) is shared, the faces unchanged
    assert moved.faces_packed().tolist() == m.faces_packed().tolist()
    assert moved.verts_packed_to_mesh_idx().device == got.device
    if kwargs.get("copy") or (len(args) > 2 and args[-1] is True):
        assert got.data_ptr() != m.verts_packed().data_ptr()


def test_polygon_meshes_to_dtype_is_float64_to_float32_and_back(device):
    m = _meshes().to(device)
    single = m.to(torch.float32)  # the call that used to raise a TypeError
    assert single.dtype == F32 and single.device == m.device
    torch.testing.assert_close(single.to(F64).verts_packed(), m.verts_packed(), rtol=1e-6, atol=0)
    L, M0 = single.laplacian()
    assert L.dtype == F32 and M0.dtype == F32


@pytest.fixture
def mesh_batch(tmp_path):
    v1, f1 = mixed_mesh()
    v2, f2 = hex_pent_mesh()
    data = PolygonMeshDataset(
        [(v1, f1), (v2, f2)], [0, 1], k=4, cache_dir=tmp_path, gradient_operators=True
    )
    return collate_meshes([data[0], data[1]])


@pytest.mark.parametrize("form", range(15))
def test_mesh_batch_and_spectrum_to_take_every_tensor_form(form, device, mesh_batch):
    args, kwargs = _forms(device)[form]
    moved = mesh_batch.to(*args, **kwargs)
    pairs = [
        (moved.meshes.verts_packed(), mesh_batch.meshes.verts_packed()),
        (moved.spectrum.evals, mesh_batch.spectrum.evals),
        (moved.spectrum.evecs, mesh_batch.spectrum.evecs),
        (moved.spectrum.mass, mesh_batch.spectrum.mass),
    ]
    for name in ("L", "grad_x", "grad_y"):
        pairs.append((getattr(moved, name).values(), getattr(mesh_batch, name).values()))
    for got, original in pairs:
        expected = _torch_moves(original, args, kwargs)
        assert got.dtype == expected.dtype and got.device == expected.device
        assert torch.equal(got.cpu(), expected.cpu())
    # integer tensors move but keep their dtype, as nn.Module.to keeps integer buffers
    assert moved.labels.dtype == torch.int64 and moved.labels.device == expected.device
    assert moved.spectrum.num_verts.dtype == torch.int64
    assert torch.equal(moved.labels.cpu(), mesh_batch.labels)
    spectrum = mesh_batch.spectrum.to(*args, **kwargs)
    assert torch.equal(spectrum.evecs.cpu(), moved.spectrum.evecs.cpu())


def test_to_refuses_what_torch_refuses_and_integer_dtypes():
    m = _meshes()
    v = m.verts_packed()
    for args, kwargs in [
        ((F32,), {"device": "cpu"}),  # torch: dtype first takes no device
        (("cpu", F32, False, True, False), {}),  # too many
        (("cpu",), {"device": "cpu"}),  # given twice
        ((v,), {"dtype": F32}),
        ((F32,), {"non_blocking": 1}),
        ((), {"devices": "cpu"}),
    ]:
        with pytest.raises(TypeError):
            v.to(*args, **kwargs)
        with pytest.raises(TypeError):
            m.to(*args, **kwargs)
    # torch casts positions to integers; a mesh container keeps them floating point
    with pytest.raises(TypeError, match="floating point"):
        m.to(torch.int64)
    with pytest.raises(TypeError, match="memory_format"):
        m.to(memory_format=torch.channels_last)


_DEVICES = [None, "cpu", torch.device("cpu"), True, "nowhere"]
_DTYPES = [None, F32, F64, torch.int64, "float32"]
_VALUES = [*_DEVICES, *_DTYPES, False, torch.zeros(1), torch.zeros(1, dtype=F64)]


@settings(max_examples=300, deadline=None)
@given(
    args=st.lists(st.sampled_from(_VALUES), max_size=5),
    kwargs=st.dictionaries(
        st.sampled_from(["device", "dtype", "non_blocking", "copy"]),
        st.sampled_from(_VALUES),
        max_size=3,
    ),
)
# torch reads the device before it casts: an unreadable device is its RuntimeError even with an
# integer dtype, and a wrongly typed argument its TypeError before the device is read
@example(args=["nowhere", torch.int64], kwargs={})
@example(args=["nowhere", "cpu"], kwargs={})
def test_to_arguments_accept_exactly_what_tensor_to_accepts(args, kwargs):
    t = torch.zeros(2, dtype=F64)
    try:
        expected = t.to(*args, **kwargs)
    except (TypeError, RuntimeError) as err:  # RuntimeError: a device string torch cannot parse
        with pytest.raises(type(err)):
            to_arguments(*args, **kwargs)
        return
    if not expected.is_floating_point():  # torch casts; the containers keep floating point
        with pytest.raises(TypeError):
            to_arguments(*args, **kwargs)
        return
    move = to_arguments(*args, **kwargs)
    got = move.apply(t)
    assert got.dtype == expected.dtype and got.device == expected.device
    index = move.apply(torch.arange(3))
    assert index.dtype == torch.int64 and index.device == expected.device

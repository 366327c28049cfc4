"""Checkpoints: operators in state dicts and modules survive torch.save / torch.load (torch's
default ``weights_only=True``), load_state_dict, pickle and deepcopy, after forward passes."""

from __future__ import annotations

import copy
import io
import pickle

import pytest
import torch
from conftest import mixed_mesh
from torch import nn

import torch_polylap as tp
from torch_polylap.sparse import UnsupportedOperation


class _Holder(nn.Module):
    """A model that keeps a mesh's operators as buffers, as spectral and diffusion layers do."""

    def __init__(self, L: torch.Tensor, M0: torch.Tensor) -> None:
        super().__init__()
        self.register_buffer("L", L)
        self.register_buffer("M0", M0)
        self.weight = nn.Parameter(torch.ones(3, dtype=L.dtype, device=L.device))

    def forward(self, X: torch.Tensor) -> torch.Tensor:
        return (self.L @ X + self.M0 @ X) * self.weight


def _operators(scale: float = 1.0) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    verts, faces = mixed_mesh()
    L, M0 = tp.laplacian(verts * scale, faces)
    return verts, L, M0


def _roundtrip(obj: object, **load_kwargs: object) -> object:
    buf = io.BytesIO()
    torch.save(obj, buf)
    buf.seek(0)
    return torch.load(buf, **load_kwargs)


def test_state_dict_loads_with_weights_only_default(device):
    verts, L, M0 = (t.to(device) for t in _operators())
    model = _Holder(L, M0)
    sd = _roundtrip(model.state_dict())  # torch's default: weights_only=True
    assert set(sd) == {"L", "M0", "weight"}
    torch.testing.assert_close(sd["L"].to_dense(), L.to_dense(), rtol=0, atol=0)
    assert sd["L"].symmetric and sd["L"].layout == torch.sparse_csr
    assert sd["L"].device.type == device.type
    torch.testing.assert_close(sd["L"] @ verts, L @ verts, rtol=0, atol=0)


def test_load_state_dict_copies_values_into_operator_buffers(device):
    verts, L, M0 = (t.to(device) for t in _operators())
    _, L2, M2 = (t.to(device) for t in _operators(scale=2.0))
    target, source = _Holder(L, M0), _Holder(L2, M2)
    target.load_state_dict(_roundtrip(source.state_dict()))
    torch.testing.assert_close(target(verts), source(verts), rtol=0, atol=0)
    # the buffer is still an operator on the same pattern, with the checkpoint's values
    assert isinstance(target.L, tp.sparse.SparseOperator)
    torch.testing.assert_close(target.L.values(), L2.values(), rtol=0, atol=0)


def test_load_state_dict_of_another_mesh_says_to_assign(device):
    verts, L, M0 = (t.to(device) for t in _operators())
    # same number of vertices, other connectivity: same shapes, other patterns
    faces = [[0, 1, 2, 3], [4, 5, 6, 7], [8, 9, 10, 11]]
    L3, M3 = tp.laplacian(verts, faces)
    with pytest.raises(RuntimeError, match="assign=True"):
        _Holder(L, M0).load_state_dict(_Holder(L3, M3).state_dict())
    model = _Holder(L, M0)
    model.load_state_dict(_Holder(L3, M3).state_dict(), assign=True)
    torch.testing.assert_close(model.L.to_dense(), L3.to_dense(), rtol=0, atol=0)
    torch.testing.assert_close(model(verts), _Holder(L3, M3)(verts), rtol=0, atol=0)


def test_copy_refuses_a_dense_tensor(device):
    L = _operators()[1].to(device)
    with pytest.raises(UnsupportedOperation, match="same sparsity pattern"):
        L.copy_(torch.zeros(L.shape, dtype=L.dtype, device=device))


@pytest.mark.parametrize("dump", ["pickle", "torch.save", "deepcopy"])
def test_modules_batches_and_topologies_pickle_after_a_forward(dump, device):
    verts, faces = mixed_mesh()
    verts = verts.to(device)
    lap = tp.PolygonLaplacian(learn_lam=True)
    L, M0 = lap(verts, faces)
    _ = M0 + 0.5 * L  # fills the pattern's union cache
    _ = L.T @ verts
    topo = tp.get_topology(tp.as_faces(faces), verts.shape[0])
    meshes = tp.PolygonMeshes([verts, verts * 2], [faces, faces])
    meshes.laplacian()
    things = (lap, topo, meshes, _Holder(L.detach(), M0.detach()))
    if dump == "pickle":
        restored = pickle.loads(pickle.dumps(things))
    elif dump == "torch.save":
        restored = _roundtrip(things, weights_only=False)
    else:
        restored = copy.deepcopy(things)
    lap2, topo2, meshes2, holder2 = restored
    L2, M2 = lap2(verts)  # the module kept its topology
    assert L2.device.type == device.type
    torch.testing.assert_close(L2.to_dense(), L.to_dense(), rtol=0, atol=0)
    L3, _ = tp.laplacian(verts, topo2)
    torch.testing.assert_close(L3.to_dense(), L.to_dense(), rtol=0, atol=0)
    torch.testing.assert_close((M2 + 0.5 * L2).to_dense(), (M0 + 0.5 * L).to_dense())
    Lb, _ = meshes2.laplacian()
    Lb0, _ = meshes.laplacian()
    torch.testing.assert_close(Lb.to_dense(), Lb0.to_dense(), rtol=0, atol=0)
    torch.testing.assert_close(holder2(verts), _Holder(L.detach(), M0.detach())(verts))

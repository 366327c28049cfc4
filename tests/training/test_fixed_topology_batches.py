"""Fixed-topology batches: ``(B, V, 3)`` vertices with one faces array give ``(B, V, V)``
batches of operators. Reference: the same computation mesh by mesh in a Python loop."""

from __future__ import annotations

import pytest
import torch
from conftest import mixed_mesh

import torch_polylap as tp
from torch_polylap.kernels import METHODS


def _batch(verts: torch.Tensor, B: int = 3, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    noise = 0.04 * torch.randn((B, *verts.shape), generator=g, dtype=torch.float64)
    return verts.double()[None] + noise


MESHES = {"mixed": mixed_mesh(), "quads": tp.shapes.quad_grid(3, 4)}


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("mesh", MESHES)
def test_batch_equals_mesh_by_mesh(mesh, method, device):
    verts, faces = MESHES[mesh]
    Vs = _batch(verts).to(device)
    L, M0 = tp.laplacian(Vs, faces, method=method)
    assert L.shape == M0.shape == (3, verts.shape[0], verts.shape[0])
    assert L.device.type == M0.device.type == device.type
    for b in range(3):
        Lb, Mb = tp.laplacian(Vs[b], faces, method=method)
        torch.testing.assert_close(L[b].to_dense(), Lb.to_dense(), rtol=1e-13, atol=1e-14)
        torch.testing.assert_close(L.to_dense()[b], Lb.to_dense(), rtol=1e-13, atol=1e-14)
        torch.testing.assert_close(M0.to_dense()[b], Mb.to_dense(), rtol=1e-13, atol=1e-15)


def test_batch_algebra_equals_mesh_by_mesh(device):
    verts, faces = mixed_mesh()
    Vs = _batch(verts, B=4).to(device)
    L, M0 = tp.laplacian(Vs, faces)
    w = torch.linspace(1, 2, verts.shape[0], dtype=torch.float64, device=device)
    A = (M0 + 0.3 * L) * w[:, None]
    shared = torch.randn(verts.shape[0], 2, dtype=torch.float64, device=device)
    vec = torch.randn(4, verts.shape[0], dtype=torch.float64, device=device)
    singles = [tp.laplacian(v, faces) for v in Vs]
    for b, (Lb, Mb) in enumerate(singles):
        Ab = (Mb + 0.3 * Lb) * w[:, None]
        torch.testing.assert_close((A @ Vs)[b], Ab @ Vs[b])
        torch.testing.assert_close((A.mT @ Vs)[b], Ab.T @ Vs[b])
        torch.testing.assert_close((L @ shared)[b], Lb @ shared)
        torch.testing.assert_close((L @ vec)[b], Lb @ vec[b])
        torch.testing.assert_close(A.sum(-1)[b], Ab.sum(1))
    assert [tuple(Lb.shape) for Lb in L] == [tuple(singles[0][0].shape)] * 4


def test_batch_gradients_equal_mesh_by_mesh(device):
    verts, faces = mixed_mesh()
    Vs = _batch(verts).to(device).requires_grad_(True)
    L, M0 = tp.laplacian(Vs, faces)
    loss = ((L @ Vs).square() * M0.diagonal()[..., None]).sum()
    (got,) = torch.autograd.grad(loss, Vs)
    per_mesh = 0.0
    for v in Vs:
        Lb, Mb = tp.laplacian(v, faces)
        per_mesh = per_mesh + ((Lb @ v).square() * Mb.diagonal()[:, None]).sum()
    (want,) = torch.autograd.grad(per_mesh, Vs)
    torch.testing.assert_close(got, want, rtol=1e-12, atol=1e-12)


def test_batch_gradcheck(device):
    verts = torch.tensor(
        [[0, 0, 0], [1, 0, 0.1], [1.1, 1, 0], [0, 1, -0.1], [2, 0.5, 0.2]], dtype=torch.float64
    )
    faces = [[0, 1, 2, 3], [1, 4, 2]]
    Vs = _batch(verts, B=2).to(device).requires_grad_(True)
    X = torch.randn(2, 5, 2, dtype=torch.float64, device=device)

    def f(Vs: torch.Tensor) -> torch.Tensor:
        L, M0 = tp.laplacian(Vs, faces)
        return (M0 + L) @ X

    assert torch.autograd.gradcheck(f, (Vs,))


def test_batch_names_the_mesh_with_bad_vertices(device):
    verts, faces = mixed_mesh()
    Vs = _batch(verts).to(device)
    Vs[2, 5, 0] = float("inf")
    with pytest.raises(ValueError, match="mesh 2 of the batch: vertex 5"):
        tp.laplacian(Vs, faces)


def test_module_takes_batches(device):
    verts, faces = mixed_mesh()
    Vs = _batch(verts).to(device)
    lap = tp.PolygonLaplacian().to(device)
    L, M0 = lap(Vs, faces)
    assert L.device.type == device.type
    L2, _ = lap(Vs * 2.0)  # the cached topology
    torch.testing.assert_close(L2.to_dense(), L.to_dense())
    torch.testing.assert_close(M0.diagonal()[1], tp.laplacian(Vs[1], faces)[1].diagonal())


def test_batch_compiles_to_one_graph(device):
    verts, faces = tp.shapes.quad_grid(3, 4)
    faces = torch.as_tensor(faces)
    Vs = _batch(verts).to(device)

    def energy(Vs: torch.Tensor) -> torch.Tensor:
        L, M0 = tp.laplacian(Vs, faces)
        return ((M0 + 0.1 * L) @ Vs).square().sum()

    torch._dynamo.reset()
    got = torch.compile(energy, backend="aot_eager", fullgraph=True)(Vs)
    torch._dynamo.reset()
    torch.testing.assert_close(got, energy(Vs))

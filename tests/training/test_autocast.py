"""Mixed precision: under torch.autocast the operators are assembled and applied in float32.

Reference: the same computation outside autocast, in float32 (autocast must not change the
operators, and a product with low-precision activations must equal the product with the
activations cast to float32).
"""

from __future__ import annotations

import pytest
import torch
from conftest import mixed_mesh

import torch_polylap as tp
from torch_polylap.kernels import METHODS


def _low(device: torch.device) -> torch.dtype:
    # CPU autocast computes in bfloat16, CUDA autocast in float16 by default
    return torch.bfloat16 if device.type == "cpu" else torch.float16


@pytest.mark.parametrize("method", METHODS)
def test_operators_under_autocast_equal_float32(device, method):
    verts, faces = mixed_mesh()
    X = verts.float().to(device)
    L_ref, M_ref = tp.laplacian(X, faces, method=method)
    with torch.autocast(device.type, dtype=_low(device)):
        L, M0 = tp.laplacian(X, faces, method=method)
    assert L.dtype == M0.dtype == torch.float32
    torch.testing.assert_close(L.to_dense(), L_ref.to_dense(), rtol=0, atol=0)
    torch.testing.assert_close(M0.to_dense(), M_ref.to_dense(), rtol=0, atol=0)


def test_products_with_low_precision_activations_run_in_float32(device):
    verts, faces = mixed_mesh()
    X = verts.float().to(device)
    layer = torch.nn.Linear(3, 8).to(device)
    with torch.autocast(device.type, dtype=_low(device)):
        L, M0 = tp.laplacian(X, faces)
        h = layer(X)
        assert h.dtype == _low(device)
        Y = L @ h
        Z = (M0 + 0.5 * L) @ h
    assert Y.dtype == Z.dtype == torch.float32
    torch.testing.assert_close(Y, L @ h.float(), rtol=0, atol=0)
    torch.testing.assert_close(Z, (M0 + 0.5 * L) @ h.float(), rtol=0, atol=0)


def test_low_precision_positions_are_taken_in_float32_with_gradients(device):
    verts, faces = mixed_mesh()
    X = verts.float().to(device).requires_grad_(True)
    with torch.autocast(device.type, dtype=_low(device)):
        Xl = X.to(_low(device))  # positions a network produced in low precision
        L, M0 = tp.laplacian(Xl, faces)
        loss = (L @ Xl).square().sum() + M0.diagonal().sum()
    L_ref, _ = tp.laplacian(Xl.detach().float(), faces)
    torch.testing.assert_close(L.to_dense(), L_ref.to_dense(), rtol=0, atol=0)
    loss.backward()
    assert X.grad is not None and torch.isfinite(X.grad).all() and X.grad.abs().sum() > 0


def test_low_precision_positions_are_refused_outside_autocast(device):
    verts, faces = mixed_mesh()
    with pytest.raises(TypeError, match="float32 or float64"):
        tp.laplacian(verts.to(device, _low(device)), faces)


def test_compiled_step_under_autocast_equals_eager(device):
    verts, faces = mixed_mesh()
    X = verts.float().to(device)
    layer = torch.nn.Linear(3, 4).to(device)

    def step(X: torch.Tensor) -> torch.Tensor:
        with torch.autocast(device.type, dtype=_low(device)):
            L, M0 = tp.laplacian(X, faces)
            return (M0 @ (L @ layer(X))).sum()

    torch._dynamo.reset()
    got = torch.compile(step, backend="aot_eager", fullgraph=True)(X)
    torch.testing.assert_close(got, step(X))
    torch._dynamo.reset()

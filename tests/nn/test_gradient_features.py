"""Per-vertex tangent gradients, spatial gradient features and DiffusionNetLike with them."""

from __future__ import annotations

import pickle

import numpy as np
import pytest
import torch
from conftest import DATA, hex_pent_mesh, mixed_mesh
from meshes import read_mesh

import torch_polylap as tp
import torch_polylap.nn as tnn
from torch_polylap.datasets import PolygonMeshDataset, collate_meshes
from torch_polylap.shapes import quad_grid

# the dataset reads the test meshes, whose object names the reader reports as skipped:
# expected here (tests/io asserts that warning)
pytestmark = pytest.mark.filterwarnings("ignore::torch_polylap.io.SkippedContentWarning")

D64 = {"dtype": torch.float64}


def rotation(seed: int) -> torch.Tensor:
    q, r = np.linalg.qr(np.random.default_rng(seed).normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    return torch.from_numpy(q * np.linalg.det(q))


def planar_meshes():
    """An irregular quad grid and a polygon fan (triangles, quads, pentagon), in tilted planes."""
    V, F = quad_grid(6, seed=1)
    Vh, Fh = hex_pent_mesh()
    Vh = Vh.clone()
    Vh[:, 2] = 0.0
    return [(V @ rotation(0).T, F), (Vh @ rotation(1).T + 0.3, Fh)]


def interior(V, F) -> torch.Tensor:
    boundary = torch.zeros(V.shape[0], dtype=torch.bool)
    boundary[torch.as_tensor(tp.build_topology(F, V.shape[0]).boundary_vertices)] = True
    return ~boundary


@pytest.mark.parametrize("which", [0, 1])
def test_gradient_of_a_linear_function_is_exact_on_a_planar_mesh(which, device):
    V, F = planar_meshes()[which]
    inside = interior(V, F).to(device)
    V, F = V.to(device), F.to(device) if torch.is_tensor(F) else F
    normal, e_x, e_y = tnn.vertex_tangent_frames(V, F)
    plane_normal = tp.face_normals(V, F)[0]
    # orthonormal frames, normal of the plane
    frame = torch.stack([normal, e_x, e_y], 1)  # (V, 3, 3)
    eye = torch.eye(3, **D64, device=device).expand_as(frame)
    assert torch.allclose(frame @ frame.transpose(1, 2), eye, atol=1e-13)
    assert torch.allclose(normal, plane_normal.expand_as(normal), atol=1e-13)
    grad_x, grad_y = tnn.vertex_gradient_operators(V, F)
    assert isinstance(grad_x, tp.sparse.SparseOperator) and grad_x.shape == (V.shape[0],) * 2
    w = torch.tensor([[0.7, -1.3, 0.4], [-0.2, 0.5, 2.0]], **D64, device=device).T  # two linear
    u = V @ w + torch.tensor([1.0, -3.0], **D64, device=device)
    assert inside.sum() >= 5
    # the part of w in the plane, in each vertex's frame; exact at interior (here: all) vertices
    assert torch.allclose((grad_x @ u)[inside], (e_x @ w)[inside], atol=1e-12)
    assert torch.allclose((grad_y @ u)[inside], (e_y @ w)[inside], atol=1e-12)
    assert torch.allclose(grad_x @ u, e_x @ w, atol=1e-12)


def test_gradient_of_a_smooth_function_converges_on_a_curved_mesh(device):
    errors = []
    for level in (2, 3):
        V, F = read_mesh(DATA / "sphere" / f"quad_{level}.obj", dtype=torch.float64)
        V = (V / V.norm(dim=1, keepdim=True)).to(device)
        normal, e_x, e_y = tnn.vertex_tangent_frames(V, F)
        grad_x, grad_y = tnn.vertex_gradient_operators(V, F)
        u = V[:, 2]  # tangential gradient e_z - z n on the unit sphere
        ez = torch.tensor([0.0, 0.0, 1.0], **D64, device=device)
        exact = ez - V[:, 2:] * V
        err_x = (grad_x @ u - (e_x * exact).sum(1)).abs().max()
        err_y = (grad_y @ u - (e_y * exact).sum(1)).abs().max()
        errors.append(float(max(err_x, err_y)))
        assert torch.allclose(normal, V, atol=0.05)
    assert errors[1] < 0.6 * errors[0] and errors[1] < 0.05


@pytest.mark.parametrize("with_rotations", [True, False])
def test_rotating_the_frames_rotates_the_gradients_and_keeps_the_features(with_rotations, device):
    V, F = mixed_mesh()
    V = V.to(device)
    _, e_x, e_y = tnn.vertex_tangent_frames(V, F)
    theta = torch.linspace(0.3, 5.0, V.shape[0], **D64, device=device)[:, None]
    c, s = torch.cos(theta), torch.sin(theta)
    f_x, f_y = c * e_x + s * e_y, -s * e_x + c * e_y
    gx, gy = tnn.vertex_gradient_operators(V, F)
    rx, ry = tnn.vertex_gradient_operators(V, F, frames=(f_x, f_y))
    x = torch.stack([V[:, 0] * V[:, 1], torch.sin(2 * V[:, 0]), V[:, 2] ** 2], 1)
    # coordinates in the rotated frame: rotated by -theta
    assert torch.allclose(rx @ x, c * (gx @ x) + s * (gy @ x), atol=1e-13)
    assert torch.allclose(ry @ x, -s * (gx @ x) + c * (gy @ x), atol=1e-13)
    torch.manual_seed(0)
    layer = tnn.SpatialGradientFeatures(3, with_rotations=with_rotations).double().to(device)
    out = layer(x, gx, gy)
    assert out.shape == x.shape and out.abs().max() > 1e-3
    assert torch.allclose(layer(x, rx, ry), out, atol=1e-13)


def test_block_diagonal_batch_equals_the_meshes_one_by_one(device):
    meshes = [(V.to(device), F) for V, F in [mixed_mesh(), hex_pent_mesh(), quad_grid(3, bump=0.2)]]
    ops = [tnn.vertex_gradient_operators(torch.as_tensor(V, **D64), F) for V, F in meshes]
    grad_x = tp.sparse.block_diag([gx for gx, _ in ops])
    grad_y = tp.sparse.block_diag([gy for _, gy in ops])
    xs = [
        torch.randn(V.shape[0], 4, **D64, generator=torch.Generator().manual_seed(i)).to(device)
        for i, (V, _) in enumerate(meshes)
    ]
    torch.manual_seed(1)
    layer = tnn.SpatialGradientFeatures(4).double().to(device)
    packed = layer(torch.cat(xs), grad_x, grad_y)
    assert packed.device.type == device.type
    one_by_one = torch.cat([layer(x, gx, gy) for x, (gx, gy) in zip(xs, ops, strict=True)])
    assert torch.allclose(packed, one_by_one, atol=1e-14)
    # and the packed mesh gives the same operators as the block diagonal
    batch = tp.PolygonMeshes([torch.as_tensor(V, **D64) for V, _ in meshes], [F for _, F in meshes])
    px, py = tnn.vertex_gradient_operators(batch.verts_packed(), batch.faces_packed())
    assert torch.allclose(px.to_dense(), grad_x.to_dense(), atol=1e-14)
    assert torch.allclose(py.to_dense(), grad_y.to_dense(), atol=1e-14)


def test_gradcheck_of_the_layer_and_the_operators(device):
    V, F = mixed_mesh()
    gen = torch.Generator().manual_seed(3)
    x = torch.randn(V.shape[0], 3, **D64, generator=gen).to(device).requires_grad_(True)
    w_re = (0.5 * torch.randn(3, 3, **D64, generator=gen)).to(device).requires_grad_(True)
    w_im = (0.5 * torch.randn(3, 3, **D64, generator=gen)).to(device).requires_grad_(True)
    verts = V.to(device, copy=True).requires_grad_(True)

    def features(x, w_re, w_im, verts):
        gx, gy = tnn.vertex_gradient_operators(verts, F)
        return tnn.spatial_gradient_features(gx @ x, gy @ x, w_re, w_im)

    assert torch.autograd.gradcheck(features, (x, w_re, w_im, verts), fast_mode=True)
    gy = torch.randn(V.shape[0], 3, **D64, generator=gen).to(device).requires_grad_(True)
    assert torch.autograd.gradcheck(tnn.spatial_gradient_features, (x, gy, w_re))  # real A


def small_batch(tmp_path, gradient_operators=True):
    items = [mixed_mesh(), hex_pent_mesh(), quad_grid(3, bump=0.2), DATA / "dodecahedron_poly.obj"]
    data = PolygonMeshDataset(
        items,
        [0, 1, 0, 1],
        k=4,
        cache_dir=tmp_path,
        dtype=torch.float64,
        gradient_operators=gradient_operators,
    )
    return data, [data[i] for i in range(len(data))]


def test_dataset_items_carry_the_operators_and_the_batch_their_block_diagonal(tmp_path):
    data, items = small_batch(tmp_path)
    for i, item in enumerate(items):
        V, F = data.mesh(i)
        gx, gy = tnn.vertex_gradient_operators(V, F)
        assert torch.equal(item["grad_x"].to_dense(), gx.to_dense())
        assert torch.equal(item["grad_y"].to_dense(), gy.to_dense())
        again = pickle.loads(pickle.dumps(item))  # crosses DataLoader worker processes
        assert torch.equal(again["grad_x"].to_dense(), gx.to_dense())
    batch = collate_meshes([items[i] for i in (2, 0, 3)])
    for key in ("grad_x", "grad_y"):
        expected = torch.block_diag(*[items[i][key].to_dense() for i in (2, 0, 3)])
        assert torch.equal(getattr(batch, key).to_dense(), expected)
    assert batch.to(dtype=torch.float32).grad_x.dtype == torch.float32
    _, plain = small_batch(tmp_path, gradient_operators=False)
    assert "grad_x" not in plain[0] and collate_meshes(plain).grad_x is None


def test_block_with_gradient_features_trains(tmp_path, device):
    _, items = small_batch(tmp_path)
    batch = collate_meshes(items).to(device=device, dtype=torch.float32)
    torch.manual_seed(0)
    model = tnn.DiffusionNetLike(
        3, 2, width=8, num_blocks=2, hks_features=0, gradient_features=True
    ).to(device)
    x = batch.meshes.verts_packed()
    opt = torch.optim.Adam(model.parameters(), lr=3e-2)
    losses = []
    for _ in range(30):
        logits = model(x, batch.spectrum, grad_x=batch.grad_x, grad_y=batch.grad_y)
        assert logits.device.type == device.type
        loss = torch.nn.functional.cross_entropy(logits, batch.labels)
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(loss.item())
    assert losses[-1] < 0.5 * losses[0]
    # the gradient features take part in training: every block's gradient-feature parameters
    # received a non-zero gradient in the last step
    for block in model.blocks:
        params = list(block.gradient.parameters())
        assert params and all(float(p.grad.abs().sum()) > 0 for p in params)
    with pytest.raises(ValueError, match="grad_x and grad_y"):
        model(x, batch.spectrum)


def test_default_model_is_unchanged():
    torch.manual_seed(0)
    plain = tnn.DiffusionNetLike(3, 2, width=8, num_blocks=2, hks_features=0)
    names = [name for name, _ in plain.named_parameters()]
    assert not any("gradient" in name for name in names)
    assert plain.blocks[0].mlp[0].in_features == 16
    torch.manual_seed(0)
    with_grad = tnn.DiffusionNetLike(
        3,
        2,
        width=8,
        num_blocks=2,
        hks_features=0,
        gradient_features=True,
        gradient_rotations=False,
    )
    assert with_grad.blocks[0].mlp[0].in_features == 24
    assert with_grad.blocks[0].gradient.weight_im is None

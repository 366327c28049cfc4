"""``tp.nn.LearnedVectorDiffusion``, ``VectorLinear``, ``VectorGate``: exact rotation and gauge
equivariance, a dense reference solve, the scalar layer on a plane, torch.compile, gradcheck."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import torch_polylap as tp
import torch_polylap.vector as tv
from torch_polylap.sparse import to_scipy

C = 3


pytestmark = pytest.mark.usefixtures("fresh_dynamo")


def mesh() -> tuple[torch.Tensor, torch.Tensor]:
    verts, faces = tp.shapes.torus(10, 6)
    g = torch.Generator().manual_seed(0)
    return verts + 0.02 * torch.randn(verts.shape, generator=g, dtype=verts.dtype), faces


def features(n: int, seed: int = 1) -> torch.Tensor:
    return torch.randn(n, C, 2, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)


def network() -> tuple[torch.nn.Module, ...]:
    torch.manual_seed(0)
    diffusion = tp.nn.LearnedVectorDiffusion(C, init_times=(1e-2, 1.0)).double()
    linear = tp.nn.VectorLinear(2 * C, C).double()
    gate = tp.nn.VectorGate(C).double()
    with torch.no_grad():  # a gate that is not close to identity
        gate.bias.copy_(torch.tensor([-1.0, 0.5, 2.0]))
    return diffusion, linear, gate


def forward(layers, x: torch.Tensor, A: torch.Tensor, M: torch.Tensor) -> torch.Tensor:
    diffusion, linear, gate = layers
    return gate(linear(torch.cat((x, diffusion(x, A, M)), 1)))


def test_diffusion_equals_a_dense_solve(device):
    """(M + t_c A) y_c = M x_c per channel, against numpy's dense solve."""
    verts, faces = mesh()
    A, M, _ = tv.connection_laplacian(verts.to(device), faces)
    layer = network()[0].to(device)
    x = features(verts.shape[0])
    y = layer(x.to(device), A, M)
    assert y.device.type == device.type
    y = y.cpu()
    Ad, Md = to_scipy(A).toarray(), to_scipy(M).toarray()
    for c, t in enumerate(layer.times.tolist()):
        xc = x[:, c].reshape(-1).numpy()  # interleaved (x0, y0, x1, y1, ...)
        want = np.linalg.solve(Md + t * Ad, Md @ xc)
        np.testing.assert_allclose(y[:, c].reshape(-1).detach().numpy(), want, atol=1e-12)


@pytest.mark.parametrize("angle", [0.3, np.pi / 2, 2.5])
def test_rotating_every_input_vector_rotates_the_output(angle, device):
    """f(R x) = R f(x) for R the rotation by one angle in every frame: the diffusion, the
    complex mixing and the length gate each commute with it (to round-off)."""
    verts, faces = mesh()
    A, M, _ = tv.connection_laplacian(verts.to(device), faces)
    layers = tuple(layer.to(device) for layer in network())
    x = features(verts.shape[0]).to(device)
    y = forward(layers, x, A, M)
    rotated = forward(layers, tp.nn.rotate_vectors(x, angle), A, M)
    torch.testing.assert_close(rotated, tp.nn.rotate_vectors(y, angle), atol=1e-12, rtol=0)


def test_a_change_of_frames_gives_the_same_vectors(device):
    """Gauge equivariance: with every vertex frame turned by its own angle, A rebuilt in the new
    frames and the input written in them, the output is the same 3D field."""
    verts, faces = mesh()
    verts = verts.to(device)
    A, M, frames = tv.connection_laplacian(verts, faces)
    layers = tuple(layer.to(device) for layer in network())
    x = features(verts.shape[0]).to(device)
    y = tv.to_ambient(forward(layers, x, A, M), frames)
    alpha = torch.linspace(0, 11, verts.shape[0], dtype=torch.float64, device=device)[:, None]
    c, s = torch.cos(alpha), torch.sin(alpha)
    turned = tv.TangentFrames(
        frames.normal, c * frames.e_x + s * frames.e_y, -s * frames.e_x + c * frames.e_y
    )
    B, _, _ = tv.connection_laplacian(verts, faces, frames=turned)
    x_turned = tv.to_tangent(tv.to_ambient(x, frames), turned)
    y_turned = tv.to_ambient(forward(layers, x_turned, B, M), turned)
    torch.testing.assert_close(y_turned, y, atol=1e-12, rtol=0)


def test_on_a_plane_it_is_the_scalar_layer_per_coordinate(device):
    """On a planar mesh, in frames common to all vertices, A = L (x) I_2: the vector diffusion
    of (x, y) equals tp.nn.LearnedDiffusion ("implicit") of the two coordinates with the same
    times."""
    verts, faces = tp.shapes.quad_grid(6, 5)
    verts = verts.double().to(device)
    normal = tv.tangent_frames(verts, tp.get_topology(faces, verts.shape[0])).normal
    e_x = torch.zeros_like(verts)
    e_x[:, 0] = 1.0
    common = (normal, e_x, torch.linalg.cross(normal, e_x, dim=1))
    A, M, _ = tv.connection_laplacian(verts, faces, frames=common)
    L, M0 = tp.laplacian(verts, faces)
    vector = tp.nn.LearnedVectorDiffusion(C).double().to(device)
    scalar = tp.nn.LearnedDiffusion(C, mode="implicit").double().to(device)
    x = features(verts.shape[0]).to(device)
    y = vector(x, A, M)
    for k in range(2):
        torch.testing.assert_close(y[..., k], scalar(x[..., k], L=L, M0=M0), atol=1e-12, rtol=0)


def test_forward_is_one_graph_and_compiles_to_eager_values(device):
    verts, faces = mesh()
    A, M, _ = tv.connection_laplacian(verts.to(device), faces)
    layers = tuple(layer.to(device) for layer in network())
    x = features(verts.shape[0]).to(device)

    def loss(x: torch.Tensor) -> torch.Tensor:
        return forward(layers, x, A, M).square().sum()

    explained = torch._dynamo.explain(loss)(x)
    assert explained.graph_count == 1 and explained.graph_break_count == 0, explained.break_reasons
    torch._dynamo.reset()

    def value_and_grad(x: torch.Tensor) -> tuple[torch.Tensor, ...]:
        value = loss(x)
        grads = torch.autograd.grad(value, (layers[0].raw_times, layers[1].real, layers[2].bias))
        return (value.detach(), *grads)

    want = value_and_grad(x)
    got = torch.compile(value_and_grad, backend="aot_eager", fullgraph=True)(x)
    torch.testing.assert_close(got, want, rtol=1e-10, atol=1e-12)


def test_gradcheck(device):
    """Differentiable in the features, the times and the vertex positions (through A, M)."""
    verts, faces = tp.shapes.torus(5, 4, device=device)
    _, linear, gate = (layer.to(device) for layer in network())
    x = features(verts.shape[0]).to(device)

    def f(v: torch.Tensor, x: torch.Tensor, raw: torch.Tensor) -> torch.Tensor:
        A, M, _ = tv.connection_laplacian(v, faces)
        return forward((with_raw_times(raw), linear, gate), x, A, M)

    raw = tp.nn.LearnedVectorDiffusion(C, init_times=(1e-2, 1.0)).raw_times.detach().double()
    raw = raw.to(device)
    args = (verts.clone(), x, raw)
    args = tuple(a.clone().requires_grad_(True) for a in args)
    assert torch.autograd.gradcheck(f, args, fast_mode=True)


def with_raw_times(raw: torch.Tensor) -> tp.nn.LearnedVectorDiffusion:
    """A layer whose raw times are the tensor ``raw`` (not a parameter: gradcheck's input)."""
    layer = tp.nn.LearnedVectorDiffusion(raw.numel())
    del layer.raw_times
    layer.raw_times = raw
    return layer


def test_bad_shapes_are_refused(device):
    verts, faces = mesh()
    A, M, _ = tv.connection_laplacian(verts.to(device), faces)
    layer, linear, gate = (layer.to(device) for layer in network())
    with pytest.raises(ValueError, match=r"\(V, 3, 2\)"):
        layer(torch.zeros(verts.shape[0], C, dtype=torch.float64, device=device), A, M)
    with pytest.raises(ValueError, match="must be"):
        layer(features(verts.shape[0] - 1).to(device), A, M)
    with pytest.raises(ValueError, match=r"\(V, 6, 2\)"):
        linear(features(verts.shape[0]).to(device))
    with pytest.raises(ValueError, match=r"\(V, 3, 2\)"):
        gate(torch.zeros(4, 3, 3, dtype=torch.float64, device=device))

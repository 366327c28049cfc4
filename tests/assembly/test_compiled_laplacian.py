"""The gather form of the assembly and the opt-in compiled Laplacian built on it.

References: the eager scatter assembly (``tp.laplacian``, itself tested against libigl, the
paper's closed forms and dense references), gradcheck in float64, and the eager function's
errors and float64 re-evaluation, which the compiled path must hand back unchanged.
"""

from __future__ import annotations

import math

import pytest
import torch
from conftest import hex_pent_mesh, mixed_mesh

import torch_polylap as tp
from torch_polylap.assembly import assemble, assemble_gathered, gather_plan_of
from torch_polylap.kernels import BLOCK_METHODS, block_kernel
from torch_polylap.shapes import quad_grid
from torch_polylap.sparse.autograd import csr_product


def _awkward_mesh() -> tuple[torch.Tensor, list[list[int]]]:
    """Quads, a triangle fan of 12 around one vertex (more corners at a vertex than the dense
    gathers cover), three quads on one edge (an entry of L with three contributions), a
    pentagon and an isolated vertex; non-planar."""
    g = torch.Generator().manual_seed(3)
    grid_v, grid_f = quad_grid(3, bump=0.2, seed=2)
    verts = [grid_v.double()]
    faces = grid_f.tolist()
    n = grid_v.shape[0]
    ang = torch.arange(12, dtype=torch.float64) * (2 * math.pi / 12)
    ring = torch.stack((5 + torch.cos(ang), torch.sin(ang), 0.2 * torch.sin(3 * ang)), 1)
    verts += [ring, torch.tensor([[5.0, 0.0, 0.3]], dtype=torch.float64)]
    center = n + 12
    faces += [[n + i, n + (i + 1) % 12, center] for i in range(12)]
    # a third quad on the grid's interior edge (5, 6): a non-manifold edge
    extra = torch.tensor([[1.3, 1.2, 0.9], [1.6, 1.1, 1.0]], dtype=torch.float64)
    verts.append(extra + 0.01 * torch.randn(2, 3, generator=g, dtype=torch.float64))
    faces.append([5, 6, center + 1, center + 2])
    pent = torch.tensor(
        [[8.0, 0, 0], [9, 0, 0.2], [9.3, 1, 0], [8.5, 1.6, 0.1], [7.7, 1, -0.1]],
        dtype=torch.float64,
    )
    verts += [pent, torch.tensor([[20.0, 20.0, 20.0]], dtype=torch.float64)]
    faces.append([center + 3 + i for i in range(5)])
    return torch.cat(verts), faces


pytestmark = pytest.mark.filterwarnings("ignore:the mesh .* is not a consistently oriented")

MESHES = {"mixed": mixed_mesh, "hexpent": hex_pent_mesh, "awkward": _awkward_mesh}


@pytest.mark.parametrize("method", BLOCK_METHODS)
@pytest.mark.parametrize("name", sorted(MESHES))
def test_gathered_assembly_equals_the_scatter_assembly(name, method, device):
    verts, faces = MESHES[name]()
    verts = verts.to(device)
    topo = tp.build_topology(faces, verts.shape[0])
    view = topo.on(verts.device)
    kernel = block_kernel(method, 1.7)
    want_values, want_masses = assemble(verts, view, topo, kernel, want_mass=True, validate=True)
    got = assemble_gathered(verts, view, kernel, gather_plan_of(topo, view), want_mass=True)
    assert bool(got.ok) and bool(got.accurate)
    torch.testing.assert_close(got.values, want_values, rtol=0, atol=1e-13)
    torch.testing.assert_close(got.masses, want_masses, rtol=1e-15, atol=0)


def test_gather_plan_covers_the_awkward_cases(device):
    """The test mesh does reach the index_add parts of the plan."""
    verts, faces = _awkward_mesh()
    topo = tp.build_topology(faces, verts.shape[0])
    plan = gather_plan_of(topo, topo.on(device))
    assert plan.rest.numel() > 0 and plan.vertex.rest.numel() > 0
    assert plan.rest.device.type == device.type
    assert gather_plan_of(topo, topo.on(device)) is plan  # computed once


def test_gathered_assembly_gradients(device):
    """First and second derivatives of the gathers (their backward is written by hand)."""
    verts, faces = _awkward_mesh()
    verts = verts.to(device)
    topo = tp.build_topology(faces, verts.shape[0])
    view = topo.on(verts.device)
    kernel = block_kernel("aw11", 1.3)
    plan = gather_plan_of(topo, view)
    U = torch.randn(verts.shape[0], 2, dtype=torch.float64, generator=torch.Generator())
    U = U.to(device)

    def parts(X):
        out = assemble_gathered(X, view, kernel, plan, want_mass=True)
        return out.values, out.masses

    def energy(X):
        values, masses = parts(X)
        LU = csr_product(view.pattern, values, U, True)
        return LU.square().sum() * (masses[:, None] * U).sum()

    X = verts.clone().requires_grad_(True)
    assert torch.autograd.gradcheck(parts, (X,), eps=1e-6, atol=1e-6, fast_mode=True)
    assert torch.autograd.gradgradcheck(energy, (X,), eps=1e-6, atol=1e-5, fast_mode=True)


@pytest.mark.slow  # inductor generates and compiles C++: about 40 s
@pytest.mark.usefixtures("fresh_dynamo")
def test_compiled_laplacian_equals_eager_with_inductor(device):
    """The default (inductor) compilation: values, masses and gradients as eager's."""
    verts, faces = _awkward_mesh()
    verts = verts.to(device)
    lap = tp.CompiledLaplacian(faces, 1.4)
    X = torch.randn(verts.shape[0], 3, dtype=torch.float64, generator=torch.Generator())
    X = X.to(device)

    def run(fn):
        V = verts.clone().requires_grad_(True)
        L, M0 = fn(V)
        (L @ X).square().sum().add((M0 @ X).sum()).backward()
        return L.to_dense(), M0.diagonal(), V.grad

    got = run(lap)
    want = run(lambda V: tp.laplacian(V, faces, 1.4))
    for g, w in zip(got, want, strict=True):
        torch.testing.assert_close(g.detach(), w.detach(), rtol=1e-10, atol=1e-12)
    assert run(lap)[0].shape == want[0].shape  # the second call reuses the compiled code


@pytest.mark.usefixtures("fresh_dynamo")
def test_compiled_laplacian_hands_bad_input_to_the_eager_checks(device):
    """Non-finite input: the eager error naming the vertex; a face too thin for float32: the
    eager float64 re-evaluation; validate=False: no check, no fallback."""
    verts, faces = quad_grid(3, bump=0.1, device=device)
    options = {"backend": "aot_eager", "dynamic": False}
    lap = tp.CompiledLaplacian(faces, options=options)
    bad = verts.double().clone()
    bad[4, 1] = float("nan")
    with pytest.raises(ValueError, match="vertex 4 has non-finite"):
        lap(bad)
    t = 5e-6  # a dart of thinness 1e-5: its float32 block is off by several percent
    dart = torch.tensor([[0, 0, 0], [2, t, 0], [0, 2 * t, 0], [1, 0.4 * t, 0.1 * t]], device=device)
    kernel = block_kernel("aw11", 1.0)
    topo = tp.build_topology([[0, 1, 2, 3]], 4)
    view = topo.on(device)
    plan = gather_plan_of(topo, view)
    assert not bool(assemble_gathered(dart, view, kernel, plan, want_mass=True).accurate)
    # and so thin that products with L lose all digits: each call warns once
    with pytest.warns(tp.checks.Float32PrecisionWarning, match="face 0 ") as record:
        L, M0 = tp.CompiledLaplacian(topo, options=options)(dart)
        L_eager, M0_eager = tp.laplacian(dart, topo)  # evaluated in float64
    assert len(record) == 2
    torch.testing.assert_close(L.to_dense(), L_eager.to_dense(), rtol=0, atol=0)
    torch.testing.assert_close(M0.diagonal(), M0_eager.diagonal(), rtol=0, atol=0)
    unchecked = tp.CompiledLaplacian(faces, validate=False, options=options)
    assert not bool(torch.isfinite(unchecked(bad)[0].to_dense()).all())


def test_compiled_laplacian_refuses_a_tensor_lam():
    with pytest.raises(TypeError, match="tensor lam"):
        tp.CompiledLaplacian([[0, 1, 2]], torch.tensor(1.0))


@pytest.mark.usefixtures("fresh_dynamo")
def test_compiled_laplacian_under_autocast_is_the_float32_operator():
    """Under CPU autocast to bfloat16 the compiled assembly stays float32, as the eager one
    (both assemble with autocast off), with the same values and a finite gradient."""
    verts, faces = quad_grid(4, bump=0.1)
    V = verts.float().requires_grad_(True)
    lap = tp.CompiledLaplacian(faces, options={"backend": "aot_eager", "dynamic": False})
    with torch.autocast("cpu", dtype=torch.bfloat16):
        L, M0 = lap(V)
        L_eager, M0_eager = tp.laplacian(V, faces)
        loss = (L @ V).square().sum()
    assert L.dtype == M0.dtype == loss.dtype == torch.float32
    torch.testing.assert_close(L.to_dense(), L_eager.to_dense())
    torch.testing.assert_close(M0.diagonal(), M0_eager.diagonal())
    loss.backward()
    assert V.grad is not None and bool(torch.isfinite(V.grad).all())

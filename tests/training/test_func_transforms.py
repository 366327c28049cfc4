"""torch.func transforms through the operators: grad, jacrev, jvp, vmap, hessian-vector products.

References: torch.autograd on the same functions (reverse mode, which the operator algebra's
tests check against finite differences), central finite differences for the forward mode, and
a Python loop over the batch for vmap.
"""

from __future__ import annotations

import pytest
import torch
from conftest import hex_pent_mesh, mixed_mesh
from torch.func import grad, jacrev, jvp, vmap

import torch_polylap as tp


def _meshes():
    verts, faces = mixed_mesh()
    yield "tensor-quads", *tp.shapes.quad_grid(3, 4)
    yield "list-mixed", verts, faces
    hv, hf = hex_pent_mesh()
    yield "polygonfaces", hv, tp.as_faces(hf)


MESHES = list(_meshes())


def _energy(X: torch.Tensor, faces) -> torch.Tensor:
    L, M0 = tp.laplacian(X, faces)
    Y = L @ X
    return (Y * (M0 @ Y)).sum() + ((M0 + 0.3 * L) @ X).square().sum()


def _perturbed(verts: torch.Tensor, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return verts.double() + 0.03 * torch.randn(verts.shape, generator=g, dtype=torch.float64)


@pytest.mark.parametrize("name,verts,faces", MESHES, ids=[m[0] for m in MESHES])
def test_grad_equals_autograd(name, verts, faces, device):
    X = _perturbed(verts).to(device)
    got = grad(_energy)(X, faces)
    assert got.device.type == device.type
    Xr = X.clone().requires_grad_(True)
    (want,) = torch.autograd.grad(_energy(Xr, faces), Xr)
    torch.testing.assert_close(got, want, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("name,verts,faces", MESHES, ids=[m[0] for m in MESHES])
def test_jacrev_equals_autograd_jacobian(name, verts, faces, device):
    X = _perturbed(verts, 1).to(device)

    def f(X):
        L, M0 = tp.laplacian(X, faces)
        return (L @ X)[:, 0] + M0.diagonal()

    got = jacrev(f)(X)
    want = torch.autograd.functional.jacobian(f, X)
    torch.testing.assert_close(got, want, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("name,verts,faces", MESHES, ids=[m[0] for m in MESHES])
def test_jvp_equals_finite_differences(name, verts, faces, device):
    X = _perturbed(verts, 2).to(device)
    T = torch.randn(X.shape, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    T = T.to(device)

    def f(X):
        L, M0 = tp.laplacian(X, faces)
        return L @ X + M0 @ X.square()

    _, tangent = jvp(f, (X,), (T,))
    h = 1e-6
    fd = (f(X + h * T) - f(X - h * T)) / (2 * h)
    assert tangent.abs().max() > 1e-3  # a zero tangent (what custom ops alone give) fails
    torch.testing.assert_close(tangent, fd, rtol=1e-6, atol=1e-7)


def test_jvp_of_a_product_with_fixed_operator(device):
    verts, faces = tp.shapes.quad_grid(3, 3, device=device)
    L, _ = tp.laplacian(verts.double(), faces)
    X = torch.randn(verts.shape[0], 2, dtype=torch.float64, device=device)
    T = torch.randn_like(X)
    _, tangent = jvp(lambda X: L @ X, (X,), (T,))
    torch.testing.assert_close(tangent, L @ T)


def test_hessian_vector_product_by_forward_over_reverse(device):
    verts, faces = tp.shapes.quad_grid(3, 3)
    X = _perturbed(verts, 4).to(device)
    v = torch.randn(X.shape, generator=torch.Generator().manual_seed(5), dtype=torch.float64)
    v = v.to(device)
    _, hvp = jvp(grad(lambda X: _energy(X, faces)), (X,), (v,))
    Xr = X.clone().requires_grad_(True)
    (g,) = torch.autograd.grad(_energy(Xr, faces), Xr, create_graph=True)
    (want,) = torch.autograd.grad(g, Xr, v)
    torch.testing.assert_close(hvp, want, rtol=1e-10, atol=1e-10)


@pytest.mark.parametrize("name,verts,faces", MESHES, ids=[m[0] for m in MESHES])
def test_vmap_over_vertex_sets(name, verts, faces, device):
    Xs = torch.stack([_perturbed(verts, s) for s in range(4)]).to(device)
    got = vmap(_energy, in_dims=(0, None))(Xs, faces)
    want = torch.stack([_energy(X, faces) for X in Xs])
    torch.testing.assert_close(got, want, rtol=1e-12, atol=1e-12)


def test_vmap_of_grad_over_vertex_sets(device):
    verts, faces = tp.shapes.quad_grid(3, 3)
    Xs = torch.stack([_perturbed(verts, s) for s in range(3)]).to(device)
    got = vmap(grad(_energy), in_dims=(0, None))(Xs, faces)
    want = torch.stack([grad(_energy)(X, faces) for X in Xs])
    torch.testing.assert_close(got, want, rtol=1e-12, atol=1e-12)


def test_vmap_of_products_with_one_operator(device):
    verts, faces = tp.shapes.quad_grid(3, 3, device=device)
    L, M0 = tp.laplacian(verts.double(), faces)
    Ys = torch.randn(5, verts.shape[0], 3, dtype=torch.float64, device=device)
    torch.testing.assert_close(vmap(lambda Y: L @ Y)(Ys), torch.stack([L @ Y for Y in Ys]))
    torch.testing.assert_close(vmap(lambda Y: Y.T @ L)(Ys), torch.stack([Y.T @ L for Y in Ys]))
    w = torch.linspace(1, 2, verts.shape[0], dtype=torch.float64, device=device)
    A = (M0 + 0.2 * L) * w[:, None]
    torch.testing.assert_close(vmap(lambda Y: A.T @ Y)(Ys), torch.stack([A.T @ Y for Y in Ys]))


def test_vmap_refuses_bad_vertices_in_any_batch_entry(device):
    verts, faces = tp.shapes.quad_grid(3, 3)
    Xs = torch.stack([_perturbed(verts, s) for s in range(3)]).to(device)
    Xs[1, 4, 2] = float("nan")
    with pytest.raises(ValueError, match="non-finite"):
        vmap(_energy, in_dims=(0, None))(Xs, faces)


def test_grad_through_module_losses_and_solve(device):
    verts, faces = tp.shapes.quad_grid(4, 3)
    faces = torch.as_tensor(faces)
    lap = tp.PolygonLaplacian().to(device)
    X = _perturbed(verts, 6).to(device)

    def f(X):
        L, M0 = lap(X, faces)
        smoothed = tp.solve(M0 + 0.1 * L, M0 @ X)
        loss = tp.losses.laplacian_smoothing((X, faces), method="polygon")
        loss = (
            loss + tp.losses.dirichlet_energy((X, faces), X) + tp.losses.bending_energy((X, faces))
        )
        return loss + (smoothed - X).square().sum()

    got = grad(f)(X)
    Xr = X.clone().requires_grad_(True)
    (want,) = torch.autograd.grad(f(Xr), Xr)
    torch.testing.assert_close(got, want, rtol=1e-10, atol=1e-12)


def test_jacfwd_and_vjp_equal_jacrev(device):
    verts, faces = tp.shapes.quad_grid(2, 3)
    X = _perturbed(verts, 7).to(device)

    def f(X):
        L, M0 = tp.laplacian(X, faces)
        return (M0 + 0.5 * L) @ X[:, 0]

    want = jacrev(f)(X)
    torch.testing.assert_close(torch.func.jacfwd(f)(X), want, rtol=1e-10, atol=1e-12)
    out, pullback = torch.func.vjp(f, X)
    v = torch.randn(out.shape, generator=torch.Generator().manual_seed(8), dtype=torch.float64)
    (got,) = pullback(v.to(device))
    torch.testing.assert_close(got, torch.einsum("i,ijk->jk", v, want), rtol=1e-10, atol=1e-12)


def _tensors_in(obj, seen=None):
    """Every tensor reachable from ``obj`` through containers and object attributes."""
    seen = set() if seen is None else seen
    if id(obj) in seen or isinstance(obj, (str, bytes, int, float, bool, type(None))):
        return
    seen.add(id(obj))
    if isinstance(obj, torch.Tensor):
        yield obj
    elif isinstance(obj, dict):
        for value in obj.values():
            yield from _tensors_in(value, seen)
    elif isinstance(obj, (list, tuple, set)):
        for value in obj:
            yield from _tensors_in(value, seen)
    elif hasattr(obj, "__dict__") and type(obj).__module__.startswith("torch_polylap"):
        yield from _tensors_in(vars(obj), seen)


TRANSFORMS = {
    "grad": lambda f, X: grad(f)(X),
    "jvp": lambda f, X: jvp(f, (X,), (torch.ones_like(X),)),
    "vmap": lambda f, X: vmap(f)(torch.stack((X, 1.01 * X))),
    "jacrev": lambda f, X: jacrev(f)(X),
}


@pytest.mark.parametrize("transform", sorted(TRANSFORMS))
def test_structure_built_inside_a_transform_is_cached_plain(transform, device):
    """Connectivity first built inside a transform (patterns, their unions and transposes, the
    device view, gradient and connection layouts, frame references) is cached as plain tensors:
    a transform's wrapper has no storage once it exits, and later host reads would fail."""
    verts, faces = tp.shapes.quad_grid(4, 5)  # fresh faces: a topology the cache has not seen
    X = _perturbed(verts, 2).to(device)

    def f(X: torch.Tensor) -> torch.Tensor:
        L, M0 = tp.laplacian(X, faces)
        G = tp.calculus.gradient_operator(X, faces)
        frames = tp.tangent.vertex_tangent_frames(X, faces)
        A = tp.vector.connection_laplacian(X, faces)[0]
        Y = torch.ones(2 * X.shape[0], dtype=X.dtype, device=X.device)
        out = ((M0 + 0.3 * L) @ X).sum() + (L.T @ X).sum() + (G @ X[:, 0]).sum()
        return out + (A @ Y).sum() + frames.e_x.sum()

    TRANSFORMS[transform](f, X)
    topo = tp.topology.get_topology(faces, X.shape[0])
    L, M0 = tp.laplacian(X, faces)
    wrapped = [
        tuple(t.shape)
        for t in _tensors_in((topo, L, M0, (M0 + L).pattern, L.T.pattern))
        if torch._C._functorch.is_functorch_wrapped_tensor(t)
    ]
    assert not wrapped, f"functorch wrappers left in the caches: {wrapped}"
    host = tp.sparse.to_scipy(M0 + 0.3 * L) if device.type == "cpu" else None
    assert host is None or host.nnz == (M0 + 0.3 * L)._nnz()


def test_vmap_of_the_connection_laplacian_equals_a_loop(device):
    """The fold check of the vector calculus is a batch-wide check under vmap, not a branch."""
    verts, faces = tp.shapes.quad_grid(4, 5)
    Xs = torch.stack([_perturbed(verts, seed) for seed in (3, 4)]).to(device)
    Y = torch.linspace(-1, 1, 2 * verts.shape[0], dtype=torch.float64, device=device)

    def f(X: torch.Tensor) -> torch.Tensor:
        return (Y * (tp.vector.connection_laplacian(X, faces)[0] @ Y)).sum()

    torch.testing.assert_close(vmap(f)(Xs), torch.stack([f(X) for X in Xs]))
    torch.testing.assert_close(vmap(grad(f))(Xs), torch.stack([grad(f)(X) for X in Xs]))

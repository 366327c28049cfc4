"""torch.compile of code that builds and uses the operators: one graph, equal to eager.

The tracing tests use the ``aot_eager`` backend (dynamo + AOTAutograd over fake tensors, no
C++ compiler), which exercises everything a device-generic compiled graph needs: the custom
operators' fake kernels, their registered derivatives, the traced topology lookup and the
in-graph checks. Inductor itself runs in the slow tests, in a fresh process (cold topology
cache, as a training script's first step).
"""

from __future__ import annotations

import subprocess
import sys
import textwrap

import pytest
import torch
from conftest import mixed_mesh

import torch_polylap as tp
from torch_polylap.kernels import METHODS
from torch_polylap.sparse.autograd import sampled_op, spmm_op, spmm_t_op
from torch_polylap.sparse.index_ops import diagonal_indices, transpose_indices, union_indices

pytestmark = pytest.mark.usefixtures("fresh_dynamo")


def _loss(L: torch.Tensor, M0: torch.Tensor, X: torch.Tensor) -> torch.Tensor:
    Y = L @ X
    A = M0 + 0.1 * L
    return (Y * (M0 @ Y)).sum() + (A @ X).square().sum() + (L.T @ X).abs().sum()


def _grid(n: int = 4) -> tuple[torch.Tensor, torch.Tensor]:
    verts, faces = tp.shapes.quad_grid(n, n + 1)
    g = torch.Generator().manual_seed(0)
    return verts.double() + 0.03 * torch.randn(verts.shape, generator=g, dtype=torch.float64), (
        torch.as_tensor(faces)
    )


def test_forward_is_one_graph_without_breaks(device):
    verts, faces = _grid()
    verts = verts.to(device)
    lap = tp.PolygonLaplacian().to(device)

    def step(X: torch.Tensor) -> torch.Tensor:
        L, M0 = lap(X, faces)
        return _loss(L, M0, X)

    explained = torch._dynamo.explain(step)(verts)
    assert explained.graph_count == 1, explained.break_reasons
    assert explained.graph_break_count == 0


@pytest.mark.parametrize("faces_kind", ["tensor", "list", "polygonfaces", "topology"])
def test_fullgraph_forward_backward_equals_eager(faces_kind, device):
    if faces_kind == "tensor":
        verts, faces = _grid()
    else:
        verts, faces = mixed_mesh()
        faces = {
            "list": faces,
            "polygonfaces": tp.as_faces(faces),
            "topology": tp.build_topology(faces, verts.shape[0]),
        }[faces_kind]

    def step(X: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        L, M0 = tp.laplacian(X, faces)
        loss = _loss(L, M0, X)
        (g,) = torch.autograd.grad(loss, X)
        return loss.detach(), g

    X = verts.to(device, copy=True).requires_grad_(True)
    want = step(X)
    got = torch.compile(step, backend="aot_eager", fullgraph=True)(X)
    assert got[1].device.type == device.type
    torch.testing.assert_close(got, want, rtol=1e-12, atol=1e-12)


def test_compiled_step_follows_the_faces_tensor(device):
    """An ``(F, k)`` faces tensor is an input of the graph (its topology looked up at every
    call): other connectivity of the same shape gives its own operators, as eagerly."""
    verts, faces = _grid()
    verts = verts.to(device)

    def energy(X: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
        L, M0 = tp.laplacian(X, faces)
        return _loss(L, M0, X)

    compiled = torch.compile(energy, backend="aot_eager", fullgraph=True)
    compiled(verts, faces)
    torch.testing.assert_close(compiled(verts, faces.clone()), energy(verts, faces))
    other = faces.flip(1).contiguous()  # same shape, other connectivity
    torch.testing.assert_close(compiled(verts, other), energy(verts, other))


def test_compiled_step_checks_that_polygon_faces_are_unchanged(device):
    """Mixed-degree faces (a PolygonFaces) still fix the graph's topology at trace time: the
    graph checks at every call that it is given the same faces, with an error saying what to
    do."""
    verts, faces = mixed_mesh()
    verts, faces = verts.to(device), tp.as_faces(faces)

    def energy(X: torch.Tensor, faces: tp.PolygonFaces) -> torch.Tensor:
        L, M0 = tp.laplacian(X, faces)
        return _loss(L, M0, X)

    compiled = torch.compile(energy, backend="aot_eager", fullgraph=True)
    compiled(verts, faces)
    torch.testing.assert_close(compiled(verts, faces), energy(verts, faces))
    faces.indices.copy_(faces.flipped().indices)  # the same object, other connectivity
    with pytest.raises(RuntimeError, match="get_topology"):
        compiled(verts, faces)


def test_topologies_as_arguments_recompile_per_structure(device):
    def energy(X: torch.Tensor, topo: tp.Topology) -> torch.Tensor:
        L, M0 = tp.laplacian(X, topo)
        return _loss(L, M0, X)

    compiled = torch.compile(energy, backend="aot_eager", fullgraph=True)
    for n in (3, 4):
        verts, faces = _grid(n)
        verts = verts.to(device)
        topo = tp.build_topology(faces, verts.shape[0])
        torch.testing.assert_close(compiled(verts, topo), energy(verts, topo))
    verts, faces = mixed_mesh()
    verts = verts.to(device)
    topo = tp.build_topology(faces, verts.shape[0])
    torch.testing.assert_close(compiled(verts, topo), energy(verts, topo))


def test_compiled_validation_refuses_non_finite_vertices(device):
    verts, faces = _grid()
    verts = verts.to(device)
    compiled = torch.compile(
        lambda X: tp.laplacian(X, faces)[0] @ X, backend="aot_eager", fullgraph=True
    )
    compiled(verts)
    bad = verts.clone()
    bad[3, 1] = float("nan")
    with pytest.raises(RuntimeError, match="non-finite"):
        compiled(bad)


@pytest.mark.parametrize("method", METHODS)
def test_methods_compile(method, device):
    verts, faces = mixed_mesh()
    verts, faces = verts.to(device), tp.as_faces(faces)

    def energy(X: torch.Tensor) -> torch.Tensor:
        L, M0 = tp.laplacian(X, faces, method=method)
        return _loss(L, M0, X)

    compiled = torch.compile(energy, backend="aot_eager", fullgraph=True)
    torch.testing.assert_close(compiled(verts), energy(verts), rtol=1e-12, atol=1e-12)


def test_custom_operators_pass_opcheck(device):
    """torch.library.opcheck: schema, fake kernel, registered derivative, AOT dispatch."""
    verts, faces = mixed_mesh()
    L, M0 = tp.laplacian(verts.to(device), faces)
    n = verts.shape[0]
    parts = (L._crow, L._col, L._row)
    vals = L.values().detach().clone().requires_grad_(True)
    X = torch.randn(n, 2, dtype=torch.float64, device=device, requires_grad=True)
    G = torch.randn(n, 2, dtype=torch.float64, device=device, requires_grad=True)
    torch.library.opcheck(spmm_op, (vals, *parts, X, True))
    torch.library.opcheck(spmm_op, (vals, *parts, X, False))
    torch.library.opcheck(spmm_t_op, (vals, *parts, G, n))
    torch.library.opcheck(sampled_op, (G, X, *parts))
    structure = ("test_schema", "test_faketensor")
    torch.library.opcheck(
        union_indices, (L._crow, L._col, M0._crow, M0._col, n), test_utils=structure
    )
    torch.library.opcheck(transpose_indices, (L._crow, L._col, n), test_utils=structure)
    torch.library.opcheck(diagonal_indices, (L._crow, L._col, n), test_utils=structure)


def test_custom_operators_on_the_meta_device():
    """Shapes without data: what a device-generic graph needs from each operator."""
    verts, faces = mixed_mesh()
    L, _ = tp.laplacian(verts, faces)
    n = verts.shape[0]
    meta = [t.to("meta") for t in (L.values().detach(), L._crow, L._col, L._row)]
    X = torch.empty(n, 5, dtype=torch.float64, device="meta")
    assert spmm_op(*meta, X, True).shape == (n, 5)
    assert spmm_t_op(*meta, X, n).shape == (n, 5)
    assert sampled_op(X, X, *meta[1:]).shape == (L._nnz(),)


def test_compiled_union_of_operators_equals_eager(device):
    verts, faces = mixed_mesh()
    verts = verts.to(device)

    def combo(X: torch.Tensor) -> torch.Tensor:
        L, M0 = tp.laplacian(X, faces)
        weights = torch.arange(1.0, X.shape[0] + 1, dtype=X.dtype, device=X.device)
        A = (M0 - 0.25 * L) * weights[:, None]
        return A.T @ X + A.diagonal()[:, None]

    got = torch.compile(combo, backend="aot_eager", fullgraph=True)(verts)
    torch.testing.assert_close(got, combo(verts))


@pytest.mark.parametrize("mode", ["implicit", "spectral"])
def test_learned_diffusion_is_one_graph(mode, device):
    verts, faces = _grid()
    L, M0 = tp.laplacian(verts.to(device), faces)
    evals, evecs = tp.eigs(L, M0, k=8)
    spectrum = tp.nn.Spectrum.from_meshes([(evals, evecs, M0)])
    layer = tp.nn.LearnedDiffusion(3, mode=mode).double().to(device)
    x = torch.randn(
        verts.shape[0], 3, dtype=torch.float64, generator=torch.Generator().manual_seed(1)
    ).to(device)

    def f(x: torch.Tensor) -> torch.Tensor:
        y = layer(x, spectrum=spectrum) if mode == "spectral" else layer(x, L=L, M0=M0)
        return y.square().sum()

    explained = torch._dynamo.explain(f)(x)
    assert explained.graph_count == 1 and explained.graph_break_count == 0
    torch._dynamo.reset()

    def value_and_grad(x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        loss = f(x)
        (g,) = torch.autograd.grad(loss, layer.raw_times)
        return loss.detach(), g

    want = value_and_grad(x)
    got = torch.compile(value_and_grad, backend="aot_eager", fullgraph=True)(x)
    torch.testing.assert_close(got, want, rtol=1e-10, atol=1e-12)


_INDUCTOR_STEP = textwrap.dedent(
    """
    import torch, torch_polylap as tp
    torch._dynamo.config.trace_autograd_ops = True
    verts, faces = tp.shapes.quad_grid(5, 6)
    g = torch.Generator().manual_seed(0)
    verts = verts.double() + 0.03 * torch.randn(verts.shape, generator=g, dtype=torch.float64)
    faces = torch.as_tensor(faces)

    def make():
        X = torch.nn.Parameter(verts.clone())
        opt = torch.optim.SGD([X], lr=1e-3)
        lap = tp.PolygonLaplacian()

        def forward_backward():
            L, M0 = lap(X, faces)
            Y = L @ X
            loss = (Y * (M0 @ Y)).sum() + ((M0 + 0.1 * L) @ X).square().sum()
            loss.backward()
            return loss.detach()

        return X, opt, forward_backward

    Xe, opt_e, eager = make()
    Xc, opt_c, compiled = make()
    compiled = torch.compile(compiled, fullgraph=True)
    for _ in range(3):
        Xe.grad = Xc.grad = None
        le, lc = eager(), compiled()
        opt_e.step(); opt_c.step()
        assert torch.allclose(le, lc, rtol=1e-12, atol=0), (le, lc)
        assert torch.allclose(Xe, Xc, rtol=0, atol=1e-14)
    print("OK")
    """
)


@pytest.mark.slow
def test_inductor_training_step_in_a_fresh_process():
    """Cold topology cache, inductor, fullgraph forward + loss + backward, three SGD steps."""
    out = subprocess.run(
        [sys.executable, "-c", _INDUCTOR_STEP], capture_output=True, text=True, timeout=900
    )
    assert out.returncode == 0, out.stderr[-3000:]
    assert out.stdout.strip().endswith("OK")


def test_one_compiled_function_over_meshes_of_several_sizes(device):
    """The second size makes torch.compile retrace with dynamic shapes; each mesh still gets
    its own topology, and returning to the first mesh is still right."""

    def energy(X: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
        L, M0 = tp.PolygonLaplacian()(X, faces)
        return _loss(L, M0, X)

    compiled = torch.compile(energy, backend="aot_eager", fullgraph=True)
    meshes = [(verts.to(device), faces) for verts, faces in map(_grid, (3, 4, 5))]
    for verts, faces in [*meshes, meshes[0]]:
        torch.testing.assert_close(compiled(verts, faces), energy(verts, faces))


def test_whole_training_step_with_optimizer_compiles_and_equals_eager(device):
    """Without fullgraph: torch's optimizer breaks the graph itself (in torch 2.13 for any
    model), the rest, the operators' assembly and backward included, compiles."""
    verts, faces = _grid()
    verts = verts.to(device)

    def make():
        X = torch.nn.Parameter(verts.clone())
        opt = torch.optim.SGD([X], lr=1e-3)
        lap = tp.PolygonLaplacian()

        def step() -> torch.Tensor:
            opt.zero_grad()
            L, M0 = lap(X, faces)
            loss = _loss(L, M0, X)
            loss.backward()
            opt.step()
            return loss.detach()

        return X, step

    Xe, eager = make()
    Xc, compiled = make()
    compiled = torch.compile(compiled, backend="aot_eager")
    for _ in range(3):
        torch.testing.assert_close(compiled(), eager(), rtol=1e-12, atol=0)
        torch.testing.assert_close(Xc, Xe, rtol=0, atol=1e-14)


def test_importing_the_package_does_not_import_dynamo():
    """torch._dynamo costs about a second to import, in every DataLoader worker and command."""
    code = "import sys, torch_polylap; print('torch._dynamo' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0 and out.stdout.strip() == "False", out.stderr[-2000:]


def test_operators_cross_a_compiled_boundary_without_gradients_only(device):
    """Returned without grad: equal to eager. With grad, as input or output: an error (never
    a silently lost gradient)."""
    verts, faces = _grid()
    verts = verts.to(device)
    got = torch.compile(lambda X: tp.laplacian(X, faces), backend="aot_eager")(verts)
    want = tp.laplacian(verts, faces)
    for a, b in zip(got, want, strict=True):
        torch.testing.assert_close(a.to_dense(), b.to_dense(), rtol=0, atol=0)
    torch._dynamo.reset()
    X = verts.clone().requires_grad_(True)
    # the errors are torch's own (AOTAutograd's), wrapped by torch.compile
    with pytest.raises(Exception):  # noqa: B017
        torch.compile(lambda X: tp.laplacian(X, faces), backend="aot_eager")(X)
    torch._dynamo.reset()
    L, _ = tp.laplacian(X, faces)
    with pytest.raises(Exception):  # noqa: B017
        torch.compile(lambda L, Y: (L @ Y).sum(), backend="aot_eager")(L, verts)


@pytest.mark.slow  # up to 7 s: three compiled measures
@pytest.mark.parametrize("what", ["principal_curvatures", "mean_edge_length", "corner_gradients"])
def test_geometry_measures_compile_in_one_graph(what, device):
    """Curvature, edge length and the gradient's corner weights in one graph, on a topology
    nothing has used yet (its face-only data computed outside the graph): gradients equal
    eager ones; a NaN vertex is refused inside the graph."""
    verts, faces = tp.shapes.quad_sphere(3, device=device)

    def measure(X: torch.Tensor, topo: tp.Topology) -> torch.Tensor:
        if what == "principal_curvatures":
            kmin, kmax, _, _ = tp.vector.principal_curvatures(X, topo)
            return (kmin * kmax).sum()
        if what == "mean_edge_length":
            return tp.mean_edge_length(X, topo)
        return tp.corner_gradients(X, topo).square().sum()

    compiled = torch.compile(measure, backend="aot_eager", fullgraph=True)
    X = verts.clone().requires_grad_(True)
    (got,) = torch.autograd.grad(compiled(X, tp.build_topology(faces, verts.shape[0])), X)
    X = verts.clone().requires_grad_(True)
    (want,) = torch.autograd.grad(measure(X, tp.build_topology(faces, verts.shape[0])), X)
    torch.testing.assert_close(got, want, rtol=1e-12, atol=1e-12)
    bad = verts.clone()
    bad[5, 0] = float("nan")
    with pytest.raises(RuntimeError, match="NaN or an infinity"):
        compiled(bad, tp.build_topology(faces, verts.shape[0]))

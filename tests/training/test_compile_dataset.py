"""torch.compile over a dataset: one graph for meshes of many sizes, not one per mesh.

A step that builds ``L, M0`` from an ``(F, k)`` faces tensor compiles at most twice over meshes
of one degree (torch's first, static graph, then one with dynamic shapes), once with
``dynamic=True``, and once more for another degree; operators built outside and passed into a
compiled layer likewise. Graphs are counted by torch.compile's own counter; gradients are
compared with the same step run eagerly.
"""

from __future__ import annotations

import subprocess
import sys

import pytest
import torch

import torch_polylap as tp

pytestmark = pytest.mark.usefixtures("fresh_dynamo")


def graphs_compiled() -> int:
    """Graphs torch.compile has compiled since the last reset (its own count: a trace that
    torch restarts internally, as it does to turn a number into a tensor, counts once)."""
    return int(torch._dynamo.utils.counters["stats"]["unique_graphs"])


@pytest.fixture(autouse=True)
def _count_from_zero():
    torch._dynamo.utils.counters.clear()


def _grids(device: torch.device, sizes=(3, 4, 6, 7)) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """Bent quad grids of different sizes, float64, with the faces as an ``(F, 4)`` tensor."""
    meshes = []
    for n in sizes:
        verts, faces = tp.shapes.quad_grid(n, n + 1)
        g = torch.Generator().manual_seed(n)
        verts = verts.double() + 0.03 * torch.randn(verts.shape, generator=g, dtype=torch.float64)
        meshes.append((verts.to(device), torch.as_tensor(faces).to(device)))
    return meshes


def _triangulated(verts: torch.Tensor, faces: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Each quad split into two triangles along its diagonal (0, 2)."""
    tris = torch.cat((faces[:, [0, 1, 2]], faces[:, [0, 2, 3]]))
    return verts, tris


def _step(X: torch.Tensor, faces: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    L, M0 = tp.laplacian(X, faces)
    Y = L @ X
    loss = (Y * (M0 @ Y)).sum() + ((M0 + 0.1 * L) @ X).square().sum() + (L.T @ X).abs().sum()
    (g,) = torch.autograd.grad(loss, X)
    return loss.detach(), g


def _run(compiled, meshes) -> None:
    for verts, faces in meshes:
        X = verts.clone().requires_grad_(True)
        got = compiled(X, faces)
        want = _step(X, faces)
        torch.testing.assert_close(got, want, rtol=1e-12, atol=1e-12)


@pytest.mark.slow  # 9-11 s: compiles over four meshes, twice
@pytest.mark.parametrize("dynamic", [None, True])
def test_building_the_operators_inside_compiles_once_per_degree(dynamic, device):
    """torch's defaults: the first graph static, the second dynamic, then none; dynamic=True:
    one. Faces of another degree: one more graph, and that graph serves them at any size."""
    compiled = torch.compile(_step, backend="aot_eager", dynamic=dynamic, fullgraph=True)
    quads = _grids(device)
    _run(compiled, quads)
    assert graphs_compiled() == (2 if dynamic is None else 1)
    before = graphs_compiled()
    _run(compiled, [_triangulated(*mesh) for mesh in quads])
    assert graphs_compiled() - before == 1
    _run(compiled, quads[:1])  # back to quads: no new graph
    assert graphs_compiled() - before == 1


@pytest.mark.slow  # 4.5 s: a module step compiled over several meshes
def test_a_module_step_without_fullgraph_compiles_once(device):
    """PolygonLaplacian in a step compiled with torch's defaults (no fullgraph): the topology's
    sizes do not break the graph, and the gradient path through it stays whole."""
    lap = tp.PolygonLaplacian()

    def step(X: torch.Tensor, faces: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        L, M0 = lap(X, faces)
        loss = ((M0 + 0.5 * L) @ X).square().sum()
        (g,) = torch.autograd.grad(loss, X)
        return loss.detach(), g

    compiled = torch.compile(step, backend="aot_eager", dynamic=True)
    for verts, faces in _grids(device):
        X = verts.clone().requires_grad_(True)
        torch.testing.assert_close(compiled(X, faces), step(X, faces), rtol=1e-12, atol=1e-12)
    assert graphs_compiled() == 1


def test_other_connectivity_of_the_same_shape_gets_its_own_topology(device):
    """The topology is looked up from the faces at every call: faces of the same shape but
    other connectivity give their own operators, as eagerly."""
    (verts, faces), *_ = _grids(device, (4,))
    compiled = torch.compile(_step, backend="aot_eager", fullgraph=True)
    other = faces.flip(1).contiguous()  # same shape, reversed orientation
    for f in (faces, other, faces):
        X = verts.clone().requires_grad_(True)
        torch.testing.assert_close(compiled(X, f), _step(X, f), rtol=1e-12, atol=1e-12)


def test_bad_faces_raise_an_error_naming_them(device):
    """Faces that reference a vertex beyond the vertices: the topology's own error, naming the
    face, from inside the compiled step."""
    (verts, faces), *_ = _grids(device, (3,))
    compiled = torch.compile(_step, backend="aot_eager", fullgraph=True)
    compiled(verts.clone().requires_grad_(True), faces)
    bad = faces.clone()
    bad[2, 1] = verts.shape[0] + 5
    with pytest.raises(ValueError, match="face 2"):
        compiled(verts.clone().requires_grad_(True), bad)


def test_isolated_vertices_in_the_traced_sum(device):
    """M0 + t L keeps L's pattern in the graph, also for a mesh with an unreferenced vertex
    (L stores its zero diagonal entry): equal to eager."""
    (verts, faces), *_ = _grids(device, (3,))
    extra = torch.cat((verts, verts[:1] + 5.0))

    def energy(X: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
        L, M0 = tp.laplacian(X, faces)
        return ((M0 + 0.1 * L) @ X).sum()

    compiled = torch.compile(energy, backend="aot_eager", fullgraph=True, dynamic=True)
    torch.testing.assert_close(compiled(verts, faces), energy(verts, faces))
    with pytest.warns(UserWarning, match="belong to no face"):
        got = compiled(extra, faces)
    torch.testing.assert_close(got, energy(extra, faces))


@pytest.mark.slow  # 3 s each: compiles over several meshes
@pytest.mark.parametrize("dynamic", [None, True])
def test_precomputed_operators_into_a_compiled_layer(dynamic, device):
    """The DiffusionNet pattern: L, M0 built outside without gradients, passed into a compiled
    implicit diffusion layer over meshes of several sizes; gradients of the layer's times equal
    eager ones."""
    layer = tp.nn.LearnedDiffusion(3, mode="implicit").double().to(device)

    def step(x: torch.Tensor, L: torch.Tensor, M0: torch.Tensor):
        loss = layer(x, L=L, M0=M0).square().sum()
        (g,) = torch.autograd.grad(loss, layer.raw_times)
        return loss.detach(), g

    compiled = torch.compile(step, backend="aot_eager", dynamic=dynamic, fullgraph=True)
    for verts, faces in _grids(device):
        L, M0 = tp.laplacian(verts, faces)
        torch.testing.assert_close(
            compiled(verts, L, M0), step(verts, L, M0), rtol=1e-10, atol=1e-12
        )
    assert graphs_compiled() == (2 if dynamic is None else 1)


def test_precomputed_spectra_into_a_compiled_layer(device):
    """Eigenpairs built outside, a spectral diffusion layer compiled: at most two graphs."""
    layer = tp.nn.LearnedDiffusion(3, mode="spectral").double().to(device)

    def step(x: torch.Tensor, spectrum: tp.nn.Spectrum) -> torch.Tensor:
        return layer(x, spectrum=spectrum).square().sum()

    compiled = torch.compile(step, backend="aot_eager", fullgraph=True)
    for verts, faces in _grids(device):
        L, M0 = tp.laplacian(verts, faces)
        evals, evecs = tp.eigs(L, M0, k=6)
        spectrum = tp.nn.Spectrum.from_meshes([(evals, evecs, M0)])
        torch.testing.assert_close(compiled(verts, spectrum), step(verts, spectrum))
    assert graphs_compiled() <= 2


_INDUCTOR_DATASET = """
import torch, torch_polylap as tp
from torch._dynamo.utils import counters
torch._dynamo.config.trace_autograd_ops = True

def step(X, faces):
    L, M0 = tp.laplacian(X, faces)
    loss = ((L @ X) * (M0 @ X)).sum() + ((M0 + 0.1 * L) @ X).square().sum()
    (g,) = torch.autograd.grad(loss, X)
    return loss.detach(), g

compiled = torch.compile(step, fullgraph=True)
for n in (3, 5, 6):
    verts, faces = tp.shapes.quad_grid(n, n + 1)
    g = torch.Generator().manual_seed(n)
    X = (verts.double() + 0.03 * torch.randn(verts.shape, generator=g, dtype=torch.float64))
    X = X.requires_grad_(True)
    faces = torch.as_tensor(faces)
    got, want = compiled(X, faces), step(X, faces)
    torch.testing.assert_close(got, want, rtol=1e-12, atol=1e-12)
assert counters["stats"]["unique_graphs"] == 2, counters["stats"]
print("OK")
"""


@pytest.mark.slow
def test_inductor_compiles_twice_for_a_dataset_in_a_fresh_process():
    """Inductor, torch's defaults, three grids of different sizes: two graphs, eager results."""
    out = subprocess.run(
        [sys.executable, "-c", _INDUCTOR_DATASET], capture_output=True, text=True, timeout=900
    )
    assert out.returncode == 0, out.stderr[-3000:]
    assert out.stdout.strip().endswith("OK")

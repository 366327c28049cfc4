"""``tp.interop.to_diffusionnet``: DiffusionNet's operators in the format of its
``geometry.get_operators``, checked against independent references.

- format: shapes, dtypes, devices and layouts of DiffusionNet's ``compute_operators`` (frames
  ``(V, 3, 3)`` rows ``e_x, e_y, n``; mass ``(V,)``; ``L``, ``gradX``, ``gradY`` coalesced
  sparse COO; evals ``(k,)``; evecs ``(V, k)``);
- on triangle meshes ``L`` and ``mass`` against libigl's cotangent matrix and barycentric mass
  (DiffusionNet's cotan Laplacian and vertex areas; it adds ``1e-8 * mean`` to the masses,
  this does not), the normals against libigl's area-weighted vertex normals;
- eigenpairs against a dense scipy solve of ``L v = lambda M v``;
- ``gradX``/``gradY`` recover the tangent gradient of linear functions on planar polygon
  meshes, in the frames;
- the calls DiffusionNet's forward makes on its inputs (``unsqueeze``, indexing a batched
  sparse tensor, ``torch.mm``, spectral and dense implicit diffusion, complex gradient
  features), written out here, run and agree with this package's own functions and with
  scipy; the real ``DiffusionNet`` where ``diffusion_net`` is importable;
- the eigenpair cache: a hit returns identical tensors without an eigensolve, shares entries
  with ``tp.cached_eigs``, and a cache that cannot be written warns and still returns;
- an operation DiffusionNet applies to ``L`` (``unsqueeze``) on the package's own operator
  raises an error that names the conversion that works.
"""

from __future__ import annotations

import numpy as np
import pytest
import scipy.linalg
import scipy.sparse
import scipy.sparse.linalg
import torch
from conftest import DATA, hex_pent_mesh, mixed_mesh
from meshes import read_mesh

import torch_polylap as tp
import torch_polylap.interop as interop
from torch_polylap.interop import to_diffusionnet
from torch_polylap.shapes import quad_grid, quad_sphere


def _triangle_sphere():
    """A closed triangle mesh: a noisy cube sphere, its quads split along a diagonal."""
    v, q = quad_sphere(3, noise=0.05, seed=2)
    return v, torch.cat([q[:, [0, 1, 2]], q[:, [0, 2, 3]]])


def _planar_polygons():
    """A planar mesh of irregular polygons (degrees 3 to 10, the file's z = 0 plane) turned out
    of the xy plane, and the unit normal of its plane."""
    verts, faces = read_mesh(DATA / "grid" / "irr_poly_2.obj")
    rotation, _ = torch.linalg.qr(
        torch.randn(3, 3, generator=torch.Generator().manual_seed(4), dtype=torch.float64)
    )
    return verts @ rotation.T, faces, rotation[:, 2]


def _dense(A: torch.Tensor) -> np.ndarray:
    return A.to_dense().cpu().double().numpy()


# --------------------------------------------------------------------------- the format


@pytest.mark.parametrize("mesh", ["mixed", "hexpent", "triangles"])
def test_outputs_have_diffusionnets_shapes_dtypes_and_layouts(mesh, dtype, device):
    if mesh == "triangles":
        v, f = _triangle_sphere()
    else:
        v, f = mixed_mesh() if mesh == "mixed" else hex_pent_mesh()
    v = v.to(device=device, dtype=dtype)
    n, k = v.shape[0], 6
    frames, mass, L, evals, evecs, gradX, gradY = to_diffusionnet(v, f, k_eig=k)
    for t, shape in [(frames, (n, 3, 3)), (mass, (n,)), (evals, (k,)), (evecs, (n, k))]:
        assert t.shape == shape and t.layout == torch.strided
        assert t.dtype == dtype and t.device == v.device and not t.requires_grad
    for A in (L, gradX, gradY):
        assert A.layout == torch.sparse_coo and A.shape == (n, n) and A.is_coalesced()
        assert A.dtype == dtype and A.device == v.device and A.indices().dtype == torch.int64
        assert not A.requires_grad
    # frames: orthonormal and right-handed rows (e_x, e_y, n), e_y = n x e_x
    f64 = frames.double().cpu()
    eye = torch.eye(3, dtype=torch.float64).expand(n, 3, 3)
    tol = 1e-5 if dtype == torch.float32 else 1e-12
    torch.testing.assert_close(f64 @ f64.transpose(1, 2), eye, rtol=0, atol=tol)
    torch.testing.assert_close(torch.linalg.det(f64), torch.ones(n, dtype=torch.float64))
    # the same L and masses as the package's operators (the float64 ones, cast)
    Lp, M0 = tp.laplacian(v.detach().cpu().double(), f)
    np.testing.assert_allclose(_dense(L), _dense(Lp).astype(np.float64), rtol=tol, atol=tol)
    np.testing.assert_allclose(mass.cpu().double(), M0.diagonal(), rtol=tol, atol=tol)


def test_triangle_mesh_matches_libigl_cotan_laplacian_mass_and_normals(device):
    igl = pytest.importorskip("igl", reason="libigl not installed: pip install libigl")
    v, f = _triangle_sphere()
    frames, mass, L, *_ = to_diffusionnet(v.to(device), f, k_eig=4)
    assert frames.device.type == mass.device.type == L.device.type == device.type
    frames, mass = frames.cpu(), mass.cpu()
    vn, fn = v.numpy(), f.numpy()
    # libigl's cotmatrix is negative semi-definite; DiffusionNet's L, like this one, is -C
    np.testing.assert_allclose(_dense(L), -igl.cotmatrix(vn, fn).toarray(), rtol=0, atol=1e-12)
    barycentric = igl.massmatrix(vn, fn, igl.MASSMATRIX_TYPE_BARYCENTRIC).diagonal()
    np.testing.assert_allclose(mass.numpy(), barycentric, rtol=1e-12)
    normals = igl.per_vertex_normals(vn, fn, igl.PER_VERTEX_NORMALS_WEIGHTING_TYPE_AREA)
    np.testing.assert_allclose(frames[:, 2].numpy(), normals, rtol=0, atol=1e-12)


@pytest.mark.parametrize("mesh", ["mixed", "planar", "triangles"])
def test_eigenpairs_solve_the_generalized_problem(mesh, device):
    if mesh == "triangles":
        v, f = _triangle_sphere()
    else:
        v, f = mixed_mesh() if mesh == "mixed" else _planar_polygons()[:2]
    k = 8
    _, mass, L, evals, evecs, _, _ = to_diffusionnet(v.to(device), f, k_eig=k)
    assert evals.device.type == evecs.device.type == device.type
    mass, evals, evecs = mass.cpu(), evals.cpu(), evecs.cpu()
    Ld, m = _dense(L), mass.numpy()
    reference = scipy.linalg.eigh(Ld, np.diag(m), eigvals_only=True, subset_by_index=[0, k - 1])
    np.testing.assert_allclose(evals.numpy(), np.clip(reference, 0, None), rtol=1e-8, atol=1e-10)
    assert bool((evals >= 0).all()) and bool((evals[1:] >= evals[:-1]).all())
    phi = evecs.numpy()
    residual = Ld @ phi - (m[:, None] * phi) * evals.numpy()
    assert np.abs(residual).max() < 1e-9 * max(1.0, float(evals.max()))
    np.testing.assert_allclose(phi.T @ (m[:, None] * phi), np.eye(k), rtol=0, atol=1e-10)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_gradients_of_linear_functions_in_the_frames(seed, device):
    v, f, normal = _planar_polygons()
    v, normal = v.to(device), normal.to(device)
    frames, _, _, _, _, gradX, gradY = to_diffusionnet(v, f, k_eig=0)
    w = torch.randn(3, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)
    w = w.to(device)
    u = v @ w + 0.7
    # on a planar mesh the tangent gradient of u is w projected on the plane; e_x, e_y lie in
    # the plane, so its components are e_x . w and e_y . w at every vertex
    torch.testing.assert_close(
        torch.sparse.mm(gradX, u[:, None])[:, 0], frames[:, 0] @ w, rtol=1e-10, atol=1e-10
    )
    torch.testing.assert_close(
        torch.sparse.mm(gradY, u[:, None])[:, 0], frames[:, 1] @ w, rtol=1e-10, atol=1e-10
    )
    # the frames' normals are the plane's (up to orientation), so e_x, e_y are tangent
    ones = torch.ones(v.shape[0], dtype=torch.float64, device=device)
    torch.testing.assert_close((frames[:, 2] @ normal).abs(), ones, rtol=0, atol=1e-12)


# ----------------------------------------------------------- DiffusionNet's usage pattern


def _diffusionnet_style_forward(ops, x, times, a_re, a_im):
    """The operations DiffusionNet's forward applies to ``get_operators``' outputs, spelled
    out: add a batch dimension to every input, spectral diffusion through the mass-weighted
    eigenbasis, per-batch ``torch.mm`` with the batched sparse gradients, and the complex
    gradient features. Returns (diffused, gx, gy, features), batch dimension removed."""
    _, mass, L, evals, evecs, gradX, gradY = ops
    for operator in (L, gradX, gradY):
        assert operator != None  # noqa: E711  (DiffusionNet tests its inputs this way)
    x, mass, evals, evecs = (
        x.unsqueeze(0),
        mass.unsqueeze(0),
        evals.unsqueeze(0),
        evecs.unsqueeze(0),
    )
    L, gradX, gradY = L.unsqueeze(0), gradX.unsqueeze(0), gradY.unsqueeze(0)
    spectral = evecs.transpose(-2, -1) @ (x * mass.unsqueeze(-1))
    decay = torch.exp(-evals.unsqueeze(-1) * times.unsqueeze(0))
    diffused = evecs @ (decay * spectral)
    gx = torch.stack([torch.mm(gradX[b, ...], diffused[b, ...]) for b in range(x.shape[0])])
    gy = torch.stack([torch.mm(gradY[b, ...], diffused[b, ...]) for b in range(x.shape[0])])
    re = gx @ a_re.T - gy @ a_im.T
    im = gy @ a_re.T + gx @ a_im.T
    features = torch.tanh(gx * re + gy * im)
    return diffused[0], gx[0], gy[0], features[0]


def test_outputs_plug_into_diffusionnets_forward_pattern(device):
    v, f = hex_pent_mesh()
    v = v.float().to(device)  # DiffusionNet's layers are float32
    ops = to_diffusionnet(v, f, k_eig=8)
    C = 4
    gen = torch.Generator().manual_seed(0)
    x = torch.randn(v.shape[0], C, generator=gen).to(device).requires_grad_(True)
    times = torch.rand(C, generator=gen).to(device).requires_grad_(True)
    a_re = torch.randn(C, C, generator=gen).to(device).requires_grad_(True)
    a_im = torch.randn(C, C, generator=gen).to(device).requires_grad_(True)
    diffused, gx, gy, features = _diffusionnet_style_forward(ops, x, times, a_re, a_im)
    assert features.device.type == device.type
    features.sum().backward()
    assert all(p.grad is not None and bool(p.grad.abs().sum() > 0) for p in (x, times, a_re))
    # the same computation with this package's own functions and operators
    _, mass, _, evals, evecs, _, _ = ops
    M0 = tp.sparse.diag(mass)
    expected = tp.spectral_heat_diffusion(x.detach(), evals, evecs, M0, times.detach())
    torch.testing.assert_close(diffused.detach(), expected, rtol=1e-5, atol=1e-6)
    grad_x, grad_y = tp.nn.vertex_gradient_operators(v, f)
    torch.testing.assert_close(gx.detach(), grad_x @ expected, rtol=1e-4, atol=1e-5)
    torch.testing.assert_close(gy.detach(), grad_y @ expected, rtol=1e-4, atol=1e-5)
    reference = tp.nn.spatial_gradient_features(
        gx.detach(), gy.detach(), a_re.detach(), a_im.detach()
    )
    torch.testing.assert_close(features.detach(), reference, rtol=1e-5, atol=1e-6)


def test_dense_implicit_diffusion_pattern_matches_a_sparse_solve(device):
    """DiffusionNet's ``implicit_dense`` method (``k_eig=0``): ``L.to_dense()`` batched, one
    Cholesky of ``M + t L`` per channel; checked against scipy's sparse solve."""
    v, f = mixed_mesh()
    _, mass, L, evals, evecs, _, _ = to_diffusionnet(v.to(device), f, k_eig=0)
    assert evals.shape == (0,) and evecs.shape == (v.shape[0], 0)
    n, C = v.shape[0], 3
    times = torch.tensor([0.01, 0.1, 1.0], dtype=torch.float64, device=device)
    x = torch.randn(1, n, C, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    x = x.to(device)
    system = L.unsqueeze(0).to_dense().unsqueeze(1).expand(-1, C, n, n).clone()
    system *= times.unsqueeze(0).unsqueeze(-1).unsqueeze(-1)
    system += torch.diag_embed(mass.unsqueeze(0)).unsqueeze(1)
    factors = torch.linalg.cholesky(system)  # M + t L is positive definite
    rhs = (x * mass.unsqueeze(0).unsqueeze(-1)).transpose(1, 2).unsqueeze(-1)
    got = torch.cholesky_solve(rhs, factors).squeeze(-1).transpose(1, 2)[0]
    assert got.device.type == device.type
    got, L, mass, x = got.cpu(), L.cpu(), mass.cpu(), x.cpu()
    S = scipy.sparse.coo_matrix((L.values().numpy(), L.indices().numpy()), shape=(n, n)).tocsc()
    Mm = scipy.sparse.diags(mass.numpy())
    for c, t in enumerate(times.tolist()):
        ref = scipy.sparse.linalg.spsolve((Mm + t * S).tocsc(), Mm @ x[0, :, c].numpy())
        np.testing.assert_allclose(got[:, c].numpy(), ref, rtol=1e-10, atol=1e-12)


def test_real_diffusionnet_trains_on_polygon_operators():
    diffusion_net = pytest.importorskip(
        "diffusion_net", reason="diffusion_net not installed (not on PyPI; optional)"
    )
    v, f = hex_pent_mesh()
    v = v.float()
    _, mass, L, evals, evecs, gradX, gradY = to_diffusionnet(v, f, k_eig=8)
    model = diffusion_net.layers.DiffusionNet(C_in=3, C_out=2, C_width=8, N_block=2)
    out = model(v, mass, L=L, evals=evals, evecs=evecs, gradX=gradX, gradY=gradY)
    assert out.shape == (v.shape[0], 2)
    out.square().mean().backward()
    assert all(p.grad is not None for p in model.parameters() if p.requires_grad)


# --------------------------------------------------------------------------- the cache


def _same(a: tuple, b: tuple) -> None:
    for x, y in zip(a, b, strict=True):
        if x.layout == torch.sparse_coo:
            assert torch.equal(x.indices(), y.indices()) and torch.equal(x.values(), y.values())
        else:
            assert torch.equal(x, y)


def test_cache_hit_returns_identical_tensors_without_an_eigensolve(tmp_path, monkeypatch, device):
    v, f = mixed_mesh()
    v = v.to(device)
    cold = to_diffusionnet(v, f, k_eig=5, cache_dir=tmp_path / "ops")
    files = sorted((tmp_path / "ops").iterdir())
    assert len(files) == 1 and files[0].suffix == ".npz"

    def no_eigensolve(*args, **kwargs):
        raise AssertionError("eigs called on a cache hit")

    monkeypatch.setattr(interop, "eigs", no_eigensolve)
    monkeypatch.setattr(tp.spectral, "eigs", no_eigensolve)
    _same(to_diffusionnet(v, f, k_eig=5, cache_dir=tmp_path / "ops"), cold)
    # the entry is the one tp.cached_eigs reads: no new file, no eigensolve there either
    evals, evecs = tp.cached_eigs(v, f, 5, tmp_path / "ops")
    assert torch.equal(evecs, cold[4]) and sorted((tmp_path / "ops").iterdir()) == files
    # another mesh, k or method is another entry
    monkeypatch.undo()
    to_diffusionnet(v, f, k_eig=4, cache_dir=tmp_path / "ops")
    to_diffusionnet(v, f, k_eig=5, cache_dir=tmp_path / "ops", method="plms")
    to_diffusionnet(v * 1.5, f, k_eig=5, cache_dir=tmp_path / "ops")
    assert len(list((tmp_path / "ops").iterdir())) == 4


def test_uncached_and_cached_results_are_the_same(tmp_path, device):
    v, f = hex_pent_mesh()
    v = v.to(device)
    uncached = to_diffusionnet(v, f, k_eig=6)
    _same(uncached, to_diffusionnet(v, f, k_eig=6, cache_dir=tmp_path))
    # a hit: read back from the entry onto the vertices' device
    _same(uncached, to_diffusionnet(v, f, k_eig=6, cache_dir=tmp_path))


def test_unwritable_cache_warns_and_returns_the_result(tmp_path, monkeypatch, device):
    v, f = mixed_mesh()
    v = v.to(device)
    expected = to_diffusionnet(v, f, k_eig=5)
    blocker = tmp_path / "a_file"
    blocker.write_text("not a folder")
    with pytest.warns(UserWarning, match="cannot be written"):
        got = to_diffusionnet(v, f, k_eig=5, cache_dir=blocker / "cache")  # mkdir fails
    _same(got, expected)

    def read_only(path, write):
        raise PermissionError(13, "Permission denied", str(path))

    # root ignores chmod: emulate it where the one eigenpair cache writes
    monkeypatch.setattr(tp.spectral, "atomic_write", read_only)
    with pytest.warns(tp.spectral.CacheWriteWarning, match="Permission denied"):
        got = to_diffusionnet(v, f, k_eig=5, cache_dir=tmp_path / "ro")
    _same(got, expected)


def test_unreadable_cache_entry_is_recomputed_with_a_warning(tmp_path, device):
    v, f = mixed_mesh()
    v = v.to(device)
    expected = to_diffusionnet(v, f, k_eig=5, cache_dir=tmp_path)
    (entry,) = tmp_path.iterdir()
    entry.write_bytes(b"PK\x03\x04 truncated")
    with pytest.warns(UserWarning, match="cannot be read"):
        got = to_diffusionnet(v, f, k_eig=5, cache_dir=tmp_path)
    _same(got, expected)
    _same(to_diffusionnet(v, f, k_eig=5, cache_dir=tmp_path), expected)  # replaced


def test_bad_arguments_say_what_to_do(tmp_path, device):
    v, f = quad_grid(2, device=device)
    with pytest.raises(ValueError, match=r"0 <= k_eig < 9"):
        to_diffusionnet(v, f, k_eig=9)
    with pytest.raises(TypeError, match="integer"):
        to_diffusionnet(v, f, k_eig=2.0)
    with pytest.raises(ValueError, match="point cloud"):
        to_diffusionnet(v, torch.zeros(0, 3, dtype=torch.int64, device=device), k_eig=2)
    with pytest.raises(ValueError, match="method"):
        to_diffusionnet(v, f, k_eig=2, method="cotan")
    (tmp_path / "file").write_text("")
    with pytest.raises(ValueError, match="not a directory"):
        to_diffusionnet(v, f, k_eig=2, cache_dir=tmp_path / "file")


def test_unsupported_operations_name_the_conversion_that_works(device):
    v, f = quad_grid(2, device=device)
    L, _ = tp.laplacian(v, f)
    with pytest.raises(tp.sparse.UnsupportedOperation, match="to_torch_sparse") as info:
        L.unsqueeze(0)
    assert "layout=torch.sparse_coo" in str(info.value)
    # and that conversion does what DiffusionNet does with L
    coo = tp.sparse.to_torch_sparse(L, layout=torch.sparse_coo)
    assert coo.unsqueeze(0)[0].to_dense().equal(L.to_dense())

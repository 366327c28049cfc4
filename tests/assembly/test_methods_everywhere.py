"""``method=`` reaches every entry point that builds ``L``.

Each entry point (batches, losses and their modules, the spectrum and dataset precompute, the
eigenpair cache, the applications and the command line) is compared with the same quantity built
from ``tp.laplacian(verts, faces, lam, method=...)`` directly, for every method. The meshes
have non-planar faces of degree 3 to 6, where the Laplacians differ (checked below), so a
``method`` that is dropped on the way fails the comparison. Default arguments stay AW11.
"""

from __future__ import annotations

import itertools
import json

import numpy as np
import pytest
import scipy.sparse.linalg as spla
import torch
from conftest import DATA, hex_pent_mesh, mixed_mesh
from meshes import read_mesh

import torch_polylap as tp
from torch_polylap import losses
from torch_polylap.apps.conformal import conformal_matrix
from torch_polylap.cli import main
from torch_polylap.datasets import PolygonMeshDataset
from torch_polylap.kernels import BLOCK_METHODS, METHODS
from torch_polylap.nn import Spectrum
from torch_polylap.spectral import eigs_cache_key

pytestmark = pytest.mark.filterwarnings("ignore:.*read vertex positions and polygons only")

LAM = 1.7  # not the default, so a dropped `lam` shows as well (PLMS ignores it)

# Quantities assembled in float64 from the same values: they agree to round-off of sums.
TIGHT = {"rtol": 1e-12, "atol": 1e-12}


def dense(op: torch.Tensor) -> torch.Tensor:
    return op.to_dense()


@pytest.fixture(scope="module")
def pair():
    """Two meshes with boundary and non-planar faces of degree 3 to 6."""
    v1, f1 = hex_pent_mesh()
    v2, f2 = mixed_mesh()
    return [(v1, f1), (v2, f2)]


@pytest.fixture(scope="module")
def batch(pair):
    return tp.PolygonMeshes([v for v, _ in pair], [f for _, f in pair])


def direct(verts, faces, method, lam=LAM):
    return tp.laplacian(verts, faces, lam, method=method)


def packed_direct(pair, method, lam=LAM):
    """Block-diagonal dense ``(L, M0)`` of the meshes built one by one."""
    Ls, Ms = zip(*(direct(v, f, method, lam) for v, f in pair), strict=True)
    return torch.block_diag(*map(dense, Ls)), torch.block_diag(*map(dense, Ms))


def test_the_methods_differ_on_these_meshes(pair, device):
    # Otherwise every comparison below would pass with the method dropped.
    pair = [(v.to(device), f) for v, f in pair]
    for verts, faces in pair:
        ops = {m: direct(verts, faces, m) for m in METHODS}
        for a, b in itertools.combinations(METHODS, 2):
            assert (dense(ops[a][0]) - dense(ops[b][0])).abs().max() > 1e-3, (a, b)
    # PLMS ignores lam; AW11 and de Goes do not.
    verts, faces = pair[0]
    for method, same in [("plms", True), ("diamond", True), ("aw11", False), ("degoes", False)]:
        L1, L2 = direct(verts, faces, method, 1.0)[0], direct(verts, faces, method, 2.0)[0]
        assert torch.allclose(dense(L1), dense(L2)) == same, method


# ------------------------------------------------------------------------------------------
# batches and losses
# ------------------------------------------------------------------------------------------


@pytest.mark.parametrize("method", METHODS)
def test_batch_laplacian(batch, pair, method, device):
    L, M0 = batch.to(device).laplacian(LAM, method=method)
    assert L.device.type == M0.device.type == device.type
    L_ref, M_ref = packed_direct(pair, method)  # mesh by mesh, on the CPU
    torch.testing.assert_close(dense(L).cpu(), L_ref, **TIGHT)
    torch.testing.assert_close(dense(M0).cpu(), M_ref, **TIGHT)


def test_batch_laplacian_default_is_aw11(batch, pair, device):
    L, M0 = batch.to(device).laplacian(LAM)
    L_ref, M_ref = packed_direct(pair, "aw11")
    torch.testing.assert_close(dense(L).cpu(), L_ref, **TIGHT)
    torch.testing.assert_close(dense(M0).cpu(), M_ref, **TIGHT)


def _per_mesh(pair, fn):
    return torch.stack([fn(v, f) for v, f in pair])


@pytest.mark.parametrize("method", METHODS)
def test_losses(batch, pair, method, device):
    rng = np.random.default_rng(0)
    signal = torch.from_numpy(rng.normal(size=(batch.verts_packed().shape[0], 2)))
    counts = [v.shape[0] for v, _ in pair]
    signals = torch.split(signal, counts)

    def mean_curvature(v, f):
        L, M0 = direct(v, f, method)
        return tp.strong_laplacian(L, M0, v).norm(dim=1).mean()

    def smoothing(v, f):
        L, _ = direct(v, f, method)
        return ((L @ v).norm(dim=1) / dense(L).diagonal()).mean()

    def dirichlet(v, f, s):
        L, _ = direct(v, f, method)
        return 0.5 * (s * (L @ s)).sum()

    def bending(v, f):
        L, M0 = direct(v, f, method)
        Lx = L @ v
        return 0.5 * ((Lx * Lx).sum(1) / dense(M0).diagonal()).sum()

    # the references mesh by mesh on the CPU; the losses on the batch on `device`
    expected = {
        "smoothing": _per_mesh(pair, smoothing),
        "mean_curvature": _per_mesh(pair, mean_curvature),
        "dirichlet": torch.stack(
            [dirichlet(v, f, s) for (v, f), s in zip(pair, signals, strict=True)]
        ),
    }
    batch, signal = batch.to(device), signal.to(device)
    if method in BLOCK_METHODS:
        expected["bending"] = _per_mesh(pair, bending)
    else:  # M0^-1 per vertex needs a diagonal mass
        with pytest.raises(ValueError, match="needs a diagonal mass"):
            losses.bending_energy(batch, None, LAM, "none", method=method)
    got = {
        "smoothing": losses.laplacian_smoothing(batch, method, LAM, reduction="none"),
        "mean_curvature": losses.mean_curvature_smoothing(
            batch, LAM, reduction="none", method=method
        ),
        "dirichlet": losses.dirichlet_energy(batch, signal, LAM, "none", method=method),
    }
    modules = {
        "smoothing": losses.LaplacianSmoothingLoss(method, LAM, reduction="none")(batch),
        "mean_curvature": losses.MeanCurvatureSmoothingLoss(LAM, "none", method=method)(batch),
        "dirichlet": losses.DirichletEnergy(LAM, "none", method=method)(batch, signal),
    }
    if method in BLOCK_METHODS:
        got["bending"] = losses.bending_energy(batch, None, LAM, "none", method=method)
        modules["bending"] = losses.BendingEnergy(LAM, "none", method=method)(batch)
    for name, ref in expected.items():
        assert got[name].device.type == modules[name].device.type == device.type
        torch.testing.assert_close(got[name].cpu(), ref, **TIGHT, msg=name)
        torch.testing.assert_close(modules[name].cpu(), ref, **TIGHT, msg=f"{name} module")
    assert f"method={method!r}" in repr(losses.BendingEnergy(method=method))


def test_loss_defaults_stay_aw11(batch):
    ref = losses.bending_energy(batch, method="aw11")
    assert losses.bending_energy(batch) == ref
    assert losses.BendingEnergy()(batch) == ref
    polygon = losses.laplacian_smoothing(batch, "polygon", LAM)
    assert polygon == losses.laplacian_smoothing(batch, "aw11", LAM)
    assert polygon == losses.laplacian_smoothing(batch, "cot", LAM)


def test_losses_reject_unknown_methods(batch):
    with pytest.raises(ValueError, match="method must be one of"):
        losses.bending_energy(batch, method="cotan")
    with pytest.raises(ValueError, match="method must be one of"):
        losses.DirichletEnergy(method="AW11")
    with pytest.raises(ValueError, match="'uniform', 'polygon'"):
        losses.laplacian_smoothing(batch, "cotan")


@pytest.mark.parametrize("method", ["plms", "degoes"])
def test_loss_gradients_follow_the_method(batch, method, device):
    # Gradients flow through the chosen Laplacian's weights and differ from AW11's.
    batch = batch.to(device)
    grads = {}
    for m in ("aw11", method):
        X = batch.verts_packed().detach().clone().requires_grad_(True)
        loss = losses.mean_curvature_smoothing(batch.update_packed(X), LAM, method=m)
        (grads[m],) = torch.autograd.grad(loss, X)
    assert torch.isfinite(grads[method]).all()
    assert (grads[method] - grads["aw11"]).abs().max() > 1e-4


# ------------------------------------------------------------------------------------------
# spectra, the eigenpair cache and the dataset
# ------------------------------------------------------------------------------------------

K = 6


@pytest.mark.parametrize("method", METHODS)
def test_spectrum_from_polygon_meshes(batch, pair, method, tmp_path):
    if method not in BLOCK_METHODS:  # the spectrum's masses are a diagonal M0's
        with pytest.raises(ValueError, match="must be a diagonal matrix"):
            Spectrum.from_polygon_meshes(batch, K, lam=LAM, method=method)
        return
    for cache_dir in (None, tmp_path):
        spec = Spectrum.from_polygon_meshes(batch, K, lam=LAM, method=method, cache_dir=cache_dir)
        for b, (v, f) in enumerate(pair):
            L, M0 = direct(v, f, method)
            evals, _ = tp.eigs(L, M0, K)
            torch.testing.assert_close(spec.evals[b], evals, rtol=1e-9, atol=1e-9)
        _, M_ref = packed_direct(pair, method)
        torch.testing.assert_close(spec.mass, M_ref.diagonal(), **TIGHT)


@pytest.mark.parametrize("method", METHODS)
def test_cached_eigs(pair, method, tmp_path, device):
    verts, faces = pair[0]
    verts = verts.to(device)
    evals, evecs = tp.cached_eigs(verts, faces, K, tmp_path, lam=LAM, method=method)
    assert evals.device.type == evecs.device.type == device.type
    L, M0 = direct(verts, faces, method)
    ref, _ = tp.eigs(L, M0, K)
    torch.testing.assert_close(evals, ref, rtol=1e-9, atol=1e-9)
    # eigenpairs of this method's pencil, whatever the signs of the vectors
    residual = L @ evecs - (M0 @ evecs) * evals
    assert residual.abs().max() < 1e-9 * dense(L).abs().max()
    again = tp.cached_eigs(verts, faces, K, tmp_path, lam=LAM, method=method)
    assert torch.equal(again[0], evals)


def test_cache_keys_differ_by_method(pair, tmp_path, device):
    verts, faces = pair[0]
    verts = verts.to(device)
    keys = {m: eigs_cache_key(verts, faces, K, LAM, m) for m in METHODS}
    assert len(set(keys.values())) == len(METHODS)
    assert keys["aw11"] == eigs_cache_key(verts, faces, K, LAM)  # the default method
    # the dtype is part of the key: float32 eigenpairs never serve a float64 request
    assert eigs_cache_key(verts.float(), faces, K, LAM) != keys["aw11"]
    # lam is part of the key where the method uses it, not for PLMS.
    assert eigs_cache_key(verts, faces, K, 0.5, "plms") == keys["plms"]
    assert eigs_cache_key(verts, faces, K, 0.5, "degoes") != keys["degoes"]
    assert eigs_cache_key(verts, faces, K, 0.5, "aw11") != keys["aw11"]
    # one file per method in the same folder, each holding its own method's eigenvalues
    results = {m: tp.cached_eigs(verts, faces, K, tmp_path, lam=LAM, method=m)[0] for m in METHODS}
    assert len(list(tmp_path.glob("eigs-*.npz"))) == len(METHODS)
    assert (results["plms"] - results["aw11"]).abs().max() > 1e-6
    assert (results["degoes"] - results["aw11"]).abs().max() > 1e-6


def test_cached_eigs_rejects_unknown_method(pair, tmp_path):
    verts, faces = pair[0]
    with pytest.raises(ValueError, match="method must be one of"):
        tp.cached_eigs(verts, faces, K, tmp_path, method="cot")
    assert not list(tmp_path.iterdir())


@pytest.mark.parametrize("method", METHODS)
def test_dataset(pair, method, tmp_path):
    if method not in BLOCK_METHODS:  # its "mass" is a diagonal M0's
        with pytest.raises(ValueError, match="needs a diagonal mass"):
            PolygonMeshDataset(pair, k=K, cache_dir=tmp_path, method=method)
        return
    ds = PolygonMeshDataset(
        pair, k=K, cache_dir=tmp_path, lam=LAM, method=method, dtype=torch.float64
    )
    for i in range(len(ds)):
        item = ds[i]
        verts, faces = ds.mesh(i)
        L, M0 = direct(verts, faces, method)
        torch.testing.assert_close(dense(item["L"]), dense(L), **TIGHT)
        torch.testing.assert_close(item["mass"], dense(M0).diagonal(), **TIGHT)
        torch.testing.assert_close(item["evals"], tp.eigs(L, M0, K)[0], rtol=1e-9, atol=1e-9)


def test_dataset_caches_each_method_separately(pair, tmp_path):
    evals = {}
    for method in ("aw11", "plms"):
        ds = PolygonMeshDataset(pair[:1], k=K, cache_dir=tmp_path, method=method)
        ds.precompute()
        evals[method] = ds[0]["evals"]
    assert len(list(tmp_path.glob("eigs-*.npz"))) == 2
    assert (evals["plms"] - evals["aw11"]).abs().max() > 1e-4
    with pytest.raises(ValueError, match="method must be one of"):
        PolygonMeshDataset(pair, k=K, cache_dir=tmp_path, method="nope")


# ------------------------------------------------------------------------------------------
# applications
# ------------------------------------------------------------------------------------------


@pytest.mark.parametrize("frozen", [False, True], ids=["live", "frozen"])
@pytest.mark.parametrize("method", METHODS)
def test_mean_curvature_flow(pair, method, frozen, device):
    verts, faces = pair[0]
    verts = verts.to(device)
    dt = 1e-2
    options = tp.apps.FlowOptions(frozen=frozen)
    got = tp.apps.mean_curvature_flow(verts, faces, dt, 2, LAM, method=method, options=options)
    got = got.verts
    X = verts
    L0, M0_0 = direct(verts, faces, method)
    for _ in range(2):
        L, M0 = (L0, M0_0) if frozen else direct(X, faces, method)
        X = tp.solve(M0 + dt * L, M0 @ X)
    torch.testing.assert_close(got, X, rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("method", METHODS)
def test_conformal(pair, method):
    verts, faces = pair[0]
    n = verts.shape[0]
    L, _ = direct(verts, faces, method)
    LC = conformal_matrix(verts, faces, LAM, method=method)
    torch.testing.assert_close(dense(LC)[:n, :n], dense(L), **TIGHT)
    torch.testing.assert_close(dense(LC)[n:, n:], dense(L), **TIGHT)

    uv = tp.apps.conformal_parameterization(verts, faces, lam=LAM, method=method)
    # E_C = 1/2 sum_c uv_c^T L uv_c - A(uv) with this method's L
    energy = tp.apps.conformal_energy(uv, verts, faces, LAM, method=method)
    z = torch.cat((uv[:, 0], uv[:, 1]))
    torch.testing.assert_close(energy, 0.5 * z @ (LC @ z), rtol=1e-10, atol=1e-12)
    # The pinned map minimizes E_C with this method's L_C: stationary at every free unknown.
    pins = torch.nonzero((LC @ z).abs() > 1e-9 * dense(LC).abs().max()).flatten() % n
    assert len(set(pins.tolist())) <= 2, "more than the two pinned vertices are not stationary"

    free = tp.apps.conformal_parameterization(
        verts, faces, lam=LAM, free_boundary=True, method=method
    )
    # The free-boundary map is L-harmonic inside (AW11 eq. 15) for this method's L.
    interior = torch.ones(n, dtype=torch.bool)
    interior[tp.build_topology(faces, n).boundary_vertices] = False
    assert interior.any()
    assert (L @ free)[interior].abs().max() < 1e-10 * free.abs().max() * dense(L).abs().max()


def test_conformal_defaults_and_method_matters(pair):
    verts, faces = pair[0]
    uv = {m: tp.apps.conformal_parameterization(verts, faces, method=m) for m in METHODS}
    assert torch.equal(tp.apps.conformal_parameterization(verts, faces), uv["aw11"])
    assert (uv["plms"] - uv["aw11"]).abs().max() > 1e-4
    assert (uv["degoes"] - uv["aw11"]).abs().max() > 1e-4


@pytest.mark.parametrize("method", METHODS)
def test_plate_bending(method, device):
    V, F = read_mesh(DATA / "grid" / "irr_poly_1.obj", dtype=torch.float64)
    if method not in BLOCK_METHODS:  # the mixed formulation lumps M0 per vertex
        with pytest.raises(ValueError, match="needs a diagonal mass"):
            tp.apps.plate_bending(V.to(device), F, load=1.0, lam=LAM, method=method)
        return
    V = V + torch.tensor([0.5, 0.5, 0.0], dtype=V.dtype)
    V[:, 2] = 0.05 * torch.sin(3 * V[:, 0]) * torch.cos(2 * V[:, 1])  # non-planar faces too
    u = tp.apps.plate_bending(V.to(device), F, load=1.0, lam=LAM, method=method)
    assert u.device.type == device.type
    L, M0 = direct(V, F, method)
    Ls, m = tp.sparse.to_scipy(L).tocsr(), dense(M0).diagonal().numpy()
    boundary = tp.build_topology(F, V.shape[0]).boundary_vertices.numpy()
    inner = np.setdiff1d(np.arange(V.shape[0]), boundary)
    L_II = Ls[inner][:, inner].tocsc()
    w = spla.spsolve(L_II, m[inner])  # L_II w = (M0 q)_I, q = 1
    ref = np.zeros(V.shape[0])
    ref[inner] = spla.spsolve(L_II, m[inner] * w)  # L_II u = (M0 w)_I
    # off the CPU the solves may be iterative (CG to a 1e-10 residual), not direct
    rtol = 1e-9 if device.type == "cpu" else 1e-6
    np.testing.assert_allclose(
        u.cpu().numpy(), ref, rtol=rtol, atol=rtol * 1e-3 * np.abs(ref).max()
    )


def test_applications_reject_unknown_methods(pair):
    verts, faces = pair[0]
    for call in (
        lambda: tp.apps.mean_curvature_flow(verts, faces, 1e-2, 1, method="x"),
        lambda: tp.apps.conformal_parameterization(verts, faces, method="x"),
        lambda: tp.apps.conformal_energy(verts[:, :2], verts, faces, method="x"),
        lambda: conformal_matrix(verts, faces, method="x"),
        lambda: tp.apps.plate_bending(verts, faces, method="x"),
    ):
        with pytest.raises(ValueError, match="method must be one of"):
            call()


# ------------------------------------------------------------------------------------------
# command line
# ------------------------------------------------------------------------------------------


@pytest.mark.parametrize("method", METHODS)
def test_cli_spectrum(method, tmp_path, capsys, one_thread):
    mesh = DATA / "dodecahedron_poly.obj"
    argv = ["spectrum", str(mesh), "-k", "5", "--npz", "--no-plot", "--lam", str(LAM)]
    assert main([*argv, "--method", method, "-o", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert method in out
    data = np.load(tmp_path / "dodecahedron_poly_spectrum.npz")
    assert str(data["method"]) == method
    verts, faces = read_mesh(mesh, dtype=torch.float64)
    L, M0 = direct(verts, faces, method)
    expected = tp.eigs(L, M0, 5)[0].numpy()
    np.testing.assert_allclose(data["eigenvalues"], expected, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(data["mass"], dense(M0).diagonal().numpy(), rtol=1e-12)


def _field(out: str, label: str) -> str:
    line = next(x for x in out.splitlines() if x.strip().startswith(label))
    return line.strip()[len(label) :].strip()


@pytest.mark.parametrize("method", METHODS)
def test_cli_smooth_and_param(method, tmp_path, capsys, one_thread):
    mesh = DATA / "dodecahedron_poly.obj"
    argv = ["smooth", str(mesh), "--steps", "2", "--dt", "0.01", "--lam", str(LAM)]
    assert main([*argv, "--method", method, "--no-plot", "--no-progress", "-o", str(tmp_path)]) == 0
    assert _field(capsys.readouterr().out, "Laplacian").startswith(method)
    verts, faces = read_mesh(mesh, dtype=torch.float64)
    smoothed, _ = read_mesh(tmp_path / "dodecahedron_poly_smooth.obj", dtype=torch.float64)
    expected = tp.apps.mean_curvature_flow(verts, faces, 0.01, 2, lam=LAM, method=method).verts
    # the OBJ writer prints 17 significant digits
    torch.testing.assert_close(smoothed, expected, rtol=1e-12, atol=1e-14)

    verts, faces = hex_pent_mesh()
    disk = tmp_path / "disk.obj"
    tp.write_mesh(disk, verts, faces)
    argv = ["param", str(disk), "--lam", str(LAM), "--method", method, "--no-plot"]
    assert main([*argv, "-o", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    uv, _ = read_mesh(tmp_path / "disk_param.obj", dtype=torch.float64)
    expected = tp.apps.conformal_parameterization(verts, faces, lam=LAM, method=method)
    torch.testing.assert_close(uv[:, :2], expected, rtol=1e-10, atol=1e-12)
    energy = float(tp.apps.conformal_energy(expected, verts, faces, LAM, method=method))
    assert float(_field(out, "conformal energy E_C")) == pytest.approx(energy, rel=1e-3)


@pytest.mark.parametrize("method", ["plms", "degoes"])
def test_cli_info_and_bench_accept_method(method, tmp_path, capsys, one_thread):
    mesh = str(DATA / "dodecahedron_poly.obj")
    assert main(["info", mesh, "--method", method, "--eigs", "3"]) == 0
    assert f"operators ({method}, " in capsys.readouterr().out
    argv = ["bench", mesh, "--repeat", "1", "-k", "3", "--json", "--no-progress"]
    assert main([*argv, "--method", method, "-o", str(tmp_path)]) == 0
    assert method in capsys.readouterr().out
    assert json.loads((tmp_path / "dodecahedron_poly_bench.json").read_text())["method"] == method


def test_cli_rejects_unknown_method(capsys):
    with pytest.raises(SystemExit) as err:
        main(["spectrum", "--method", "cotan"])
    assert err.value.code == 2
    assert "invalid choice: 'cotan'" in capsys.readouterr().err


def test_every_laplacian_command_has_the_option(capsys):
    for command in ("info", "smooth", "param", "spectrum", "bench", "demo"):
        with pytest.raises(SystemExit):
            main([command, "--help"])
        assert "--method {aw11,plms,degoes,diamond}" in capsys.readouterr().out, command

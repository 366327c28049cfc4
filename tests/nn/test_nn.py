"""Learning layers (torch_polylap.nn) against the library's functionals and closed forms."""

from __future__ import annotations

import math

import pytest
import torch
from conftest import DATA, assert_directional_derivative, mixed_mesh
from meshes import read_mesh

import torch_polylap as tp
import torch_polylap.nn as tnn
from torch_polylap.batch import PolygonMeshes
from torch_polylap.shapes import quad_grid

D64 = {"dtype": torch.float64}


def mesh_with_spectrum(path, k):
    V, F = read_mesh(path, dtype=torch.float64)
    L, M0 = tp.laplacian(V, F)
    evals, evecs = tp.eigs(L, M0, k)
    return V, F, L, M0, evals, evecs


@pytest.fixture(scope="module")
def sphere():
    """Quad sphere with 386 vertices and 30 eigenpairs (modes l <= 4 plus some of l = 5)."""
    return mesh_with_spectrum(DATA / "sphere" / "quad_2.obj", 30)


@pytest.fixture(scope="module")
def batch():
    """Three closed meshes of different sizes and degrees (pentagons; triangles to pentagons;
    hexagons and pentagons) with 8 eigenpairs each."""
    meshes = [
        mesh_with_spectrum(DATA / name, 8)
        for name in ("dodecahedron_poly.obj", "spot_control_mesh.obj", "sphere/hex_2.obj")
    ]
    spectrum = tnn.Spectrum.from_meshes([(e, v, M0) for _, _, _, M0, e, v in meshes])
    return meshes, spectrum


def m_norm(M0, u):
    return torch.sqrt((M0.diagonal()[:, None] * u * u).sum())


def test_spectral_diffusion_is_the_library_functional(sphere, device):
    V, _, _, M0, evals, evecs = sphere
    V, M0, evals, evecs = (t.to(device) for t in (V, M0, evals, evecs))
    spectrum = tnn.Spectrum.from_meshes([(evals, evecs, M0)])
    x = torch.stack([V[:, 2], V[:, 0] * V[:, 1], torch.cos(4 * V[:, 0])], 1)
    times = torch.tensor([1e-3, 1e-2, 0.1], **D64, device=device)
    out = spectrum.heat_diffusion(x, times)
    assert out.device.type == device.type
    ref = tp.spectral_heat_diffusion(x, evals, evecs, M0, times)
    assert torch.allclose(out, ref, atol=1e-13)


def test_implicit_diffusion_is_the_library_functional_and_the_resolvent(sphere, device):
    V, _, L, M0, evals, evecs = sphere
    V, L, M0, evals, evecs = (t.to(device) for t in (V, L, M0, evals, evecs))
    times = torch.tensor([1e-3, 0.05], **D64, device=device)
    x = torch.stack([V[:, 2], torch.sin(3 * V[:, 1])], 1)
    out = tp.implicit_heat_diffusion(L, M0, x, times)
    for c in range(2):
        ref = tp.implicit_heat_diffusion(L, M0, x[:, c], times[c])
        assert torch.allclose(out[:, c], ref, atol=1e-13)
    # on an eigenvector (M0 + tL) phi = (1 + t mu) M0 phi: one step scales it by 1 / (1 + t mu)
    phi = evecs[:, [3, 7]]
    out = tp.implicit_heat_diffusion(L, M0, phi, times)
    expected = phi / (1 + times * evals[[3, 7]])
    assert torch.allclose(out, expected, atol=1e-9)


def test_spectral_and_implicit_diffusion_agree_for_small_times(sphere, device):
    """Bound: implicit keeps every mode i with factor 1/(1 + t mu_i) <= 1, spectral keeps the
    first k with exp(-t mu_i), so in the M0-norm
    ``|spectral - implicit| <= max_{i<k} |exp(-t mu_i) - 1/(1 + t mu_i)| |P_k u| + |u - P_k u|``
    with ``P_k`` the M0-orthogonal projection on the k eigenvectors. For a smooth signal on
    this 386-vertex sphere ``|u - P_k u|`` is small, and the first term is O((t mu_k)^2)."""
    V, _, L, M0, evals, evecs = sphere
    V, L, M0, evals, evecs = (t.to(device) for t in (V, L, M0, evals, evecs))
    spectrum = tnn.Spectrum.from_meshes([(evals, evecs, M0)])
    u = torch.stack([V[:, 2], V[:, 0] * V[:, 1] + 0.3 * V[:, 2] ** 3], 1)
    projected = spectrum.synthesize(spectrum.project(u))
    residual = m_norm(M0, u - projected)
    assert residual < 0.02 * m_norm(M0, u)  # the mesh resolves these signals
    errors = []
    for t in (1e-2, 1e-3, 1e-4):
        times = torch.full((2,), t, **D64, device=device)
        gap = (torch.exp(-t * evals) - 1 / (1 + t * evals)).abs().max()
        diff = m_norm(
            M0, spectrum.heat_diffusion(u, times) - tp.implicit_heat_diffusion(L, M0, u, times)
        )
        assert diff <= gap * m_norm(M0, projected) + residual + 1e-12
        errors.append(diff)
    # once the truncation part dominates the difference stops shrinking, at the residual level
    assert errors[-1] <= 1.01 * residual + 1e-12
    # on the band-limited part the gap is exactly sum_i c_i (exp(-t mu_i) - 1/(1 + t mu_i))
    # phi_i, second order in t: ten times smaller t, a hundred times smaller gap
    coeffs = spectrum.project(u)[0]  # (k, 2)
    gaps = []
    for t in (1e-3, 1e-4):
        times = torch.full((2,), t, **D64, device=device)
        factor = (torch.exp(-t * evals) - 1 / (1 + t * evals))[:, None]
        implicit = tp.implicit_heat_diffusion(L, M0, projected, times)
        diff = spectrum.heat_diffusion(projected, times) - implicit
        gaps.append(m_norm(M0, diff))
        assert torch.isclose(gaps[-1], torch.linalg.norm(factor * coeffs), rtol=1e-6)
    assert 80 < gaps[0] / gaps[1] < 101


def test_zero_time_is_the_identity(sphere, device):
    V, _, L, M0, evals, evecs = sphere
    V, L, M0, evals, evecs = (t.to(device) for t in (V, L, M0, evals, evecs))
    spectrum = tnn.Spectrum.from_meshes([(evals, evecs, M0)])
    band_limited = evecs[:, :12] @ torch.randn(
        12, 3, generator=torch.Generator().manual_seed(0), **D64
    ).to(device)
    zero = torch.zeros(3, **D64, device=device)
    assert torch.allclose(spectrum.heat_diffusion(band_limited, zero), band_limited, atol=1e-10)
    x = torch.randn(V.shape[0], 2, generator=torch.Generator().manual_seed(1), **D64).to(device)
    tiny = torch.full((2,), 1e-12, **D64, device=device)
    assert torch.allclose(tp.implicit_heat_diffusion(L, M0, x, tiny), x, atol=1e-8)
    layer = tnn.LearnedDiffusion(2, mode="implicit").double().to(device)
    with torch.no_grad():
        layer.raw_times.fill_(-40.0)  # softplus(-40) ~ 4e-18
    assert torch.allclose(layer(x, L=L, M0=M0), x, atol=1e-12)


@pytest.mark.parametrize("mode", ["spectral", "implicit"])
def test_diffusion_conserves_heat_on_closed_meshes(batch, mode, device):
    """``1^T M0 u(t) = 1^T M0 u0``: L 1 = 0 (implicit: exactly; spectral: phi_0 is constant and
    the other eigenvectors are M0-orthogonal to it)."""
    meshes, spectrum = batch
    spectrum = spectrum.to(device)
    L = tp.sparse.block_diag([m[2] for m in meshes]).to(device)
    M0 = tp.sparse.block_diag([m[3] for m in meshes]).to(device)
    x = torch.rand(spectrum.evecs.shape[0], 3, generator=torch.Generator().manual_seed(2), **D64)
    x = x.to(device)
    layer = tnn.LearnedDiffusion(3, mode=mode, init_times=(0.01, 1.0)).double().to(device)
    out = layer(x, spectrum, L, M0)
    assert out.device.type == device.type
    before = tp.batch.per_mesh_mean(x, spectrum.vert_to_mesh, 3, weights=spectrum.mass)
    after = tp.batch.per_mesh_mean(out, spectrum.vert_to_mesh, 3, weights=spectrum.mass)
    assert torch.allclose(before, after, atol=1e-10)
    assert not torch.allclose(out, x, atol=1e-3)  # it did diffuse


def test_batch_equals_meshes_one_by_one(batch, device):
    meshes, spectrum = batch
    spectrum = spectrum.to(device)
    gen = torch.Generator().manual_seed(3)
    x = torch.randn(spectrum.evecs.shape[0], 4, generator=gen, **D64).to(device)
    pm = PolygonMeshes([m[0].to(device) for m in meshes], [m[1] for m in meshes])
    L, M0 = pm.laplacian()
    spectral = tnn.LearnedDiffusion(4).double().to(device)
    implicit = tnn.LearnedDiffusion(4, mode="implicit").double().to(device)
    cheb = tnn.ChebyshevFilter(4, 5, K=4).double().to(device)
    hks = tnn.SpectralFeatures("hks", 6, normalize=True).to(device)
    wks = tnn.SpectralFeatures("wks", 6).to(device)
    torch.manual_seed(0)
    model = tnn.DiffusionNetLike(4, 3, width=8, num_blocks=2, hks_features=4).double().to(device)
    segmenter = tnn.DiffusionNetLike(4, 2, width=8, num_blocks=1, task="segmentation")
    segmenter = segmenter.double().to(device)
    batched = {
        "spectral": spectral(x, spectrum),
        "implicit": implicit(x, L=L, M0=M0),
        "cheb": cheb(x, L, M0, vert_to_mesh=pm.verts_packed_to_mesh_idx()),
        "hks": hks(spectrum),
        "wks": wks(spectrum),
        "model": model(x, spectrum),
        "segmenter": segmenter(x, spectrum),
    }
    singles = {name: [] for name in batched}
    for b, (V, _, Lb, M0b, evals, evecs) in enumerate(meshes):
        Lb, M0b, evals, evecs = (t.to(device) for t in (Lb, M0b, evals, evecs))
        first, n = int(spectrum.first_idx[b]), V.shape[0]
        xb = x[first : first + n]
        sb = tnn.Spectrum.from_meshes([(evals, evecs, M0b)])
        singles["spectral"].append(spectral(xb, sb))
        singles["implicit"].append(implicit(xb, L=Lb, M0=M0b))
        singles["cheb"].append(cheb(xb, Lb, M0b))
        singles["hks"].append(hks(sb))
        singles["wks"].append(wks(sb))
        singles["model"].append(model(xb, sb))
        singles["segmenter"].append(segmenter(xb, sb))
    assert batched["model"].shape == (3, 3) and batched["segmenter"].shape == (x.shape[0], 2)
    for name, out in batched.items():
        assert torch.allclose(out, torch.cat(singles[name]), atol=1e-12), name
    # the batch's own block-diagonal assembly equals the concatenated blocks
    expected = tp.sparse.block_diag([m[2] for m in meshes]).to_dense()
    assert L.device.type == device.type and torch.allclose(L.to_dense().cpu(), expected)


def test_spectrum_from_polygon_meshes_uses_the_disk_cache(batch, tmp_path, device):
    meshes, spectrum = batch
    spectrum = spectrum.to(device)
    pm = PolygonMeshes([m[0].to(device) for m in meshes], [m[1] for m in meshes])
    first = tnn.Spectrum.from_polygon_meshes(pm, 8, cache_dir=tmp_path)
    assert len(list(tmp_path.glob("eigs-*.npz"))) == 3
    again = tnn.Spectrum.from_polygon_meshes(pm, 8, cache_dir=tmp_path)
    assert again.evecs.device.type == device.type
    assert torch.equal(first.evecs, again.evecs)
    assert torch.allclose(first.evals, spectrum.evals, atol=1e-10)
    assert torch.allclose(first.mass, spectrum.mass)
    assert torch.equal(first.vert_to_mesh, spectrum.vert_to_mesh)


def test_diffusion_gradcheck(device):
    V, F = read_mesh(DATA / "dodecahedron_poly.obj", dtype=torch.float64, device=device)
    L, M0 = tp.laplacian(V, F)
    evals, evecs = tp.eigs(L, M0, 6)
    spectrum = tnn.Spectrum.from_meshes([(evals, evecs, M0)])
    x = torch.randn(20, 2, generator=torch.Generator().manual_seed(4), **D64).to(device)
    x.requires_grad_(True)
    t = torch.tensor([0.05, 0.3], **D64, device=device, requires_grad=True)
    assert torch.autograd.gradcheck(lambda x, t: spectrum.heat_diffusion(x, t), (x, t))
    # fast mode (random directions): every perturbed evaluation costs two sparse factorizations
    assert torch.autograd.gradcheck(
        lambda x, t: tp.implicit_heat_diffusion(L, M0, x, t), (x, t), fast_mode=True
    )
    # the module's parameters (raw times behind a softplus) receive gradients too
    for mode in ("spectral", "implicit"):
        layer = tnn.LearnedDiffusion(2, mode=mode).double().to(device)
        layer(x.detach(), spectrum, L, M0).pow(2).sum().backward()
        assert torch.isfinite(layer.raw_times.grad).all() and (layer.raw_times.grad != 0).all()


def test_implicit_diffusion_differentiates_vertex_positions(device):
    V, F = mixed_mesh()
    V = V.to(device)
    x = torch.stack([V[:, 0], V[:, 1] ** 2], 1)
    times = torch.tensor([0.1, 0.4], **D64, device=device)

    def f(X):
        L, M0 = tp.laplacian(X, F)
        return tp.implicit_heat_diffusion(L, M0, x, times).pow(2).sum()

    assert_directional_derivative(f, V, rtol=1e-5)


def dense_chebyshev(L, M0, K, normalization):
    """``T_k(S_hat) = U cos(k arccos Lambda) U^T`` from a dense eigendecomposition."""
    Ld = L.to_dense()
    m = M0.diagonal()
    S = Ld / torch.sqrt(m[:, None] * m[None, :])
    if normalization == "sym":
        lam_max = (S.abs()).sum(1).max()
    else:
        lam_max = (Ld / m[:, None]).abs().sum(1).max()
    lam, U = torch.linalg.eigh(2 * S / lam_max - torch.eye(len(m), **D64, device=m.device))
    assert lam.min() >= -1 - 1e-12 and lam.max() <= 1 + 1e-12  # Gershgorin: spectrum in [-1, 1]
    polys = [
        U @ torch.diag(torch.cos(k * torch.arccos(lam.clamp(-1, 1)))) @ U.t() for k in range(K)
    ]
    if normalization == "rw":  # M0^{-1} L = M0^{-1/2} S M0^{1/2}
        polys = [p / m.sqrt()[:, None] * m.sqrt()[None, :] for p in polys]
    return polys


@pytest.mark.parametrize("normalization", ["sym", "rw"])
def test_chebyshev_filter_is_the_dense_polynomial(normalization, device):
    V, F = quad_grid(4, bump=0.3, seed=5)
    L, M0 = tp.laplacian(V.to(device), F)
    K = 5
    layer = tnn.ChebyshevFilter(3, 2, K=K, normalization=normalization).double().to(device)
    x = torch.randn(V.shape[0], 3, generator=torch.Generator().manual_seed(6), **D64).to(device)
    polys = dense_chebyshev(L, M0, K, normalization)
    expected = sum(p @ x @ layer.weight[k] for k, p in enumerate(polys)) + layer.bias
    assert torch.allclose(layer(x, L, M0), expected, atol=1e-10)


def test_chebyshev_gradcheck(device):
    V, F = mixed_mesh()
    x = torch.randn(V.shape[0], 2, generator=torch.Generator().manual_seed(7), **D64)
    w = torch.randn(3, 2, 2, generator=torch.Generator().manual_seed(8), **D64)
    x, w = x.to(device).requires_grad_(True), w.to(device).requires_grad_(True)
    Vg = V.to(device, copy=True).requires_grad_(True)

    def f(x, w, X):
        L, M0 = tp.laplacian(X, F)
        return tnn.chebyshev_filter(x, tnn.chebyshev_operator(L, M0), w)

    assert torch.autograd.gradcheck(f, (x, w, Vg), fast_mode=True)


def test_spectral_features_equal_the_functionals(batch, device):
    meshes, spectrum = batch
    spectrum = spectrum.to(device)
    times = torch.tensor([0.01, 0.1, 1.0], **D64, device=device)
    fixed = tnn.SpectralFeatures("hks", times=times).double().to(device)
    learnable = tnn.SpectralFeatures("hks", 5, learnable=True).double().to(device)
    wks = tnn.SpectralFeatures("wks", 7).double().to(device)
    out_fixed, out_learn, out_wks = fixed(spectrum), learnable(spectrum), wks(spectrum)
    refs = {"fixed": [], "learn": [], "wks": []}
    for _, _, _, _, evals, evecs in meshes:
        evals, evecs = evals.to(device), evecs.to(device)
        refs["fixed"].append(tp.heat_kernel_signature(evals, evecs, times))
        # Sun et al.: log-spaced over [4 ln 10 / mu_max, 4 ln 10 / mu_min], mu_min > 0
        mu = evals[1:]
        t_paper = torch.logspace(
            math.log10(4 * math.log(10) / mu.max()),
            math.log10(4 * math.log(10) / mu.min()),
            5,
            **D64,
            device=device,
        )
        refs["learn"].append(tp.heat_kernel_signature(evals, evecs, t_paper))
        energies = torch.linspace(
            float(mu.min().log()), float(mu.max().log()), 7, **D64, device=device
        )
        refs["wks"].append(tp.wave_kernel_signature(evals, evecs, energies))
    assert torch.allclose(out_fixed, torch.cat(refs["fixed"]), atol=1e-12)
    assert torch.allclose(out_learn, torch.cat(refs["learn"]), atol=1e-12)
    assert torch.allclose(out_wks, torch.cat(refs["wks"]), atol=1e-12)
    out_learn.sum().backward()
    assert learnable.samples.grad.abs().min() > 0
    with pytest.raises(ValueError, match="positive"):
        tnn.SpectralFeatures("hks", times=torch.tensor([0.1, -1.0]))


def test_classifier_pools_with_mass_weights(batch, device):
    """Mean pooling is M0-weighted: a per-vertex constant field pools to itself, and a model
    with a zero-width path (all blocks zeroed) gives head(lift(mean input))."""
    meshes, spectrum = batch
    spectrum = spectrum.to(device)
    x = torch.randn(spectrum.evecs.shape[0], 2, generator=torch.Generator().manual_seed(9), **D64)
    x = x.to(device)
    model = tnn.DiffusionNetLike(2, 4, width=6, num_blocks=1, hks_features=0).double().to(device)
    with torch.no_grad():
        for p in model.blocks.parameters():
            p.zero_()
    logits = model(x, spectrum)
    mean = tp.batch.per_mesh_mean(x, spectrum.vert_to_mesh, 3, weights=spectrum.mass)
    expected = model.head(model.lift(mean))
    assert logits.shape == (3, 4) and torch.allclose(logits, expected, atol=1e-12)
    for b in range(3):
        sel = spectrum.vert_to_mesh == b
        manual = (spectrum.mass[sel, None] * x[sel]).sum(0) / spectrum.mass[sel].sum()
        assert torch.allclose(mean[b], manual)


def test_bad_arguments_are_named(device):
    with pytest.raises(ValueError, match="mode must be"):
        tnn.LearnedDiffusion(3, mode="explicit")
    layer = tnn.LearnedDiffusion(3, mode="implicit").to(device)
    with pytest.raises(ValueError, match="needs the .*L and M0"):
        layer(torch.zeros(5, 3, device=device))
    with pytest.raises(ValueError, match=r"shape \(sumV, 3\)"):
        layer(torch.zeros(5, 2, device=device))
    V, F = quad_grid(2, device=device)
    L, M0 = tp.laplacian(V, F)
    with pytest.raises(ValueError, match="normalization"):
        tnn.chebyshev_operator(L, M0, "lap")
    with pytest.raises(ValueError, match="diagonal"):
        evals, evecs = torch.zeros(2, device=device), torch.zeros(9, 2, device=device)
        tnn.Spectrum.from_meshes([(evals, evecs, L)])
    with pytest.raises(ValueError, match="same number of eigenpairs"):
        e, v = tp.eigs(L, M0, 3)
        tnn.Spectrum.from_meshes([(e, v, M0), (e[:2], v[:, :2], M0)])

"""Spectral shape features and heat diffusion on polygon meshes.

All functions take the eigenpairs of ``L phi = mu M0 phi`` (from :func:`torch_polylap.eigs`,
``M0``-orthonormal) or the operators themselves, work on batches of channels, and follow the
dtype and device of their inputs.

* heat kernel signature (Sun, Ovsjanikov & Guibas 2009):
  ``HKS(x, t) = sum_i exp(-mu_i t) phi_i(x)^2``
* wave kernel signature (Aubry, Schlickewei & Cremers 2011):
  ``WKS(x, e) = sum_i phi_i(x)^2 w_i(e) / sum_i w_i(e)``,
  ``w_i(e) = exp(-(e - log mu_i)^2 / 2 s^2)``
* heat diffusion ``u(t) = exp(-t M0^{-1} L) u0``, spectrally (truncated eigenbasis) or by one
  implicit Euler step ``(M0 + t L) u = M0 u0``.
* :func:`cached_eigs`: eigenpairs stored on disk, keyed by the mesh, for datasets.
"""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np
import torch

from .linalg import eigs, solve
from .operators import MeshFaces, get_topology, laplacian
from .sparse import csr_parts, csr_tensor, spmm

__all__ = [
    "heat_kernel_signature",
    "wave_kernel_signature",
    "spectral_heat_diffusion",
    "implicit_heat_diffusion",
    "cached_eigs",
]


def heat_kernel_signature(
    evals: torch.Tensor, evecs: torch.Tensor, times: torch.Tensor
) -> torch.Tensor:
    """``(V, T)`` heat kernel signature ``sum_i exp(-mu_i t) phi_i(x)^2`` at each time.

    Args:
        evals: ``(k,)`` eigenvalues; evecs: ``(V, k)`` ``M0``-orthonormal eigenvectors.
        times: ``(T,)`` diffusion times (may require grad, e.g. learnable times).
    """
    decay = torch.exp(-evals[:, None] * times[None, :])  # (k, T)
    return (evecs * evecs) @ decay


def wave_kernel_signature(
    evals: torch.Tensor,
    evecs: torch.Tensor,
    energies: torch.Tensor,
    sigma: float | torch.Tensor | None = None,
) -> torch.Tensor:
    """``(V, E)`` wave kernel signature at log-energies ``energies``.

    Zero eigenvalues (the constants of each component) are skipped, as ``log 0`` is undefined.
    With ``sigma=None`` the bandwidth is 7 times the spacing of ``energies`` (Aubry et al.).
    Each column is normalized so that ``sum_x m_x WKS(x, e) = 1`` for ``M0``-orthonormal
    eigenvectors.
    """
    keep = evals > 1e-12 * evals.abs().max().clamp_min(torch.finfo(evals.dtype).tiny)
    log_mu = torch.log(evals[keep])
    if sigma is None:
        if energies.numel() < 2:
            raise ValueError("wave_kernel_signature: pass sigma when using a single energy.")
        sigma = 7.0 * (energies[1] - energies[0]).abs()
    weights = torch.exp(-((energies[None, :] - log_mu[:, None]) ** 2) / (2 * sigma**2))  # (k, E)
    weights = weights / weights.sum(0, keepdim=True).clamp_min(torch.finfo(evals.dtype).tiny)
    phi = evecs[:, keep]
    return (phi * phi) @ weights


def spectral_heat_diffusion(
    u0: torch.Tensor,
    evals: torch.Tensor,
    evecs: torch.Tensor,
    M0: torch.Tensor,
    times: float | torch.Tensor,
) -> torch.Tensor:
    """Heat diffusion ``Phi exp(-mu t) Phi^T M0 u0`` in the truncated eigenbasis.

    Args:
        u0: ``(V,)`` or ``(V, C)`` signals.
        times: a scalar, or ``(C,)`` one time per channel (differentiable, e.g. learned).

    Returns:
        ``u0``'s shape.
    """
    vec = u0.dim() == 1
    U = u0[:, None] if vec else u0
    coeffs = evecs.t() @ spmm(M0, U)  # (k, C)
    t = torch.as_tensor(times, dtype=U.dtype, device=U.device)
    decay = torch.exp(-evals[:, None] * (t[None, :] if t.dim() else t))
    out = evecs @ (decay * coeffs)
    return out[:, 0] if vec else out


def implicit_heat_diffusion(
    L: torch.Tensor, M0: torch.Tensor, u0: torch.Tensor, time: float | torch.Tensor
) -> torch.Tensor:
    """One implicit Euler step of the heat equation: ``(M0 + t L) u = M0 u0``.

    Differentiable in ``L``'s and ``M0``'s values, ``u0`` and ``time`` (one time for all
    channels; call once per time for several). ``M0 + t L`` is formed on ``L``'s pattern, so
    ``L`` must store its diagonal (as :func:`torch_polylap.laplacian`'s does) and ``M0`` be
    diagonal.
    """
    crow, col, l_values = csr_parts(L)
    m = csr_parts(M0)[2]
    n = L.shape[0]
    row = torch.repeat_interleave(torch.arange(n, device=crow.device), crow.diff())
    on_diag = row == col
    diag_mass = torch.zeros_like(l_values).masked_scatter(on_diag, m)
    A = csr_tensor(crow, col, diag_mass + time * l_values, (n, n))
    A._polylap_symmetric = True
    return solve(A, spmm(M0, u0))


def _mesh_key(verts: torch.Tensor, faces: MeshFaces, k: int, lam: float) -> str:
    topo = get_topology(faces, verts.shape[0])
    digest = hashlib.sha256()
    digest.update(verts.detach().cpu().to(torch.float64).numpy().tobytes())
    digest.update(topo.faces.indices.numpy().tobytes())
    digest.update(topo.faces.sizes.numpy().tobytes())
    digest.update(f"k={k};lam={lam!r}".encode())
    return digest.hexdigest()[:32]


def cached_eigs(
    verts: torch.Tensor,
    faces: MeshFaces,
    k: int,
    cache_dir: str | Path,
    *,
    lam: float = 1.0,
) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`eigs` of the mesh's ``(L, M0)``, stored in ``cache_dir`` and reused across runs.

    The key hashes the vertex positions, the faces, ``k`` and ``lam``: any change recomputes.
    Returned tensors have ``verts``' dtype and device and carry no gradient (precomputation for
    datasets; use :func:`eigs` directly for differentiable eigenvalues).
    """
    path = Path(cache_dir) / f"eigs-{_mesh_key(verts, faces, k, lam)}.npz"
    if path.exists():
        data = np.load(path)
        evals, evecs = torch.from_numpy(data["evals"]), torch.from_numpy(data["evecs"])
    else:
        with torch.no_grad():
            L, M0 = laplacian(verts.detach(), faces, lam)
            evals, evecs = eigs(L, M0, k)
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(".tmp.npz")
        np.savez(tmp, evals=evals.cpu().numpy(), evecs=evecs.cpu().numpy())
        tmp.replace(path)  # atomic: concurrent workers never read a half-written file
    return evals.to(verts), evecs.to(verts)

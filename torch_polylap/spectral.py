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

import errno
import hashlib
import os
import warnings
import zipfile
import zlib
from pathlib import Path

import numpy as np
import torch

from ._typing import MeshFaces
from .atomic import atomic_write
from .kernels import LAM_FREE_METHODS, check_method
from .linalg import eigs, solve
from .operators import laplacian
from .topology import get_topology

__all__ = [
    "heat_kernel_signature",
    "wave_kernel_signature",
    "spectral_heat_diffusion",
    "implicit_heat_diffusion",
    "cached_eigs",
    "CacheWriteWarning",
]


def heat_kernel_signature(
    evals: torch.Tensor, evecs: torch.Tensor, times: torch.Tensor
) -> torch.Tensor:
    """``(V, T)`` heat kernel signature ``sum_i exp(-mu_i t) phi_i(x)^2`` at each time.

    Args:
        evals: ``(k,)`` eigenvalues.
        evecs: ``(V, k)`` ``M0``-orthonormal eigenvectors.
        times: ``(T,)`` diffusion times (may require grad, e.g. learnable times).

    Examples:
        >>> import torch
        >>> import torch_polylap as tp
        >>> verts, faces = tp.shapes.quad_sphere(2)  # a closed quad mesh, 26 vertices
        >>> L, M0 = tp.laplacian(verts, faces)
        >>> evals, evecs = tp.eigs(L, M0, k=4)
        >>> times = torch.tensor([0.1, 1.0, 10.0], dtype=torch.float64)
        >>> tp.heat_kernel_signature(evals, evecs, times).shape
        torch.Size([26, 3])
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
    coeffs = evecs.t() @ (M0 @ U)  # (k, C)
    t = torch.as_tensor(times, dtype=U.dtype, device=U.device)
    decay = torch.exp(-evals[:, None] * (t[None, :] if t.dim() else t))
    out = evecs @ (decay * coeffs)
    return out[:, 0] if vec else out


def implicit_heat_diffusion(
    L: torch.Tensor, M0: torch.Tensor, u0: torch.Tensor, times: float | torch.Tensor
) -> torch.Tensor:
    """One implicit Euler step of the heat equation: ``(M0 + t L) u = M0 u0``.

    Args:
        L: ``(V, V)`` Laplacian (block-diagonal for a packed batch).
        M0: ``(V, V)`` mass matrix, of the same mesh or batch.
        u0: ``(V,)`` or ``(V, C)`` signals.
        times: a scalar (one time for all channels: one factorization), or ``(C,)`` one time
            per channel (one factorization per channel).

    Returns:
        ``u0``'s shape. Differentiable in ``L``'s and ``M0``'s values, ``u0`` and the times, at
        O(nnz) memory.
    """
    t = torch.as_tensor(times)
    if t.dim() == 0:
        return solve(M0 + times * L, M0 @ u0)
    if u0.dim() != 2 or t.shape != (u0.shape[1],):
        raise ValueError(
            f"per-channel times must have shape (C,) for u0 of shape (V, C); got times "
            f"{tuple(t.shape)} and u0 {tuple(u0.shape)}."
        )
    tt = times if isinstance(times, torch.Tensor) else t
    columns = [solve(M0 + tt[c] * L, M0 @ u0[:, c]) for c in range(u0.shape[1])]
    return torch.stack(columns, 1)


# The layout of the entries (members, their meaning, the checksum): part of every key, so a
# new layout misses the entries of an older one instead of misreading them.
CACHE_FORMAT = 2


def eigs_cache_key(
    verts: torch.Tensor, faces: MeshFaces, k: int, lam: float, method: str = "aw11"
) -> str:
    """Content address of the eigenpairs: a hash of everything they depend on, the positions,
    faces, their dtype, ``k``, ``method`` and ``lam`` (except for ``"plms"`` and
    ``"diamond"``, which do not use it, so every ``lam`` shares one entry), and the entries'
    format version (``CACHE_FORMAT``)."""
    topo = get_topology(faces, verts.shape[0])
    digest = hashlib.sha256()
    digest.update(verts.detach().cpu().to(torch.float64).numpy().tobytes())
    digest.update(topo.faces.indices.numpy().tobytes())
    digest.update(topo.faces.sizes.numpy().tobytes())
    lam_used = None if method in LAM_FREE_METHODS else lam
    fields = f"format={CACHE_FORMAT};dtype={str(verts.dtype).removeprefix('torch.')}"
    digest.update(f"{fields};k={k};lam={lam_used!r};method={method}".encode())
    return digest.hexdigest()[:32]


def eigs_cache_path(
    cache: Path, verts: torch.Tensor, faces: MeshFaces, k: int, lam: float, method: str
) -> Path:
    """The cache entry of these eigenpairs: ``cache / "eigs-<key>.npz"``
    (:func:`eigs_cache_key`)."""
    return cache / f"eigs-{eigs_cache_key(verts, faces, k, lam, method)}.npz"


def cached_eigs(
    verts: torch.Tensor,
    faces: MeshFaces,
    k: int,
    cache_dir: str | Path,
    *,
    lam: float = 1.0,
    method: str = "aw11",
) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`eigs` of the mesh's ``(L, M0)``, stored in ``cache_dir`` and reused across runs.

    ``(L, M0) = laplacian(verts, faces, lam, method=method)`` (``"aw11"``, ``"plms"`` or
    ``"degoes"``). The key hashes the vertex positions, the faces, ``k``, ``method`` and ``lam``
    (not for ``"plms"``, which ignores it): any change recomputes.
    Returned tensors have ``verts``' dtype and device and carry no gradient (precomputation for
    datasets; use :func:`eigs` directly for differentiable eigenvalues).

    A cache file that cannot be used (truncated, corrupted, altered so that its ``sha256`` no
    longer matches, or holding arrays of the wrong shape for ``k`` and this mesh) counts as a
    miss: the eigenpairs are recomputed, the file replaced,
    and one warning names it.  Files are written to a unique temporary and moved into place
    (:func:`~torch_polylap.atomic.atomic_write`), so concurrent processes computing the same
    key never see or leave half a file.

    A cache that cannot be written (no permission, a read-only file system, a full disk, a path
    through a regular file or a symbolic link loop: any :class:`OSError`) never loses the
    computed eigenpairs: they are returned, and one :class:`CacheWriteWarning` per folder and
    process names the folder and the reason (every call then recomputes).

    Raises:
        ValueError: ``cache_dir`` exists but is not a directory (checked before any work).
    """
    check_method(method)
    cache = Path(cache_dir)
    check_cache_dir(cache)
    return eigs_through_cache(verts, faces, k, cache, lam, method)


def eigs_through_cache(
    verts: torch.Tensor,
    faces: MeshFaces,
    k: int,
    cache: Path,
    lam: float,
    method: str,
    operators: tuple[torch.Tensor, torch.Tensor] | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`cached_eigs` for callers that have checked ``method`` and ``cache`` (the one
    place that reads and writes the eigenpair cache); ``operators``: the mesh's ``(L, M0)``
    when the caller has built them already, used on a miss instead of building them again."""
    path = eigs_cache_path(cache, verts, faces, k, lam, method)
    # is_file: False also where the path cannot be reached (a symbolic link loop, say)
    cached = load_cached_eigs(path, k, verts.shape[0]) if path.is_file() else None
    if cached is None:
        with torch.no_grad():
            if operators is None:
                operators = laplacian(verts.detach(), faces, lam, method=method)
            evals, evecs = eigs(*operators, k)
        _store_eigs(path, evals.cpu().numpy(), evecs.cpu().numpy())
    else:
        evals, evecs = (torch.from_numpy(a) for a in cached)
    return evals.to(verts), evecs.to(verts)


class CacheWriteWarning(UserWarning):
    """An on-disk cache could not be written; the computed result was returned all the same.

    Issued once per cache folder and process (:func:`cached_eigs`)."""


# cache folders already reported as unwritable in this process: one warning each
_UNWRITABLE_REPORTED: set[str] = set()


def _store_eigs(path: Path, evals: np.ndarray, evecs: np.ndarray) -> None:
    """Write the cache file; on an :class:`OSError` warn (once per folder) instead of raising,
    so that the caller still gets the eigenpairs it computed."""
    folder = path.parent
    try:
        folder.mkdir(parents=True, exist_ok=True)
        digest = eigs_checksum(evals, evecs)
        atomic_write(path, lambda f: np.savez(f, evals=evals, evecs=evecs, sha256=digest))
    except OSError as err:
        key = os.path.abspath(folder)
        if key in _UNWRITABLE_REPORTED:
            return
        _UNWRITABLE_REPORTED.add(key)
        warnings.warn(
            f"eigenpair cache folder {folder} cannot be written ({_write_failure(folder, err)}); "
            "the eigenpairs were computed and are returned, but not stored, so every call "
            "recomputes them. Pass a writable cache_dir. (Reported once per folder.)",
            CacheWriteWarning,
            stacklevel=3,
        )


def _write_failure(folder: Path, err: OSError) -> str:
    """The reason a cache write failed, in words. ``mkdir`` reports a symbolic link loop or a
    dangling link as "File exists": ask ``stat`` for the real reason then."""
    if isinstance(err, FileExistsError):
        try:
            os.stat(folder)
        except OSError as real:
            err = real
        else:
            return f"{folder} exists and is not a folder"
    reason = err.strerror or str(err) or type(err).__name__
    code = errno.errorcode.get(err.errno, "") if err.errno is not None else ""
    where = f" at {err.filename}" if err.filename is not None else ""
    return f"{type(err).__name__}{f' {code}' if code else ''}: {reason}{where}"


def check_cache_dir(cache_dir: Path) -> None:
    """Reject a cache folder path that names an existing file (or other non-folder)."""
    if cache_dir.exists() and not cache_dir.is_dir():
        raise ValueError(
            f"cache_dir {cache_dir} exists but is not a directory; pass a folder path (it is "
            "created if missing)."
        )


# TypeError: a bare .npy (np.load returns an array, not an archive); the others: truncated or
# corrupted archives and members
_UNREADABLE = (OSError, ValueError, KeyError, EOFError, TypeError, zipfile.BadZipFile, zlib.error)


def eigs_checksum(evals: np.ndarray, evecs: np.ndarray) -> np.ndarray:
    """``(32,)`` uint8: SHA-256 of ``evals`` then ``evecs`` as little-endian float64, C order.

    Stored as the ``sha256`` member of every cache entry this version writes; a reader
    recomputes it, so flipped bits that still parse as arrays are caught (the zip CRC of an
    ``.npz`` member is not checked on every read path)."""
    digest = hashlib.sha256()
    for array in (evals, evecs):
        digest.update(np.ascontiguousarray(array, dtype="<f8").tobytes())
    return np.frombuffer(digest.digest(), dtype=np.uint8).copy()


def load_cached_eigs(path: Path, k: int, num_verts: int) -> tuple[np.ndarray, np.ndarray] | None:
    """``(evals (k,), evecs (V, k))`` from a cache file, or None (with a warning naming the
    file) when it is unreadable, does not hold eigenpairs of this shape, or its ``sha256``
    member is missing or does not match them."""
    try:
        # our own handle: np.load leaks the one it opens when the archive is unreadable
        with open(path, "rb") as f, np.load(f, allow_pickle=False) as data:
            evals, evecs = data["evals"], data["evecs"]
            stored = data["sha256"] if "sha256" in data.files else None
        problem = None
        if stored is None:
            problem = "it has no sha256 member (another format, or not written by this package)"
        elif evals.shape != (k,) or evecs.shape != (num_verts, k):
            problem = (
                f"it holds evals {evals.shape} and evecs {evecs.shape}, expected ({k},) and "
                f"({num_verts}, {k})"
            )
        elif evals.dtype.kind != "f" or evecs.dtype.kind != "f":
            problem = f"it holds {evals.dtype} and {evecs.dtype} arrays, not floating point"
        elif not (np.isfinite(evals).all() and np.isfinite(evecs).all()):
            problem = "it holds non-finite values"
        elif not np.array_equal(stored, eigs_checksum(evals, evecs)):
            problem = "its sha256 member does not match its arrays (the file was altered)"
    except _UNREADABLE as e:
        problem = f"it cannot be read ({type(e).__name__}: {e})"
    if problem is None:
        return evals, evecs
    warnings.warn(
        f"eigenpair cache file {path}: {problem}; recomputing and replacing it.",
        UserWarning,
        stacklevel=3,
    )
    return None

"""Block Lanczos for the largest eigenpairs of a symmetric operator given as a block product.

:func:`torch_polylap.eigs` runs it on the shift-inverted operator ``(A - sigma I)^{-1}``, whose
largest eigenvalues belong to the smallest eigenvalues of ``A``. ARPACK (scipy's ``eigsh``)
does the same with one vector at a time: each Lanczos step reorthogonalizes against every
earlier vector with a matrix-vector product (BLAS-2, memory bound), which is where most of its
time goes for ``k`` in the hundreds, and each step is one triangular solve. Working on blocks of
``b`` vectors turns both into matrix-matrix work (BLAS-3 products; one multi-column solve per
block).

The method is unrestarted: the basis grows until every wanted Ritz pair has converged
(a few times ``k`` vectors on Laplacian spectra; ``benchmarks/README.md`` records the sizes
measured), so it stores
``n x dim`` floats; the caller bounds ``dim``.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

__all__ = ["block_lanczos"]


def block_lanczos(
    apply: Callable[[np.ndarray], np.ndarray],
    n: int,
    k: int,
    *,
    block: int = 8,
    tol: float = 1e-10,
    max_dim: int,
    seed: int = 0,
) -> tuple[np.ndarray, np.ndarray, bool]:
    """The ``k`` largest eigenpairs of a symmetric ``(n, n)`` operator.

    Block Lanczos with full reorthogonalization (classical Gram-Schmidt applied twice, which
    keeps the basis orthonormal to round-off) and Rayleigh-Ritz on the block tridiagonal
    matrix ``T = Q^T C Q`` (Golub & Van Loan, *Matrix Computations*, sec. 10.3.6). The
    residual of a Ritz pair ``(theta, Q s)`` is ``|R s_last|``, ``R`` being the last block's
    QR factor and ``s_last`` the last ``block`` rows of ``s``, so convergence is checked
    without touching the ``n``-long vectors.

    Args:
        apply: ``Y (n, b) -> C Y (n, b)`` for a symmetric ``C``.
        n: size of ``C``.
        k: number of eigenpairs, ``k + block <= max_dim <= n``.
        block: block size ``b``. Blocks of 8 needed fewer vectors than 16 or 32 on Laplacian
            spectra. A block Krylov space holds at most ``b`` directions of one eigenspace in
            exact arithmetic: directions of an eigenvalue repeated more than ``b`` times come
            in only through round-off, and some may be missing when every wanted Ritz pair has
            converged (32 of 40 on 40 disjoint copies of a mesh). :func:`torch_polylap.eigs`
            checks for that by an inertia count.
        tol: a Ritz pair has converged when ``|C y - theta y| <= tol |theta|``.
        max_dim: the largest basis to build before giving up.
        seed: seed of the random starting block (results are deterministic).

    Returns:
        ``theta (k,)`` descending, ``Y (n, k)`` orthonormal Ritz vectors, and whether all ``k``
        pairs met ``tol``.
    """
    rng = np.random.default_rng(seed)
    # Fortran order: the basis Q[:, :m] is one contiguous block for the products below
    Q = np.empty((n, max_dim + block), order="F")
    Q[:, :block] = np.linalg.qr(rng.standard_normal((n, block)))[0]
    T = np.zeros((max_dim + block, max_dim + block))
    R_prev = np.zeros((block, block))
    m = 0
    while True:
        current = Q[:, m : m + block]
        W = apply(current)
        # the block three-term recurrence removes what the basis holds in exact arithmetic ...
        A = current.T @ W
        W -= current @ A
        T[m : m + block, m : m + block] = A
        if m:
            W -= Q[:, m - block : m] @ R_prev.T
            T[m - block : m, m : m + block] = R_prev.T
        # ... and one pass of full reorthogonalization the round-off; a second pass runs only
        # where the first removed a large part of a column (Kahan's "twice is enough" test)
        basis = Q[:, : m + block]
        for _ in range(2):
            before = np.linalg.norm(W, axis=0)
            H = basis.T @ W
            W -= basis @ H
            T[: m + block, m : m + block] += H
            if (np.linalg.norm(W, axis=0) >= 0.7 * before).all():
                break
        Qn, R = np.linalg.qr(W)
        # A (numerically) rank-deficient block means an invariant subspace was found; random
        # directions, orthogonalized, keep the basis growing without changing the spectrum
        # already captured (their coupling block R is then zero).
        if (np.abs(np.diag(R)) <= 1e-12 * max(np.abs(A).max(), 1e-300)).any():
            fresh = rng.standard_normal((n, block))
            fresh -= basis @ (basis.T @ fresh)
            fresh -= basis @ (basis.T @ fresh)
            Qn = np.linalg.qr(fresh)[0]
            R = np.zeros_like(R)
        T[m + block : m + 2 * block, m : m + block] = R
        R_prev = R
        m += block
        # Ritz values are only worth computing once the basis can hold the wanted ones; the
        # last block that fits max_dim (which need not be a multiple of block) is the last one
        if (m >= 2 * k + block and (m // block) % 2 == 0) or m + block > max_dim:
            Tm = T[:m, :m]
            theta, S = np.linalg.eigh(0.5 * (Tm + Tm.T))
            theta, S = theta[::-1][:k], S[:, ::-1][:, :k]
            residual = np.linalg.norm(R @ S[m - block : m], axis=0)
            converged = bool((residual <= tol * np.abs(theta)).all())
            if converged or m + block > max_dim:
                return theta, Q[:, :m] @ S, converged
        Q[:, m : m + block] = Qn

"""Shape-Up quad planarization (Bouaziz, Deuss, Schwartzburg, Weise & Pauly 2012), vectorized.

The benchmark's second peer beside libigl's ``igl.planarize_quad_mesh``: the same local and
global steps, without libigl's per-face loop, and for polygons of any degree (libigl's takes
quads only; a mixed mesh is passed as one corner array per degree). Each iteration

* **local step**: every face's corners, centered at their mean, are projected onto the plane
  through that mean spanned by the two largest principal directions of the corners (the
  eigenvectors of the ``3 x 3`` scatter matrix; the smallest one is the plane normal);
* **global step**: the positions minimizing ``sum_f |N (S_f x) - p_f|^2``, with ``S_f`` the
  selection of face ``f``'s corners, ``N = I - 11^T / k`` the centering and ``p_f`` the projected
  corners. The normal equations ``K x = sum_f S_f^T p_f`` with ``K = sum_f S_f^T N S_f`` (one
  scalar matrix for the three coordinates) are factored once, before the first iteration.

``K`` is singular: every connected part can translate freely (libigl factors it anyway and its
output then carries an arbitrary translation per part, of which it removes only the global
mean). Here one vertex per part is held, which makes ``K`` positive definite, and every part is
translated back so that its mean stays that of the input; on a connected mesh that is libigl's
result, which ``bench_planarize.py`` checks.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
import torch
from scipy.sparse.csgraph import connected_components

import torch_polylap as tp


@dataclass
class ShapeUpTrace:
    """Positions after the run, and per iteration: seconds since the start (factorization
    included) and the largest :func:`torch_polylap.face_nonplanarity`."""

    verts: np.ndarray
    seconds: list[float] = field(default_factory=list)
    nonplanarity: list[float] = field(default_factory=list)
    setup_seconds: float = 0.0

    @property
    def iterations(self) -> int:
        return len(self.seconds)


class ShapeUp:
    """Vectorized Shape-Up on a mesh of ``k``-gons (``F`` of shape ``(F, k)``), or of mixed
    degrees (a list of such arrays, one per degree)."""

    def __init__(self, V: np.ndarray, F: np.ndarray | list[np.ndarray]) -> None:
        from cholespy import CholeskySolverD, MatrixType

        start = time.perf_counter()
        self.V0 = np.ascontiguousarray(V, dtype=np.float64)
        groups = [F] if isinstance(F, np.ndarray) else F
        self.groups = [np.ascontiguousarray(g, dtype=np.int64) for g in groups]
        self.F = self.groups[0]  # the faces, on a mesh of one degree
        n = self.V0.shape[0]
        K = sp.csr_matrix((n, n))
        for g in self.groups:
            nf, k = g.shape
            center = np.eye(k) - 1.0 / k
            rows = np.repeat(g, k, axis=1).reshape(-1)
            cols = np.tile(g, (1, k)).reshape(-1)
            K = K + sp.csr_matrix((np.tile(center.reshape(-1), nf), (rows, cols)), shape=(n, n))
        # one held vertex per connected part (and every vertex outside all faces)
        used = np.zeros(n, dtype=bool)
        for g in self.groups:
            used[g.reshape(-1)] = True
        _, part = connected_components(K, directed=False)
        part[~used] = part.max() + 1 + np.arange(int((~used).sum()))
        self.part = part
        _, first = np.unique(part, return_index=True)
        held = np.zeros(n, dtype=bool)
        held[first] = True
        held |= ~used
        self.free = np.flatnonzero(~held)
        Kf = K[self.free][:, self.free].tocoo()
        self.solver = CholeskySolverD(
            self.free.size,
            torch.from_numpy(Kf.row.astype(np.int32)),
            torch.from_numpy(Kf.col.astype(np.int32)),
            torch.from_numpy(Kf.data.astype(np.float64)),
            MatrixType.COO,
        )
        self.K_free_held = K[self.free][:, np.flatnonzero(held)].tocsr()
        self.held = np.flatnonzero(held)
        counts = np.bincount(part)
        self.part_mean0 = np.stack(
            [np.bincount(part, self.V0[:, c]) / counts for c in range(3)], axis=1
        )
        self.counts = counts
        self.setup_seconds = time.perf_counter() - start

    def project(self, X: np.ndarray) -> list[np.ndarray]:
        """Local step: per degree, ``(F, k, 3)`` centered corners projected onto their best-fit
        planes."""
        out = []
        for g in self.groups:
            corners = X[g]
            centered = corners - corners.mean(axis=1, keepdims=True)
            scatter = np.einsum("fki,fkj->fij", centered, centered)
            _, vecs = np.linalg.eigh(scatter)
            normal = vecs[:, :, 0]
            out.append(centered - (centered @ normal[:, :, None]) * normal[:, None, :])
        return out

    def global_step(self, projected: list[np.ndarray], X: np.ndarray) -> np.ndarray:
        """Global step: the least-squares positions for the projected corners, every part
        translated back to its input mean."""
        n = X.shape[0]
        index = np.concatenate([g.reshape(-1) for g in self.groups])
        corners = np.concatenate([p.reshape(-1, 3) for p in projected])
        rhs = np.stack([np.bincount(index, corners[:, c], minlength=n) for c in range(3)], 1)
        b = rhs[self.free] - self.K_free_held @ X[self.held]
        rhs_free = torch.from_numpy(np.ascontiguousarray(b))
        out = torch.empty_like(rhs_free)
        self.solver.solve(rhs_free, out)
        Y = X.copy()
        Y[self.free] = out.numpy()
        mean = (
            np.stack(
                [np.bincount(self.part, Y[:, c], minlength=self.counts.size) for c in range(3)],
                axis=1,
            )
            / self.counts[:, None]
        )
        return Y + (self.part_mean0 - mean)[self.part]

    def run(
        self,
        max_iter: int,
        tol: float = 0.0,
        time_limit: float | None = None,
        faces: object = None,
    ) -> ShapeUpTrace:
        """Iterate until ``max_iter`` iterations, the largest non-planarity below ``tol`` or
        ``time_limit`` seconds have passed. The non-planarity is measured after every iteration,
        as libigl does, but its time is not counted: ``seconds`` holds the setup and the
        iterations only, in Shape-Up's favour. ``faces``: the mesh's faces for
        :func:`torch_polylap.face_nonplanarity` (default: the one degree's array)."""
        F = torch.from_numpy(self.F) if faces is None else faces
        X = self.V0.copy()
        trace = ShapeUpTrace(verts=X, setup_seconds=self.setup_seconds)
        elapsed = self.setup_seconds
        for _ in range(max_iter):
            start = time.perf_counter()
            X = self.global_step(self.project(X), X)
            elapsed += time.perf_counter() - start
            worst = float(tp.face_nonplanarity(torch.from_numpy(X), F).max())
            trace.seconds.append(elapsed)
            trace.nonplanarity.append(worst)
            if worst < tol or (time_limit is not None and elapsed >= time_limit):
                break
        trace.verts = X
        return trace

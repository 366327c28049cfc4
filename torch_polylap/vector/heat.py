"""The vector heat method (Sharp, Soliman and Crane 2019) on polygon meshes.

Parallel transport (their Algorithm 1).  Diffusing a vector ``Y_0`` given at the sources for a
short time with the connection Laplacian ``A`` (:mod:`torch_polylap.vector.connection`),

    (M + t A) Y = M Y_0,                                                          (1)

gives a field whose *direction* at every vertex approaches the parallel transport of ``Y_0``
along the shortest geodesic from the nearest source as ``t -> 0`` (SSC19, sec. 4: the
short-time asymptotics of the connection heat kernel). The magnitudes decay with distance, so
they are interpolated separately by two scalar heat flows with the scalar Laplacian ``L``:
``u`` from ``|Y_0|`` and ``phi`` from the sources' indicator, ``(M0 + t L) u = M0 |Y_0| delta``;
the result is ``X = (u / phi) Y / |Y|`` (SSC19, eq. 4 / Algorithm 1).

Logarithmic map (their sec. 7.2 and Algorithm 2).  For a source vertex ``s``:

1. the *horizontal* field ``H``: (1) with ``Y_0 = e_x(s)``, the transport of the source's first
   axis;
2. the radius ``r``: the heat-method geodesic distance from ``s``
   (:class:`~torch_polylap.HeatGeodesicSolver`);
3. the *radial* field ``R = grad r`` at the vertices (the area-weighted mean of the face
   gradients, :func:`~torch_polylap.tangent.vertex_gradient_operators`), the direction in which
   the geodesic from ``s`` arrives;
4. the polar angle ``theta_v = arg(R_v conj(H_v))``: the angle from the transported axis to the
   arriving geodesic, which parallel transport preserves, so it is the angle at ``s``, in
   ``s``'s frame, of the geodesic that reaches ``v``;

and ``log_s(v) = r_v (cos theta_v, sin theta_v)``.  SSC19 obtain ``R`` by diffusing, with (1),
unit vectors pointing away from the source on its one-ring; on polygon meshes with irregular
rings (Voronoi cells) that field keeps a bias from the ring's imbalance that refinement does not
remove (mean angle error 0.22 and 0.33 rad on the Voronoi spheres at levels 3 and 4), while
``grad r`` converges (0.064 and 0.055 rad; ``docs/vector.md`` has the numbers).
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence

import numpy as np
import scipy.sparse as sp
import torch

from .._typing import MeshFaces
from ..checks import Lam, check_index_or_mask
from ..geodesics import POISSON_LAM, HeatGeodesicSolver, with_unit_diagonal_at_isolated
from ..kernels import check_method
from ..linalg import (
    HermitianLDL,
    LDLFactorization,
    cached_factorization,
    qdldl_available,
    solve,
)
from ..sparse import as_operator, sparse_values, to_scipy
from ..sparse.construct import solver_cache
from ..tangent import vertex_gradient_operators
from .connection import connection_laplacian_of
from .transport import TangentFrames, to_ambient, to_tangent

__all__ = ["VectorHeatSolver"]

SourceLike = int | torch.Tensor | Sequence[int]


class VectorHeatSolver:
    """Parallel transport and the logarithmic map by the vector heat method (Sharp, Soliman and
    Crane 2019), with a polygon Laplacian (AW11 by default), prefactored for repeated queries.

    Both system matrices, ``M + t A`` (``(2V, 2V)``, the connection Laplacian of
    :func:`~torch_polylap.vector.connection_laplacian`) and the scalar ``M0 + t L`` (held by
    the :class:`~torch_polylap.HeatGeodesicSolver` in :attr:`geodesic`, which also gives the log
    map's radius), are built once; their factorizations are cached on them by
    :func:`~torch_polylap.solve` and serve every query.  A query that needs no gradient solves
    ``M + t A`` in complex form instead (``torch_polylap.linalg.HermitianLDL``: one
    complex entry per four of the real form's factor), in the AMD ordering of the scalar
    heat system's QDLDL factor; so on the CPU, with qdldl installed, :attr:`geodesic` factors
    with QDLDL (``backend="ldl"``) at any size.  Every step runs in float64 (the heat
    decays like ``exp(-d^2 / 4 t)``, which leaves float32's range a few dozen edge lengths from
    the sources); results have ``verts``' dtype.  Differentiable with respect to ``verts``
    through the solves (O(nnz) backward), away from the cut locus (where ``|Y| -> 0``).

    Args:
        verts: ``(V, 3)`` vertex positions.
        faces: faces in any accepted form, or a :class:`~torch_polylap.topology.Topology`.
        t: heat time; default that of :class:`~torch_polylap.HeatGeodesicSolver`, ``4 h^2``
            with ``h`` the mean edge length (SSC19 use ``h^2``; the factor 4 measured on the
            sphere families is at least as accurate for transport, see ``docs/vector.md``).
        lam: the stabilizer weight of the Laplacians (see :func:`~torch_polylap.laplacian`).
        poisson_lam: the Poisson step's weight for the log map's radius (see
            :class:`~torch_polylap.HeatGeodesicSolver`).
        method: the polygon Laplacian whose face blocks build both the connection Laplacian
            ``A`` and the scalar ``L``: ``"aw11"`` (default), ``"plms"`` or ``"degoes"`` (see
            :func:`~torch_polylap.laplacian` and
            :func:`~torch_polylap.vector.connection_laplacian`).

    Raises:
        ValueError: an unknown ``method``, a non-positive ``t``, or bad input as for
            :func:`~torch_polylap.vector.connection_laplacian`.

    Attributes:
        frames: the :class:`~torch_polylap.vector.TangentFrames` in which ``log_map``'s
            coordinates are given.
        geodesic: the scalar :class:`~torch_polylap.HeatGeodesicSolver` (same ``t``).
    """

    def __init__(
        self,
        verts: torch.Tensor,
        faces: MeshFaces,
        t: float | torch.Tensor | None = None,
        lam: Lam = 1.0,
        *,
        poisson_lam: Lam = POISSON_LAM,
        method: str = "aw11",
    ) -> None:
        check_method(method, diagonal_mass="VectorHeatSolver")
        # the scalar solver checks verts (and lam, t) first. QDLDL factors its systems at any
        # size on the CPU: the AMD ordering it finds orders the complex vector system too
        # (on bunny-dual, 72k vertices, 7.1 s to factor against 11 s in SuperLU's own
        # ordering, which also fills more), where CHOLMOD's cannot be read
        cpu = verts.device.type == "cpu"
        self.geodesic = HeatGeodesicSolver(
            verts,
            faces,
            t,
            lam,
            poisson_lam=poisson_lam,
            method=method,
            backend="ldl" if cpu and qdldl_available() else "auto",
        )
        self.topology = self.geodesic.topology
        self.verts = verts
        self.method = method
        self.t = self.geodesic.t
        A, M, self.frames = connection_laplacian_of(verts, self.topology, lam, method)
        self.vector_operator = with_unit_diagonal_at_isolated(M + self.t * A).double()
        self.vector_mass = M.diagonal().double()
        self._grad: tuple[torch.Tensor, torch.Tensor] | None = None

    def _direct_backend(self) -> str | None:
        """The scalar factorization of a query outside autograd (see
        :meth:`~torch_polylap.HeatGeodesicSolver._direct_backend`), or ``None`` where the
        query takes the differentiable torch path."""
        backend = self.geodesic._direct_backend()
        values = sparse_values(self.vector_operator)
        if backend is None or (torch.is_grad_enabled() and values.requires_grad):
            return None
        return backend

    def _hermitian(self, backend: str) -> HermitianLDL:
        """The ``L D L^H`` of ``M + t A`` in complex form (:class:`.HermitianLDL`), cached on
        :attr:`vector_operator` (built by the first query outside autograd). It has the
        scalar heat system's pattern: it is factored in the AMD ordering QDLDL computed for
        that system where the scalar heat factor is QDLDL's."""

        def build() -> HermitianLDL:
            heat = cached_factorization(as_operator(self.geodesic.heat_operator), backend)
            ordering = heat.ordering() if isinstance(heat, LDLFactorization) else None
            return HermitianLDL(_complex_form(to_scipy(self.vector_operator)), ordering)

        return solver_cache(as_operator(self.vector_operator), "hermitian", build)

    def _diffuse_array(self, rhs: np.ndarray, backend: str) -> np.ndarray:
        """``(V, Q)`` complex ``Y`` of ``(M + t A) Y = M Y_0`` for the complex ``(V, Q)``
        ``Y_0`` ``rhs`` (frame coordinates ``x + i y``), outside autograd."""
        mass = self.vector_mass.detach().numpy()
        rhs = mass[0::2, None] * rhs.real + 1j * (mass[1::2, None] * rhs.imag)
        return self._hermitian(backend).solve(rhs)

    def _sources(self, sources: SourceLike, name: str = "sources") -> torch.Tensor:
        n = self.topology.num_verts
        if isinstance(sources, int) and not isinstance(sources, bool):
            sources = [sources]
        idx = check_index_or_mask(sources, n, name)
        if idx.numel() == 0:
            raise ValueError(f"{name} is empty; give at least one source vertex.")
        return idx.to(self.verts.device)

    def diffuse(self, initial: torch.Tensor) -> torch.Tensor:
        """``(V, Q, 2)`` float64 solution ``Y`` of ``(M + t A) Y = M Y_0`` (eq. (1)) for
        ``initial`` ``Y_0`` ``(V, Q, 2)`` in frame coordinates."""
        n, q = initial.shape[:2]
        backend = None if initial.requires_grad else self._direct_backend()
        if backend is not None:
            # complex form: a quarter of the real form's factor entries (see HermitianLDL)
            Y0 = initial.detach().double().numpy()
            Y = self._diffuse_array(Y0[..., 0] + 1j * Y0[..., 1], backend)
            return torch.from_numpy(np.stack((Y.real, Y.imag), -1))
        rhs = self.vector_mass[:, None] * initial.double().transpose(1, 2).reshape(2 * n, q)
        return solve(self.vector_operator, rhs).reshape(n, 2, q).transpose(1, 2)

    def transport(self, sources: SourceLike, vectors: torch.Tensor) -> torch.Tensor:
        """Parallel transport of tangent vectors given at source vertices to every vertex.

        Args:
            sources: ``S`` distinct source vertices (an int, a sequence or an index tensor).
            vectors: ``(3,)`` or ``(S, 3)`` ambient vectors at the sources; their parts tangent
                to the sources' planes are transported.

        Returns:
            ``(V, 3)`` tangent vectors (``e_x``, ``e_y`` combinations): at every vertex, the
            vector of the nearest source (several sources blend near their Voronoi borders,
            SSC19 sec. 5), with the length interpolated by the scalar heat flows (within the
            sources' lengths, also where the heat falls to round-off).  Zero on
            connected components without a source.

        Raises:
            ValueError: bad sources (see :func:`~torch_polylap.checks.check_index_or_mask`), a
                shape mismatch, or a vector with no tangent part at its source.
        """
        idx = self._sources(sources)
        vectors = torch.as_tensor(vectors, dtype=self.verts.dtype, device=self.verts.device)
        if vectors.dim() == 1:
            vectors = vectors[None]
        if vectors.shape != (idx.numel(), 3):
            raise ValueError(
                f"transport: vectors must have shape (3,) or ({idx.numel()}, 3) for "
                f"{idx.numel()} source(s), got {tuple(vectors.shape)}."
            )
        frames = TangentFrames(*(f[idx] for f in self.frames))
        coords = to_tangent(vectors, frames)  # (S, 2)
        length = torch.linalg.vector_norm(coords, dim=1)
        flat = length <= torch.finfo(length.dtype).eps * torch.linalg.vector_norm(vectors, dim=1)
        if bool(flat.any()):
            s = int(torch.nonzero(flat)[0, 0])
            raise ValueError(
                f"transport: the vector {vectors[s].tolist()} at source vertex {int(idx[s])} "
                "has no part tangent to the surface there (it is zero or normal to it)."
            )
        backend = None if vectors.requires_grad else self._direct_backend()
        if backend is not None:
            return self._transport_array(idx, coords, length, backend)
        n = self.topology.num_verts
        initial = self.verts.new_zeros(n, 1, 2).index_put((idx,), coords[:, None])
        Y = self.diffuse(initial)[:, 0]  # (V, 2)
        weights = self.verts.new_zeros(n, 2)
        weights[idx, 0] = length
        weights[idx, 1] = 1.0
        u_phi = self.geodesic.heat(weights)
        ratio = u_phi[:, 0] / u_phi[:, 1].clamp_min(torch.finfo(u_phi.dtype).tiny)
        ratio = ratio.clamp(*_length_bounds(length))
        norm = torch.linalg.vector_norm(Y, dim=1)
        reached = self._reached(idx)
        _warn_underflow(reached & (norm == 0), self.t)
        # the unit vector first: ratio / norm overflows where Y underflowed to round-off
        X = (Y / norm.clamp_min(torch.finfo(Y.dtype).tiny)[:, None]) * ratio[:, None]
        X = torch.where(reached[:, None], X, torch.zeros_like(X))
        return to_ambient(X.to(self.verts.dtype), self.frames)

    def _transport_array(
        self, idx: torch.Tensor, coords: torch.Tensor, length: torch.Tensor, backend: str
    ) -> torch.Tensor:
        """:meth:`transport` outside autograd on float64 arrays, for the ``(S,)`` sources
        ``idx`` with the ``(S, 2)`` frame coordinates ``coords`` of their vectors and the
        ``(S,)`` ``length``: the same steps, the vector heat solve in complex form, the scalar
        ones over the sources' elimination-tree paths; ``(V, 3)``."""
        tiny = np.finfo(np.float64).tiny
        index = idx.numpy()
        lengths = length.detach().double().numpy()
        mass = self.geodesic.mass.detach().numpy()[index]
        # the scalar heat first: the complex factorization takes the scalar factor's ordering
        if np.all(lengths == lengths[0]):
            # u = |Y_0| phi: one solve (the same ratio u / phi to round-off)
            _, phi = self.geodesic._heat_array([index], [mass], backend)
            u = lengths[0] * phi[:, 0]
            phi = phi[:, 0]
        else:
            _, u_phi = self.geodesic._heat_array([index, index], [lengths * mass, mass], backend)
            u, phi = u_phi[:, 0], u_phi[:, 1]
        # as the torch path: no warning where the far field underflowed (checked below)
        with np.errstate(over="ignore", divide="ignore", invalid="ignore"):
            low, high = _length_bounds(length.double())
            ratio = np.clip(u / np.maximum(phi, tiny), float(low), float(high))
        c = coords.detach().double().numpy()
        vm = self.vector_mass.detach().numpy()  # M Y_0, nonzero at the sources only
        rhs = vm[2 * index] * c[:, 0] + 1j * (vm[2 * index + 1] * c[:, 1])
        Y = self._hermitian(backend).solve_sparse(index, rhs)
        norm = np.abs(Y)
        with np.errstate(over="ignore", invalid="ignore"):
            X = (Y / np.maximum(norm, tiny)) * ratio  # as the torch path: no overflow
        if self.geodesic.num_components > 1:
            reached = self._reached(idx).numpy()
            X = np.where(reached, X, 0.0)
            _warn_underflow(reached & (norm == 0), self.t)
        else:
            _warn_underflow(norm == 0, self.t)
        planar = torch.from_numpy(np.stack((X.real, X.imag), 1)).to(self.verts.dtype)
        return to_ambient(planar, self.frames)

    def _reached(self, idx: torch.Tensor) -> torch.Tensor:
        """``(V,)`` bool: the vertex lies on a connected component holding one of ``idx``."""
        labels = self.geodesic.labels
        hit = torch.zeros(self.geodesic.num_components, dtype=torch.bool, device=labels.device)
        hit[labels[idx]] = True
        return hit[labels]

    def log_map(self, source: SourceLike) -> torch.Tensor:
        """The logarithmic map at ``source``: ``(V, 2)`` coordinates in the source's frame
        (``frames.e_x[source]``, ``frames.e_y[source]``) of the tangent vector at the source
        whose geodesic reaches each vertex after its length.

        Args:
            source: one vertex (an int), giving ``(V, 2)``; or a sequence or index tensor of
                ``Q`` vertices, independent queries solved together, giving ``(V, Q, 2)``.

        Returns:
            Coordinates in ``verts``' dtype; 0 at the source, ``inf`` on connected components
            without the source. ``to_ambient``-style 3D vectors at the source are
            ``log[..., :1] * e_x[s] + log[..., 1:] * e_y[s]``.
        """
        single = isinstance(source, (int, torch.Tensor)) and torch.as_tensor(source).dim() == 0
        idx = self._sources(torch.as_tensor(source).reshape(-1) if single else source, "source")
        n, q = self.topology.num_verts, idx.numel()
        horizontal = self.verts.new_zeros(n, q, 2)
        horizontal[idx, torch.arange(q, device=idx.device), 0] = 1.0
        Y = self.diffuse(horizontal)
        radius = self.geodesic.distance([[s] for s in idx.tolist()])  # (V, Q)
        finite = torch.isfinite(radius)
        _warn_underflow(finite & (torch.linalg.vector_norm(Y, dim=-1) == 0), self.t)
        r = torch.where(finite, radius, torch.zeros_like(radius)).double()
        grad_x, grad_y = self._gradients()
        w = torch.complex(grad_x @ r, grad_y @ r) * torch.complex(Y[..., 0], Y[..., 1]).conj()
        unit = w / w.abs().clamp_min(torch.finfo(r.dtype).tiny)
        log = torch.stack((unit.real, unit.imag), -1) * r[..., None]
        log = torch.where(finite[..., None], log, torch.inf).to(self.verts.dtype)
        return log[:, 0] if single else log

    def _gradients(self) -> tuple[torch.Tensor, torch.Tensor]:
        """The vertex gradient operators in :attr:`frames` (float64), built on first use."""
        if self._grad is None:
            frames = (self.frames.e_x, self.frames.e_y)
            grad_x, grad_y = vertex_gradient_operators(self.verts, self.topology, frames)
            self._grad = (grad_x.double(), grad_y.double())
        return self._grad


def _complex_form(S: sp.spmatrix) -> sp.csr_matrix:
    """The complex ``(V, V)`` matrix whose real form is the ``(2V, 2V)`` ``S`` (entry
    ``a + i b`` as the block ``[[a, -b], [b, a]]`` at rows and columns ``2v, 2v + 1``): the
    even columns of ``S``, the even rows as real parts and the odd ones as imaginary parts."""
    S = sp.csr_matrix(S)
    n = S.shape[0] // 2
    rows = np.repeat(np.arange(2 * n), np.diff(S.indptr))
    even = S.indices % 2 == 0
    real, imag = even & (rows % 2 == 0), even & (rows % 2 == 1)
    cols = S.indices[real] // 2
    if S.has_canonical_format and np.array_equal(cols, S.indices[imag] // 2):
        # every block stored whole, as the operator's pattern has them: the two rows of a
        # block row hold the same columns, in order
        counts = np.bincount(rows[real] // 2, minlength=n)
        indptr = np.concatenate(([0], np.cumsum(counts)))
        return sp.csr_matrix((S.data[real] + 1j * S.data[imag], cols, indptr), shape=(n, n))
    rows, cols, data = rows[even], S.indices[even] // 2, S.data[even]
    values = np.where(rows % 2 == 0, data, 1j * data)
    return sp.csr_matrix((values, (rows // 2, cols)), shape=(n, n))


def _warn_underflow(lost: torch.Tensor | np.ndarray, t: float | torch.Tensor) -> None:
    """Warn when the diffused field underflowed to exactly zero at reachable vertices."""
    if bool(lost.any()):
        warnings.warn(
            f"VectorHeatSolver: the diffused field is exactly zero at {int(lost.sum())} vertices "
            f"(the heat decays like exp(-d^2 / 4t) and underflowed far from the sources at "
            f"t = {float(t):.3g}); their result is zero. Use a larger t for such distances.",
            RuntimeWarning,
            stacklevel=3,
        )


def _length_bounds(length: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The range within which :meth:`VectorHeatSolver.transport` keeps the magnitudes
    ``u / phi``: the ``(S,)`` source lengths', widened by a relative ``1e-6``.

    ``u / phi`` is a weighted mean of the source lengths wherever the heat is positive. Far
    from the sources ``phi`` falls to round-off or below zero, and the quotient is noise that
    overflowed to inf (and NaN in ``Y * ratio``). The margin keeps the clamp away from
    quotients that are right to round-off, so their gradients are untouched.
    """
    low, high = length.detach().aminmax()
    return low * (1 - 1e-6), high * (1 + 1e-6)

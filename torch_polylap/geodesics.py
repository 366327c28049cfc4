"""Geodesic distance by the heat method on polygon meshes.

The heat method (Crane, Weischedel and Wardetzky 2013, "Geodesics in Heat", Algorithm 1) uses
the face gradient (1) of :mod:`torch_polylap.calculus`,
``grad_f u = sum_i u_i (g_i x a_f) / |a_f|^2``, with the divergence ``div = -G^T A_F``, its
negative adjoint under the face-area inner product, and the polygon Laplacian ``L`` for both
the heat flow and the Poisson problem.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import numpy as np
import scipy.sparse as sp
import torch

from ._typing import MeshFaces
from .calculus import gradient_layout, grouped_corner_gradients
from .checks import Lam, check_index_or_mask, check_verts
from .kernels import check_method
from .kernels.frames import component_norm
from .linalg import (
    Factor,
    LDLFactorization,
    cached_factorization,
    cholespy_available,
    qdldl_available,
    solve,
)
from .measures import mean_edge_length
from .operators import laplacian
from .sparse import SparseOperator, as_operator, diag, sparse_values
from .sparse.construct import solver_cache
from .topology import get_topology
from .tracing import tracing

__all__ = [
    "HeatGeodesicSolver",
    "heat_geodesic_distance",
]


# Default heat time t = T_FACTOR * h^2 (h the mean edge length; Crane et al. use factor 1) and
# default stabilizer weight of the Poisson step, from the mean relative error from one source
# (heat lam = 1) on the sphere hex/quad/Voronoi/concave families at levels 3 and 4 and on the
# planar quad/Voronoi/concave grids at levels 4 and 5:
# - factor 1 fails on the concave grids (0.35 at level 4, 0.47 at level 5, whatever the Poisson
#   weight; potpourri3d's polygon heat solver at t = h^2 fails there too);
# - factor 4 with Poisson weight 0.1 brings all these cases below 2%; factor 8 gains at most a
#   third more and smooths more;
# - the Poisson weight matters most: the stabilizer lambda d^T Pi d penalizes the non-linear
#   part of phi on each face, which the least-squares fit of grad phi to X never asks for.
#   Weight 1 doubles to quadruples the error of 0.1 (hex sphere level 4: 0.020 vs 0.0037);
#   0.05 gains little and weakens the conditioning.
T_FACTOR = 4.0
POISSON_LAM = 0.1

# Up to this many vertices the heat solver factors its two systems with QDLDL (simplicial
# L D L^T) rather than cholespy's CHOLMOD: measured on the real meshes, one thread, QDLDL took
# 0.4-0.6x CHOLMOD's time to factor up to 28k vertices (loki, rockerArm, sword) and 0.84x at
# 51k (a planar Voronoi grid), but 1.2-2.2x on the 46k-82k-vertex closed surfaces (lion vase,
# bunny dual, hex_cos_6), whose factors fill in enough for CHOLMOD's supernodes to pay.
LDL_MAX_VERTS = 40_000


SourcesLike = torch.Tensor | Sequence[int] | Sequence[torch.Tensor | Sequence[int]]


class _Corners(NamedTuple):
    """One degree group's share of the heat method's per-face steps: ``corners`` ``(k, F_k)``,
    the hat-function gradients ``weights`` ``(3, k, F_k)`` in float64 (eq. (1)), the same
    times the face area, ``flux`` ``(3, k, F_k)`` in ``verts``' dtype (the entries of
    ``G^T A_F``), and the ``(F_k,)`` float64 face ``area``."""

    face_ids: torch.Tensor
    corners: torch.Tensor
    weights: torch.Tensor
    flux: torch.Tensor
    area: torch.Tensor


class _QueryArrays(NamedTuple):
    """What a query outside autograd reads (:meth:`HeatGeodesicSolver._distance_without_grad`):
    the ``(3F, V)`` float64 ``gradient`` matrix ``G`` (eq. (1)), the ``(V, 3F)`` ``flux``
    matrix ``-G^T A_F`` (``A_F`` the face areas repeated per component; ``flux X`` for a unit
    field ``X`` of ``grad u`` is the Poisson right-hand side ``G^T A_F (-X)``), the ``(V,)``
    lumped ``mass``, the ``(V,)`` component ``labels`` and the number of
    ``components``."""

    gradient: sp.csr_matrix
    flux: sp.csr_matrix
    mass: np.ndarray
    labels: np.ndarray
    components: int


class HeatGeodesicSolver:
    """Geodesic distances by the heat method (Crane, Weischedel and Wardetzky 2013, Alg. 1),
    with a polygon Laplacian (AW11 by default), for repeated queries on one mesh.

    1. Heat flow ``(M0 + t L) u = M0 delta``, ``delta`` the indicator of the sources (Crane et
       al.'s single backward-Euler step, with the lumped mass ``M0``).
    2. ``X_f = -grad_f u / |grad_f u|`` per face (eq. (1) of :mod:`torch_polylap.calculus`).
    3. Poisson problem ``L phi = -div X = G^T A_F X``: the least-squares fit of ``grad phi`` to
       ``X`` (on planar faces ``G^T A_F G`` is the geometric part of ``L``; ``L`` adds the
       stabilizer, weighted by ``poisson_lam``).  ``L`` is positive semi-definite here (the
       paper's ``L_C`` is ``-L``), so this sign makes ``phi`` grow away from the sources.
    4. ``phi`` shifted by its mean at the sources, so that a single source is at exactly 0.

    ``L`` is singular (the constants on each connected component).  The Poisson system adds
    ``c e_p e_p^T`` for one pinned vertex ``p`` per component (``c`` the mean diagonal of
    ``L``): for a right-hand side in the range of ``L`` (``-div X`` sums to zero on each
    component) its solution is the exact solution of the singular system with ``phi_p = 0``, and
    the matrix is symmetric positive definite, fixed for the mesh and independent of the
    sources.  So both system matrices are built once here and their factorizations, cached on
    them by the first query, serve every later one.  (A Dirichlet solve with the sources fixed
    at 0 would change the matrix with every query.)  The factorizations are those of
    ``backend``; on the CPU by default QDLDL's ``L D L^T``, which builds in about half
    CHOLMOD's time on meshes up to :data:`LDL_MAX_VERTS` vertices.  The two matrices share
    their pattern, so QDLDL orders and analyses it once: after the first query's heat solve,
    the Poisson matrix is factored numerically in place with the heat factor's ordering and
    elimination tree, the heat factor having been read out first
    (``torch_polylap.linalg.LDLFactorization.refactored``).  Steps 2 and 3's right-hand
    side are one pass over the faces of each degree, with the per-corner gradient weights
    computed here once.  A query that needs no gradient (neither ``verts`` nor a tensor ``t`` or
    ``lam`` requires grad, or it runs under ``torch.no_grad()``) with a direct backend on the
    CPU runs steps 1-4 on float64 arrays instead: ``grad u`` as one product with the
    ``(3F, V)`` gradient matrix, ``-div X`` as one with ``-G^T A_F`` (the face areas folded
    in), both solves straight through the cached factorizations; the same distances to
    round-off, at a fraction of the per-query cost outside the solves.  With QDLDL's factors,
    the heat system's right-hand side ``M0 delta``, nonzero at the sources only, has a forward
    solve that is nonzero only on the sources' paths to the root of the factor's elimination
    tree (7-20% of its entries on meshes of 20k-30k vertices), and is solved there only
    (``torch_polylap.linalg.etree_solve``), from the second query on.

    So with QDLDL the first query costs the two factorizations and four triangular solves
    through QDLDL's own solve; the second also makes the faster copies of the factors (32-bit
    indices, and the heat factor's elimination-tree paths: about 40-70 ms on meshes of 20k-30k
    vertices, some ten times a query); every later query takes about 0.9x the time of one with
    CHOLMOD (``backend="cholesky"``).  A single query, as :func:`heat_geodesic_distance`
    makes, never pays for the copies.

    Vertices of components without a source get ``inf`` (isolated vertices included).
    Differentiable with respect to ``verts`` through both solves (O(nnz) backward).  The heat
    step runs in float64 whatever ``verts``' dtype: ``u`` decays like ``exp(-d / sqrt(t))``,
    which leaves float32's range (``exp(-87)``) about 175 mean edge lengths from the sources at
    ``t = 4 h^2``; the result has ``verts``' dtype.

    Args:
        verts: ``(V, 3)`` vertex positions.
        faces: faces in any accepted form, or a :class:`~torch_polylap.topology.Topology`.
        t: heat time; default ``4 h^2`` with ``h`` the mean edge length (Crane et al. use
            ``h^2``; see :data:`T_FACTOR` for the measurements behind the factor).  A float or a
            0-dim tensor.
        lam: the stabilizer weight of the heat step's Laplacian (see
            :func:`~torch_polylap.laplacian`).
        poisson_lam: the stabilizer weight of the Poisson step's Laplacian; default 0.1, which
            keeps it positive definite on the non-constant functions while staying close to the
            pure least-squares fit ``G^T A_F G`` (see :data:`POISSON_LAM`).
        method: the polygon Laplacian of both steps: ``"aw11"`` (default), ``"plms"`` or
            ``"degoes"`` (see :func:`~torch_polylap.laplacian`; ``lam`` and ``poisson_lam``
            are each method's own stabilizer weight, ignored by ``"plms"``).  The gradient and
            divergence of steps 2 and 3 are (1) whatever the method.
        backend: how the two systems are solved: ``"ldl"`` (QDLDL's ``L D L^T``, CPU, the
            optional ``qdldl``), or a backend of :func:`~torch_polylap.solve` (``"cholesky"``,
            ``"splu"``, ``"cg"``, ``"auto"``).  The default ``"auto"`` takes ``"ldl"`` on the
            CPU when qdldl is installed and the mesh has at most :data:`LDL_MAX_VERTS`
            vertices, else :func:`~torch_polylap.solve`'s ``"auto"``.  From the second query
            on, QDLDL's solves run through copies of its factors with 32-bit indices, and the
            heat solve's forward half over the sources' elimination-tree paths only (see
            above).

    Raises:
        ValueError: ``t`` not positive, an unknown ``backend``, or ``"ldl"`` without qdldl or
            off the CPU.
    """

    def __init__(
        self,
        verts: torch.Tensor,
        faces: MeshFaces,
        t: float | torch.Tensor | None = None,
        lam: Lam = 1.0,
        *,
        poisson_lam: Lam = POISSON_LAM,
        backend: str = "auto",
        method: str = "aw11",
    ) -> None:
        check_verts(verts)
        check_method(method, diagonal_mass="HeatGeodesicSolver")
        self.topology = get_topology(faces, verts.shape[0])
        self.verts = verts
        self.backend = _geodesic_backend(backend, verts.device, self.topology.num_verts)
        self.method = method
        L, M0 = laplacian(verts, self.topology, lam, method=method)
        L_poisson, _ = laplacian(verts, self.topology, poisson_lam, method=method)
        if t is None:
            t = T_FACTOR * mean_edge_length(verts, self.topology, validate=False) ** 2
        elif not bool(torch.as_tensor(t) > 0):
            raise ValueError(f"HeatGeodesicSolver: t must be a positive heat time, got {t}.")
        self.t = t
        self.mass = M0.diagonal().double()
        self.heat_operator = with_unit_diagonal_at_isolated(M0 + t * L).double()
        self.poisson_operator = L_poisson + self._pin(L_poisson)
        self._corners = [
            _Corners(grp.face_ids, grp.corners_t, w.double(), w * area, area.detach().double())
            for grp, w, area in grouped_corner_gradients(verts, self.topology)
        ]
        self.num_components, labels = self.topology.connected_components()
        self.labels = labels.to(verts.device)
        self._arrays: _QueryArrays | None = None
        # queries answered through the array path: the first solves with QDLDL itself, the
        # next ones make (then use) the faster copies of its factors
        self._queries = 0
        # heat_geodesic_distance queries once: the heat factor need not outlive its solve
        self._one_query = False

    def _pin(self, L: torch.Tensor) -> SparseOperator:
        """``c sum_p e_p e_p^T`` over the first vertex of every connected component."""
        count, labels = self.topology.connected_components()
        first = torch.full((count,), labels.numel(), dtype=torch.int64)
        first = first.scatter_reduce(0, labels, torch.arange(labels.numel()), "amin")
        diagonal = L.diagonal().detach()
        scale = diagonal[diagonal > 0].mean() if bool((diagonal > 0).any()) else 1.0
        weights = torch.zeros_like(diagonal)
        weights[first.to(weights.device)] = scale
        return diag(weights)

    def _indicator(self, sources: SourcesLike) -> torch.Tensor:
        """``(V, Q)`` 0/1 indicator of each query's sources (``Q = 1`` for a single query)."""
        queries = self._source_indices(sources)
        ind = self.verts.new_zeros(self.topology.num_verts, len(queries))
        for q, idx in enumerate(queries):
            ind[idx.to(ind.device), q] = 1.0
        return ind

    def _source_indices(self, sources: SourcesLike) -> list[torch.Tensor]:
        """Each query's source vertices as ``(m_q,)`` int64 indices, checked."""
        n = self.topology.num_verts
        queries = _as_queries(sources)
        out = []
        for q, src in enumerate(queries):
            name = f"sources[{q}]" if len(queries) > 1 else "sources"
            # An empty list reads as a float array; say what is wrong with it, not its dtype.
            empty = len(src) == 0 if isinstance(src, (list, tuple)) else False
            idx = None if empty else check_index_or_mask(src, n, name)
            if idx is None or idx.numel() == 0:
                raise ValueError(f"{name} is empty; give at least one source vertex per query.")
            out.append(idx)
        return out

    def _solve(self, A: torch.Tensor, B: torch.Tensor) -> torch.Tensor:
        """``A^{-1} B`` with :attr:`backend`'s factorization, cached on ``A``."""
        return solve(A, B, backend=self.backend)

    def heat(self, indicator: torch.Tensor) -> torch.Tensor:
        """``(V, Q)`` float64 heat ``u = (M0 + t L)^{-1} M0 delta`` (step 1)."""
        rhs = self.mass[:, None] * indicator.double()
        return self._solve(self.heat_operator, rhs)

    def _unit_gradient(self, c: _Corners, u: torch.Tensor) -> torch.Tensor:
        """``(3, F_k, Q)`` ``grad u / |grad u|`` on one degree group's faces, in ``verts``'
        dtype; faces where the heat is exactly constant (none on a connected mesh in float64)
        get 0."""
        grad = (c.weights[..., None] * u[c.corners][None]).sum(1)
        # no underflow: the heat falls below 1e-154, whose square does, some 700 edge lengths
        # from the sources
        norm = component_norm(grad[0], grad[1], grad[2])
        return (grad / norm.clamp_min(torch.finfo(grad.dtype).tiny)).to(self.verts.dtype)

    def _add_flux(self, rhs: torch.Tensor, c: _Corners, field: torch.Tensor) -> torch.Tensor:
        """``rhs + G^T A_F X`` over one degree group's faces, ``field`` ``X`` ``(3, F_k, Q)``."""
        flux = (c.flux[..., None] * field[:, None]).sum(0)  # (k, F_k, Q)
        return rhs.index_add(0, c.corners.reshape(-1), flux.flatten(0, 1))

    def normalized_field(self, u: torch.Tensor) -> torch.Tensor:
        """``(F, 3, Q)`` unit field ``X = -grad u / |grad u|`` (step 2), in ``verts``' dtype."""
        out = self.verts.new_zeros(self.topology.num_faces, 3, u.shape[1])
        for c in self._corners:
            out = out.index_copy(0, c.face_ids, -self._unit_gradient(c, u).transpose(0, 1))
        return out

    def potential(self, field: torch.Tensor) -> torch.Tensor:
        """``(V, Q)`` solution of ``L phi = -div X`` with one pinned vertex per component, for
        a ``(F, 3, Q)`` field ``X``."""
        rhs = self.verts.new_zeros(self.topology.num_verts, field.shape[2])
        for c in self._corners:
            rhs = self._add_flux(rhs, c, field[c.face_ids].transpose(0, 1))
        return self._solve(self.poisson_operator, rhs)

    def _potential_of_heat(self, u: torch.Tensor) -> torch.Tensor:
        """``potential(normalized_field(u))`` in one pass over each degree group's faces,
        without the ``(F, 3, Q)`` field."""
        rhs = self.verts.new_zeros(self.topology.num_verts, u.shape[1])
        for c in self._corners:
            rhs = self._add_flux(rhs, c, -self._unit_gradient(c, u))
        return self._solve(self.poisson_operator, rhs)

    def shift_to_sources(self, phi: torch.Tensor, indicator: torch.Tensor) -> torch.Tensor:
        """Subtract from ``phi`` its mean at the sources, per component (step 4); ``inf`` on
        components without a source."""
        count = self.num_components
        sums = phi.new_zeros(count, phi.shape[1]).index_add(0, self.labels, phi * indicator)
        hits = phi.new_zeros(count, phi.shape[1]).index_add(0, self.labels, indicator)
        reached = hits[self.labels] > 0
        shift = sums[self.labels] / hits[self.labels].clamp_min(1.0)
        return torch.where(reached, phi - shift, torch.full_like(phi, float("inf")))

    def distance(self, sources: SourcesLike) -> torch.Tensor:
        """Approximate geodesic distance from ``sources``.

        Args:
            sources: one query, the source vertices as indices (a tensor, array or list of
                ints) or a ``(V,)`` boolean mask, giving a ``(V,)`` result; or a list of such
                queries (a list of index tensors or of lists), giving ``(V, Q)``, column ``q``
                the distance to the nearest source of query ``q``.

        Raises:
            ValueError, TypeError: an empty query, an index out of range or repeated, a
                non-integer index (see :func:`~torch_polylap.checks.check_index_or_mask`).
        """
        backend = self._direct_backend()
        if backend is None:
            indicator = self._indicator(sources)
            phi = self._potential_of_heat(self.heat(indicator))
            dist = self.shift_to_sources(phi, indicator)
        else:
            dist = self._distance_without_grad(self._source_indices(sources), backend)
        return dist if _is_batch(sources) else dist[:, 0]

    def _direct_backend(self) -> str | None:
        """The factorization a query may use outside autograd, or ``None``: a query that
        needs gradients, runs under a trace, or solves with CG (or on CUDA) takes the torch
        path of :meth:`heat`, :meth:`_potential_of_heat` and :meth:`shift_to_sources`."""
        if self.verts.device.type != "cpu" or tracing():
            return None
        heat, poisson = sparse_values(self.heat_operator), sparse_values(self.poisson_operator)
        if torch.is_grad_enabled() and any(x.requires_grad for x in (self.verts, heat, poisson)):
            return None
        if self.backend == "auto":
            # as solve()'s "auto" on the CPU: both operators are symmetric
            return "cholesky" if cholespy_available() else "splu"
        return None if self.backend == "cg" else self.backend

    def _query_arrays(self) -> _QueryArrays:
        """The per-mesh arrays of :meth:`_distance_without_grad`, built by its first call."""
        if self._arrays is None:
            groups = self.topology.on(self.verts.device).groups
            pattern, order = gradient_layout(self.topology, groups, self.verts.device)
            weights = torch.cat([c.weights.detach().reshape(-1) for c in self._corners])
            gradient = sp.csr_matrix(
                (weights.index_select(0, order).numpy(), pattern.col.numpy(), pattern.crow.numpy()),
                shape=pattern.shape,
            )
            area = np.zeros(self.topology.num_faces)
            for c in self._corners:
                area[c.face_ids.numpy()] = c.area.numpy()
            # -G^T A_F as one CSR matrix: the area and the field's sign fold into its entries,
            # and a row-major product writes each vertex's sum once
            row_scale = np.repeat(-np.repeat(area, 3), np.diff(gradient.indptr))
            scaled = sp.csr_matrix(
                (gradient.data * row_scale, gradient.indices, gradient.indptr),
                shape=gradient.shape,
            )
            flux = sp.csr_matrix(scaled.T)
            mass = self.mass.detach().numpy()
            labels = self.labels.numpy()
            self._arrays = _QueryArrays(gradient, flux, mass, labels, self.num_components)
        return self._arrays

    def _heat_array(
        self, rows: list[np.ndarray], values: list[np.ndarray], backend: str
    ) -> tuple[Factor, np.ndarray]:
        """Step 1 outside autograd, for :meth:`_direct_backend`'s ``backend``: the heat
        factorization and the ``(V, Q)`` float64 ``(M0 + t L)^{-1} B``, column ``q`` of ``B``
        ``values[q]`` ``(m_q,)`` at the rows ``rows[q]`` (no repeats) and zero elsewhere.

        With QDLDL's factor the forward solve runs over the rows' elimination-tree paths only,
        from the second call on (the first solves with QDLDL: for one solve the copies of
        the factor would cost more than they save)."""
        heat = cached_factorization(as_operator(self.heat_operator), backend)
        if isinstance(heat, LDLFactorization):
            copy = self._queries > 0
            self._queries += 1
            return heat, heat.solve_sparse_array(rows, values, copy_factor=copy)
        rhs = np.zeros((self.topology.num_verts, len(rows)))
        for q, idx in enumerate(rows):
            rhs[idx, q] = values[q]
        return heat, heat.solve_array(rhs)

    def _distance_without_grad(self, sources: list[torch.Tensor], backend: str) -> torch.Tensor:
        """Steps 1-4 on float64 arrays, for each query's ``(m_q,)`` source indices: the two
        solves through the cached factorizations, ``grad u`` as one product with the
        ``(3F, V)`` gradient matrix and ``-div X`` as one with the flux matrix ``-G^T A_F``,
        instead of a pass of torch operations per degree group. The same steps as the
        differentiable path, in float64 whatever ``verts``' dtype; ``(V, Q)``."""
        arrays = self._query_arrays()
        index = [idx.cpu().numpy() for idx in sources]
        mass = [arrays.mass[idx] for idx in index]  # M0 delta, nonzero at the sources
        copy = self._queries > 0
        heat, u = self._heat_array(index, mass, backend)
        if isinstance(heat, LDLFactorization):
            flux = arrays.flux @ _unit_rows(arrays.gradient @ u)
            # the Poisson system has the heat system's pattern: after the heat solve, QDLDL
            # refactors in place with the heat factor's ordering and elimination tree
            pair = solver_cache(
                as_operator(self.poisson_operator),
                "ldl",
                lambda: heat.refactored(self.poisson_operator, keep=not self._one_query),
            )
            phi = pair.solve_array(flux, copy_factor=copy)
        else:
            poisson = cached_factorization(as_operator(self.poisson_operator), backend)
            phi = poisson.solve_array(arrays.flux @ _unit_rows(arrays.gradient @ u))
        dist = np.empty_like(phi)
        for q, idx in enumerate(index):
            dist[:, q] = _shift_to_sources(phi[:, q], idx, arrays.labels, arrays.components)
        return torch.from_numpy(dist).to(self.verts.dtype)


def with_unit_diagonal_at_isolated(A: torch.Tensor) -> torch.Tensor:
    """The heat system ``A = M + t L`` (scalar or connection, ``(n, n)``) with a unit diagonal
    where its diagonal is zero: the rows of isolated vertices (no face: zero mass, an empty row
    and column), which would make it singular. Their heat (or field) is then 0, and the rest of
    the system is unchanged."""
    isolated = (A.diagonal() == 0).detach()
    return A + diag(isolated.to(A.dtype)) if bool(isolated.any()) else A


def _unit_rows(grad: np.ndarray) -> np.ndarray:
    """``grad u / |grad u|`` per face, in place in the ``(3F, Q)`` face gradients ``grad``
    (face-major, components ``x, y, z``); 0 on faces where ``grad u = 0``.

    The squared norm underflows where the heat's gradient falls below 1e-154 (some 700 edge
    lengths from the sources at the default time): such faces, and any whose squared norm
    overflows, take ``hypot``'s scaled norm; the others the plain sum of squares, a third of
    the work. In place: each temporary of a query is a fresh allocation the size of the
    mesh, which costs about as much as the arithmetic."""
    tiny, huge = np.finfo(np.float64).tiny, np.finfo(np.float64).max
    g = grad.reshape(-1, 3, grad.shape[1])
    norm = np.einsum("fdq,fdq->fq", g, g)
    if norm.min() >= tiny and norm.max() <= huge:
        np.sqrt(norm, out=norm)
    else:
        bad = ~((norm >= tiny) & (norm <= huge))
        np.sqrt(norm, out=norm)
        f, q = np.nonzero(bad)
        norm[f, q] = np.hypot(np.hypot(g[f, 0, q], g[f, 1, q]), g[f, 2, q])
    # the clamp keeps faces with grad u = 0 at 0 (a component without a source)
    np.maximum(norm, tiny, out=norm)
    g /= norm[:, None]
    return g.reshape(grad.shape)


def _shift_to_sources(
    phi: np.ndarray, sources: np.ndarray, labels: np.ndarray, count: int
) -> np.ndarray:
    """``(V,)`` ``phi`` less its mean at the ``sources`` of each connected component, ``inf``
    on components without a source (step 4 for one query)."""
    if count == 1:
        return phi - phi[sources].mean()
    comp = labels[sources]
    hits = np.bincount(comp, minlength=count)
    shift = np.bincount(comp, weights=phi[sources], minlength=count) / np.maximum(hits, 1)
    return np.where(hits[labels] > 0, phi - shift[labels], np.inf)


def _geodesic_backend(backend: str, device: torch.device, num_verts: int) -> str:
    """The solve backend :class:`HeatGeodesicSolver` uses for ``backend`` (see there)."""
    cpu = device.type == "cpu"
    if backend == "auto":
        return "ldl" if cpu and num_verts <= LDL_MAX_VERTS and qdldl_available() else "auto"
    if backend == "ldl":
        if not cpu:
            raise ValueError(
                f"HeatGeodesicSolver: backend='ldl' factors on the CPU, but verts are on "
                f"{device}; use backend='auto' (CHOLMOD on CUDA through cholespy, or CG)."
            )
        if not qdldl_available():
            raise ValueError(
                "HeatGeodesicSolver: backend='ldl' needs the optional package qdldl "
                "(pip install 'torch_polylap[ldl]'); use backend='auto' without it."
            )
        return backend
    if backend not in ("cholesky", "splu", "cg"):
        raise ValueError(
            "HeatGeodesicSolver: backend must be 'auto', 'ldl', 'cholesky', 'splu' or 'cg', "
            f"got {backend!r}."
        )
    return backend


def _is_batch(sources: SourcesLike) -> bool:
    """A list or tuple whose items are themselves index collections is a batch of queries."""
    return isinstance(sources, (list, tuple)) and any(
        isinstance(s, (list, tuple, torch.Tensor)) and not _is_scalar(s) for s in sources
    )


def _is_scalar(s: object) -> bool:
    return isinstance(s, torch.Tensor) and s.dim() == 0


def _as_queries(sources: SourcesLike) -> list:
    return list(sources) if _is_batch(sources) else [sources]


def heat_geodesic_distance(
    verts: torch.Tensor,
    faces: MeshFaces,
    sources: SourcesLike,
    t: float | torch.Tensor | None = None,
    lam: Lam = 1.0,
    *,
    poisson_lam: Lam = POISSON_LAM,
    backend: str = "auto",
    method: str = "aw11",
) -> torch.Tensor:
    """Geodesic distance from ``sources`` by the heat method (Crane et al. 2013), ``(V,)`` for
    one query or ``(V, Q)`` for a list of ``Q`` queries; see :class:`HeatGeodesicSolver`, which
    reuses its factorizations across calls."""
    solver = HeatGeodesicSolver(
        verts, faces, t, lam, poisson_lam=poisson_lam, backend=backend, method=method
    )
    solver._one_query = True
    return solver.distance(sources)

"""Geometry losses and energies on batches of polygon meshes, built on the polygon Laplacians.

Every loss takes a :class:`~torch_polylap.batch.PolygonMeshes` or a single ``(verts, faces)``
pair, computes one value per mesh and reduces over the batch:

* ``reduction="mean"`` (default): the mean of the per-mesh values, so every mesh counts the
  same whatever its size (pytorch3d's convention);
* ``"sum"``: their sum; ``"none"``: the ``(B,)`` per-mesh values.

Per-vertex quantities are averaged within a mesh (weight ``1 / V_i``), per-edge ones over the
mesh's interior edges, energies are summed within a mesh.  All operators are assembled once on
the packed batch (block diagonal) and multiplied as ``L @ X`` (a sparse operator), so gradients
cost O(nnz).  Each function has a thin ``nn.Module`` wrapper holding its options.

Every loss that builds ``L`` takes ``method=``: ``"aw11"`` (default, Alexa and Wardetzky 2011),
``"plms"`` (Bunge et al. 2020; ``lam`` unused), ``"degoes"`` (de Goes et al. 2020) or
``"diamond"`` (Bunge et al. 2021; ``lam`` unused; not :func:`bending_energy`, which needs a
diagonal mass), as in :func:`torch_polylap.laplacian`; :func:`laplacian_smoothing`, whose
``method`` is pytorch3d's ``"uniform"`` / ``"cot"`` switch, accepts these names there as well.
"""

from __future__ import annotations

from typing import Literal

import torch
from torch import nn

from .batch import PolygonMeshes, per_mesh_mean, per_mesh_sum
from .checks import Lam, check_verts, inverse_or_zero
from .faces import FacesLike
from .kernels import METHODS, check_method
from .measures import face_planarity_energy, vector_area
from .operators import strong_laplacian

__all__ = [
    "laplacian_smoothing",
    "mean_curvature_smoothing",
    "dirichlet_energy",
    "planarity_loss",
    "bending_energy",
    "normal_consistency",
    "LaplacianSmoothingLoss",
    "MeanCurvatureSmoothingLoss",
    "DirichletEnergy",
    "PlanarityLoss",
    "BendingEnergy",
    "NormalConsistencyLoss",
]

MeshesLike = PolygonMeshes | tuple[torch.Tensor, FacesLike]
Reduction = Literal["mean", "sum", "none"]
_REDUCTIONS = ("mean", "sum", "none")


def _as_meshes(meshes: MeshesLike) -> PolygonMeshes:
    if isinstance(meshes, PolygonMeshes):
        return meshes
    if (
        isinstance(meshes, (tuple, list))
        and len(meshes) == 2
        and isinstance(meshes[0], torch.Tensor)
        and meshes[0].dim() == 2
    ):
        return PolygonMeshes([meshes[0]], [meshes[1]])
    raise TypeError(
        f"expected a PolygonMeshes or a (verts (V, 3), faces) pair, got {type(meshes).__name__}."
    )


def _reduce(per_mesh: torch.Tensor, reduction: str) -> torch.Tensor:
    if reduction == "mean":
        return per_mesh.mean()
    if reduction == "sum":
        return per_mesh.sum()
    if reduction == "none":
        return per_mesh
    raise ValueError(f"reduction must be one of {_REDUCTIONS}, got {reduction!r}.")


def _check_reduction(reduction: str) -> None:
    if reduction not in _REDUCTIONS:
        raise ValueError(f"reduction must be one of {_REDUCTIONS}, got {reduction!r}.")


def _vertex_norm(v: torch.Tensor) -> torch.Tensor:
    """``(V,)`` Euclidean row norms; the gradient at a zero row is 0 (torch's subgradient)."""
    return torch.linalg.vector_norm(v, dim=1)


SmoothingMethod = Literal["uniform", "polygon", "cot", "aw11", "plms", "degoes", "diamond"]


def laplacian_smoothing(
    meshes: MeshesLike,
    method: SmoothingMethod = "uniform",
    lam: Lam = 1.0,
    *,
    frozen_weights: bool = False,
    reduction: Reduction = "mean",
) -> torch.Tensor:
    """Laplacian smoothing loss, a drop-in for pytorch3d's ``mesh_laplacian_smoothing``.

    Per vertex ``p`` of mesh ``i`` the loss is the length of a normalized Laplacian of the
    coordinates ``X``, averaged over the mesh (weight ``1 / V_i``), then reduced over the batch:

    * ``"uniform"``: ``|mean_{q ~ p} X_q - X_p|`` over the neighbours ``q`` along polygon edges
      (face diagonals are not edges), pytorch3d's ``"uniform"``;
    * ``"polygon"`` (alias ``"cot"``): ``|(L X)_p| / L_pp`` with the AW11 Laplacian ``L``
      (AW11 eq. 3, 9; stabilizer weight ``lam``). Since ``L 1 = 0``, ``L_pp = sum_{q != p}
      -L_pq``, so this is ``|sum_q w_pq X_q / sum_q w_pq - X_p|`` with ``w_pq = -L_pq``: the
      weighted neighbour mean of pytorch3d's ``"cot"`` with AW11 weights in the place of
      cotangents (on triangles ``L`` is the cotan Laplacian, AW11 Theorem 2, and the two agree
      wherever the cotan row sums are positive). ``L_pp > 0`` for every vertex of a face;
    * ``"aw11"`` (same as ``"polygon"``), ``"plms"``, ``"degoes"``: ``|(L X)_p| / L_pp`` with
      ``L = laplacian(..., method=method)`` (``lam`` unused by ``"plms"``).

    Args:
        meshes: a :class:`PolygonMeshes` or ``(verts, faces)``.
        lam: stabilizer weight of ``L`` (``"polygon"``, ``"aw11"``, ``"degoes"``).
        frozen_weights: compute ``L`` under ``no_grad`` (pytorch3d's behaviour: the gradient
            moves vertices towards the weighted mean with fixed weights) instead of
            differentiating the weights too ("live" weights, the exact gradient of the loss).
        reduction: ``"mean"``, ``"sum"`` or ``"none"`` (``(B,)``).

    Isolated vertices contribute 0 (pytorch3d counts ``|X_p|`` for them).

    Examples:
        >>> import torch
        >>> from torch_polylap.losses import laplacian_smoothing
        >>> verts = torch.tensor([[0.0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [2, 0.5, 0.5]],
        ...                      dtype=torch.float64, requires_grad=True)
        >>> loss = laplacian_smoothing((verts, [[0, 1, 2, 3], [1, 4, 2]]), method="polygon")
        >>> loss.backward()
        >>> loss.dim(), verts.grad.shape
        (0, torch.Size([5, 3]))
    """
    _check_reduction(reduction)
    m = _as_meshes(meshes)
    X = m.verts_packed()
    if method == "uniform":
        edges = m.edges_packed()
        p, q = edges[:, 0], edges[:, 1]
        deg = torch.bincount(edges.reshape(-1), minlength=X.shape[0]).to(X.dtype)
        nbr = X.new_zeros(X.shape).index_add(0, p, X[q]).index_add(0, q, X[p])
        inv = inverse_or_zero(deg)[:, None]
        per_vertex = _vertex_norm(nbr * inv - X * (inv > 0))
    elif method in ("polygon", "cot") or method in METHODS:
        operator = "aw11" if method in ("polygon", "cot") else method
        with torch.set_grad_enabled(torch.is_grad_enabled() and not frozen_weights):
            L, _ = m.laplacian(lam, method=operator)
        per_vertex = _vertex_norm(L @ X) * inverse_or_zero(L.diagonal())
    else:
        raise ValueError(
            "method must be 'uniform', 'polygon' ('cot') or a Laplacian of "
            f"{', '.join(map(repr, METHODS))}, got {method!r}."
        )
    per_mesh = per_mesh_mean(per_vertex, m.verts_packed_to_mesh_idx(), len(m))
    return _reduce(per_mesh, reduction)


def mean_curvature_smoothing(
    meshes: MeshesLike, lam: Lam = 1.0, reduction: Reduction = "mean", *, method: str = "aw11"
) -> torch.Tensor:
    """Mean of ``|H_p|``, ``H = M0^{-1} L X`` the mean curvature normal (AW11 sec. 3.2), per mesh.

    ``|H_p| -> 2 |H_mean|`` under refinement (2 on the unit sphere), so unlike
    :func:`laplacian_smoothing` the value has units of curvature and is not scale invariant.
    Isolated vertices contribute 0. ``method``: the Laplacian (``"aw11"``, ``"plms"``,
    ``"degoes"``).
    """
    _check_reduction(reduction)
    m = _as_meshes(meshes)
    X = m.verts_packed()
    L, M0 = m.laplacian(lam, method=check_method(method))
    H = strong_laplacian(L, M0, X)
    per_mesh = per_mesh_mean(_vertex_norm(H), m.verts_packed_to_mesh_idx(), len(m))
    return _reduce(per_mesh, reduction)


def _packed_signal(m: PolygonMeshes, signal: torch.Tensor, name: str) -> torch.Tensor:
    total = m.verts_packed().shape[0]
    if not isinstance(signal, torch.Tensor) or signal.dim() not in (1, 2):
        raise ValueError(f"{name} must be a tensor of shape ({total},) or ({total}, C).")
    if signal.shape[0] != total:
        raise ValueError(
            f"{name} has {signal.shape[0]} rows but the batch has {total} packed vertices; "
            "give one row per vertex of verts_packed()."
        )
    return signal if signal.dim() == 2 else signal[:, None]


def dirichlet_energy(
    meshes: MeshesLike,
    signal: torch.Tensor,
    lam: Lam = 1.0,
    reduction: Reduction = "mean",
    *,
    method: str = "aw11",
) -> torch.Tensor:
    """Dirichlet energy ``1/2 f^T L f`` of a vertex signal, per mesh (AW11 eq. 3: ``L = d^T M1 d``).

    Args:
        signal: ``(sum V_i,)`` or ``(sum V_i, C)`` packed per-vertex values; channels are summed.
        method: the Laplacian (``"aw11"``, ``"plms"``, ``"degoes"``).

    Differentiable in the signal and the vertex positions.
    """
    _check_reduction(reduction)
    m = _as_meshes(meshes)
    f = _packed_signal(m, signal, "signal")
    L, _ = m.laplacian(lam, method=check_method(method))
    f = f.to(L.dtype)
    per_vertex = 0.5 * (f * (L @ f)).sum(1)
    per_mesh = per_mesh_sum(per_vertex, m.verts_packed_to_mesh_idx(), len(m))
    return _reduce(per_mesh, reduction)


def bending_energy(
    meshes: MeshesLike,
    u: torch.Tensor | None = None,
    lam: Lam = 1.0,
    reduction: Reduction = "mean",
    *,
    method: str = "aw11",
) -> torch.Tensor:
    """Bending energy ``1/2 u^T L^T M0^{-1} L u = 1/2 sum_p |(L u)_p|^2 / m_p`` per mesh.

    With ``u`` the coordinates (default) this is ``1/2 sum_p m_p |H_p|^2``, a discrete Willmore
    energy (``H = M0^{-1} L X``, AW11 sec. 3.2). Isolated vertices contribute 0.

    Args:
        u: ``(sum V_i,)`` or ``(sum V_i, C)`` packed per-vertex values; defaults to
            ``verts_packed()``.
        method: the Laplacian (``"aw11"``, ``"plms"``, ``"degoes"``).
    """
    _check_reduction(reduction)
    m = _as_meshes(meshes)
    f = m.verts_packed() if u is None else _packed_signal(m, u, "u")
    L, M0 = m.laplacian(lam, method=check_method(method, diagonal_mass="bending_energy"))
    Lu = L @ f.to(L.dtype)
    per_vertex = 0.5 * (Lu * Lu).sum(1) * inverse_or_zero(M0.diagonal())
    per_mesh = per_mesh_sum(per_vertex, m.verts_packed_to_mesh_idx(), len(m))
    return _reduce(per_mesh, reduction)


def planarity_loss(
    meshes: MeshesLike, lam: Lam = 2.0, reduction: Reduction = "mean"
) -> torch.Tensor:
    """Planarity energy ``E_plan = 1/2 sum_c X_c^T L_plan X_c`` per mesh (AW11 sec. 5.3).

    Per face ``lam / 2 |Pi E|_F^2`` with ``E`` the ``k x 3`` edge matrix and ``Pi`` the projector
    onto the complement of the maximal projection's edge space: zero exactly for planar faces
    (triangles always). Evaluated face by face, without assembling ``L_plan``.
    """
    _check_reduction(reduction)
    m = _as_meshes(meshes)
    # refused like the losses that assemble L: a NaN would otherwise become a NaN loss
    verts = check_verts(m.verts_packed(), "verts_packed()")
    per_face = face_planarity_energy(verts, m.topology(), lam, validate=False)
    per_mesh = per_mesh_sum(per_face, m.faces_packed_to_mesh_idx(), len(m))
    return _reduce(per_mesh, reduction)


def normal_consistency(meshes: MeshesLike, reduction: Reduction = "mean") -> torch.Tensor:
    """Mean of ``1 - n_f . n_g`` over the interior edges of each mesh, faces ``f, g`` across it.

    The polygon analogue of pytorch3d's ``mesh_normal_consistency``: ``n_f = a_f / |a_f|`` is
    the unit normal of the maximal projection (vector area, AW11 Lemma 1, eq. 8), well defined
    for non-planar faces. A mesh without interior edges contributes 0.

    The normals' signs come from the faces' orientation, so every mesh must be consistently
    oriented: a flipped neighbour would read as a full fold (``n_f . n_g = -1``). A misoriented
    or non-orientable mesh raises a ValueError naming the mesh and its first misoriented edges
    (repair: ``torch_polylap.repair.orient_faces``). Edges used by 3+ faces (non-manifold,
    e.g. a fin) have no two sides: they contribute nothing and are not counted in the mean,
    like boundary edges (pytorch3d instead averages over every pair of faces there); they are
    listed in ``meshes.topology_reports()``, and the topology warns about them once.

    Raises:
        ValueError: a mesh whose faces are not consistently oriented, or a bad ``reduction``.
    """
    _check_reduction(reduction)
    m = _as_meshes(meshes)
    m.require_oriented("normal_consistency")
    X = m.verts_packed()
    a = vector_area(X, m.topology())
    n = a / torch.linalg.vector_norm(a, dim=1, keepdim=True).clamp_min(torch.finfo(X.dtype).tiny)
    f0, f1 = m.interior_edge_faces()
    per_edge = 1.0 - (n[f0] * n[f1]).sum(1)
    per_mesh = per_mesh_mean(per_edge, m.faces_packed_to_mesh_idx()[f0], len(m))
    return _reduce(per_mesh, reduction)


class LaplacianSmoothingLoss(nn.Module):
    """``nn.Module`` for :func:`laplacian_smoothing`; ``forward(meshes)``."""

    def __init__(
        self,
        method: SmoothingMethod = "uniform",
        lam: float = 1.0,
        *,
        frozen_weights: bool = False,
        reduction: Reduction = "mean",
    ) -> None:
        super().__init__()
        _check_reduction(reduction)
        self.method, self.lam, self.frozen_weights, self.reduction = (
            method,
            lam,
            frozen_weights,
            reduction,
        )

    def forward(self, meshes: MeshesLike) -> torch.Tensor:
        return laplacian_smoothing(
            meshes,
            self.method,
            self.lam,
            frozen_weights=self.frozen_weights,
            reduction=self.reduction,
        )

    def extra_repr(self) -> str:
        return (
            f"method={self.method!r}, lam={self.lam}, frozen_weights={self.frozen_weights}, "
            f"reduction={self.reduction!r}"
        )


class _LamLoss(nn.Module):
    def __init__(
        self, lam: float = 1.0, reduction: Reduction = "mean", *, method: str = "aw11"
    ) -> None:
        super().__init__()
        _check_reduction(reduction)
        self.lam, self.reduction, self.method = lam, reduction, check_method(method)

    def extra_repr(self) -> str:
        return f"lam={self.lam}, reduction={self.reduction!r}, method={self.method!r}"


class MeanCurvatureSmoothingLoss(_LamLoss):
    """``nn.Module`` for :func:`mean_curvature_smoothing`; ``forward(meshes)``."""

    def forward(self, meshes: MeshesLike) -> torch.Tensor:
        return mean_curvature_smoothing(meshes, self.lam, self.reduction, method=self.method)


class DirichletEnergy(_LamLoss):
    """``nn.Module`` for :func:`dirichlet_energy`; ``forward(meshes, signal)``."""

    def forward(self, meshes: MeshesLike, signal: torch.Tensor) -> torch.Tensor:
        return dirichlet_energy(meshes, signal, self.lam, self.reduction, method=self.method)


class BendingEnergy(_LamLoss):
    """``nn.Module`` for :func:`bending_energy`; ``forward(meshes, u=None)``."""

    def forward(self, meshes: MeshesLike, u: torch.Tensor | None = None) -> torch.Tensor:
        return bending_energy(meshes, u, self.lam, self.reduction, method=self.method)


class PlanarityLoss(_LamLoss):
    """``nn.Module`` for :func:`planarity_loss` (default ``lam = 2``); ``forward(meshes)``.

    The planarity energy is AW11's stabilizer (sec. 5.3) and has no other method.
    """

    def __init__(self, lam: float = 2.0, reduction: Reduction = "mean") -> None:
        super().__init__(lam, reduction)

    def extra_repr(self) -> str:
        return f"lam={self.lam}, reduction={self.reduction!r}"

    def forward(self, meshes: MeshesLike) -> torch.Tensor:
        return planarity_loss(meshes, self.lam, self.reduction)


class NormalConsistencyLoss(nn.Module):
    """``nn.Module`` for :func:`normal_consistency`; ``forward(meshes)``."""

    def __init__(self, reduction: Reduction = "mean") -> None:
        super().__init__()
        _check_reduction(reduction)
        self.reduction = reduction

    def forward(self, meshes: MeshesLike) -> torch.Tensor:
        return normal_consistency(meshes, self.reduction)

    def extra_repr(self) -> str:
        return f"reduction={self.reduction!r}"

"""The Alexa-Wardetzky Laplacian ``L``, the lumped mass ``M0`` and their relatives.

For a face with ``k`` corners (AW11 sec. 3.3; ``docs/math/aw11.md``):

    L_f = d^T M_f d = G G^T / |f| + lambda d^T Pi d                 (AW11 eq. 3 and 9)

with ``G`` the rows ``g_i = (x_{i+1} - x_{i-1}) / 2`` and ``Pi`` the projector onto the kernel of
the maximal projection's edge matrix.  ``L = sum_f P_f^T L_f P_f`` is symmetric positive
semi-definite (the paper's sign; libigl's ``cotmatrix`` is ``-L`` on triangles), and ``M0`` is
diagonal with ``m_p = sum_{f ni p} |f| / k_f`` (AW11 eq. 10).

Assembly only evaluates the ``k (k - 1) / 2`` off-diagonal entries of each block; the diagonal
follows from ``L_f 1 = 0`` (``d 1 = 0``), which holds exactly and saves a third of the work.
All entries are closed-form elementwise expressions over the faces of one degree
(:mod:`torch_polylap.kernels`), scattered onto the pattern cached in
:class:`~torch_polylap.topology.Topology` by the one assembly (:mod:`torch_polylap.assembly`).
This module orchestrates: it checks the arguments, takes the topology's device view once and
wraps the values as :class:`~torch_polylap.sparse.SparseOperator`. Face measures live in
:mod:`torch_polylap.measures`, the paper's DEC factors in :mod:`torch_polylap.dec`.
"""

from __future__ import annotations

import torch
from torch import nn

from ._typing import MeshFaces
from .assembly import (
    BAD_INPUT,
    FLOAT32_INACCURATE,
    FLOAT32_STRETCH_LIMIT,
    FlaggedAssembly,
    assemble,
    assemble_flagged,
    warn_float32_products,
)
from .assembly.diamond import diamond_laplacian
from .assembly.traced import traced_laplacian
from .checks import Lam, check_lam, check_lam_tensor_shape, check_verts, inverse_or_zero
from .kernels import block_kernel, check_method
from .linalg import solve
from .sparse import SparseOperator, as_operator, diag
from .sparse.operator import operator_on
from .topology import Topology, TopologyView, topology_of
from .tracing import functional, require, tracing

__all__ = [
    "laplacian",
    "PolygonLaplacian",
    "planarity_laplacian",
    "strong_laplacian",
    "mean_curvature_normal",
]


def _checked_lam(lam: Lam, *, validate: bool = True) -> Lam:
    """``lam`` checked finite and >= 0; a tensor only with ``validate`` (reading it syncs;
    traced or vmapped, the check of its value is an in-graph assertion instead)."""
    if isinstance(lam, torch.Tensor) and functional():
        if validate:
            check_lam_tensor_shape(lam)
            require(torch.isfinite(lam) & (lam >= 0), _BAD_LAM)
        return lam
    return check_lam(lam) if validate or not isinstance(lam, torch.Tensor) else lam


_BAD_LAM = "torch_polylap: lam must be a finite number >= 0."


def _operator(view: TopologyView, values: torch.Tensor) -> SparseOperator:
    """The symmetric ``V x V`` operator with ``values`` on the view's cached pattern."""
    return operator_on(view.pattern, values, symmetric=True)


def _mass(view: TopologyView, masses: torch.Tensor) -> SparseOperator:
    """The diagonal lumped mass matrix ``M0`` with ``masses`` ``(V,)`` (or ``(B, V)``) on the
    view's cached diagonal pattern."""
    return operator_on(view.diagonal, masses, symmetric=True)


def laplacian(
    verts: torch.Tensor,
    faces: MeshFaces,
    lam: Lam = 1.0,
    *,
    validate: bool = True,
    method: str = "aw11",
) -> tuple[torch.Tensor, torch.Tensor]:
    """The weak Laplacian ``L`` and lumped mass ``M0`` of a polygon mesh (AW11 eq. 3, 9, 10).

    Args:
        verts: ``(V, 3)`` vertex positions, float32 or float64, any device. ``L`` and ``M0``
            follow its dtype and device, and their values are differentiable functions of it.
            ``(B, V, 3)``: ``B`` meshes of one connectivity (a fixed-topology batch); ``L`` and
            ``M0`` are then ``(B, V, V)`` batches of operators on one pattern.
        faces: ``(F, k)`` indices, a list of index lists of mixed degree, a
            :class:`~torch_polylap.PolygonFaces`, or a prebuilt
            :class:`~torch_polylap.topology.Topology` (cached on tensors/PolygonFaces).
        lam: weight ``lambda > 0`` of the stabilizer ``lambda d^T Pi d`` (AW11 eq. 9 with
            ``U = lambda Id``);
            a float or a 0-dim tensor (which may require grad). Default 1 (the paper finds
            ``1 <= lambda <= 3`` comparable). Triangles do not depend on it (Theorem 2).
        validate: check the input and the result (one device sync): finite coordinates, no
            zero-area face, finite ``L`` and masses the dtype represents; for float32, faces
            whose blocks float32 would get wrong by more than 1e-2 (thin or nearly degenerate
            ones) are evaluated in float64. With ``False`` none of this: a zero-area face gives
            huge but finite entries instead of an error. Under torch.compile the checks are an
            in-graph assertion and there is no float64 re-evaluation.
        method: ``"aw11"`` (default, this docstring), ``"plms"`` (Bunge et al. 2020, "Polygon
            Laplacian Made Simple": a virtual vertex per face, ``lam`` ignored), ``"degoes"``
            (de Goes et al. 2020, with ``lam`` their ``beta``) or ``"diamond"`` (Bunge, Botsch
            and Alexa 2021, ``lam`` ignored; :mod:`torch_polylap.kernels.diamond`); see
            :mod:`torch_polylap.kernels`. All share the topology, sign and dtype/device rules;
            the first three the pattern. ``"diamond"`` has a wider pattern and a mass ``M0``
            that is **not diagonal** (the one its published errors need): ``M0^{-1}`` is a
            solve, and callers that need lumped masses refuse the method.

    Returns:
        ``L``: ``(V, V)`` :class:`~torch_polylap.sparse.SparseOperator`, symmetric positive
        semi-definite, rows sum to zero, kernel the constants on each connected component.
        ``M0``: ``(V, V)`` diagonal :class:`~torch_polylap.sparse.SparseOperator`.  Both are torch
        tensors whose algebra keeps O(nnz) gradients: ``L @ X``, ``M0 + t * L``, ``L.T``,
        ``M0.diagonal()``, the value array ``tp.sparse.sparse_values(L)`` (see
        :mod:`torch_polylap.sparse`).

    Examples:
        A unit square: ``L`` is symmetric with zero row sums, ``M0`` shares the area evenly.

        >>> import torch, torch_polylap as tp
        >>> verts = torch.tensor([[0.0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]]).double()
        >>> L, M0 = tp.laplacian(verts, [[0, 1, 2, 3]])
        >>> L.to_dense().sum(1).abs().max() < 1e-15, M0.diagonal().sum().item()
        (tensor(True), 1.0)

    Raises:
        ValueError: bad connectivity (see :func:`~torch_polylap.topology.build_topology`),
            non-finite coordinates or zero-area faces, naming the vertex or face.
    """
    lam = _checked_lam(lam, validate=validate)
    if check_method(method) == "diamond":
        return _diamond(verts, faces, validate=validate)
    if isinstance(verts, torch.Tensor) and verts.dim() == 3:
        return _laplacian_batch(verts, faces, lam, validate=validate, method=method)
    verts = check_verts(verts, finite=False)
    if tracing() and isinstance(faces, torch.Tensor) and faces.dim() == 2:
        # one graph for every mesh of this face degree (see assembly.traced)
        return traced_laplacian(verts, faces, block_kernel(method, lam), validate=validate)
    topo = topology_of(faces, verts)
    view = topo.on(verts.device)
    values, masses = assemble(
        verts, view, topo, block_kernel(method, lam), want_mass=True, validate=validate
    )
    assert masses is not None
    return _operator(view, values), _mass(view, masses)


def _diamond(
    verts: torch.Tensor, faces: MeshFaces, *, validate: bool
) -> tuple[torch.Tensor, torch.Tensor]:
    """``L``, ``M0`` of ``method="diamond"`` (one mesh or a fixed-topology batch), both on the
    Diamond pattern; ``M0`` is its non-diagonal mass (see :mod:`torch_polylap.kernels.diamond`)."""
    if isinstance(verts, torch.Tensor) and verts.dim() == 3:
        if verts.shape[-1] != 3:
            raise ValueError(
                f"verts must have shape (V, 3) or (B, V, 3), got {tuple(verts.shape)}."
            )
        first = check_verts(verts[0], finite=False)
        verts = verts.to(first.dtype)
    else:
        verts = check_verts(verts, finite=False)
    topo = topology_of(faces, verts)
    pattern, L, M = diamond_laplacian(verts, topo, validate=validate)
    return operator_on(pattern, L, symmetric=True), operator_on(pattern, M, symmetric=True)


def _laplacian_batch(
    verts: torch.Tensor,
    faces: MeshFaces,
    lam: Lam,
    *,
    validate: bool,
    method: str,
) -> tuple[torch.Tensor, torch.Tensor]:
    """``L``, ``M0`` of ``B`` meshes of one connectivity, ``verts`` ``(B, V, 3)``: one
    topology, and the assembly vectorized over the batch (torch.func.vmap of the one-mesh
    assembly: each step of the kernels is one operation on all ``B`` meshes)."""
    if verts.shape[-1] != 3:
        raise ValueError(f"verts must have shape (V, 3) or (B, V, 3), got {tuple(verts.shape)}.")
    first = check_verts(verts[0], finite=False)
    if first.dtype != verts.dtype:  # half precision under autocast
        verts = verts.to(first.dtype)
    topo = topology_of(faces, verts)
    view = topo.on(verts.device)
    kernel = block_kernel(method, lam)

    def one(v: torch.Tensor) -> FlaggedAssembly:
        with torch.autocast(v.device.type, enabled=False):
            return assemble_flagged(v, view, topo, kernel, want_mass=True)

    values, masses, ok, accurate, stretch = torch.func.vmap(one)(verts)
    if validate and not require(ok, BAD_INPUT):
        # name the mesh and the element: the one-mesh assembly's message
        bad = int(torch.nonzero(~ok)[0, 0])
        try:
            assemble(verts[bad].detach(), view, topo, kernel, want_mass=False, validate=True)
        except ValueError as err:
            raise ValueError(f"mesh {bad} of the batch: {err}") from None
    if validate and not require(accurate, FLOAT32_INACCURATE):
        if functional():
            raise ValueError(FLOAT32_INACCURATE)
        # eagerly, mesh by mesh: the one-mesh assembly evaluates such faces in float64
        pairs = [
            assemble(v, view, topo, kernel, want_mass=True, validate=True, warn=False)
            for v in verts.unbind(0)
        ]
        values = torch.stack([p[0] for p in pairs])
        masses = torch.stack([p[1] for p in pairs if p[1] is not None])
    if validate and not functional() and verts.dtype == torch.float32 and stretch.numel():
        # eagerly only (a warning cannot depend on traced or transformed values): once per
        # call, naming the mesh with the thinnest face
        thinnest, mesh = stretch.max(0)
        if bool(thinnest > FLOAT32_STRETCH_LIMIT):
            warn_float32_products(verts[int(mesh)], topo, kernel, mesh=int(mesh))
    assert masses is not None
    return _operator(view, values), _mass(view, masses)


def planarity_laplacian(
    verts: torch.Tensor,
    faces: MeshFaces,
    lam: Lam = 1.0,
    *,
    validate: bool = True,
) -> torch.Tensor:
    """The planarity operator of AW11 sec. 5.3, ``sum_f P_f^T (lambda d^T Pi d) P_f``, ``(V, V)``.

    ``1/2 sum_c X_c^T Lplan X_c`` is zero exactly when every face is planar; see
    :func:`planarity_energy` for that energy without building the matrix. Triangles contribute
    nothing.
    """
    verts = check_verts(verts, finite=False)
    lam = _checked_lam(lam, validate=validate)
    topo = topology_of(faces, verts)
    view = topo.on(verts.device)
    kernel = block_kernel("aw11", lam, geometric=False)
    values, _ = assemble(verts, view, topo, kernel, want_mass=False, validate=validate)
    return _operator(view, values)


def strong_laplacian(L: torch.Tensor, M0: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
    """``M0^{-1} L u`` (AW11 eq. 3, the pointwise Laplacian), ``u`` of shape ``(V,)`` or ``(V, c)``.

    Rows of isolated vertices (zero mass) are set to zero rather than divided by zero. A
    non-diagonal ``M0`` (``method="diamond"``) is solved with (:func:`torch_polylap.solve`,
    differentiable), its isolated vertices' rows made the identity.
    """
    m = M0.diagonal()
    Lu = L @ u
    if as_operator(M0).pattern.nnz != m.numel():
        return solve(M0 + diag((m == 0).to(m.dtype)), Lu)
    inv = inverse_or_zero(m)
    return Lu * (inv if u.dim() == 1 else inv[:, None])


def mean_curvature_normal(
    verts: torch.Tensor, faces: MeshFaces, lam: Lam = 1.0, *, method: str = "aw11"
) -> torch.Tensor:
    """``(V, 3)`` mean curvature vector ``H = M0^{-1} L X`` (AW11 sec. 3.2).

    ``H`` tends to ``2 H_mean n`` (outward ``n`` for counter-clockwise faces seen from outside),
    so on the unit sphere ``|H| / 2 -> 1``. ``method`` picks the Laplacian (see
    :func:`laplacian`).
    """
    L, M0 = laplacian(verts, faces, lam, method=method)
    return strong_laplacian(L, M0, verts)


class PolygonLaplacian(nn.Module):
    """``nn.Module`` computing ``(L, M0)`` with the topology cached across calls.

    Args:
        lam: stabilizer weight (see :func:`laplacian`).
        learn_lam: make ``lam`` a learnable ``nn.Parameter``.
        validate: see :func:`laplacian`.
        method: ``"aw11"`` (default), ``"plms"``, ``"degoes"`` or ``"diamond"`` (see
            :func:`laplacian`).

    The topology is rebuilt only when the faces change (a different object, or a tensor
    modified in place), so a training loop with fixed connectivity only recomputes values.

    >>> import torch, torch_polylap as tp
    >>> lap = tp.PolygonLaplacian(lam=1.0)
    >>> square = torch.tensor([[0.0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], dtype=torch.float64)
    >>> L, M0 = lap(square, [[0, 1, 2, 3]])
    >>> L, M0 = lap(square + 1.0)  # same faces: the cached topology, new values
    >>> M0.diagonal().tolist()
    [0.25, 0.25, 0.25, 0.25]
    """

    def __init__(
        self,
        lam: float = 1.0,
        *,
        learn_lam: bool = False,
        validate: bool = True,
        method: str = "aw11",
    ) -> None:
        super().__init__()
        self.method = check_method(method)
        value = float(check_lam(lam))
        self.lam: float | nn.Parameter = nn.Parameter(torch.tensor(value)) if learn_lam else value
        self.validate = validate
        self.topology: Topology | None = None

    def _topology_for(self, faces: MeshFaces | None, verts: torch.Tensor) -> Topology:
        if faces is None:
            if self.topology is None:
                raise ValueError("PolygonLaplacian: pass faces on the first call.")
            return self.topology
        # The package's one topology cache (keyed weakly on the faces tensor): the module
        # keeps no reference to the faces, so a loop over fresh tensors pins no memory.
        self.topology = topology_of(faces, verts)
        return self.topology

    def forward(
        self, verts: torch.Tensor, faces: MeshFaces | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """``(L, M0)`` at ``verts``.

        Args:
            verts: ``(V, 3)`` vertex positions (float32 or float64, any device).
            faces: the faces in any accepted form, or ``None`` to reuse those of the previous
                call.

        Returns:
            ``L`` and ``M0``, ``(V, V)`` operators as :func:`laplacian` returns them.
        """
        if verts.dim() != 3:
            verts = check_verts(verts, finite=False)
        lam = self.lam.to(verts.dtype) if isinstance(self.lam, torch.Tensor) else self.lam
        if tracing() and verts.dim() == 2 and isinstance(faces, torch.Tensor) and faces.dim() == 2:
            # traced for any mesh of this degree: no topology kept (it is the graph's input)
            return laplacian(verts, faces, lam, validate=self.validate, method=self.method)
        topo = self._topology_for(faces, verts)
        return laplacian(verts, topo, lam, validate=self.validate, method=self.method)

    def extra_repr(self) -> str:
        lam = float(self.lam) if isinstance(self.lam, torch.Tensor) else self.lam
        return f"lam={lam}, method={self.method!r}, cached={self.topology is not None}"

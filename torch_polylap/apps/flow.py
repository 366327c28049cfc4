"""Implicit mean-curvature flow on polygon meshes (AW11 sec. 5.1, after Desbrun et al. 1999).

The flow ``dX/dt = -M0^{-1} L X`` moves every vertex along minus its mean-curvature vector.  With
this package's ``L`` (positive semi-definite, weak form) ``M0^{-1} L X`` tends to ``2 H n`` with
``H`` the mean of the principal curvatures (``docs/math/aw11.md``, "Mean curvature"), so a
round sphere of radius ``r`` shrinks as ``r(t)^2 = r(0)^2 - 4 t``.  Each step is one
backward-Euler solve

    (M0 + dt L) X_{t+1} = M0 X_t,

with ``L`` and ``M0`` rebuilt from the current positions (or, with :attr:`FlowOptions.frozen`,
taken once from the initial positions so that one factorization serves every step).  The steps
are differentiable with respect to the initial vertex positions through
:func:`torch_polylap.solve`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from .._typing import MeshFaces
from ..checks import check_index_or_mask, check_verts
from ..kernels import check_method
from ..kernels.frames import corner_terms, gather_corners
from ..linalg import solve
from ..measures import face_areas
from ..operators import laplacian, strong_laplacian
from ..shapes import schwarz_lantern  # re-exported: the lantern of AW11 Fig. 2
from ..sparse.construct import as_operator, eliminate
from ..topology import Topology, get_topology, half_edge_vertices

__all__ = [
    "mean_curvature_flow",
    "FlowOptions",
    "FlowResult",
    "scale_free_mean_curvature",
    "enclosed_volume",
    "schwarz_lantern",
]

_NORMALIZE = (None, "area", "volume")

# Mean-curvature flow develops singularities in finite time where a thin part of the surface
# pinches off (a cylinder of radius r at t = r^2 / 2): on a coarse mesh with thin ears that is
# within a few steps, and the ears turn into spikes whose curvature grows without bound. A
# healthy flow lowers the largest scale-free curvature; the guard refuses a step that raises it
# above this multiple of its initial value (or of a round sphere's, 1, if that is larger).
SINGULARITY_FACTOR = 4.0


@dataclass(frozen=True)
class FlowOptions:
    """How :func:`mean_curvature_flow` steps: the operator's updates, rescaling, what it keeps,
    and the singularity guard. The defaults take every step asked for, rebuilding ``L`` and
    ``M0`` from the current positions each time.

    Attributes:
        frozen: build ``L`` and ``M0`` once from the input positions and reuse them (and their
            sparse factorization) for every step: the linearized flow, much cheaper, close to
            the true flow for small ``dt * steps``.
        normalize: ``None``; ``"area"`` or ``"volume"``: after each step, scale the mesh about
            its area-weighted centroid so that the total area (sum of ``|f|``) or the enclosed
            volume (:func:`enclosed_volume`, closed consistently oriented meshes only) keeps its
            initial value. Cannot be combined with ``fixed`` vertices.
        trajectory: also keep every intermediate state (:attr:`FlowResult.trajectory`).
        progress: show a tqdm progress bar over the steps.
        stop_at_singularity: guard the flow against the singularities it develops in finite
            time (a thin part pinching off, faces folding over, a small closed part shrinking
            to a point). A step is refused when the largest
            :func:`scale_free_mean_curvature` over the interior vertices (all vertices of a
            mesh without interior) rises above ``singularity_factor`` times the input's, or a
            round sphere's (1) if that is larger, or when the step fails (its system singular,
            the normalized measure vanishing). The flow then stops at the last state before it
            and :attr:`FlowResult.stopped` says why. The check runs without gradient; the steps
            taken stay differentiable. Off by default: every step is taken, whatever it does.
        singularity_factor: the guard's bound, ``> 1`` (default 4, what ``polylap smooth``
            keeps).
        max_halvings: with the guard, retry a refused step with half the time step up to this
            many times in all before stopping (default 0: the ``dt`` asked for is kept;
            ``polylap smooth`` halves its default step up to 6 times). Needs ``frozen=False``,
            whose operator depends on ``dt``.
    """

    frozen: bool = False
    normalize: str | None = None
    trajectory: bool = False
    progress: bool = False
    stop_at_singularity: bool = False
    singularity_factor: float = SINGULARITY_FACTOR
    max_halvings: int = 0


@dataclass(frozen=True)
class FlowResult:
    """What :func:`mean_curvature_flow` did.

    Attributes:
        verts: ``(V, 3)`` positions after the last step taken (the input itself after zero
            steps); dtype and device follow the input.
        steps: steps taken; fewer than asked where the singularity guard stopped the flow.
        dt: the time step of the last step (smaller than asked after halvings).
        stopped: why the guard stopped the flow, e.g. ``"at step 7 the scale-free mean
            curvature at vertex 12 would reach ..."``; empty when every step ran.
        trajectory: with :attr:`FlowOptions.trajectory`, ``(steps + 1, V, 3)``: every state,
            index 0 the input, the last one ``verts``; else ``None``.
    """

    verts: torch.Tensor
    steps: int
    dt: float
    stopped: str
    trajectory: torch.Tensor | None = None


def scale_free_mean_curvature(
    verts: torch.Tensor, faces: MeshFaces, lam: float | torch.Tensor = 1.0, method: str = "aw11"
) -> torch.Tensor:
    """``(V,)`` ``|H| sqrt(A / 4 pi)``: the mean curvature ``|M0^{-1} L X| / 2`` (AW11 sec. 3.2)
    times the radius of the sphere with the mesh's total area ``A``.

    1 at every vertex of a round sphere of any radius, so that flows that shrink the mesh compare
    by shape, not size. On boundary vertices the value is a boundary term, not a curvature.

    Args:
        verts: ``(V, 3)`` positions.
        faces: any face form accepted by :func:`torch_polylap.laplacian`.
        lam: the Laplacian's ``lambda`` (AW11 eq. 9).
        method: ``"aw11"``, ``"plms"`` or ``"degoes"`` (see :func:`torch_polylap.laplacian`).
    """
    L, M0 = laplacian(verts, faces, lam, method=method)
    H = torch.linalg.vector_norm(strong_laplacian(L, M0, verts), dim=1) / 2
    return H * math.sqrt(float(face_areas(verts, faces).sum()) / (4 * math.pi))


def _require_closed_oriented(topo: Topology, what: str, hint: str = "") -> None:
    """Raise a ValueError unless ``topo`` is a closed, consistently oriented surface.

    The divergence theorem gives a volume (independent of the origin) exactly when the faces
    form a closed oriented 2-cycle: every edge is traversed as often in one direction as in
    the other. Checked in that spirit: consistent orientation across every edge of two faces
    (:meth:`Topology.require_oriented`, which also refuses a Moebius band or a Klein bottle),
    no boundary edge, and on an edge of 3+ faces (non-manifold) as many traversals each way;
    an unbalanced one is refused with :meth:`Topology.require_manifold`'s message. (A balanced
    non-manifold edge, say two closed cubes sharing an edge, encloses a well defined volume.)
    """
    suffix = f" {hint}" if hint else ""
    try:
        topo.require_oriented(what)
    except ValueError as err:
        raise ValueError(f"{err}{suffix}") from None
    n_boundary = int((topo.edge_faces == 1).sum())
    if n_boundary:
        first = topo.boundary_edges[:5].tolist()
        raise ValueError(
            f"{what} needs a closed mesh, but this one has {n_boundary} boundary edges "
            f"(first: {first}); the enclosed volume of an open surface depends on the origin."
            f"{suffix}"
        )
    if topo.report.non_manifold_edges.size:
        src, dst = half_edge_vertices(topo.faces)
        sign = np.where(src.numpy() < dst.numpy(), 1.0, -1.0)
        balance = np.bincount(topo.half_edge_edge.numpy(), weights=sign, minlength=topo.num_edges)
        if np.any(balance != 0):
            try:
                topo.require_manifold(what, vertices=False)
            except ValueError as err:
                raise ValueError(f"{err}{suffix}") from None


def enclosed_volume(verts: torch.Tensor, faces: MeshFaces) -> torch.Tensor:
    """Signed volume enclosed by a closed polygon mesh, a differentiable scalar.

    Each face is fanned from the mean of its corners ``c_f``; by the divergence theorem the
    volume is ``1/3 sum_f c_f . a_f`` with ``a_f`` the vector area (AW11 eq. 8).  Positive for
    outward-oriented faces.

    Args:
        verts: ``(V, 3)``.
        faces: any face form accepted by :func:`torch_polylap.laplacian`.

    Raises:
        ValueError: the mesh is not closed and consistently oriented (a boundary, a flipped
            face, a non-orientable component, an edge of 3+ faces not traversed equally often
            in both directions); the volume would depend on the origin. The message says
            which, and which repair to run (e.g. :func:`torch_polylap.repair.orient_faces`).

    Examples:
        The unit cube, six outward-oriented quads:

        >>> import torch
        >>> from torch_polylap.apps import enclosed_volume
        >>> verts = torch.tensor([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)],
        ...                      dtype=torch.float64)
        >>> faces = [[0, 1, 3, 2], [4, 6, 7, 5], [0, 4, 5, 1], [2, 3, 7, 6], [0, 2, 6, 4],
        ...          [1, 5, 7, 3]]
        >>> float(enclosed_volume(verts, faces))
        1.0
    """
    topo = get_topology(faces, verts.shape[0])
    _require_closed_oriented(topo, "enclosed_volume")
    return _volume(verts, topo)


def _volume(verts: torch.Tensor, topo: Topology) -> torch.Tensor:
    groups = topo.on(verts.device).groups
    verts_t = verts.t().contiguous()
    total = verts.new_zeros(())
    for grp in groups:
        x = gather_corners(verts_t, grp.corners_t)  # (3, k, F_k)
        _, _, a = corner_terms(x)  # vector area, (3, F_k)
        total = total + (x.mean(1) * a).sum() / 3.0
    return total


def _check_count(name: str, value: int) -> None:
    if not isinstance(value, int) or isinstance(value, bool) or value < 0:
        raise ValueError(f"{name} must be an integer >= 0, got {value!r}.")


def _check_args(
    verts: torch.Tensor, dt: float, steps: int, method: str, options: FlowOptions
) -> None:
    check_verts(verts)
    _check_count("steps", steps)
    dt_value = float(dt)
    if not dt_value > 0.0 or dt_value == float("inf"):
        raise ValueError(
            f"dt must be a finite time step > 0, got {dt!r}; a sensible start is "
            "0.01-1 times the squared mean edge length."
        )
    if options.normalize not in _NORMALIZE:
        raise ValueError(f"normalize must be None, 'area' or 'volume', got {options.normalize!r}.")
    check_method(method)
    _check_count("max_halvings", options.max_halvings)
    factor = options.singularity_factor
    if not float(factor) > 1.0 or math.isinf(float(factor)):
        raise ValueError(f"singularity_factor must be a finite number > 1, got {factor!r}.")
    if options.max_halvings and not options.stop_at_singularity:
        raise ValueError("max_halvings halves refused steps: it needs stop_at_singularity=True.")
    if options.max_halvings and options.frozen:
        raise ValueError(
            "max_halvings needs frozen=False: a frozen flow factors M0 + dt L once, for one dt."
        )


def _fixed_mask(fixed: torch.Tensor | None, num_verts: int, device: torch.device) -> torch.Tensor:
    mask = torch.zeros(num_verts, dtype=torch.bool, device=device)
    if fixed is None:
        return mask
    index = check_index_or_mask(fixed, num_verts, "fixed")
    return mask.index_fill(0, index.to(device), True)


class _StepSystem:
    """``M0 + dt L`` with the rows and columns of fixed vertices eliminated.

    A fixed vertex keeps its position: its row and column keep only the diagonal mass ``m_p``
    (with right-hand side ``m_p x_p``; the mass rather than 1 keeps the scale uniform), and the
    coupling ``-(dt L)_{free, fixed} X_fixed`` moves to the right-hand side.  The matrix stays
    symmetric positive definite, so :func:`solve` applies and its cached factorization is reused
    for every step when the system is built once (``frozen``).
    """

    def __init__(self, L: torch.Tensor, M0: torch.Tensor, dt: float, fixed: torch.Tensor):
        self.mass = M0.diagonal()
        # a non-diagonal mass (method="diamond") multiplies as a matrix; the fixed rows keep
        # its diagonal, which only scales their identity equations
        self.M0 = None if as_operator(M0).pattern.nnz == self.mass.numel() else M0
        self.fixed = fixed
        self.any_fixed = bool(fixed.any())
        self.A = M0 + dt * L
        if self.any_fixed:
            self.A, self.coupling = eliminate(self.A, fixed, self.mass)

    def step(self, X: torch.Tensor) -> torch.Tensor:
        rhs = self.mass[:, None] * X if self.M0 is None else self.M0 @ X
        if self.any_fixed:
            X_fixed = torch.where(self.fixed[:, None], X, torch.zeros_like(X))
            rhs = torch.where(self.fixed[:, None], rhs, rhs - self.coupling @ X_fixed)
        return solve(self.A, rhs)


def _centroid(X: torch.Tensor, topo: Topology) -> torch.Tensor:
    """Area-weighted centroid ``sum_p m_p x_p / sum_p m_p`` (lumped masses, AW11 eq. 10)."""
    areas = face_areas(X, topo)
    faces = topo.faces.to(X.device)
    share = (areas / faces.sizes.to(areas.dtype))[faces.corner_face]
    m = X.new_zeros(X.shape[0]).index_add(0, faces.indices, share)
    return (m[:, None] * X).sum(0) / m.sum()


def _measure(X: torch.Tensor, topo: Topology, normalize: str) -> torch.Tensor:
    return face_areas(X, topo).sum() if normalize == "area" else _volume(X, topo)


def mean_curvature_flow(
    verts: torch.Tensor,
    faces: MeshFaces,
    dt: float,
    steps: int,
    lam: float | torch.Tensor = 1.0,
    *,
    method: str = "aw11",
    fixed: torch.Tensor | None = None,
    options: FlowOptions | None = None,
) -> FlowResult:
    """Implicit mean-curvature flow ``(M0 + dt L) X' = M0 X`` (AW11 sec. 5.1; Desbrun et al. 1999).

    Args:
        verts: ``(V, 3)`` initial positions, float32 or float64, any device; may require grad
            (every step is differentiable, so a loss on the result reaches the initial shape).
        faces: ``(F, k)`` indices, a list of index lists, a :class:`~torch_polylap.PolygonFaces`
            or a :class:`~torch_polylap.Topology`.
        dt: time step in absolute units (time has units of length squared: a sphere of radius
            ``r`` vanishes at ``t = r^2 / 4``). Backward Euler is stable for any ``dt``; for an
            accurate flow take ``dt`` around ``0.01``-``1`` times the squared mean edge length,
            larger steps smooth faster but shrink less faithfully.
        steps: number of implicit steps, ``>= 0``.
        lam: the Laplacian's ``lambda`` (AW11 eq. 9; the paper's flow uses 2).
        method: the Laplacian, ``"aw11"`` (default), ``"plms"`` (``lam`` unused) or
            ``"degoes"`` (see :func:`torch_polylap.laplacian`).
        fixed: optional vertex indices (each once) or a ``(V,)`` bool mask, held in place, e.g.
            a boundary to fair a patch towards a minimal surface (checked by
            :func:`torch_polylap.checks.check_index_or_mask`).
        options: a :class:`FlowOptions`: a frozen operator, rescaling, the trajectory, a
            progress bar and the singularity guard; default ``FlowOptions()``.

    Returns:
        A :class:`FlowResult`: the final ``(V, 3)`` positions (dtype and device of ``verts``),
        the steps taken and the last ``dt`` (fewer steps and a smaller ``dt`` only with the
        guard), why the guard stopped, and the trajectory where asked for.

    Raises:
        ValueError: ``dt <= 0``, ``steps < 0``, an unknown ``normalize``, ``"volume"`` on a mesh
            that is not closed and consistently oriented (see :func:`enclosed_volume`; the flow
            itself runs on any mesh, non-manifold or non-orientable ones included), ``fixed``
            together with ``normalize``, ``max_halvings`` without the guard or with ``frozen``,
            a ``singularity_factor <= 1``, or bad mesh input (``fixed`` out of range, repeated,
            or a mask of the wrong length).

    Examples:
        The tube of a thin torus pinches in finite time; the guard stops the flow before:

        >>> from torch_polylap.apps import FlowOptions, mean_curvature_flow
        >>> from torch_polylap.shapes import torus
        >>> verts, faces = torus(24, 8, major=1.0, minor=0.15)
        >>> guarded = FlowOptions(stop_at_singularity=True)
        >>> result = mean_curvature_flow(verts, faces, 0.01, 20, options=guarded)
        >>> 0 < result.steps < 20 and "pinching off" in result.stopped
        True
    """
    options = options or FlowOptions()
    _check_args(verts, dt, steps, method, options)
    topo = get_topology(faces, verts.shape[0])
    flow = _Flow.start(verts, topo, lam, method, fixed, options.normalize)
    system = flow.system(verts, float(dt)) if options.frozen else None
    guard = None
    if options.stop_at_singularity:
        guard = _Guard(verts, topo, lam, method, options.singularity_factor)
    return _run(flow, verts, float(dt), steps, system, guard, options)


def _run(
    flow: _Flow,
    verts: torch.Tensor,
    dt: float,
    steps: int,
    system: _StepSystem | None,
    guard: _Guard | None,
    options: FlowOptions,
) -> FlowResult:
    """Take ``steps`` steps of ``dt`` from ``verts``, halving ``dt`` or stopping where the guard
    refuses one."""
    X, trajectory, taken, halvings_left, stopped = verts, [verts], 0, options.max_halvings, ""
    bar = None
    if options.progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=steps, desc="mean curvature flow", unit="step")
    try:
        while taken < steps:
            if guard is None:
                new = flow.step(X, system, dt)
            else:
                try:
                    new = flow.step(X, system, dt)
                    reason = guard.check(new)
                except ValueError as err:
                    reason = f"the step fails ({err}): a small closed part shrank to a point"
                if reason:
                    if halvings_left:
                        dt, halvings_left = dt / 2, halvings_left - 1
                        continue
                    stopped = f"at step {taken + 1} {reason}"
                    break
            X, taken = new, taken + 1
            if options.trajectory:
                trajectory.append(X)
            if bar is not None:
                bar.update()
    finally:  # also when interrupted: a bar left open would take the next message's line
        if bar is not None:
            bar.close()
    path = torch.stack(trajectory) if options.trajectory else None
    return FlowResult(X, taken, dt, stopped, path)


class _Flow:
    """One backward-Euler step of the flow, rescaled where ``normalize`` asks."""

    def __init__(
        self,
        topo: Topology,
        lam: float | torch.Tensor,
        method: str,
        fixed: torch.Tensor,
        normalize: str | None,
        target: torch.Tensor | None,
    ) -> None:
        self.topo, self.lam, self.method, self.fixed = topo, lam, method, fixed
        self.normalize, self.target = normalize, target

    @classmethod
    def start(
        cls,
        verts: torch.Tensor,
        topo: Topology,
        lam: float | torch.Tensor,
        method: str,
        fixed: torch.Tensor | None,
        normalize: str | None,
    ) -> _Flow:
        """The flow from ``verts``: the fixed vertices as a mask, the measure to keep."""
        if normalize == "volume":
            _require_closed_oriented(topo, "normalize='volume'", "Use normalize='area' or None.")
        fixed_mask = _fixed_mask(fixed, verts.shape[0], verts.device)
        if normalize is not None and bool(fixed_mask.any()):
            raise ValueError("`fixed` vertices cannot be kept in place while normalize rescales.")
        target = _measure(verts, topo, normalize) if normalize else None
        if target is not None and not float(target.abs()) > 0.0:
            raise ValueError(f"the initial {normalize} is zero; it cannot be kept by rescaling.")
        return cls(topo, lam, method, fixed_mask, normalize, target)

    def system(self, X: torch.Tensor, dt: float) -> _StepSystem:
        return _StepSystem(*laplacian(X, self.topo, self.lam, method=self.method), dt, self.fixed)

    def step(self, X: torch.Tensor, system: _StepSystem | None, dt: float) -> torch.Tensor:
        X = (system or self.system(X, dt)).step(X)
        if self.normalize and self.target is not None:  # (target is set exactly when normalize is)
            ratio = self.target / _measure(X, self.topo, self.normalize)
            if not float(ratio) > 0.0:
                raise ValueError(
                    f"the {self.normalize} changed sign or vanished during the flow (the mesh "
                    "collapsed); take a smaller dt or fewer steps."
                )
            scale = ratio.sqrt() if self.normalize == "area" else ratio.pow(1.0 / 3.0)
            center = _centroid(X, self.topo)
            X = center + scale * (X - center)
        return X


class _Guard:
    """Refuses states whose largest interior scale-free mean curvature exceeds the bound."""

    def __init__(
        self,
        verts: torch.Tensor,
        topo: Topology,
        lam: float | torch.Tensor,
        method: str,
        factor: float,
    ) -> None:
        self.topo, self.lam, self.method, self.factor = topo, lam, method, float(factor)
        interior = torch.ones(verts.shape[0], dtype=torch.bool, device=verts.device)
        interior[topo.boundary_vertices.to(verts.device)] = False
        if not bool(interior.any()):  # a strip of faces: its boundary values after all
            interior[:] = True
        self.interior = interior
        self.largest = max(float(self._curvature(verts).max()), 1.0)
        self.bound = self.factor * self.largest

    def _curvature(self, X: torch.Tensor) -> torch.Tensor:
        with torch.no_grad():
            h = scale_free_mean_curvature(X.detach(), self.topo, self.lam, self.method)
        return h.where(self.interior, torch.zeros_like(h))

    def check(self, X: torch.Tensor) -> str:
        """Why ``X`` is refused, or ``""``."""
        h = self._curvature(X)
        if bool(torch.isfinite(h).all()) and not float(h.max()) > self.bound:
            return ""
        v = int(torch.nan_to_num(h, nan=float("inf")).argmax())
        return (
            f"the scale-free mean curvature at vertex {v} would reach {float(h[v]):.3g}, more "
            f"than {self.factor:g} x the input's largest ({self.largest:.3g}): a thin part is "
            "pinching off or faces are folding over"
        )

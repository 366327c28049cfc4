"""Planarization (AW11 sec. 5.3): make every face planar, with fixed vertices and a closeness term.

Two optimizers, chosen by ``method=``:

``"gauss-newton"`` (default): a Levenberg-Marquardt / Gauss-Newton method on the per-face plane
residuals ``r_fi = n_f . (x_i - c_f) / diam_f`` (corner distance from the face's plane through
the corner centroid ``c_f``, over the face diameter; the quantity the stopping criterion
measures), with the unit normals ``n_f`` as unknowns next to the positions. The normals are
eliminated face by face and reset to the least-squares normals after every step (variable
projection); what remains of a ``k``-gon's residuals are ``k - 3`` plane conditions (one per
quad, three per hexagon). Each iteration is one sparse SPD solve in those conditions, not in
the vertex coordinates: the same step by the Woodbury identity, with a system of one row per
quad instead of three per vertex, fewer nonzeros and far less fill (CHOLMOD when cholespy is
installed, else SuperLU; on the CPU, the per-face work on the input's device).
It minimizes

    Phi(X) = 1/2 sum_f sum_{i in f} r_fi^2 + closeness/2 sum_i |x_i - x0_i|^2 / h^2

(``h``: the input's mean edge length), accepting a step only when ``Phi`` decreases (otherwise
the damping grows and the step is retried), so ``Phi`` never increases. The residuals vanish
exactly on meshes of planar faces, as ``E_plan`` does; as a zero-residual least-squares problem
it converges about quadratically near the solution.

``"lbfgs"``: the paper's method, quasi-Newton descent of

    E_plan(X) = 1/2 sum_c X_c^T Lplan X_c = sum_f lambda/2 |Pi_f E_f|_F^2,

with ``Lplan`` the Laplacian without its geometric part ``M~_f`` (only ``lambda d^T Pi d``): per
face the part of the edge vectors that leaves the plane of the maximal projection.
``torch.optim.LBFGS`` with a strong Wolfe line search; ``E_plan`` never increases.

Why Gauss-Newton is the default (``benchmarks/bench_planarize.py``, tol 1e-4, one thread):
L-BFGS needs hundreds to thousands of iterations on real quad meshes and stopped above the
tolerance at its old default of 500 iterations on some; Gauss-Newton reaches the tolerance in
a handful of iterations (each one factorization), faster in wall time on every mesh measured
and with a displacement of the same order. Both stop when the largest
:func:`torch_polylap.face_nonplanarity` (maximal-projection plane) is below ``tol``, and both warn
(``UserWarning``) when they stop above it.
"""

from __future__ import annotations

import math
import time
import warnings
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import scipy.sparse as sp
import torch

from .._typing import MeshFaces
from ..checks import check_index_or_mask, check_verts
from ..linalg import CholeskyFactorization, cholespy_available, spd_splu
from ..measures import face_nonplanarity, mean_edge_length, planarity_energy
from ..topology import Topology, get_topology

__all__ = ["planarize", "PlanarizeOptions", "PlanarizeResult"]


@dataclass
class PlanarizeResult:
    """Outcome of :func:`planarize`.

    Attributes:
        verts: ``(V, 3)`` planarized positions (detached, dtype/device of the input).
        nonplanarity_before, nonplanarity_after: ``(max, mean)`` of
            :func:`torch_polylap.face_nonplanarity` over all faces (corner distance from the
            maximal projection's plane over the face diameter).
        displacement: ``(max, mean)`` vertex displacement over the bounding-box diagonal.
        iterations: iterations taken: L-BFGS iterations (a multiple of ``check_every`` unless
            it stopped earlier), or Gauss-Newton linear solves (rejected steps included).
        seconds: wall-clock time of the optimization.
        converged: whether the largest non-planarity fell below ``tol``.
        energies: ``E_plan`` (with ``lam``) of the centered positions in bounding-box-diagonal
            units, at the start and after every check (L-BFGS: every ``check_every``
            iterations; Gauss-Newton: every accepted step). Non-increasing for L-BFGS without
            closeness; Gauss-Newton minimizes another objective (``objectives``).
        method: the optimizer that ran, ``"gauss-newton"`` or ``"lbfgs"``.
        objectives: the objective each method minimizes (with its closeness term), at the same
            points as ``energies``; never increases.
        message: why it stopped (``"converged"``, or what ran out and what to change).
    """

    verts: torch.Tensor
    nonplanarity_before: tuple[float, float]
    nonplanarity_after: tuple[float, float]
    displacement: tuple[float, float]
    iterations: int
    seconds: float
    converged: bool
    energies: list[float] = field(default_factory=list)
    method: str = "gauss-newton"
    objectives: list[float] = field(default_factory=list)
    message: str = "converged"


def _stats(x: torch.Tensor) -> tuple[float, float]:
    return (float(x.max()), float(x.mean())) if x.numel() else (0.0, 0.0)


# per degree group (k > 3): (k, corners (F, k), free dof of each corner coordinate (F, 3k) or -1)
_Parts = list[tuple[int, torch.Tensor, torch.Tensor]]
# what a method returns: (positions, iterations, energies, objectives, stop reason)
_Run = tuple[torch.Tensor, int, list[float], list[float], str]
# Levenberg-Marquardt damping, relative to each vertex's stiffness: start, and floor
_MU_START = 1e-6
_MU_MIN = 1e-12


def _dof_setup(topo: Topology, free_mask: torch.Tensor, n: int) -> tuple[_Parts, torch.Tensor]:
    """Per degree group (k > 3): corners and their free dofs (``3 i + c`` numbered among the free
    ones, -1 where fixed), computed once; and the ``(m,)`` free dofs themselves."""
    device = free_mask.device
    dof_map = torch.full((3 * n,), -1, dtype=torch.int64, device=device)
    free_dofs = 3 * torch.nonzero(free_mask).reshape(-1, 1) + torch.arange(3, device=device)
    free_dofs = free_dofs.reshape(-1)
    dof_map[free_dofs] = torch.arange(free_dofs.numel(), device=device)
    parts: _Parts = []
    for grp in topo.on(device).groups:
        if grp.k <= 3:
            continue  # triangles are planar: no residual
        corners = grp.corners_t.t().to(torch.int64)  # (F, k)
        dofs = dof_map[
            (3 * corners[:, :, None] + torch.arange(3, device=device)).reshape(corners.shape[0], -1)
        ]  # (F, 3k), -1 where fixed
        parts.append((grp.k, corners, dofs))
    return parts, free_dofs


def _face_fit(
    y: torch.Tensor, corners: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Least-squares planes of ``(F, k)`` faces: centered corners, diameters, eigenpairs of the
    scatter matrices (ascending)."""
    centered, diameter, scatter = _face_scatter(y, corners)
    evals, evecs = torch.linalg.eigh(scatter)
    return centered, diameter, evals, evecs


def _face_scatter(
    y: torch.Tensor, corners: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Centered corners ``(F, k, 3)``, diameters ``(F,)`` and scatter matrices ``(F, 3, 3)``."""
    x = y[corners]  # (F, k, 3)
    centered = x - x.mean(1, keepdim=True)
    diameter = torch.cdist(x, x).amax((1, 2)).clamp_min(torch.finfo(y.dtype).tiny)
    return centered, diameter, centered.transpose(1, 2) @ centered


def _plane_objective(y: torch.Tensor, parts: _Parts) -> float:
    """``1/2 sum_f sum_i (n_f . (x_i - c_f))^2 / diam_f^2`` with least-squares normals (the
    smallest eigenvalue of the scatter matrix: eigenvalues only, half the cost of eigenpairs)."""
    total = 0.0
    for _, corners, _ in parts:
        _, diameter, scatter = _face_scatter(y, corners)
        smallest = torch.linalg.eigvalsh(scatter)[:, 0]
        total += 0.5 * float((smallest.clamp_min(0) / diameter**2).sum())
    return total


def _plane_conditions(
    y: torch.Tensor, parts: _Parts, free_dofs: torch.Tensor, h: float
) -> tuple[sp.csr_matrix, np.ndarray, np.ndarray]:
    """The Gauss-Newton model of the plane residuals with the normals eliminated, as ``k - 3``
    conditions per ``k``-gon: ``(R, m)`` Jacobian ``C`` in the free dofs, ``(R,)`` values ``c``,
    and each free dof's stiffness for the damping.

    Per face, the residuals ``r_i = n . (x_i - c) / s`` (``s``: diameter) and the rows of their
    Jacobian in the positions, ``d r_i / d x_j = (I - 11^T / k)_ij n^T / s``, are orthogonal to
    ``1``; a rotation of the normal towards tangent ``t_a`` changes ``r`` along ``u_a = (x - c)
    t_a / sqrt(lambda_a)`` (``lambda_a``: the scatter matrix's eigenvalue of ``t_a``; the two
    ``u_a`` are orthonormal). Eliminating the normals from the linearized least-squares problem
    (a Schur complement) projects each face's residuals and Jacobian onto the complement of
    ``{1, u_1, u_2}``; ``B`` (``k x (k - 3)``) is an orthonormal basis of it, so ``C_f = B^T J_f``
    and ``c_f = B^T r_f``, with ``|c_f| = |r_f|`` (the least-squares normal makes ``r`` orthogonal
    to the ``u_a``). ``C^T C`` is the Gauss-Newton matrix in the positions and ``C^T c`` the
    gradient of ``1/2 |r|^2``.

    The stiffness is a third of the trace of a vertex's ``3 x 3`` block of ``C^T C`` before the
    elimination, ``sum_f (1 - 1/k) / (3 s_f^2)``, plus ``1 / h^2`` (``h``: the mean edge length) so
    that vertices of triangles only are damped too. Per vertex, not global: a face much smaller
    than the others has entries ``1 / s_f^2`` that a global damping would not reach, leaving the
    system numerically indefinite.
    """
    stiffness = y.new_full((y.shape[0],), 1.0 / h**2)
    rows, cols, vals, values = [], [], [], []
    first = 0
    for k, corners, dofs in parts:
        count = corners.shape[0]
        centered, s, evals, evecs = _face_fit(y, corners)
        nrm = evecs[:, :, 0]  # (F, 3)
        u = (centered @ evecs[:, :, 1:]) / evals[:, None, 1:].clamp_min(
            torch.finfo(y.dtype).tiny
        ).sqrt()  # (F, k, 2)
        spanned = torch.cat([u.new_full((count, k, 1), k**-0.5), u], 2)  # (F, k, 3)
        # a complete QR of the orthonormal (k, 3) columns: the last k - 3 columns of Q span
        # their complement (Householder: a quarter of the time of a k x k eigh)
        basis = torch.linalg.qr(spanned, mode="complete")[0][:, :, 3:]
        r = (centered @ nrm[:, :, None]) / s[:, None, None]  # (F, k, 1)
        values.append((basis.transpose(1, 2) @ r).reshape(-1))
        jac = basis.transpose(1, 2)[:, :, :, None] * (nrm / s[:, None])[:, None, None, :]
        jac = jac.reshape(count, k - 3, 3 * k)  # (F, k - 3, 3k): columns as dofs
        row = first + torch.arange(count * (k - 3), device=y.device).reshape(count, k - 3, 1)
        col = dofs[:, None, :].expand(-1, k - 3, -1)
        keep = col >= 0
        rows.append(row.expand(-1, -1, 3 * k)[keep])
        cols.append(col[keep])
        vals.append(jac[keep])
        first += count * (k - 3)
        stiffness.index_add_(
            0, corners.reshape(-1), ((1 - 1 / k) / (3 * s**2)).repeat_interleave(k)
        )
    C = sp.csr_matrix(
        (
            torch.cat(vals).cpu().numpy(),
            (torch.cat(rows).cpu().numpy(), torch.cat(cols).cpu().numpy()),
        ),
        shape=(first, free_dofs.numel()),
    )
    stiffness = stiffness.repeat_interleave(3)[free_dofs]
    return C, torch.cat(values).cpu().numpy(), stiffness.cpu().numpy()


def _damped_step(C: sp.csr_matrix, c: np.ndarray, g0: np.ndarray, d: np.ndarray) -> np.ndarray:
    """The Levenberg-Marquardt step ``dx = -(C^T C + D)^-1 (C^T c + g0)`` (``D = diag(d) > 0``)
    through the ``R x R`` system of the plane conditions, ``G = I + C D^-1 C^T``:

        dx = -D^-1 (g0 + C^T G^-1 (c - C D^-1 g0))

    (the Woodbury identity). Equal to the solve in the positions, but ``G`` has one row per
    condition (one per quad, three per hexagon) instead of three per vertex, fewer nonzeros and
    far less fill in its Cholesky factor. ``G >= I`` is positive definite however rank deficient
    ``C`` is; ``D^-1 g0`` (the closeness pull, ``g0 = w (x - x0)`` with ``d >= w``) stays bounded.
    """
    w = g0 / d
    scaled = C @ sp.diags(1.0 / np.sqrt(d))
    G = (scaled @ scaled.T + sp.identity(C.shape[0], format="csr")).tocsc()
    rhs = c - C @ w
    if cholespy_available():
        z = CholeskyFactorization(G, check=False).solve(torch.from_numpy(rhs)[:, None])[:, 0]
        z_np = z.numpy()
    else:
        z_np = spd_splu(G).solve(rhs)
        if not np.isfinite(z_np).all():
            raise ValueError("non-finite Gauss-Newton step")
    return -w - (C.T @ z_np) / d


METHODS = ("gauss-newton", "lbfgs")
DEFAULT_MAX_ITER = {"gauss-newton": 100, "lbfgs": 500}


@dataclass(frozen=True)
class PlanarizeOptions:
    """The knobs of :func:`planarize` beyond the tolerance and the iteration limit.

    Attributes:
        closeness: weight of ``closeness/2 sum_i |x_i - x0_i|^2 / h^2`` (``h``: mean edge length;
            for ``"lbfgs"`` ``closeness * lam/2 sum_i |y_i - y0_i|^2`` in bounding-box units,
            comparable to ``E_plan``). Default 0: nothing pulls towards the input but the
            damping of the steps, which already keeps the displacement small. A positive weight
            trades planarity for closeness: the residual non-planarity at the optimum grows
            about like ``closeness`` times the displacement in edge lengths, so with ``tol =
            1e-4`` weights above about ``1e-5`` can stop above ``tol`` (with a warning).
        time_limit: optional wall-clock budget in seconds, checked after every iteration.
        history_size: L-BFGS memory (``"lbfgs"`` only).
        check_every: L-BFGS iterations between two checks of the stopping criterion.
        progress: show a tqdm progress bar with the current largest non-planarity.
        warn: issue a ``UserWarning`` when it stops above ``tol``.
    """

    closeness: float = 0.0
    time_limit: float | None = None
    history_size: int = 20
    check_every: int = 5
    progress: bool = False
    warn: bool = True


@dataclass
class _Problem:
    """What both optimizers need: the centered, scaled start ``y0`` (bounding-box units), the
    free vertices, the method and its stopping rule, and the progress bar."""

    y0: torch.Tensor
    topo: Topology
    free: torch.Tensor
    free_mask: torch.Tensor
    method: str
    lam: float
    tol: float
    max_iter: int
    h: float  # the mean edge length of y0
    worst: float  # the largest non-planarity of the input
    options: PlanarizeOptions
    bar: Any = None  # a tqdm bar, or None
    deadline: float | None = None

    def stop(self, iterations: int) -> str:
        """Why to stop before the next iteration (``"max_iter"``, ``"time"``), or ``""``."""
        if iterations >= self.max_iter:
            return "max_iter"
        if self.deadline is not None and time.perf_counter() > self.deadline:
            return "time"
        return ""

    def report(self, done: int, worst: float) -> None:
        """Advance the progress bar by ``done`` iterations, showing ``worst``."""
        if self.bar is not None:
            self.bar.update(done)
            self.bar.set_postfix(max_nonplanarity=f"{worst:.2e}")


def planarize(
    verts: torch.Tensor,
    faces: MeshFaces,
    lam: float = 2.0,
    tol: float = 1e-4,
    max_iter: int | None = None,
    fixed: torch.Tensor | list[int] | None = None,
    *,
    method: str = "gauss-newton",
    options: PlanarizeOptions | None = None,
) -> PlanarizeResult:
    """Make every face planar (AW11 sec. 5.3); see the module docstring for the two methods.

    Args:
        verts: ``(V, 3)`` positions, float32 or float64.
        faces: polygon faces (triangles are planar and contribute nothing).
        lam: stabilizer weight ``lambda`` of the planarity operator (paper: 2); the objective of
            ``"lbfgs"``, and the ``energies`` reported by both.
        tol: stop once the largest face non-planarity (distance over diameter) is below it.
        max_iter: iteration limit; default 100 Gauss-Newton solves or 500 L-BFGS iterations.
        fixed: optional vertex indices (each once) or a ``(V,)`` bool mask of vertices that do
            not move; they keep their exact input values.
        method: ``"gauss-newton"`` (default) or ``"lbfgs"`` (the paper's quasi-Newton descent).
        options: a :class:`PlanarizeOptions`: a closeness term, a time limit, the L-BFGS memory
            and check interval, a progress bar, the warning; default ``PlanarizeOptions()``.

    Returns:
        :class:`PlanarizeResult`; ``converged`` is False (and a ``UserWarning`` says so, with
        the reached non-planarity, the iteration count and what to change) when the largest
        non-planarity is still at or above ``tol``.

    Positions are optimized in units of the bounding-box diagonal (centered), in float64 for
    ``"gauss-newton"``; tolerances are scale free.
    """
    options = options or PlanarizeOptions()
    max_iter = _checked_max_iter(verts, tol, max_iter, method, options)
    n = verts.shape[0]
    if n == 0:
        raise ValueError("planarize: the mesh has no vertices; nothing to planarize.")
    topo = get_topology(faces, n)
    x0 = verts.detach()
    center = (x0.amax(0) + x0.amin(0)) / 2
    scale = float(torch.linalg.vector_norm(x0.amax(0) - x0.amin(0)))
    if not scale > 0:
        raise ValueError("all vertices coincide; nothing to planarize.")
    free_mask = torch.ones(n, dtype=torch.bool, device=verts.device)
    if fixed is not None:
        free_mask[check_index_or_mask(fixed, n, "fixed").to(verts.device)] = False
    free = torch.nonzero(free_mask).reshape(-1)
    before = face_nonplanarity(x0, topo)

    work = torch.float64 if method == "gauss-newton" else verts.dtype
    y0 = (x0.to(work) - center.to(work)) / scale
    h = float(mean_edge_length(y0, topo, validate=False))
    problem = _Problem(
        y0=y0,
        topo=topo,
        free=free,
        free_mask=free_mask,
        method=method,
        lam=lam,
        tol=tol,
        max_iter=max_iter,
        h=max(h, torch.finfo(work).tiny),
        worst=float(before.max()) if before.numel() else 0.0,
        options=options,
    )
    if options.progress:
        from tqdm.auto import tqdm

        problem.bar = tqdm(total=max_iter, desc="planarize", unit="it")
    start = time.perf_counter()
    if options.time_limit is not None:
        problem.deadline = start + options.time_limit
    run = (_gauss_newton if method == "gauss-newton" else _lbfgs)(problem)
    seconds = time.perf_counter() - start
    if problem.bar is not None:
        problem.bar.close()

    with torch.no_grad():
        # add the displacement, so that vertices that did not move keep their exact input values
        moved = ((run[0][free] - y0[free]) * scale).to(x0.dtype)
        out = x0.index_put((free,), x0[free] + moved)
    return _result(out, x0, before, scale, run, seconds, problem)


def _checked_max_iter(
    verts: torch.Tensor, tol: float, max_iter: int | None, method: str, options: PlanarizeOptions
) -> int:
    """Check :func:`planarize`'s arguments; ``max_iter`` with the method's default filled in."""
    check_verts(verts)
    if method not in METHODS:
        raise ValueError(f"method must be one of {METHODS}, got {method!r}.")
    if max_iter is None:
        max_iter = DEFAULT_MAX_ITER[method]
    if tol <= 0 or max_iter < 0:
        raise ValueError(f"need tol > 0 and max_iter >= 0, got tol={tol}, max_iter={max_iter}.")
    closeness = options.closeness
    if not closeness >= 0 or not math.isfinite(closeness):
        raise ValueError(f"closeness must be finite and >= 0, got {closeness}.")
    return max_iter


def _result(
    out: torch.Tensor,
    x0: torch.Tensor,
    before: torch.Tensor,
    scale: float,
    run: _Run,
    seconds: float,
    problem: _Problem,
) -> PlanarizeResult:
    """The :class:`PlanarizeResult` of positions ``out`` reached from ``x0`` by ``run`` in
    ``seconds``, with the message (and warning) of a stop above the tolerance."""
    method = problem.method
    _, iterations, energies, objectives, reason = run
    with torch.no_grad():
        after = face_nonplanarity(out, problem.topo)
        disp = torch.linalg.vector_norm(out - x0, dim=1) / scale
    converged = bool(after.numel() == 0 or float(after.max()) < problem.tol)
    message = "converged"
    if not converged:
        hint = {
            "max_iter": "raise max_iter",
            "time": "raise time_limit",
            "stalled": "no further decrease at this precision: lower closeness, raise tol, "
            "or free some fixed vertices",
        }[reason]
        other = "lbfgs" if method == "gauss-newton" else "gauss-newton"
        message = (
            f"planarize ({method}) stopped at max non-planarity {float(after.max()):.3g} >= tol "
            f"{problem.tol:g} after {iterations} iterations and {seconds:.1f} s ({reason}); "
            f"{hint}, or try method={other!r}."
        )
        if problem.options.warn:
            warnings.warn(message, UserWarning, stacklevel=3)
    return PlanarizeResult(
        verts=out.detach(),
        nonplanarity_before=_stats(before),
        nonplanarity_after=_stats(after),
        displacement=_stats(disp),
        iterations=iterations,
        seconds=seconds,
        converged=converged,
        energies=energies,
        method=method,
        objectives=objectives,
        message=message,
    )


def _gauss_newton(problem: _Problem) -> _Run:
    y0, topo, lam, worst = problem.y0, problem.topo, problem.lam, problem.worst
    parts, free_dofs = _dof_setup(topo, problem.free_mask, y0.shape[0])
    m = free_dofs.numel()
    wc = problem.options.closeness / problem.h**2
    y = y0.clone()

    def total(z: torch.Tensor) -> float:
        return _plane_objective(z, parts) + 0.5 * wc * float((z - y0).square().sum())

    phi = total(y)
    energies = [float(planarity_energy(y, topo, lam))]
    objectives = [phi]
    mu = _MU_START
    iterations, reason = 0, "max_iter"
    model = None  # the linearization at y, kept while steps from y are rejected
    while worst >= problem.tol and m:
        reason = problem.stop(iterations) or ("stalled" if mu > 1e6 else "")
        if reason:
            break
        if model is None:
            model = _plane_conditions(y, parts, free_dofs, problem.h)
        C, c, stiffness = model
        pull = (wc * (y - y0).reshape(-1)[free_dofs]).cpu().numpy()
        try:
            # no singularity check: the damping keeps the system positive definite, and a step
            # that still comes out non-finite (ValueError) counts as one that fails to decrease
            # Phi: more damping
            delta = _damped_step(C, c, pull, wc + mu * stiffness)
            trial = y.clone()
            trial.view(-1)[free_dofs] += torch.from_numpy(delta).to(y)
            phi_trial = total(trial)
        except ValueError:
            trial, phi_trial = y, math.inf
        iterations += 1
        if phi_trial < phi:
            y, phi, model = trial, phi_trial, None
            mu = max(mu / 10, _MU_MIN)
            energies.append(float(planarity_energy(y, topo, lam)))
            objectives.append(phi)
            worst = float(face_nonplanarity(y, topo).max())
        else:
            mu *= 10
        problem.report(1, worst)
    return y, iterations, energies, objectives, reason or "max_iter"


def _lbfgs(problem: _Problem) -> _Run:
    y0, topo, free, lam, worst = problem.y0, problem.topo, problem.free, problem.lam, problem.worst
    check_every = problem.options.check_every
    param = y0[free].clone().requires_grad_(True)
    wc = problem.options.closeness * lam

    def positions(p: torch.Tensor) -> torch.Tensor:
        return y0.index_put((free,), p)

    def energy(p: torch.Tensor) -> torch.Tensor:
        e = planarity_energy(positions(p), topo, lam)
        return e + 0.5 * wc * (p - y0[free]).square().sum() if wc else e

    with torch.no_grad():
        e0 = float(planarity_energy(y0, topo, lam))
    # L-BFGS has absolute thresholds (it skips curvature pairs with y^T s <= 1e-10); rescale the
    # objective so that it is O(1) at the target tolerance (E_plan ~ non-planarity squared).
    weight = (worst / problem.tol) ** 2 / e0 if e0 > 0 else 1.0
    eps = torch.finfo(y0.dtype).eps
    optimizer = torch.optim.LBFGS(
        [param],
        lr=1.0,
        max_iter=check_every,
        max_eval=25 * check_every,  # the default (5/4 max_iter) starves short line searches
        history_size=problem.options.history_size,
        line_search_fn="strong_wolfe",
        tolerance_grad=0.0,
        tolerance_change=eps * 1e-3,
    )

    def closure() -> torch.Tensor:
        optimizer.zero_grad()
        e = weight * energy(param)
        e.backward()
        return e

    energies, objectives = [e0], [e0]
    iterations, reason = 0, "max_iter"
    while worst >= problem.tol and free.numel():
        reason = problem.stop(iterations)
        if reason:
            break
        chunk = min(check_every, problem.max_iter - iterations)
        optimizer.param_groups[0].update(max_iter=chunk, max_eval=25 * chunk)
        optimizer.step(closure)
        done = optimizer.state[param]["n_iter"] - iterations
        iterations += done
        with torch.no_grad():
            energies.append(float(planarity_energy(positions(param), topo, lam)))
            objectives.append(float(energy(param)))
            worst = float(face_nonplanarity(positions(param), topo).max())
        problem.report(done, worst)
        if objectives[-1] >= objectives[-2]:
            reason = "stalled"
            break  # no progress left at this precision
    return positions(param.detach()), iterations, energies, objectives, reason or "max_iter"

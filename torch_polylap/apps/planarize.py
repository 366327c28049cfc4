"""Planarizing flow (AW11 sec. 5.3): quasi-Newton descent of the planarity energy.

    E_plan(X) = 1/2 sum_c X_c^T Lplan X_c = sum_f lambda/2 |Pi_f E_f|_F^2,

with ``Lplan`` the Laplacian without its geometric part ``M~_f`` (only ``lambda d^T Pi d``). Per
face it measures the part of the edge vectors that leaves the plane of the maximal projection,
so it vanishes exactly on meshes of planar faces and has no term that pulls vertices together
within that plane: the flow moves vertices (mostly) normal to their faces, and a planar
configuration near the start is reached long before any shrinkage could pay off. The paper
(and this function) runs it without constraints, lambda = 2, with a quasi-Newton method; here
``torch.optim.LBFGS`` with a strong Wolfe line search, stopped when the largest
:func:`torch_polylap.face_nonplanarity` drops below ``tol``.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import torch

from ..checks import check_index_or_mask
from ..operators import MeshFaces, face_nonplanarity, get_topology, planarity_energy

__all__ = ["planarize", "PlanarizeResult"]


@dataclass
class PlanarizeResult:
    """Outcome of :func:`planarize`.

    Attributes:
        verts: ``(V, 3)`` planarized positions (detached, dtype/device of the input).
        nonplanarity_before, nonplanarity_after: ``(max, mean)`` of
            :func:`torch_polylap.face_nonplanarity` over all faces (corner distance from the
            maximal projection's plane over the face diameter).
        displacement: ``(max, mean)`` vertex displacement over the bounding-box diagonal.
        iterations: L-BFGS iterations taken (a multiple of ``check_every`` unless it stopped
            earlier).
        seconds: wall-clock time of the optimization.
        converged: whether the largest non-planarity fell below ``tol``.
        energies: ``E_plan`` of the centered positions in bounding-box-diagonal units, at the
            start and after every ``check_every`` iterations; non-increasing.
    """

    verts: torch.Tensor
    nonplanarity_before: tuple[float, float]
    nonplanarity_after: tuple[float, float]
    displacement: tuple[float, float]
    iterations: int
    seconds: float
    converged: bool
    energies: list[float] = field(default_factory=list)


def _stats(x: torch.Tensor) -> tuple[float, float]:
    return (float(x.max()), float(x.mean())) if x.numel() else (0.0, 0.0)


def planarize(
    verts: torch.Tensor,
    faces: MeshFaces,
    lam: float = 2.0,
    tol: float = 1e-4,
    max_iter: int = 500,
    fixed: torch.Tensor | list[int] | None = None,
    progress: bool = False,
    history_size: int = 20,
    check_every: int = 5,
) -> PlanarizeResult:
    """Make every face planar by minimizing ``E_plan`` with L-BFGS (AW11 sec. 5.3).

    Args:
        verts: ``(V, 3)`` positions, float32 or float64.
        faces: polygon faces (triangles are planar and contribute nothing).
        lam: stabilizer weight ``lambda`` of the planarity operator (paper: 2).
        tol: stop once the largest face non-planarity (distance over diameter) is below it.
        max_iter: L-BFGS iteration limit.
        fixed: optional vertex indices (each once) or a ``(V,)`` bool mask of vertices that do
            not move.
        progress: show a tqdm progress bar with the current largest non-planarity.
        history_size: L-BFGS memory.
        check_every: L-BFGS iterations between two checks of the stopping criterion.

    Returns:
        :class:`PlanarizeResult`.

    The energy is quadratic in scale, so the positions are optimized in units of the bounding-box
    diagonal (centered); the gradient tolerances of L-BFGS and ``tol`` are then scale free.
    """
    if verts.dim() != 2 or verts.shape[1] != 3:
        raise ValueError(f"verts must have shape (V, 3), got {tuple(verts.shape)}.")
    if not verts.is_floating_point():
        raise ValueError(f"verts must be float32 or float64, got {verts.dtype}.")
    if tol <= 0 or max_iter < 0:
        raise ValueError(f"need tol > 0 and max_iter >= 0, got tol={tol}, max_iter={max_iter}.")
    n = verts.shape[0]
    topo = get_topology(faces, n)
    x0 = verts.detach()
    center = (x0.amax(0) + x0.amin(0)) / 2
    scale = float(torch.linalg.vector_norm(x0.amax(0) - x0.amin(0)))
    if not scale > 0:
        raise ValueError("all vertices coincide; nothing to planarize.")
    y0 = (x0 - center) / scale

    free_mask = torch.ones(n, dtype=torch.bool, device=verts.device)
    if fixed is not None:
        free_mask[check_index_or_mask(fixed, n, "fixed").to(verts.device)] = False
    free = torch.nonzero(free_mask).reshape(-1)
    param = y0[free].clone().requires_grad_(True)

    def positions(p: torch.Tensor) -> torch.Tensor:
        return y0.index_put((free,), p)

    def energy(p: torch.Tensor) -> torch.Tensor:
        return planarity_energy(positions(p), topo, lam)

    before = face_nonplanarity(x0, topo)
    worst = float(before.max()) if before.numel() else 0.0
    with torch.no_grad():
        e0 = float(planarity_energy(y0, topo, lam))
    # L-BFGS has absolute thresholds (it skips curvature pairs with y^T s <= 1e-10); rescale the
    # objective so that it is O(1) at the target tolerance (E_plan ~ non-planarity squared).
    weight = (worst / tol) ** 2 / e0 if e0 > 0 else 1.0
    eps = torch.finfo(verts.dtype).eps
    optimizer = torch.optim.LBFGS(
        [param],
        lr=1.0,
        max_iter=check_every,
        max_eval=25 * check_every,  # the default (5/4 max_iter) starves short line searches
        history_size=history_size,
        line_search_fn="strong_wolfe",
        tolerance_grad=0.0,
        tolerance_change=eps * 1e-3,
    )

    def closure() -> torch.Tensor:
        optimizer.zero_grad()
        e = weight * energy(param)
        e.backward()
        return e

    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=max_iter, desc="planarize", unit="it")
    energies = [e0]
    iterations = 0
    start = time.perf_counter()
    while worst >= tol and iterations < max_iter and free.numel():
        chunk = min(check_every, max_iter - iterations)
        optimizer.param_groups[0].update(max_iter=chunk, max_eval=25 * chunk)
        optimizer.step(closure)
        done = optimizer.state[param]["n_iter"] - iterations
        iterations += done
        with torch.no_grad():
            energies.append(float(energy(param)))
            worst = float(face_nonplanarity(positions(param), topo).max())
        if bar is not None:
            bar.update(done)
            bar.set_postfix(max_nonplanarity=f"{worst:.2e}")
        if energies[-1] >= energies[-2]:
            break  # no progress left at this precision
    seconds = time.perf_counter() - start
    if bar is not None:
        bar.close()

    with torch.no_grad():
        # add the displacement, so that vertices that did not move keep their exact input values
        out = x0.index_put((free,), x0[free] + (param - y0[free]) * scale)
        after = face_nonplanarity(out, topo)
        disp = torch.linalg.vector_norm(out - x0, dim=1) / scale
    return PlanarizeResult(
        verts=out.detach(),
        nonplanarity_before=_stats(before),
        nonplanarity_after=_stats(after),
        displacement=_stats(disp),
        iterations=iterations,
        seconds=seconds,
        converged=bool(after.numel() == 0 or float(after.max()) < tol),
        energies=energies,
    )

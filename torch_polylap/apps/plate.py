"""Thin plate bending with the polygon Laplacian (AW11 sec. 5.4) and the analytic Navier plate.

The bending energy of a vertical deflection ``u`` is ``E_bend(u) = 1/2 u^T L^T M0^{-1} L u``
(after Wardetzky et al. 2007).  For a *simply supported* plate (``u = 0`` on the boundary, the
bending moment, here ``Laplacian u``, zero there as well) under a load ``q`` with flexural rigidity
1 the minimizer solves the biharmonic problem ``Delta^2 u = q`` with Navier boundary conditions.
This module uses the mixed form of that energy, two Dirichlet Poisson solves with the same matrix:

    L_II w_I = (M0 q)_I,    L_II u_I = (M0 w)_I,    u_B = w_B = 0,

which minimizes ``1/2 sum_{p interior} (L u)_p^2 / m_p - u^T M0 q`` over ``u`` with ``u_B = 0``:
the paper's energy with the rows of ``L`` at boundary vertices left out.  The paper does not say
how it imposes the support.  Keeping those rows (the energy over all of ``L u``, only ``u_B = 0``)
also penalizes the boundary flux of ``grad u`` and converges to the *clamped* plate instead:
center deflection 0.00126 q (the classical clamped value) rather than the Navier plate's
0.00406 q, a relative L2 error near 0.74 at every level of the paper's grids, whereas the mixed
form converges to the Navier solution (``examples/plate_bending_study.py``,
``tests/apps/test_apps_plate.py``).
"""

from __future__ import annotations

import math

import numpy as np
import torch

from .._typing import MeshFaces
from ..checks import check_index_or_mask
from ..kernels import check_method
from ..linalg import solve
from ..measures import mass
from ..operators import laplacian
from ..sparse.construct import eliminate
from ..topology import get_topology

__all__ = ["plate_bending", "navier_deflection", "plate_error"]


def _boundary_mask(
    boundary: torch.Tensor | None, num_verts: int, default: torch.Tensor, device: torch.device
) -> torch.Tensor:
    mask = torch.zeros(num_verts, dtype=torch.bool, device=device)
    index = default if boundary is None else check_index_or_mask(boundary, num_verts, "boundary")
    return mask.index_fill(0, index.to(device), True)


def plate_bending(
    verts: torch.Tensor,
    faces: MeshFaces,
    load: float | torch.Tensor = 1.0,
    lam: float | torch.Tensor = 1.0,
    boundary: torch.Tensor | None = None,
    *,
    method: str = "aw11",
) -> torch.Tensor:
    """Deflection of a simply supported thin plate under a load (AW11 sec. 5.4).

    Minimizes ``E_bend(u) - u^T M0 q`` with ``E_bend = 1/2 u^T L^T M0^{-1} L u`` restricted to
    the interior rows of ``L`` (mixed form, see the module docstring), ``u = 0`` on the support,
    flexural rigidity 1: ``L_II w = (M0 q)_I``, then ``L_II u = (M0 w)_I``.

    Args:
        verts: ``(V, 3)`` positions of the (usually planar) plate mesh; differentiable.
        faces: any face form accepted by :func:`torch_polylap.laplacian`.
        load: load per unit area ``q``, a scalar or a ``(V,)`` tensor (lumped with ``M0``).
        lam: the Laplacian's ``lambda`` (AW11 eq. 9). ``lambda = 0`` has spurious zero-energy
            modes on meshes with faces of degree > 3 (AW11 sec. 5.4); the solve then fails
            with a ValueError or gives a meaningless deflection.
        boundary: supported vertices (indices, each once, or a ``(V,)`` bool mask); default:
            the mesh boundary (defined on any mesh, non-manifold or non-orientable ones
            included). Every connected component needs at least one.
        method: the Laplacian, ``"aw11"`` (default), ``"plms"`` (``lam`` unused, no spurious
            modes to stabilize) or ``"degoes"`` (see :func:`torch_polylap.laplacian`); ``M0``
            is that method's mass.

    Returns:
        ``(V,)`` deflection ``u`` (positive along the load), zero on the support; dtype and
        device of ``verts``.

    Raises:
        ValueError: no supported vertex, a singular system, or bad mesh input.
    """
    check_method(method, diagonal_mass="plate_bending")
    topo = get_topology(faces, verts.shape[0])
    support = _boundary_mask(boundary, verts.shape[0], topo.boundary_vertices, verts.device)
    if not bool(support.any()):
        raise ValueError(
            "plate_bending needs supported vertices (u = 0): the mesh has no boundary; pass "
            "`boundary` with the vertex indices to hold."
        )
    L, M0 = laplacian(verts, topo, lam, method=method)
    m = M0.diagonal()
    # Dirichlet zeros: the support's rows and columns become the identity's; the matrix stays
    # symmetric positive definite and one factorization (cached by solve) serves both solves.
    A, _ = eliminate(L, support, torch.ones_like(m))
    q = torch.as_tensor(load, dtype=verts.dtype, device=verts.device)
    zero = torch.zeros((), dtype=verts.dtype, device=verts.device)
    moment = solve(A, torch.where(support, zero, m * q))
    return solve(A, torch.where(support, zero, m * moment))


def _levy_correction(m: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """Lévy's ``y``-factor minus one, ``bracket_m(y) - 1``, for the unit square, without overflow.

    ``bracket_m(y) = 1 - (a tanh a + 2) cosh(2 a y') / (2 cosh a) + a y' sinh(2 a y') / cosh a``
    with ``a = m pi / 2`` and ``y' = y - 1/2``.  The hyperbolic ratios are written with decaying
    exponentials: the result is of size ``m exp(-m pi d)`` with ``d`` the distance of ``y`` to
    the nearer edge ``y = 0`` or ``y = 1``.
    """
    a = m * (math.pi / 2)
    s = m * math.pi * (y - 0.5).abs()  # 2 a |y'| <= a
    damp = torch.exp(s - a) / (1 + torch.exp(-2 * a))
    cosh_ratio = damp * (1 + torch.exp(-2 * s))
    sinh_ratio = damp * (1 - torch.exp(-2 * s))
    return 0.5 * s * sinh_ratio - 0.5 * (a * torch.tanh(a) + 2) * cosh_ratio


def _default_terms() -> int:
    # the m-th term is at most 4/pi^5 m^-5 in size: the tail beyond M is below float64
    # round-off of the center deflection (~4.06e-3) once 4/pi^5 * M^-4 / 8 < eps * 4.06e-3
    eps = torch.finfo(torch.float64).eps
    return int(math.ceil((4 / math.pi**5 / 8 / (eps * 4.06e-3)) ** 0.25 / 2))


def navier_deflection(
    x: torch.Tensor | np.ndarray | float,
    y: torch.Tensor | np.ndarray | float,
    load: float = 1.0,
    terms: int | None = None,
) -> torch.Tensor:
    """Deflection of a simply supported unit square plate (flexural rigidity 1) under load ``q``.

    Navier's double series ``w = 16 q / pi^6 sum_{m,n odd} sin(m pi x) sin(n pi y) /
    (m n (m^2 + n^2)^2)``, evaluated in Lévy's single-series form (the sum over ``n`` in
    closed form; Timoshenko & Woinowsky-Krieger, Theory of Plates and Shells, sec. 30):

        w = q (x^4 - 2 x^3 + x) / 24 + 4 q / pi^5 sum_{m odd} sin(m pi x) / m^5 (bracket_m(y) - 1)

    where the first term is the plate strip's deflection (``4 q / pi^5 sum sin(m pi x) / m^5``)
    and the correction's terms decay like ``exp(-m pi d)``, ``d`` the distance to the nearer
    edge ``y = 0, 1``.  The plate is symmetric in ``x <-> y``; each point is evaluated in the
    orientation with the larger ``d``, and only as many terms as its ``d`` needs are summed.

    Args:
        x: coordinates in ``[0, 1]``, broadcastable with ``y`` (tensors keep their dtype and
            device; other inputs become float64; the series is summed in float64).
        y: coordinates in ``[0, 1]``, like ``x``.
        load: uniform load ``q``.
        terms: largest number of odd ``m`` summed (points far from the edges need far fewer).
            Default: enough that the remainder is below float64 round-off of the center
            deflection (about 3300 terms near the corners, under 100 inside).

    Returns:
        ``w`` with the broadcast shape of ``x`` and ``y``. Center value ``0.00406235 q``.

    Examples:
        >>> from torch_polylap.apps import navier_deflection
        >>> round(float(navier_deflection(0.5, 0.5)), 8)
        0.00406235
    """
    # new names: torch types broadcast_tensors' result as Any, which would widen x back to its
    # parameter type
    xt = torch.as_tensor(x, dtype=torch.float64) if not torch.is_tensor(x) else x
    yt = torch.as_tensor(y, dtype=xt.dtype, device=xt.device) if not torch.is_tensor(y) else y
    xt, yt = torch.broadcast_tensors(xt, yt)
    terms = _default_terms() if terms is None else terms
    if terms < 1:
        raise ValueError(f"terms must be >= 1, got {terms}.")
    xs = xt.reshape(-1).to(torch.float64)
    ys = yt.reshape(-1).to(torch.float64)
    dx, dy = torch.minimum(xs, 1 - xs), torch.minimum(ys, 1 - ys)
    swap = dx > dy
    xs, ys = torch.where(swap, ys, xs), torch.where(swap, xs, ys)
    d = torch.maximum(dx, dy)
    # the correction's m-th term carries exp(-m pi d): past m = 40 / (pi d) it is below 1e-17
    needed = torch.ceil(40 / (math.pi * d.clamp_min(1e-300)) / 2).clamp(max=terms)
    strip = (xs**4 - 2 * xs**3 + xs) / 24
    correction = torch.zeros_like(xs)
    lo = 0
    for hi in sorted({min(terms, 2**k) for k in range(5, 13)} | {terms}):
        batch = torch.nonzero((needed > lo) & (needed <= hi)).reshape(-1)
        lo = hi
        if batch.numel() == 0:
            continue
        m = torch.arange(1, 2 * hi, 2, dtype=torch.float64, device=xs.device)
        for part in batch.split(max(1, 2**21 // hi)):  # bounds the temporaries to ~16 MB
            xc, yc = xs[part, None], ys[part, None]
            series = torch.sin(m * math.pi * xc) * _levy_correction(m, yc) / m**5
            correction[part] = series.flip(1).sum(1)  # smallest terms first
    w = load * (strip + 4 / math.pi**5 * correction)
    return w.reshape(xt.shape).to(xt.dtype)


def plate_error(
    verts: torch.Tensor,
    faces: MeshFaces,
    u: torch.Tensor,
    reference: torch.Tensor | None = None,
    load: float = 1.0,
) -> torch.Tensor:
    """Relative ``L2`` error ``sqrt(e^T M0 e / u*^T M0 u*)`` with ``e = u - u*`` (AW11 Fig. 6, 7).

    Args:
        verts: ``(V, 3)``; the masses ``M0`` come from it (AW11 eq. 10).
        faces: the mesh faces.
        u: ``(V,)`` computed deflection.
        reference: ``(V,)`` exact deflection; default: :func:`navier_deflection` at the
            vertices' ``x, y`` (the mesh must cover the unit square ``[0, 1]^2``).
        load: the load used for the default reference.

    Returns:
        A scalar tensor.
    """
    if reference is None:
        reference = navier_deflection(verts[:, 0], verts[:, 1], load)
    m = mass(verts, faces)
    e = u - reference
    return torch.sqrt((m * e * e).sum() / (m * reference * reference).sum())

"""The smoothest ``n``-direction field (Knoeppel, Crane, Pinkall and Schroeder 2013).

An ``n``-direction field (``n = 1`` vectors, ``2`` lines, ``4`` crosses) is stored at each
vertex as the complex number ``X = r e^{i n theta}``, which is the same for the ``n`` directions
``theta + 2 pi k / n``.  Its smoothness is measured by the connection Laplacian with the
``n``-fold connection (:func:`~torch_polylap.vector.connection_laplacian` with ``symmetry=n``),
and the smoothest field of unit mean length is the eigenvector of the smallest eigenvalue of
``A_n X = mu M X`` (Knoeppel et al. 2013, sec. 5, "globally optimal" fields without
alignment constraints).  On a surface without boundary of genus ``g != 1`` no such field is
free of zeros (Poincare-Hopf), and the field's singularities appear where ``|X|`` is small.
"""

from __future__ import annotations

from typing import Any

import torch

from .._typing import MeshFaces
from ..checks import Lam
from ..linalg import eigenpair_gradients, eigs
from ..sparse import sparse_values
from .connection import connection_laplacian

__all__ = ["smoothest_field"]


def smoothest_field(
    verts: torch.Tensor,
    faces: MeshFaces,
    symmetry: int = 1,
    lam: Lam = 1.0,
    *,
    method: str = "aw11",
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The globally smoothest ``n``-direction field (module docstring).

    Args:
        verts: ``(V, 3)`` vertex positions.
        faces: faces in any accepted form, or a :class:`~torch_polylap.topology.Topology`.
        symmetry: ``n``: 1 (vector field), 2 (line field), 4 (cross field), any ``n >= 1``.
        lam: the scalar Laplacian's stabilizer weight (see :func:`~torch_polylap.laplacian`).
        method: the scalar Laplacian's construction (see :func:`~torch_polylap.laplacian`).

    Returns:
        ``directions`` ``(V, 3)``: one unit tangent vector per vertex, the representative
        ``theta = arg(X) / n`` (the others are its rotations by ``2 pi k / n``);
        ``magnitude`` ``(V,)``: ``|X|`` with ``X^* M X = 1``, small near singularities;
        ``energy``: the eigenvalue ``mu`` (0-dim), ``X^* A_n X``.  At a vertex where ``X = 0``
        exactly (a singularity on a vertex) the direction is the frame's ``e_x`` and the
        magnitude 0, both with a zero gradient there.

    Gradients (in ``verts``, through :func:`~torch_polylap.eigs`): the field is unique only up
    to its phase, ``X -> e^{i t} X``, which turns every direction by ``t / n``, so only a loss
    that does not change under that turn has one (``magnitude``, ``energy``, angles between
    the directions measured in the frames, ...); any other raises a ``RuntimeError`` in the
    backward.  Where the smallest eigenvalue is repeated as a complex eigenvalue (symmetric
    meshes: spheres), the field is not unique even up to phase and the backward raises
    ``eigs``' error for a repeated eigenvalue (``energy``'s gradient is then that of one
    branch of the repeated eigenvalue, as for ``eigs``' ``evals``).
    """
    A, M, frames = connection_laplacian(verts, faces, lam, method=method, symmetry=symmetry)
    with torch.no_grad():
        mu, X = eigs(A, M, k=1)
    if torch.is_grad_enabled() and (
        sparse_values(A).requires_grad or sparse_values(M).requires_grad
    ):
        # The real form of the complex A has each eigenvalue twice, for X and i X: eigs(k=1)
        # returns one of them, and its backward sees the other as an uncomputed eigenvalue
        # at the same place (and refuses). Both belong to the cluster the gradient needs.
        twins = torch.stack((X[:, 0], _times_i(X[:, 0])), 1)
        mu, twins = eigenpair_gradients(A, M, mu.repeat(2), twins)
        X = _PhaseInvariant.apply(twins[:, :1])
    theta, magnitude = polar(X[0::2, 0], X[1::2, 0])
    theta = theta / symmetry
    directions = torch.cos(theta)[:, None] * frames.e_x + torch.sin(theta)[:, None] * frames.e_y
    return directions, magnitude, mu[0]


def _times_i(X: torch.Tensor) -> torch.Tensor:
    """``i X`` for interleaved complex coordinates ``X`` ``(2V,)``: ``(x, y) -> (-y, x)`` per
    vertex, the rotation of every vector by a quarter turn in its frame."""
    return torch.stack((-X[1::2], X[0::2]), 1).reshape(-1)


class _PhaseInvariant(torch.autograd.Function):
    """The identity on the field ``X`` ``(2V, 1)``, whose backward refuses a loss that depends
    on ``X``'s phase: its upstream gradient ``G`` must be orthogonal to ``i X`` (the derivative
    of the loss under ``X -> e^{i t} X``) up to ``sqrt(eps) |G| |X|``, as the eigenvector
    backward checks for a cluster too, but with a message about the field."""

    @staticmethod
    def forward(ctx: Any, X: torch.Tensor) -> torch.Tensor:
        ctx.save_for_backward(X)
        return X.clone()

    @staticmethod
    def backward(ctx: Any, G: torch.Tensor) -> torch.Tensor:
        (X,) = ctx.saved_tensors
        rate = float((G[:, 0] * _times_i(X[:, 0])).sum())
        size = float(torch.linalg.vector_norm(G) * torch.linalg.vector_norm(X))
        if abs(rate) > torch.finfo(X.dtype).eps ** 0.5 * size:
            raise RuntimeError(
                "smoothest_field: no gradient for this loss: the smoothest field is unique "
                "only up to its phase (turning every direction by one angle t / n in its "
                f"tangent plane), and the loss changes under that turn (at the rate {rate:.6g} "
                f"per radian of t, against {size:.6g} for the size of its gradient). Use a loss "
                "that does not depend on the phase: the magnitude, the energy, or angles "
                "between directions measured in the frames (e.g. cos(n (theta_i - theta_j)))."
            )
        return G


def polar(x: torch.Tensor, y: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``(arg, |.|)`` of ``x + i y`` (any matching shapes), with finite gradients everywhere.

    ``atan2`` and ``hypot`` have ``0 / 0`` derivatives at the origin, which autograd turns
    into NaN for every input the result depends on.  There the angle is taken as 0 and the
    length as 0, both constant near the point, so their gradient is 0: the origin is fed to
    the functions as ``1 + 0 i`` and the length masked (``where`` passes no gradient to the
    branch it does not select, and the substituted branch has a finite one)."""
    origin = (x == 0) & (y == 0)
    safe_x = torch.where(origin, torch.ones_like(x), x)
    safe_y = torch.where(origin, torch.zeros_like(y), y)
    length = torch.hypot(safe_x, safe_y)
    return torch.atan2(safe_y, safe_x), torch.where(origin, torch.zeros_like(length), length)

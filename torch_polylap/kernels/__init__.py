"""The per-face block kernels of the polygon Laplacians that ``tp.laplacian(method=...)`` selects.

All methods share one assembly (:mod:`torch_polylap.assembly`): a kernel evaluates the blocks of
a chunk of faces of one degree, and the assembly scatters them onto the topology's cached CSR
pattern with its scatter maps. Every block satisfies ``L_f 1 = 0``, so a kernel returns only
the off-diagonal entries and the diagonal is minus their row sums.

- ``"aw11"``: Alexa and Wardetzky 2011 (:mod:`.aw11`; quads in closed form);
- ``"plms"``: Bunge, Herholz, Kazhdan and Botsch 2020, "Polygon Laplacian Made Simple"
  (:mod:`.plms`); ``lam`` is ignored (the method has no stabilizer);
- ``"degoes"``: de Goes, Butts and Desbrun 2020, "Discrete Differential Operators on Polygonal
  Meshes" (:mod:`.degoes`); ``lam`` weights their projection term;
- ``"diamond"``: Bunge, Botsch and Alexa 2021, "The Diamond Laplace for Polygonal and
  Polyhedral Meshes" (:mod:`.diamond`); ``lam`` is ignored. Its stencil couples the two faces
  of every edge, so it has no per-face blocks:
  :func:`torch_polylap.assembly.diamond.diamond_laplacian` assembles it on its own pattern
  (and its ``M0`` is not diagonal), and :func:`block_kernel` refuses it.

:mod:`.frames` holds the per-face geometry they share (gathers, vector area, plane basis).
"""

from __future__ import annotations

import torch

from ..topology import DegreeGroup
from .aw11 import aw11_entries
from .degoes import degoes_entries
from .entries import BlockEntries, FaceEntries
from .frames import gather_coordinates, gather_corners
from .plms import plms_entries

__all__ = [
    "METHODS",
    "BLOCK_METHODS",
    "LAM_FREE_METHODS",
    "BlockEntries",
    "FaceEntries",
    "BlockKernel",
    "check_method",
    "block_kernel",
    "thin_error",
]

METHODS = ("aw11", "plms", "degoes", "diamond")

#: The methods that are sums of per-face blocks (all but ``"diamond"``).
BLOCK_METHODS = ("aw11", "plms", "degoes")

#: The methods without a stabilizer, which ignore ``lam``.
LAM_FREE_METHODS = ("plms", "diamond")


def check_method(method: object, *, diagonal_mass: str = "", face_blocks: str = "") -> str:
    """``method`` must name one of :data:`METHODS`.

    ``diagonal_mass`` names the caller when it needs a diagonal ``M0`` (lumped masses per
    vertex), ``face_blocks`` when it needs ``L`` as a sum of per-face blocks: either refuses
    ``"diamond"``, whose mass couples the corners of each face and whose stencil couples the
    two faces beside each edge.
    """
    if not isinstance(method, str) or method not in METHODS:
        raise ValueError(f"method must be one of {', '.join(map(repr, METHODS))}, got {method!r}.")
    others = ", ".join(map(repr, BLOCK_METHODS))
    if diagonal_mass and method not in BLOCK_METHODS:
        raise ValueError(
            f"{diagonal_mass} needs a diagonal mass M0, and method={method!r} has none (its M0 "
            f"couples the corners of each face); use one of {others}."
        )
    if face_blocks and method not in BLOCK_METHODS:
        raise ValueError(
            f"{face_blocks} needs a Laplacian that is a sum of per-face blocks, and "
            f"method={method!r} is not (its stencil couples the faces beside each edge); use "
            f"one of {others}."
        )
    return method


class BlockKernel:
    """The per-chunk block kernel of one method (see :func:`block_kernel`).

    Called as ``kernel(verts_t (3, V), group, corners_t (k, F))`` it gathers the corners and
    evaluates their blocks; :meth:`on_corners` evaluates already gathered ``(3, k, F)`` corner
    positions (the eager assembly gathers all its chunks in one autograd node).
    """

    def __init__(self, method: str, lam: float | torch.Tensor, *, geometric: bool) -> None:
        self.method = method
        self.lam = lam
        self.geometric = geometric

    def __call__(
        self, verts_t: torch.Tensor, grp: DegreeGroup, corners_t: torch.Tensor
    ) -> BlockEntries:
        if self.method == "aw11" and grp.k == 4:
            # quads read three coordinate rows (the closed form's faster gather)
            return self._aw11(gather_coordinates(verts_t, corners_t), grp)
        return self.on_corners(gather_corners(verts_t, corners_t), grp)

    def on_corners(self, x: torch.Tensor, grp: DegreeGroup) -> BlockEntries:
        """The blocks of the faces whose ``(3, k, F)`` corner positions are ``x``."""
        if self.method == "aw11":
            return self._aw11(x, grp)
        if self.method == "plms":
            return plms_entries(x, grp.pair_i, grp.pair_j)
        return _with_masses(degoes_entries(x, grp.pair_i, grp.pair_j, self.lam), grp.k)

    def stretch(self, area: torch.Tensor, size2: torch.Tensor, grp: DegreeGroup) -> torch.Tensor:
        """``(F,)`` ``s^2 / |f|`` of faces of ``grp`` from their entries' ``area`` and ``size2``,
        ``s^2`` the sum of the squared half-diagonals (2 for a square): the conditioning of
        float32 products with their blocks (not differentiable)."""
        ratio = size2.detach() / area.detach()
        # AW11's closed form for quads takes the squared diagonals: twice that sum
        return ratio * 0.5 if self.method == "aw11" and grp.k == 4 else ratio

    def _aw11(
        self,
        x: torch.Tensor | tuple[torch.Tensor, torch.Tensor, torch.Tensor],
        grp: DegreeGroup,
    ) -> BlockEntries:
        entries = aw11_entries(x, grp, self.lam, geometric=self.geometric)
        return _with_masses(entries, grp.k)


def block_kernel(method: str, lam: float | torch.Tensor, *, geometric: bool = True) -> BlockKernel:
    """The per-chunk block kernel of ``method`` for the shared assembly.

    The kernel maps ``(verts_t (3, V), group, corners_t (k, F))`` to the off-diagonal entries
    ``(P, F)``, the corner masses ``(k, F)``, the areas ``(F,)``, the squared sizes ``(F,)``
    against which a zero area is judged, and ``(F,)`` a bound on the relative error of each
    block and its gradient in units of the working precision's eps (not differentiable), by
    which the assembly re-evaluates ill-conditioned float32 faces in float64.
    ``geometric=False`` (AW11 only) keeps the stabilizer ``lam d^T Pi d`` alone: the planarity
    operator's blocks (AW11 sec. 5.3).
    """
    check_method(method)
    if method not in BLOCK_METHODS:
        raise ValueError(
            f"method={method!r} is not a sum of per-face blocks; this operation supports "
            f"{', '.join(map(repr, BLOCK_METHODS))}."
        )
    if not geometric and method != "aw11":
        raise ValueError("only method='aw11' has a planarity (stabilizer-only) operator.")
    return BlockKernel(method, lam, geometric=geometric)


def _with_masses(e: FaceEntries, k: int) -> BlockEntries:
    """The block entries of a method whose faces share their area evenly among the corners."""
    corner_mass = (e.area / k).expand(k, -1)
    return BlockEntries(e.off, corner_mass, e.area, e.size2, thin_error(e.area, e.size2))


def thin_error(area: torch.Tensor, size2: torch.Tensor) -> torch.Tensor:
    """``(F,)`` bound on the relative error of an AW11 or dGBD20 block and its gradient, in
    units of eps: ``4 s^2 / |f|``.

    Both divide ``G G^T`` by the area, whose cross products cancel to ``|f| / s^2`` of their
    terms on thin faces; measured in float32 against float64 on random convex, concave and
    thin faces, the error stays below ``2 eps s^2 / |f|`` (docs/math/properties.md, "Finite
    precision").
    """
    return (size2.detach() / area.detach()).mul_(4.0)

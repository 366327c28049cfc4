"""The assembly's checks: the flags every form computes on the device, and the error that
names the offending vertex or face once a flag is read false.

The eager assembly reads all its flags with one device sync; traced and transformed code turns
them into an in-graph assertion (:func:`~torch_polylap.tracing.require`) and, when that fails
eagerly, calls :func:`raise_bad_input` for the message that names the element.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch

from ..checks import Float32PrecisionWarning, warn_outside_package
from ..kernels import BlockKernel
from ..kernels.aw11 import aw11_entries
from ..topology import DegreeGroup, Topology
from .corners import face_groups
from .scaling import normalizer

__all__ = [
    "FLOAT32_TOLERANCE",
    "FLOAT32_INACCURATE",
    "FLOAT32_STRETCH_LIMIT",
    "BAD_INPUT",
    "FlaggedAssembly",
    "any_degenerate",
    "input_ok",
    "output_ok",
    "raise_bad_input",
    "warn_float32_products",
]


# A float32 face whose kernel bounds the relative error of its block above this is evaluated
# in float64 (eager assembly with validation; see docs/math/properties.md, "Finite precision").
FLOAT32_TOLERANCE = 1e-2


# The expected relative error of float32 products with L (L @ X, and the gradients of losses
# through them) on a face of stretch r = s^2 / |f| (2 for a square): PRODUCT_FACTOR * eps * r^2.
# A block's entries grow as r while L_f X of a smooth X stays of the face's size, and the
# diagonal, minus the row sum of entries r times larger, cancels to it: on a rectangle of
# width t, L x of the long coordinate is t from entries 1 / t. Measured on 240 random faces
# (thin to 1e-5, half concave, planar or bumpy), the float32 gradient of |L X|^2 against
# float64 on the same coordinates is off by a median 0.4 to 0.5 eps r^2 (up to 4 eps r^2) for
# AW11 and dGBD20 once r exceeds 100.
PRODUCT_FACTOR = 0.5

# the stretch above which float32 products lose more than FLOAT32_TOLERANCE (about 410)
FLOAT32_STRETCH_LIMIT = math.sqrt(
    FLOAT32_TOLERANCE / (PRODUCT_FACTOR * torch.finfo(torch.float32).eps)
)


FLOAT32_INACCURATE = (
    "torch_polylap: a face is too thin or nearly degenerate for float32 (its blocks' expected "
    "relative error exceeds 1e-2). Eagerly such faces are evaluated in float64; inside "
    "torch.compile or torch.func they cannot be: use float64 vertices there, or validate=False "
    "to accept the error."
)


BAD_INPUT = (
    "torch_polylap: non-finite vertex coordinates, a zero-area face, or a Laplacian or masses "
    "that the dtype cannot represent. Inside torch.compile or torch.func.vmap the offending "
    "element cannot be named: call torch_polylap.laplacian eagerly on these vertices to find "
    "it, or pass validate=False to skip the checks."
)


class FlaggedAssembly(NamedTuple):
    """What :func:`assemble_flagged` returns; unpacks as ``values, masses, ok, accurate,
    stretch``."""

    values: torch.Tensor
    """``(nnz,)`` the values on the view's pattern."""
    masses: torch.Tensor | None
    """``(V,)`` the lumped masses, or ``None`` when not asked for."""
    ok: torch.Tensor
    """0-dim bool: every check passed."""
    accurate: torch.Tensor
    """0-dim bool: every face's expected relative error stays within
    :data:`FLOAT32_TOLERANCE` (always true in float64)."""
    stretch: torch.Tensor
    """0-dim: the largest ``s^2 / |f|`` of a face in float32 (``BlockKernel.stretch``), zero in
    float64 and for the planarity operator; above :data:`FLOAT32_STRETCH_LIMIT` the caller
    warns with :func:`warn_float32_products`."""


def any_degenerate(area: torch.Tensor, size2: torch.Tensor, eps: float) -> torch.Tensor:
    """Whether a face has zero vector area (NaN included), or is too small against the mesh's
    largest coordinate for the dtype (``s^2`` of the normalized face below ``tiny / eps``: its
    products would be subnormal)."""
    tiny = torch.finfo(area.dtype).tiny
    return (~(area > eps * size2)).any() | ~(size2.amin() >= tiny / eps)


def warn_float32_products(
    verts: torch.Tensor, topo: Topology, kernel: BlockKernel, *, mesh: int | None = None
) -> None:
    """Warn once (:class:`~torch_polylap.checks.Float32PrecisionWarning`) that float32 products
    with ``L`` lose accuracy on ``verts`` ``(V, 3)``, naming the face of largest ``s^2 / |f|``
    (``kernel.stretch``), its expected relative error and the digits lost; ``mesh``: the index
    of ``verts`` in a batch. The rare path, after an assembly found such a face: one pass over
    the faces, with host syncs."""
    eps = torch.finfo(torch.float32).eps
    verts_t = (verts.detach() * normalizer(verts.detach()).scale).t().contiguous()
    worst, face = -1.0, 0
    for grp in topo.on(verts.device).groups:
        _, _, area, size2, _ = kernel(verts_t, grp, grp.corners_t)
        value, local = kernel.stretch(area, size2, grp).max(0)
        if float(value) > worst:
            worst, face = float(value), int(grp.face_ids[int(local)])
    error = PRODUCT_FACTOR * worst * worst * eps
    digits = min(math.log10(error / eps), -math.log10(eps))
    where = "" if mesh is None else f"mesh {mesh} of the batch: "
    message = (
        f"torch_polylap: {where}face {face} (vertices {topo.faces[face].tolist()}) is so thin "
        f"(s^2 / |f| = {worst:.3g}, 2 for a square) that float32 products with L (L @ X, and "
        f"gradients through them) are expected to lose about {digits:.1f} of float32's 7 "
        f"digits (relative error {error:.1g} on this face)."
    )
    if error > 1:
        # the cotangents of L's entries are summed in float32 before any kernel sees them
        message += (
            " Evaluating its block in float64 would not help: the product and the backward "
            "pass round in float32."
        )
    message += " Use float64 vertices (verts.double()) for this mesh, or repair the face."
    warn_outside_package(message, Float32PrecisionWarning)


def _finite(t: torch.Tensor, symbolic: bool = False) -> torch.Tensor:
    """Whether every entry of ``t`` is finite: its extremes are (NaN propagates through them),
    which is one read of ``t`` where ``isfinite(t).all()`` takes several. ``symbolic``: the
    size is a symbol of a traced graph (whether ``t`` is empty is not known; no extremes)."""
    if symbolic:
        return torch.isfinite(t).all()
    if t.numel() == 0:
        return torch.ones((), dtype=torch.bool, device=t.device)
    return torch.isfinite(torch.stack(torch.aminmax(t))).all()


def input_ok(finite: torch.Tensor, degenerate: list[torch.Tensor]) -> torch.Tensor:
    """Finite coordinates (``finite``, from :func:`normalizer`) and no degenerate face."""
    return finite & ~torch.stack(degenerate).any() if degenerate else finite


def output_ok(
    values: torch.Tensor,
    masses_n: torch.Tensor | None,
    masses: torch.Tensor | None,
    symbolic: bool = False,
) -> torch.Tensor:
    """Finite values, and masses that neither overflow nor underflow (``symbolic``: the
    number of values is a symbol of a graph traced for many meshes)."""
    ok = _finite(values, symbolic)
    # no vertex, no mass to check (amin of an empty tensor raises)
    if masses_n is not None and masses is not None and masses.numel():
        tiny = torch.finfo(masses.dtype).tiny
        smallest = torch.where(masses_n == 0, tiny, masses).abs().amin()
        ok = ok & _finite(masses) & (smallest >= tiny)
    return ok


def _masses_ok(masses_n: torch.Tensor, masses: torch.Tensor) -> torch.Tensor:
    """``(V,)`` masses ``masses`` (of the normalized ones ``masses_n``) that are finite and not
    under- (subnormal, or zero where the normalized mass is not) or overflowed."""
    tiny = torch.finfo(masses.dtype).tiny
    return torch.isfinite(masses) & ((masses.abs() >= tiny) | (masses_n == 0))


def _first_face(mask: torch.Tensor, grp: DegreeGroup, topo: Topology) -> tuple[int, str]:
    """The position in ``grp`` of the first face ``mask`` ``(F_k,)`` flags, and its name with
    its vertices for an error message."""
    local = int(torch.nonzero(mask)[0, 0])
    f = int(grp.face_ids[local])
    return local, f"face {f} (vertices {topo.faces[f].tolist()})"


def raise_bad_input(
    verts: torch.Tensor,
    topo: Topology,
    kernel: BlockKernel | None = None,
    masses: tuple[torch.Tensor | None, torch.Tensor | None] = (None, None),
    *,
    mixed: bool = False,
) -> None:
    """Raise the ValueError that names the first non-finite vertex, zero-area or too small
    face, face with a non-finite block (``kernel``; with ``mixed`` its ill-conditioned faces
    evaluated in float64, as the assembly did), or mass out of the dtype's range (``masses``:
    those of the normalized coordinates and the caller's)."""
    bad_v = ~torch.isfinite(verts).all(1)
    if bool(bad_v.any()):
        v = int(torch.nonzero(bad_v)[0, 0])
        raise ValueError(
            f"vertex {v} has non-finite coordinates {verts[v].tolist()} "
            f"({int(bad_v.sum())} such vertices); fix or remove them before building operators."
        )
    verts = verts.detach()
    info = torch.finfo(verts.dtype)
    scale, unscale, _ = normalizer(verts)
    biggest = float(verts.abs().max())
    verts_n = verts * scale
    for _, grp, x in face_groups(verts_n, topo):
        _, area, size2 = aw11_entries(x, grp, 0.0)
        small = ~(size2 >= info.tiny / info.eps)
        if bool(small.any()):
            local, face = _first_face(small, grp, topo)
            raise ValueError(
                f"{face} is about "
                f"{math.sqrt(float(size2[local])):.1g} times the mesh's largest coordinate "
                f"({biggest:.3g}): too small for {verts.dtype} to compute its block "
                f"({int(small.sum())} such face(s) of degree {grp.k}). Use float64, or move "
                "far-away vertices (unreferenced ones included) closer."
            )
        bad = ~(area > info.eps * size2)
        if bool(bad.any()):
            local, face = _first_face(bad, grp, topo)
            rel = float(area[local] / size2[local])
            raise ValueError(
                f"{face} has zero vector area "
                f"(|f| / s^2 = {rel:.3g}, s^2 the sum of its squared half-diagonals); its "
                f"corners are collinear or its loop cancels out ({int(bad.sum())} such face(s) "
                f"of degree {grp.k}). The Laplacian divides by |f|: remove the face, collapse "
                "it, or move its vertices apart. Thin faces with non-zero area are fine."
            )
    if kernel is not None:
        verts_t = verts_n.t().contiguous()
        for grp in topo.on(verts.device).groups:
            off, corner_mass, _, _, error = kernel(verts_t, grp, grp.corners_t)
            bad = ~(torch.isfinite(off).all(0) & torch.isfinite(corner_mass).all(0))
            if mixed:
                redo = torch.nonzero(bad & ~(error * info.eps <= FLOAT32_TOLERANCE))[:, 0]
                off, corner_mass = kernel(verts_t.double(), grp, grp.corners_t[:, redo])[:2]
                finite = torch.isfinite(off).all(0) & torch.isfinite(corner_mass).all(0)
                bad[redo] = ~finite
            if bool(bad.any()):
                face = _first_face(bad, grp, topo)[1]
                raise ValueError(
                    f"{face} has a non-finite block in "
                    f"{verts.dtype} ({int(bad.sum())} such face(s) of degree {grp.k}); "
                    "compute in float64 or repair the face (torch_polylap.repair)."
                )
    masses_n, m = masses
    if masses_n is not None and m is not None:
        out = ~_masses_ok(masses_n, m)
        if bool(out.any()):
            v = int(torch.nonzero(out)[0, 0])
            mass = float(masses_n[v].double()) * float(unscale) ** 2
            raise ValueError(
                f"the mass of vertex {v} ({mass:.3g}; {int(out.sum())} such vertices) is "
                f"outside the normal range of {verts.dtype} ({info.tiny:.3g} .. {info.max:.3g}): "
                f"M0 scales with the square of the mesh's size, and its coordinates reach "
                f"{biggest:.3g}. Use float64, or rescale the vertices (L is scale invariant, "
                "M0 scales by the square of the factor)."
            )
    raise ValueError(
        f"L holds non-finite values in {verts.dtype} although every face block is finite: "
        "their sums overflow (a huge lam?). Use float64 or a smaller lam."
    )

"""The one assembly of every Laplacian in the package: per-face blocks scattered onto a pattern.

``L = sum_f P_f^T L_f P_f`` (AW11 eq. 3): a block kernel (:mod:`torch_polylap.kernels`)
evaluates the off-diagonal entries of the blocks of a chunk of faces of one degree, and
:func:`assemble` adds them, their mirrors and the diagonal ``-row sums`` (``L_f 1 = 0``) into
the CSR value array at the positions the :class:`~torch_polylap.topology.Topology` cached.
Validation costs one device sync per call: the degenerate-face flags of all chunks are reduced
on the device and read once.
"""

from __future__ import annotations

from collections.abc import Iterator

import torch

from .checks import check_verts
from .faces import FacesLike
from .kernels import BlockKernel
from .kernels.aw11 import aw11_entries, row_sums
from .kernels.frames import gather_corners
from .topology import DegreeGroup, Topology, TopologyView, get_topology
from .tracing import functional, require

__all__ = ["MeshFaces", "assemble", "assemble_flagged", "face_groups", "raise_bad_input"]

MeshFaces = FacesLike | Topology


def assemble(
    verts: torch.Tensor,
    view: TopologyView,
    topo: Topology,
    kernel: BlockKernel,
    want_mass: bool,
    validate: bool,
) -> tuple[torch.Tensor, torch.Tensor | None]:
    """CSR values of ``sum_f P_f^T L_f P_f`` and, optionally, the lumped masses (AW11 eq. 10).

    ``kernel`` (see :func:`~torch_polylap.kernels.block_kernel`) evaluates the blocks of each
    chunk of faces of one degree; each block's off-diagonal entries are scattered to their two
    mirrored positions and minus their row sums to the diagonal. ``view`` is ``topo.on(device)``,
    taken once by the caller.

    Autocast is off inside: the kernels form products of coordinates that half precision
    cannot hold, and some (dGBD20's einsum) would otherwise be cast to it.

    Returns:
        ``values`` ``(nnz,)`` on ``view``'s pattern and ``masses`` ``(V,)`` (or ``None``).
    """
    with torch.autocast(verts.device.type, enabled=False):
        if functional():
            return _assemble_functional(verts, view, topo, kernel, want_mass, validate)
        return _assemble_chunked(verts, view, topo, kernel, want_mass, validate)


def _assemble_chunked(
    verts: torch.Tensor,
    view: TopologyView,
    topo: Topology,
    kernel: BlockKernel,
    want_mass: bool,
    validate: bool,
) -> tuple[torch.Tensor, torch.Tensor | None]:
    """:func:`assemble` eagerly: chunks whose temporaries stay small, in place."""
    verts_t = verts.t().contiguous()
    values = verts.new_zeros(topo.nnz)
    masses = verts.new_zeros(topo.num_verts) if want_mass else None
    eps = torch.finfo(verts.dtype).eps
    degenerate = []
    for grp in view.groups:
        for chunk in grp.chunks:
            off, corner_mass, area, size2 = kernel(verts_t, grp, chunk.corners_t)
            flat = off.reshape(-1)
            values.index_add_(0, chunk.pos_upper, flat)
            values.index_add_(0, chunk.pos_lower, flat)
            values.index_add_(0, chunk.pos_diag, row_sums(off, grp).reshape(-1), alpha=-1)
            if masses is not None:
                masses.index_add_(0, chunk.corners_t.reshape(-1), corner_mass.reshape(-1))
            if validate:
                degenerate.append((area <= eps * size2).any())
    if validate:
        _validate(verts, topo, degenerate)
    return values, masses


def _assemble_functional(
    verts: torch.Tensor,
    view: TopologyView,
    topo: Topology,
    kernel: BlockKernel,
    want_mass: bool,
    validate: bool,
) -> tuple[torch.Tensor, torch.Tensor | None]:
    values, masses, ok = assemble_flagged(verts, view, topo, kernel, want_mass)
    if validate and not require(ok, _BAD_INPUT):
        raise_bad_input(verts, topo)
    return values, masses


def assemble_flagged(
    verts: torch.Tensor,
    view: TopologyView,
    topo: Topology,
    kernel: BlockKernel,
    want_mass: bool,
) -> tuple[torch.Tensor, torch.Tensor | None, torch.Tensor]:
    """:func:`assemble` for traced and transformed code: out of place, one pass per group.

    In place updates of a value array from batched blocks fail under vmap, and a loop over
    chunks would unroll into the traced graph (thousands of nodes at a million faces, which
    the C++ compiler behind inductor then fails on); torch.compile fuses the whole group
    instead, so the chunking that keeps eager temporaries small is not needed there.
    """
    verts_t = verts.t().contiguous()
    values = verts.new_zeros(topo.nnz)
    masses = verts.new_zeros(topo.num_verts) if want_mass else None
    eps = torch.finfo(verts.dtype).eps
    degenerate = []
    for i, grp in enumerate(view.groups):
        whole = view.whole(i)
        off, corner_mass, area, size2 = kernel(verts_t, grp, whole.corners_t)
        flat = off.reshape(-1)
        positions = torch.cat((whole.pos_upper, whole.pos_lower, whole.pos_diag))
        entries = torch.cat((flat, flat, -row_sums(off, grp).reshape(-1)))
        values = values.index_add(0, positions, entries)
        if masses is not None:
            masses = masses.index_add(0, whole.corners_t.reshape(-1), corner_mass.reshape(-1))
        degenerate.append((area <= eps * size2).any())
    return values, masses, _valid(verts, degenerate)


_BAD_INPUT = (
    "torch_polylap: non-finite vertex coordinates or a zero-area face. Inside torch.compile "
    "or torch.func.vmap the offending element cannot be named: call torch_polylap.laplacian "
    "eagerly on these vertices to find it, or pass validate=False to accept huge entries."
)


def _valid(verts: torch.Tensor, degenerate: list[torch.Tensor]) -> torch.Tensor:
    """0-dim bool: finite coordinates and no zero-area face."""
    ok = torch.isfinite(verts).all()
    if degenerate:
        ok = ok & ~torch.stack(degenerate).any()
    return ok


def _validate(verts: torch.Tensor, topo: Topology, degenerate: list[torch.Tensor]) -> None:
    """Raise on non-finite coordinates or a zero-area face (one device sync eagerly; an
    in-graph assertion when traced; a check of every batch entry under vmap)."""
    if not require(_valid(verts, degenerate), _BAD_INPUT):
        raise_bad_input(verts, topo)


def raise_bad_input(verts: torch.Tensor, topo: Topology) -> None:
    """Raise the ValueError that names the first non-finite vertex or zero-area face."""
    bad_v = ~torch.isfinite(verts).all(1)
    if bool(bad_v.any()):
        v = int(torch.nonzero(bad_v)[0, 0])
        raise ValueError(
            f"vertex {v} has non-finite coordinates {verts[v].tolist()} "
            f"({int(bad_v.sum())} such vertices); fix or remove them before building operators."
        )
    eps = torch.finfo(verts.dtype).eps
    for _, grp, x in face_groups(verts, topo):
        _, area, size2 = aw11_entries(x, grp, 0.0)
        bad = area <= eps * size2
        if bool(bad.any()):
            local = int(torch.nonzero(bad)[0, 0])
            f = int(grp.face_ids[local])
            raise ValueError(
                f"face {f} (vertices {topo.faces[f].tolist()}) has zero vector area "
                f"(|f| = {float(area[local]):.3g}); its corners are collinear or its loop cancels "
                f"out ({int(bad.sum())} such face(s) of degree {grp.k}). The Laplacian divides by "
                "|f|: remove the face, collapse it, or move its vertices apart. Thin faces with "
                "non-zero area are fine."
            )


def face_groups(
    verts: torch.Tensor, faces: MeshFaces
) -> Iterator[tuple[Topology, DegreeGroup, torch.Tensor]]:
    """``(topology, group, corners (3, k, F_k))`` for each degree group of the faces, in one
    device-bound view: the loop every face measure and DEC view runs."""
    check_verts(verts, finite=False)
    topo = get_topology(faces, verts.shape[0])
    verts_t = verts.t().contiguous()
    for grp in topo.on(verts.device).groups:
        yield topo, grp, gather_corners(verts_t, grp.corners_t)

"""The eager assembly: chunks of faces of one degree, their blocks scattered in place.

Each chunk's off-diagonal block entries are added at their two mirrored positions of the CSR
value array and minus their row sums at the diagonal (``L_f 1 = 0``), at the positions the
:class:`~torch_polylap.topology.Topology` cached; chunks keep the kernels' temporaries small.
With validation one device sync reads every check, and float32 faces whose kernel expects a
relative error above :data:`~torch_polylap.assembly.checks.FLOAT32_TOLERANCE` are evaluated
again in float64; a face so thin that float32 products with ``L`` lose more than that
(:data:`~torch_polylap.assembly.checks.FLOAT32_STRETCH_LIMIT`), read in the same sync, gives
one :class:`~torch_polylap.checks.Float32PrecisionWarning`.
"""

from __future__ import annotations

import torch

from ..kernels import BlockKernel
from ..kernels.aw11 import row_sums
from ..topology import DegreeGroup, GroupChunk, Topology, TopologyView
from .checks import (
    FLOAT32_STRETCH_LIMIT,
    FLOAT32_TOLERANCE,
    any_degenerate,
    input_ok,
    output_ok,
    raise_bad_input,
    warn_float32_products,
)
from .corners import gather_chunks
from .scaling import normalizer, unscaled

__all__ = ["assemble_chunked"]


def assemble_chunked(
    verts: torch.Tensor,
    view: TopologyView,
    topo: Topology,
    kernel: BlockKernel,
    *,
    want_mass: bool,
    validate: bool,
    warn: bool = True,
) -> tuple[torch.Tensor, torch.Tensor | None]:
    """:func:`assemble` eagerly: chunks whose temporaries stay small, in place; ``warn=False``
    leaves the float32 warning to the caller."""
    scale, unscale, finite = normalizer(verts)
    verts_t = verts.t().contiguous() * scale
    mixed = validate and verts.dtype == torch.float32
    parts = _scatter(verts_t, view, topo, kernel, want_mass=want_mass, mixed=mixed, verts_t64=None)
    values, masses_n, degenerate, ill, stretch = parts
    masses = unscaled(masses_n, unscale)
    if not validate:
        return values, masses
    flags = [input_ok(finite, degenerate), output_ok(values, masses_n, masses)]
    if ill:
        # NaN propagates: counts as ill-conditioned (and a NaN stretch as no warning: such a
        # face is degenerate, which raises)
        flags += [torch.stack(ill).amax(), torch.stack(stretch).amax()]
    read = torch.stack([f.to(verts.dtype) for f in flags]).tolist()
    checks = [bool(read[0]), bool(read[1])]
    worst, thinnest = (read[2], read[3]) if ill else (0.0, 0.0)
    if not worst <= FLOAT32_TOLERANCE:
        # rare: faces too ill-conditioned for float32; assembled again, those in float64
        values, masses_n = _scatter(
            verts_t,
            view,
            topo,
            kernel,
            want_mass=want_mass,
            mixed=mixed,
            verts_t64=verts_t.double(),
        )[:2]
        masses = unscaled(masses_n, unscale)
        checks[1] = bool(output_ok(values, masses_n, masses))
    if not (checks[0] and checks[1]):
        raise_bad_input(verts, topo, kernel, (masses_n, masses), mixed=mixed)
    if warn and thinnest > FLOAT32_STRETCH_LIMIT:
        warn_float32_products(verts, topo, kernel)
    return values, masses


def _scatter(
    verts_t: torch.Tensor,
    view: TopologyView,
    topo: Topology,
    kernel: BlockKernel,
    *,
    want_mass: bool,
    mixed: bool,
    verts_t64: torch.Tensor | None,
) -> tuple[
    torch.Tensor,
    torch.Tensor | None,
    list[torch.Tensor],
    list[torch.Tensor],
    list[torch.Tensor],
]:
    """The eager, chunked, in place assembly on normalized coordinates ``verts_t (3, V)``.

    Returns the values, the masses and per chunk 0-dim tensors: whether a face is degenerate;
    with ``mixed``, the largest expected relative error of a block (in units of one) and the
    largest ``s^2 / |f|`` (``kernel.stretch``, zero for the planarity operator, whose blocks
    do not divide by the area). With ``verts_t64`` given, the faces whose expected relative
    error exceeds :data:`FLOAT32_TOLERANCE` are evaluated from it in float64 and cast back
    (their float32 blocks never enter the values or the graph, so their gradients are the
    float64 ones).
    """
    values = verts_t.new_zeros(topo.nnz)
    masses = verts_t.new_zeros(topo.num_verts) if want_mass else None
    eps = torch.finfo(verts_t.dtype).eps
    degenerate, ill, stretch = [], [], []
    # differentiated: every chunk's corners gathered by one autograd node, whose backward
    # forms one (3, V) gradient rather than one per chunk
    one_node = verts_t64 is None and torch.is_grad_enabled() and verts_t.requires_grad
    for grp in view.groups:
        xs = gather_chunks(verts_t, [c.corners_t for c in grp.chunks]) if one_node else None
        for i, chunk in enumerate(grp.chunks):
            if verts_t64 is not None:
                _scatter_mixed(verts_t, verts_t64, grp, chunk, kernel, values, masses, eps)
                continue
            entries = (
                kernel(verts_t, grp, chunk.corners_t)
                if xs is None
                else kernel.on_corners(xs[i], grp)
            )
            off, corner_mass, area, size2, error = entries
            _scatter_blocks(grp, chunk, off, corner_mass, values, masses)
            degenerate.append(any_degenerate(area, size2, eps))
            if mixed:
                # the chunk's worst expected relative error (amax propagates NaN)
                ill.append(error.amax() * eps)
                geometric = kernel.geometric  # the planarity operator does not divide by |f|
                stretch.append(
                    kernel.stretch(area, size2, grp).amax() if geometric else area.new_zeros(())
                )
    return values, masses, degenerate, ill, stretch


def _scatter_blocks(
    grp: DegreeGroup,
    chunk: GroupChunk,
    off: torch.Tensor,
    corner_mass: torch.Tensor,
    values: torch.Tensor,
    masses: torch.Tensor | None,
) -> None:
    flat = off.reshape(-1)
    values.index_add_(0, chunk.pos_upper, flat)
    values.index_add_(0, chunk.pos_lower, flat)
    values.index_add_(0, chunk.pos_diag, row_sums(off, grp).reshape(-1), alpha=-1)
    if masses is not None:
        masses.index_add_(0, chunk.corners_t.reshape(-1), corner_mass.reshape(-1))


def _scatter_mixed(
    verts_t: torch.Tensor,
    verts_t64: torch.Tensor,
    grp: DegreeGroup,
    chunk: GroupChunk,
    kernel: BlockKernel,
    values: torch.Tensor,
    masses: torch.Tensor | None,
    eps: float,
) -> None:
    """One chunk with its ill-conditioned faces evaluated in float64 (host syncs: the rare
    path, after the validation found such faces)."""
    off, corner_mass, _, _, error = kernel(verts_t, grp, chunk.corners_t)
    ill = ~(error * eps <= FLOAT32_TOLERANCE)  # NaN bounds count as ill-conditioned
    if not bool(ill.any()):
        _scatter_blocks(grp, chunk, off, corner_mass, values, masses)
        return
    for part, source in ((~ill, verts_t), (ill, verts_t64)):
        faces = torch.nonzero(part)[:, 0]
        if faces.numel() == 0:
            continue
        sub = _sub_chunk(grp, chunk, faces)
        off, corner_mass = (t.to(values.dtype) for t in kernel(source, grp, sub.corners_t)[:2])
        _scatter_blocks(grp, sub, off, corner_mass, values, masses)


def _sub_chunk(grp: DegreeGroup, chunk: GroupChunk, faces: torch.Tensor) -> GroupChunk:
    """The faces ``faces`` (indices into the chunk) of ``chunk``, with their scatter maps."""
    p, k = grp.pair_i.numel(), grp.k

    def cols(t: torch.Tensor, rows: int) -> torch.Tensor:
        return t.view(rows, -1).index_select(1, faces).reshape(-1)

    return GroupChunk(
        chunk.start,
        chunk.stop,
        chunk.corners_t.index_select(1, faces),
        cols(chunk.pos_upper, p),
        cols(chunk.pos_lower, p),
        cols(chunk.pos_diag, k),
    )

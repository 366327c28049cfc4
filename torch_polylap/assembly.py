"""The one assembly of every Laplacian in the package: per-face blocks scattered onto a pattern.

``L = sum_f P_f^T L_f P_f`` (AW11 eq. 3): a block kernel (:mod:`torch_polylap.kernels`)
evaluates the off-diagonal entries of the blocks of a chunk of faces of one degree, and
:func:`assemble` adds them, their mirrors and the diagonal ``-row sums`` (``L_f 1 = 0``) into
the CSR value array at the positions the :class:`~torch_polylap.topology.Topology` cached.
Validation costs one device sync per call: the checks of all chunks are reduced on the device
and read once.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from typing import NamedTuple

import torch

from ._typing import MeshFaces
from .checks import check_verts, warn_outside_package
from .kernels import BlockKernel
from .kernels.aw11 import aw11_entries, row_sums
from .kernels.frames import gather_corners
from .kernels.gather import gather_chunks
from .sparse.gather_plan import GatherPlan, gather_plan
from .topology import DegreeGroup, GroupChunk, Topology, TopologyView, get_topology
from .tracing import functional, require, run_eagerly, tracing

__all__ = [
    "MeshFaces",
    "FLOAT32_TOLERANCE",
    "assemble",
    "assemble_flagged",
    "FlaggedAssembly",
    "face_groups",
    "raise_bad_input",
]


# A float32 face whose kernel bounds the relative error of its block above this is evaluated
# in float64 (eager assembly with validation; see docs/math/properties.md, "Finite precision").
FLOAT32_TOLERANCE = 1e-2
# expected relative errors above which float64 blocks do not save a float32 gradient: faces of
# thinness below about 1e-6 (AW11's bound 4 / t times float32's epsilon)
FLOAT32_HOPELESS = 0.4


def assemble(
    verts: torch.Tensor,
    view: TopologyView,
    topo: Topology,
    kernel: BlockKernel,
    *,
    want_mass: bool,
    validate: bool,
) -> tuple[torch.Tensor, torch.Tensor | None]:
    """CSR values of ``sum_f P_f^T L_f P_f`` and, optionally, the lumped masses (AW11 eq. 10).

    ``kernel`` (see :func:`~torch_polylap.kernels.block_kernel`) evaluates the blocks of each
    chunk of faces of one degree; each block's off-diagonal entries are scattered to their two
    mirrored positions and minus their row sums to the diagonal. ``view`` is ``topo.on(device)``,
    taken once by the caller.

    The kernels see the coordinates divided by a power of two near their largest magnitude
    (exact: ``L`` is scale invariant and the masses are scaled back by its square), so no
    intermediate under- or overflows whatever the mesh's scale. With ``validate``, one device
    sync reads every check: finite coordinates, no zero-area face, finite ``L`` and masses
    that the dtype represents. For float32 input the same sync reads whether a face's kernel
    expects a relative error above :data:`FLOAT32_TOLERANCE` (thin or nearly degenerate
    faces; PLMS on nearly planar ones); if one does, the values are assembled again with
    those faces evaluated in float64.

    Autocast is off inside: the kernels form products of coordinates that half precision
    cannot hold, and some (dGBD20's einsum) would otherwise be cast to it.

    Returns:
        ``values`` ``(nnz,)`` on ``view``'s pattern and ``masses`` ``(V,)`` (or ``None``).
    """
    with torch.autocast(verts.device.type, enabled=False):
        if functional():
            return _assemble_functional(
                verts, view, topo, kernel, want_mass=want_mass, validate=validate
            )
        return _assemble_chunked(verts, view, topo, kernel, want_mass=want_mass, validate=validate)


def _assemble_chunked(
    verts: torch.Tensor,
    view: TopologyView,
    topo: Topology,
    kernel: BlockKernel,
    *,
    want_mass: bool,
    validate: bool,
) -> tuple[torch.Tensor, torch.Tensor | None]:
    """:func:`assemble` eagerly: chunks whose temporaries stay small, in place."""
    scale, unscale, finite = _normalizer(verts)
    verts_t = verts.t().contiguous() * scale
    mixed = validate and verts.dtype == torch.float32
    parts = _scatter(verts_t, view, topo, kernel, want_mass=want_mass, mixed=mixed, verts_t64=None)
    values, masses_n, degenerate, ill = parts
    masses = _unscaled(masses_n, unscale)
    if not validate:
        return values, masses
    flags = [_input_ok(finite, degenerate), _output_ok(values, masses_n, masses)]
    if ill:
        flags.append(torch.stack(ill).amax())  # NaN propagates: counts as ill-conditioned
    read = torch.stack([f.to(verts.dtype) for f in flags]).tolist()
    checks = [bool(read[0]), bool(read[1])]
    worst = read[2] if ill else 0.0
    if checks[0] and worst > FLOAT32_HOPELESS:
        warn_outside_package(
            f"torch_polylap: a face is so thin that float32 gradients lose accuracy even with its "
            f"blocks evaluated in float64 (expected relative error {worst:.1g}; the backward "
            "pass itself rounds in float32): use float64 vertices for this mesh."
        )
    if not worst <= FLOAT32_TOLERANCE:
        # rare: faces too ill-conditioned for float32; assembled again, those in float64
        values, masses_n, _, _ = _scatter(
            verts_t,
            view,
            topo,
            kernel,
            want_mass=want_mass,
            mixed=mixed,
            verts_t64=verts_t.double(),
        )
        masses = _unscaled(masses_n, unscale)
        checks[1] = bool(_output_ok(values, masses_n, masses))
    if not (checks[0] and checks[1]):
        raise_bad_input(verts, topo, kernel, (masses_n, masses), mixed=mixed)
    return values, masses


class _Normalizer(NamedTuple):
    scale: torch.Tensor
    """0-dim power of two that brings the largest coordinate magnitude into ``[1/2, 1)``."""
    unscale: torch.Tensor
    """0-dim, its reciprocal."""
    finite: torch.Tensor
    """0-dim bool: every coordinate is finite (NaN and infinities reach the extremes)."""


def _normalizer(verts: torch.Tensor) -> _Normalizer:
    """The exact rescaling of the coordinates (multiplying by powers of two), without a
    device sync, and whether they are finite: one pass over ``verts`` for both."""
    info = torch.finfo(verts.dtype)
    if verts.numel() == 0:
        one = verts.new_ones(())
        return _Normalizer(one, one, torch.ones((), dtype=torch.bool, device=verts.device))
    extremes = torch.stack(torch.aminmax(verts.detach()))
    low, high = extremes.unbind(0)
    exponent = torch.frexp(torch.maximum(high, -low)).exponent
    # within the normal range both ways; a non-finite maximum is refused by the validation
    exponent = exponent.clamp(int(math.log2(info.tiny)) + 1, int(math.log2(info.max)) - 1)
    one = verts.new_ones(())
    return _Normalizer(
        torch.ldexp(one, -exponent), torch.ldexp(one, exponent), torch.isfinite(extremes).all()
    )


def _unscaled(masses: torch.Tensor | None, unscale: torch.Tensor) -> torch.Tensor | None:
    """The masses of the normalized coordinates in the caller's units (two factors: the
    square of ``unscale`` alone can overflow where the product does not)."""
    return None if masses is None else masses * unscale * unscale


def _scatter(
    verts_t: torch.Tensor,
    view: TopologyView,
    topo: Topology,
    kernel: BlockKernel,
    *,
    want_mass: bool,
    mixed: bool,
    verts_t64: torch.Tensor | None,
) -> tuple[torch.Tensor, torch.Tensor | None, list[torch.Tensor], list[torch.Tensor]]:
    """The eager, chunked, in place assembly on normalized coordinates ``verts_t (3, V)``.

    With ``mixed``, also returns per chunk the ``(F_c,)`` flags of faces whose expected
    relative error exceeds :data:`FLOAT32_TOLERANCE`; with ``verts_t64`` given, those faces
    are evaluated from it in float64 and cast back (their float32 blocks never enter the
    values or the graph, so their gradients are the float64 ones).
    """
    values = verts_t.new_zeros(topo.nnz)
    masses = verts_t.new_zeros(topo.num_verts) if want_mass else None
    eps = torch.finfo(verts_t.dtype).eps
    degenerate, ill = [], []
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
            degenerate.append(_any_degenerate(area, size2, eps))
            if mixed:
                # the chunk's worst expected relative error (amax propagates NaN)
                ill.append(error.amax() * eps)
    return values, masses, degenerate, ill


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


def _any_degenerate(area: torch.Tensor, size2: torch.Tensor, eps: float) -> torch.Tensor:
    """Whether a face has zero vector area (NaN included), or is too small against the mesh's
    largest coordinate for the dtype (``s^2`` of the normalized face below ``tiny / eps``: its
    products would be subnormal)."""
    tiny = torch.finfo(area.dtype).tiny
    return (~(area > eps * size2)).any() | ~(size2.amin() >= tiny / eps)


def _finite(t: torch.Tensor) -> torch.Tensor:
    """Whether every entry of ``t`` is finite: its extremes are (NaN propagates through them),
    which is one read of ``t`` where ``isfinite(t).all()`` takes several."""
    if t.numel() == 0:
        return torch.ones((), dtype=torch.bool, device=t.device)
    return torch.isfinite(torch.stack(torch.aminmax(t))).all()


def _input_ok(finite: torch.Tensor, degenerate: list[torch.Tensor]) -> torch.Tensor:
    """Finite coordinates (``finite``, from :func:`_normalizer`) and no degenerate face."""
    return finite & ~torch.stack(degenerate).any() if degenerate else finite


def _output_ok(
    values: torch.Tensor, masses_n: torch.Tensor | None, masses: torch.Tensor | None
) -> torch.Tensor:
    """Finite values, and masses that neither overflow nor underflow."""
    ok = _finite(values)
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


def _assemble_functional(
    verts: torch.Tensor,
    view: TopologyView,
    topo: Topology,
    kernel: BlockKernel,
    *,
    want_mass: bool,
    validate: bool,
) -> tuple[torch.Tensor, torch.Tensor | None]:
    """:func:`assemble` for traced and transformed code (see :func:`assemble_flagged`); the
    checks are an in-graph assertion when traced, a batch-wide check under vmap, and under
    the other torch.func transforms the eager error that names the vertex or face."""
    if tracing():
        # compiled: the gather form, which inductor fuses far better than scatters
        plan = run_eagerly(gather_plan_of, topo, view)
        flagged = assemble_gathered(verts, view, kernel, plan, want_mass=want_mass)
    else:
        flagged = assemble_flagged(verts, view, topo, kernel, want_mass=want_mass)
    values, masses, ok, accurate = flagged
    if validate:
        if not require(ok, BAD_INPUT):
            raise_bad_input(verts, topo, kernel)
        if not require(accurate, FLOAT32_INACCURATE):
            raise ValueError(FLOAT32_INACCURATE)
    return values, masses


class FlaggedAssembly(NamedTuple):
    """What :func:`assemble_flagged` returns; unpacks as ``values, masses, ok, accurate``."""

    values: torch.Tensor
    """``(nnz,)`` the values on the view's pattern."""
    masses: torch.Tensor | None
    """``(V,)`` the lumped masses, or ``None`` when not asked for."""
    ok: torch.Tensor
    """0-dim bool: every check passed."""
    accurate: torch.Tensor
    """0-dim bool: every face's expected relative error stays within
    :data:`FLOAT32_TOLERANCE` (always true in float64)."""


def assemble_flagged(
    verts: torch.Tensor,
    view: TopologyView,
    topo: Topology,
    kernel: BlockKernel,
    *,
    want_mass: bool,
) -> FlaggedAssembly:
    """The assembly out of place, one pass per group, with its checks as 0-dim flags (see
    :class:`FlaggedAssembly`). No error is raised here: batches check theirs together.

    In place updates of a value array from batched blocks fail under vmap, and a loop over
    chunks would unroll into the traced graph (thousands of nodes at a million faces, which
    the C++ compiler behind inductor then fails on); torch.compile fuses the whole group
    instead, so the chunking that keeps eager temporaries small is not needed there. Faces
    that float32 evaluates poorly are not re-evaluated in float64 here (that needs their
    number on the host): such faces make ``accurate`` false, and the callers refuse them
    rather than return a silently inaccurate result.
    """
    scale, unscale, finite = _normalizer(verts)
    verts_t = verts.t().contiguous() * scale
    values = verts.new_zeros(topo.nnz)
    masses = verts.new_zeros(topo.num_verts) if want_mass else None
    eps = torch.finfo(verts.dtype).eps
    degenerate, accurate = [], []
    for i, grp in enumerate(view.groups):
        whole = view.whole(i)
        off, corner_mass, area, size2, error = kernel(verts_t, grp, whole.corners_t)
        if verts.dtype == torch.float32:
            accurate.append(error.amax() * eps <= FLOAT32_TOLERANCE)
        flat = off.reshape(-1)
        positions = torch.cat((whole.pos_upper, whole.pos_lower, whole.pos_diag))
        entries = torch.cat((flat, flat, -row_sums(off, grp).reshape(-1)))
        values = values.index_add(0, positions, entries)
        if masses is not None:
            masses = masses.index_add(0, whole.corners_t.reshape(-1), corner_mass.reshape(-1))
        degenerate.append(_any_degenerate(area, size2, eps))
    masses_n, masses = masses, _unscaled(masses, unscale)
    ok = _input_ok(finite, degenerate) & _output_ok(values, masses_n, masses)
    all_accurate = torch.stack(accurate).all() if accurate else torch.ones_like(ok)
    return FlaggedAssembly(values, masses, ok, all_accurate)


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
    scale, unscale, _ = _normalizer(verts)
    biggest = float(verts.abs().max())
    verts_n = verts * scale
    for _, grp, x in face_groups(verts_n, topo):
        _, area, size2 = aw11_entries(x, grp, 0.0)
        small = ~(size2 >= info.tiny / info.eps)
        if bool(small.any()):
            local = int(torch.nonzero(small)[0, 0])
            f = int(grp.face_ids[local])
            raise ValueError(
                f"face {f} (vertices {topo.faces[f].tolist()}) is about "
                f"{math.sqrt(float(size2[local])):.1g} times the mesh's largest coordinate "
                f"({biggest:.3g}): too small for {verts.dtype} to compute its block "
                f"({int(small.sum())} such face(s) of degree {grp.k}). Use float64, or move "
                "far-away vertices (unreferenced ones included) closer."
            )
        bad = ~(area > info.eps * size2)
        if bool(bad.any()):
            local = int(torch.nonzero(bad)[0, 0])
            f = int(grp.face_ids[local])
            rel = float(area[local] / size2[local])
            raise ValueError(
                f"face {f} (vertices {topo.faces[f].tolist()}) has zero vector area "
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
                local = int(torch.nonzero(bad)[0, 0])
                f = int(grp.face_ids[local])
                raise ValueError(
                    f"face {f} (vertices {topo.faces[f].tolist()}) has a non-finite block in "
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


def gather_plan_of(topo: Topology, view: TopologyView) -> GatherPlan:
    """``topo``'s :class:`~torch_polylap.sparse.gather_plan.GatherPlan` on ``view``'s device,
    computed once per topology and device."""
    key = ("gather_plan", view.col.device)
    plan = topo.derived.get(key)
    if plan is None:
        wholes = [view.whole(i) for i in range(len(view.groups))]
        shapes = [(g.pair_i.numel(), g.face_ids.numel()) for g in view.groups]
        cpu = gather_plan(
            [w.pos_upper.cpu().numpy().reshape(s) for w, s in zip(wholes, shapes, strict=True)],
            [w.pos_lower.cpu().numpy().reshape(s) for w, s in zip(wholes, shapes, strict=True)],
            [g.corners_t.cpu().numpy() for g in view.groups],
            view.pattern.diagonal_positions().cpu().numpy(),
            topo.nnz,
        )
        plan = cpu.to(view.col.device)
        topo.derived[key] = plan
    assert isinstance(plan, GatherPlan)
    return plan


def assemble_gathered(
    verts: torch.Tensor,
    view: TopologyView,
    kernel: BlockKernel,
    plan: GatherPlan,
    *,
    want_mass: bool,
) -> FlaggedAssembly:
    """:func:`assemble_flagged` with gathers instead of scatters (``plan``, from
    :func:`gather_plan_of`): every group's blocks at once, then each stored value as the sum
    of its (mostly two) per-face entries and each diagonal as minus the sum of the row sums
    of its vertex's blocks. Written for torch.compile, which fuses the kernels and the
    gathers; eagerly the chunked :func:`assemble` is faster."""
    scale, unscale, finite = _normalizer(verts)
    verts_t = verts.t() * scale
    eps = torch.finfo(verts.dtype).eps
    offs, sums, corner_masses, degenerate, accurate = [], [], [], [], []
    corners = plan.vertex.corners(verts_t)
    start = 0
    for grp in view.groups:
        k, count = grp.corners_t.shape
        x = corners[:, start : start + k * count].view(3, k, count)
        start += k * count
        off, corner_mass, area, size2, error = kernel.on_corners(x, grp)
        offs.append(off.reshape(-1))
        sums.append(row_sums(off, grp).reshape(-1))
        corner_masses.append(corner_mass.reshape(-1))
        degenerate.append(_any_degenerate(area, size2, eps))
        if verts.dtype == torch.float32:
            accurate.append(error.amax() * eps <= FLOAT32_TOLERANCE)
    # an empty piece each, for a mesh without faces
    none = verts_t.new_zeros(0)
    diagonal = -plan.vertex.total(torch.cat([*sums, none]))
    values = plan.values(torch.cat([*offs, none]), diagonal)
    masses_n = plan.vertex.total(torch.cat([*corner_masses, none])) if want_mass else None
    masses = _unscaled(masses_n, unscale)
    ok = _input_ok(finite, degenerate) & _output_ok(values, masses_n, masses)
    all_accurate = torch.stack(accurate).all() if accurate else torch.ones_like(ok)
    return FlaggedAssembly(values, masses, ok, all_accurate)

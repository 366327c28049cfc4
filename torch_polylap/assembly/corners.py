"""Corner positions: of every degree group of a mesh, and of many chunks as one autograd node.

:func:`face_groups` is the loop every face measure and DEC view runs.

The eager assembly evaluates its kernels chunk by chunk so that their temporaries stay in
cache. Were each chunk's corners gathered by its own differentiable gather, the backward would
form one dense ``(3, V)`` gradient per chunk (eighteen at a million quads, each zero-filled,
written and added to the others: most of a Laplacian's backward). :class:`CornerGather`
gathers every chunk's corners in one node whose backward adds all the chunks' corner gradients
into a single ``(3, V)`` array.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import torch

from .._typing import MeshFaces
from ..checks import check_verts
from ..kernels.frames import gather_corners
from ..topology import DegreeGroup, Topology, get_topology

__all__ = ["face_groups", "gather_chunks"]


def _gather(verts_t: torch.Tensor, corners_t: torch.Tensor) -> torch.Tensor:
    """``(3, k, c)`` positions of the corners ``corners_t`` ``(k, c)``: one 1-D
    ``index_select`` per coordinate row over the flattened corners (faster on the CPU than
    ``take`` or a 2-D ``index_select``)."""
    out = verts_t.new_empty((3, *corners_t.shape))
    flat = corners_t.reshape(-1)
    for i in range(3):
        torch.index_select(verts_t[i], 0, flat, out=out[i].view(-1))
    return out


def _scatter(
    grads: tuple[torch.Tensor | None, ...], corners: tuple[torch.Tensor, ...], out: torch.Tensor
) -> torch.Tensor:
    """``out`` ``(3, V)`` zeros plus the corner gradients ``grads[c]`` ``(3, k, c)`` added at
    their vertices (in place: the one dense array of the backward)."""
    for g, c in zip(grads, corners, strict=True):
        if g is not None:
            out.index_add_(1, c.reshape(-1), g.reshape(3, -1))
    return out


class CornerGather(torch.autograd.Function):
    """``verts_t (3, V), *corners (k_c, c)`` to the ``(3, k_c, c)`` corner positions of each
    chunk. Reverse mode: one ``(3, V)`` gradient for all chunks (differentiable again, for
    Hessian-vector products); forward mode: the gathered tangents."""

    @staticmethod
    def forward(verts_t: torch.Tensor, *corners: torch.Tensor) -> tuple[torch.Tensor, ...]:
        return tuple(_gather(verts_t, c) for c in corners)

    @staticmethod
    def setup_context(ctx: Any, inputs: tuple[Any, ...], output: Any) -> None:
        ctx.set_materialize_grads(False)
        ctx.corners = inputs[1:]
        verts_t = inputs[0]
        ctx.meta = (verts_t.shape, verts_t.dtype, verts_t.device)

    @staticmethod
    def backward(ctx: Any, *grads: torch.Tensor | None) -> tuple[torch.Tensor | None, ...]:
        shape, dtype, device = ctx.meta
        out = torch.zeros(shape, dtype=dtype, device=device)
        return (_scatter(grads, ctx.corners, out), *(None for _ in ctx.corners))

    @staticmethod
    def jvp(ctx: Any, dverts: torch.Tensor, *_: Any) -> tuple[torch.Tensor, ...]:
        return tuple(_gather(dverts, c) for c in ctx.corners)


def gather_chunks(verts_t: torch.Tensor, corners: list[torch.Tensor]) -> list[torch.Tensor]:
    """``(3, k, c)`` corner positions of each chunk's ``(k, c)`` corners, differentiable in
    ``verts_t`` ``(3, V)`` as one node (see :class:`CornerGather`)."""
    return list(CornerGather.apply(verts_t, *corners))


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

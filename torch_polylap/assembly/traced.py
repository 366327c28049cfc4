"""``L`` and ``M0`` inside torch.compile, for any mesh of one face degree: one graph per degree.

Traced code cannot read the faces, yet the topology (pattern, corner layout, gather plan) fixes
what the assembly does. Baking one mesh's topology into the graph as constants would compile a
graph per mesh. Here the topology is the output of one operator, ``torch_polylap::topology``,
that runs at every call of the compiled code (eagerly, on the real faces: a lookup in the
package's topology cache) and whose index arrays enter the graph as tensors. Their sizes are
symbols: the vertex and face counts are those of the inputs, the stored entries and the few
irregular corners are sizes only the data decides. A dataset of meshes of one degree (quad
grids of any size, triangle meshes) then runs through one graph with dynamic shapes; only the
degree ``k`` of an ``(F, k)`` faces tensor is part of the graph, and torch.compile guards on it.

The faces and the topology can no longer disagree: the topology is that of the faces given.
"""

from __future__ import annotations

import torch

from .._torch_compat import data_dependent_size
from ..kernels import BlockKernel
from ..sparse.operator import SparseOperator
from ..topology import get_topology
from ..topology.groups import DegreeGroup
from ..tracing import require
from .checks import BAD_INPUT, FLOAT32_INACCURATE
from .gather_plan import GatherPlan, VertexSums
from .gathered import assemble_gathered, gather_plan_of

__all__ = ["traced_laplacian", "uniform_topology"]


@torch.library.custom_op("torch_polylap::topology", mutates_args=())
def uniform_topology(
    faces: torch.Tensor, num_verts: int, device: torch.device
) -> list[torch.Tensor]:
    """The index arrays of the topology of ``faces`` ``(F, k)`` with ``num_verts`` vertices, on
    ``device`` (the vertices'), for :func:`traced_laplacian`.

    Returns ``[crow (V + 1,), col (nnz,), row (nnz,), corners_t (k, F), first (nnz,),
    second (nnz,), rest_pos (R,), rest (R,), layers (D, V), rest_vertex (S,), rest_corner (S,),
    corner_vertex (k F,), pos_upper (P F,), pos_lower (P F,), diag_pos (V,)]``: the pattern of
    ``L``, the corners of the faces and the
    :class:`~torch_polylap.assembly.gather_plan.GatherPlan`. The topology comes from the
    package's cache (built on the first call for a faces tensor, with its errors naming the
    face); copies are returned, since a compiled graph may write into its buffers.
    """
    topo = get_topology(faces, num_verts)
    view = topo.on(device)
    plan = gather_plan_of(topo, view)
    vertex = plan.vertex
    (group,) = view.groups if view.groups else (None,)
    k = faces.shape[1]
    corners_t = group.corners_t if group is not None else view.col.new_zeros((k, 0))
    arrays = [
        view.crow,
        view.col,
        view.pattern.row,
        corners_t,
        plan.first,
        plan.second,
        plan.rest_pos,
        plan.rest,
        vertex.layers,
        vertex.rest_vertex,
        vertex.rest,
        vertex.corner_vertex,
        plan.pos_upper,
        plan.pos_lower,
        plan.diag_pos,
    ]
    return [a.clone() for a in arrays]


@uniform_topology.register_fake
def _uniform_topology_fake(
    faces: torch.Tensor, num_verts: int, device: torch.device
) -> list[torch.Tensor]:
    ctx = torch.library.get_ctx()
    count, k = faces.shape
    nnz, rest, layers, rest_vertex = (data_dependent_size(ctx) for _ in range(4))
    pairs = k * (k - 1) // 2 * count
    sizes = [
        (num_verts + 1,),
        (nnz,),
        (nnz,),
        (k, count),
        (nnz,),
        (nnz,),
        (rest,),
        (rest,),
        (layers, num_verts),
        (rest_vertex,),
        (rest_vertex,),
        (k * count,),
        (pairs,),
        (pairs,),
        (num_verts,),
    ]
    return [torch.empty(size, dtype=torch.int64, device=device) for size in sizes]


class _Groups:
    """The one degree group, as :func:`assemble_gathered` reads a view."""

    def __init__(self, group: DegreeGroup) -> None:
        self.groups = [group]


def traced_laplacian(
    verts: torch.Tensor,
    faces: torch.Tensor,
    kernel: BlockKernel,
    *,
    validate: bool,
) -> tuple[SparseOperator, SparseOperator]:
    """``(L, M0)`` of ``verts`` ``(V, 3)`` and ``faces`` ``(F, k)`` in traced code, the
    topology's arrays computed at every call by :func:`uniform_topology` (see the module).

    The checks are in-graph assertions, as in the other traced assembly.
    """
    num_verts = verts.shape[0]
    k = int(faces.shape[1])  # the graph's one structural constant: torch.compile guards on it
    (crow, col, row, corners_t, first, second, rest_pos, rest, layers, rest_vertex,
     rest_corner, corner_vertex, pos_upper, pos_lower, diag_pos) = uniform_topology(
        faces, num_verts, verts.device
    )  # fmt: skip
    pair_i, pair_j = torch.triu_indices(k, k, 1, device=verts.device)
    face_ids = torch.arange(faces.shape[0], device=verts.device)
    group = DegreeGroup(k, face_ids, corners_t, pair_i, pair_j, ())
    vertex = VertexSums(layers, rest_vertex, rest_corner, corner_vertex, symbolic=True)
    plan = GatherPlan(
        first,
        second,
        rest_pos,
        rest,
        vertex,
        pos_upper,
        pos_lower,
        diag_pos,
        num_off=pos_upper.shape[0],
        symbolic=True,
    )
    # autocast off, as in every assembly: half precision cannot hold the kernels' products
    with torch.autocast(verts.device.type, enabled=False):
        values, masses, ok, accurate, _ = assemble_gathered(
            verts, _Groups(group), kernel, plan, want_mass=True
        )
    if validate:
        require(ok, BAD_INPUT)
        require(accurate, FLOAT32_INACCURATE)
    assert masses is not None
    shape = (num_verts, num_verts)
    # L is taken to store every diagonal entry (diagonal class 1), which M0 + t L checks in
    # the graph (a mesh without isolated vertices); M0 is a diagonal (class 2)
    L = SparseOperator(values, crow, col, row, shape, True, -1, 1)
    diagonal = torch.arange(num_verts + 1, device=verts.device)
    M0 = SparseOperator(masses, diagonal, diagonal[:-1], diagonal[:-1], shape, True, -1, 2)
    return L, M0

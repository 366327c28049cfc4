"""AW11's discrete-exterior-calculus view: ``L = d^T M1 d`` with its factors made explicit.

The paper builds ``L`` from the half-edge coboundary ``d`` (eq. 2) and an inner product on
1-forms ``M1 = blockdiag(M_f)`` (eq. 5, 9). :func:`~torch_polylap.laplacian` never forms them;
they are here for inspection, teaching and tests (``coboundary(F).T @ M1 @ coboundary(F)``
equals ``L`` to round-off), together with the dense per-face blocks ``L_f``.
"""

from __future__ import annotations

import torch

from ._typing import MeshFaces
from .assembly import face_groups
from .checks import Lam, check_lam
from .kernels import block_kernel
from .kernels.aw11 import row_sums
from .kernels.frames import corner_terms, plane_basis, stable_norm
from .sparse import operator_from_parts
from .topology import Topology, build_topology, half_edge_vertices

__all__ = ["coboundary", "one_form_inner_product", "local_laplacians"]


def local_laplacians(
    verts: torch.Tensor,
    faces: MeshFaces,
    lam: Lam = 1.0,
    *,
    geometric: bool = True,
    method: str = "aw11",
) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """Dense blocks ``L_f = d^T M_f d``: ``(face_ids (F_k,), blocks (F_k, k, k))`` per degree.

    For inspection and tests; :func:`~torch_polylap.laplacian` never materializes them.
    ``geometric=False`` gives AW11's planarity blocks ``lambda d^T Pi d``; ``method`` the
    blocks of another Laplacian (``"plms"``, ``"degoes"``; see
    :func:`~torch_polylap.laplacian`), which sum to its ``L`` the same way.
    """
    lam = check_lam(lam)
    kernel = block_kernel(method, lam, geometric=geometric)
    verts_t = verts.t().contiguous()
    out = []
    for _, grp, x in face_groups(verts, faces):
        off = kernel(verts_t, grp, grp.corners_t)[0]
        blocks = verts.new_zeros(x.shape[2], grp.k, grp.k)
        blocks[:, grp.pair_i, grp.pair_j] = off.t()
        blocks[:, grp.pair_j, grp.pair_i] = off.t()
        ar = torch.arange(grp.k, device=verts.device)
        blocks[:, ar, ar] = -row_sums(off, grp).t()
        out.append((grp.face_ids, blocks))
    return out


def coboundary(
    faces: MeshFaces,
    num_verts: int | None = None,
    *,
    dtype: torch.dtype = torch.float64,
    device: torch.device | str | None = None,
) -> torch.Tensor:
    """The half-edge coboundary ``d`` (AW11 eq. 2), ``(N, V)`` sparse CSR; ``N`` counts corners.

    Row ``h`` is the half-edge leaving corner ``h`` of the packed faces (corner ``c`` of face ``f``
    goes to corner ``c + 1``): ``(d u)_h = u(next) - u(this)``. Together with
    :func:`one_form_inner_product`, ``L = d^T M1 d``. Its entries are ``+-1`` in ``dtype``.
    """
    topo = faces if isinstance(faces, Topology) else build_topology(faces, num_verts)
    this_v, next_v = half_edge_vertices(topo.faces)
    n = this_v.numel()
    cols = torch.stack((torch.minimum(this_v, next_v), torch.maximum(this_v, next_v)), 1)
    sign = torch.where(this_v < next_v, 1.0, -1.0).to(dtype)
    vals = torch.stack((-sign, sign), 1)  # -1 at the tail, +1 at the head, sorted by column
    crow = torch.arange(0, 2 * n + 1, 2)
    return operator_from_parts(
        crow.to(device),
        cols.reshape(-1).to(device),
        vals.reshape(-1).to(device),
        (n, topo.num_verts),
    )


def one_form_inner_product(verts: torch.Tensor, faces: MeshFaces, lam: Lam = 1.0) -> torch.Tensor:
    """The inner product on 1-forms ``M1 = blockdiag(M_f)`` (AW11 eq. 5, 9), ``(N, N)`` sparse CSR.

    ``M_f = B B^T / |f| + lambda Pi`` with the midpoints ``B`` taken relative to the face's vertex
    centroid (the paper's choice for stability; ``M_f`` itself depends on the origin, ``d^T M_f d``
    does not). Positive definite for ``lambda > 0`` (Theorem 1). Rows follow :func:`coboundary`.
    """
    lam = check_lam(lam)
    parts = []
    topo = None
    for topo, grp, x in face_groups(verts, faces):  # noqa: B007 (topo is used after the loop)
        e, _, a = corner_terms(x)
        area = stable_norm(a, 0)
        b = 0.5 * (x + torch.roll(x, -1, dims=1))
        b = b - x.mean(1, keepdim=True)
        geo = torch.einsum("cif,cjf->fij", b, b) / area[:, None, None]
        q1, q2 = plane_basis(e, a / area)
        proj = torch.eye(grp.k, dtype=x.dtype, device=x.device) - (
            torch.einsum("if,jf->fij", q1, q1) + torch.einsum("if,jf->fij", q2, q2)
        )
        parts.append((grp, geo + lam * proj))
    if topo is None:
        return operator_from_parts(
            torch.zeros(1, dtype=torch.int64),
            torch.zeros(0, dtype=torch.int64),
            verts.new_zeros(0),
            (0, 0),
        )
    pf = topo.faces
    n = pf.num_corners
    off = pf.offsets.to(verts.device)
    sizes = pf.sizes.to(verts.device)
    row_len = sizes[pf.corner_face.to(verts.device)]
    crow = torch.zeros(n + 1, dtype=torch.int64, device=verts.device)
    torch.cumsum(row_len, 0, out=crow[1:])
    col = torch.empty(int(crow[-1]), dtype=torch.int64, device=verts.device)
    values = verts.new_zeros(int(crow[-1]))
    for grp, blocks in parts:
        k = grp.k
        first = off[grp.face_ids]  # (F_k,) first corner of each face
        rows = first[:, None] + torch.arange(k, device=verts.device)  # (F_k, k)
        slots = crow[rows][:, :, None] + torch.arange(k, device=verts.device)  # (F_k, k, k)
        col[slots.reshape(-1)] = (
            (first[:, None, None] + torch.arange(k, device=verts.device))
            .expand(-1, k, k)
            .reshape(-1)
        )
        values = values.index_put((slots.reshape(-1),), blocks.reshape(-1))
    return operator_from_parts(crow, col, values, (n, n), symmetric=True)

"""The Diamond Laplacian of Bunge, Botsch and Alexa 2021, surface version (``method="diamond"``).

"The Diamond Laplace for Polygonal and Polyhedral Meshes" (Comput. Graph. Forum 40(5)), 2-D
case. Unlike the other methods it is not a sum of per-face blocks: its stencil couples the two
faces at every edge, so it has its own pattern and assembly here.

The construction, in this module's words:

* every face ``f`` gets the virtual vertex of PLMS, ``x_f = sum_i w_i x_i`` with the affine
  weights minimizing the sum of squared areas of the triangle fan
  (:func:`~torch_polylap.kernels.plms.virtual_vertices`); ``P`` (``(V + F) x V``) prolongs
  vertex values to vertices and face points, ``u_f = sum_i w_i u_i``;
* every edge ``(i, j)`` with faces ``g`` and ``f`` spans the *diamond* ``(x_i, x_g, x_j, x_f)``
  with the diagonals ``d_1 = x_j - x_i`` and ``d_2 = x_g - x_f``. At a boundary edge the missing
  face point is the edge's midpoint (value ``(u_i + u_j) / 2``): the diamond is a triangle;
* the diamond is flattened into the plane of the triangle ``(x_i, x_j, x_g)``, ``g`` the first
  face (in the mesh's face order) that uses the edge, with ``i -> j`` in that face's
  orientation; ``x_f`` is projected orthogonally into that plane. There, the function that is
  linear along both diagonals has the constant gradient ``grad u`` with
  ``grad u . d_1 = u_j - u_i = alpha`` and ``grad u . d_2 = u_g - u_f = beta``, and the diamond
  has the (signed) area ``c / 2`` with ``c = d_1 x d_2``. Its Dirichlet energy is

      area |grad u|^2 = (alpha^2 |d_2|^2 - 2 alpha beta (d_1 . d_2) + beta^2 |d_1|^2) / (2 c)

  (projected ``d_2``; ``d_1`` lies in the plane). With ``e = x_j - x_i``, ``a_perp`` the part of
  ``x_g - x_i`` orthogonal to ``e`` and ``d = x_g - x_f``: ``c = |e| (d . a_perp) / |a_perp|``,
  ``d_1 . d_2 = d . e`` and ``|d_2|^2 = (d . a_perp)^2 / |a_perp|^2 + (d . e)^2 / |e|^2``;
* ``L = P^T L_diamond P`` where ``u^T L_diamond u`` sums the diamonds' energies: symmetric,
  ``L 1 = 0`` (``alpha`` and ``beta`` vanish on constants, ``P 1 = 1``), positive
  semi-definite when every diamond has ``c > 0`` (its face points lie on either side of the
  edge), which the validation checks;
* the mass is the research code's (polyLaplace, ``setup_diamond_mass_matrix``): each diamond
  gives a quarter of its area (the sum of the 3-D areas of ``(x_i, x_j, x_g)`` and
  ``(x_i, x_j, x_f)``) to each of its four points, a boundary diamond a third of its triangle's
  area to each of its three, and ``M0 = P^T diag(m) P = diag(m_V) + sum_f m_f w_f w_f^T``.
  This ``M0`` is *not diagonal* (within each face it couples the corners); it is the mass with
  which the published Diamond errors reproduce (its row sums, lumped, do not: the SH error on
  the level-1 hex sphere is 0.042 instead of 0.0151), so it is the one returned.

The gradient of ``L`` and ``M0`` in the vertex positions is that of gathers, elementwise
arithmetic and ``index_add`` into the value arrays: ``O(nnz)`` memory. The pattern and the
index plan depend only on the faces and are cached on the topology per device;
:mod:`torch_polylap.assembly.diamond` rescales, validates and batches.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from ..sparse.pattern import SparsityPattern
from ..topology import Topology
from ..tracing import run_eagerly, tracing
from .frames import component_norm
from .plms import virtual_vertices

__all__ = ["DiamondPlan", "diamond_plan", "diamond_values"]


@dataclass(frozen=True)
class DiamondPlan:
    """The index plan of the Diamond ``L`` and ``M0`` of one topology on one device.

    Attributes:
        pattern: the ``V x V`` symmetric pattern of ``L`` (and ``M0``, a subset).
        groups: per degree group, ``(corners_t (k, F_k), face_ids (F_k,))``.
        face_slot: ``(F,)`` each face's column in the concatenation of the groups.
        edge_i, edge_j, edge_g, edge_f: ``(E,)`` each diamond's edge ``i -> j`` (in face ``g``'s
            orientation), its first face ``g`` and other face ``f`` (``F``, a dummy, on the
            boundary); faces as columns of the concatenated groups, except ``edge_f``'s dummy.
        boundary: ``(E,)`` bool, edges with one face.
        node_index: ``(4 E,)`` the mass nodes of the diamonds' points (``V + F``: the dummy).
        s_coef, s_p, s_q, s_pos: the stiffness terms: coefficient (index into the stacked
            ``(3 E,)`` edge coefficients), the two factors (indices into the corner weights
            ``w`` concatenated with ``[1, 1/2, -1, -1/2]`` and ``-w``), the value position.
        m_node, m_p, m_q, m_pos: the mass terms (node mass, two weight factors, position).
        mirror: ``(nnz,)`` each position's transposed position.
        off_diagonal: ``(nnz,)`` bool.
    """

    pattern: SparsityPattern
    groups: tuple[tuple[torch.Tensor, torch.Tensor], ...]
    face_slot: torch.Tensor
    edge_i: torch.Tensor
    edge_j: torch.Tensor
    edge_g: torch.Tensor
    edge_f: torch.Tensor
    boundary: torch.Tensor
    node_index: torch.Tensor
    s_coef: torch.Tensor
    s_p: torch.Tensor
    s_q: torch.Tensor
    s_pos: torch.Tensor
    m_node: torch.Tensor
    m_p: torch.Tensor
    m_q: torch.Tensor
    m_pos: torch.Tensor
    mirror: torch.Tensor
    off_diagonal: torch.Tensor


def diamond_plan(topo: Topology, device: torch.device) -> DiamondPlan:
    """The :class:`DiamondPlan` of ``topo`` on ``device``, built once and cached on it."""
    if tracing():
        return run_eagerly(_cached_plan, topo, device)
    return _cached_plan(topo, device)


def _cached_plan(topo: Topology, device: torch.device) -> DiamondPlan:
    key = ("diamond", device)
    plan = topo.derived.get(key)
    if plan is None:
        cpu = topo.derived.get(("diamond", torch.device("cpu")))
        plan = _build_plan(topo) if cpu is None else cpu
        if device.type != "cpu":
            plan = _plan_to(plan, device)
        topo.derived[key] = plan
    return plan


def _plan_to(plan: DiamondPlan, device: torch.device) -> DiamondPlan:
    fields = {
        name: getattr(plan, name).to(device)
        for name in DiamondPlan.__dataclass_fields__
        if isinstance(getattr(plan, name), torch.Tensor)
    }
    groups = tuple((c.to(device), f.to(device)) for c, f in plan.groups)
    return DiamondPlan(pattern=plan.pattern.to(device), groups=groups, **fields)


def _ranges(starts: np.ndarray, lengths: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For ranges ``[starts[r], starts[r] + lengths[r])``: the owner ``r`` and the value of
    every element, concatenated in order."""
    owner = np.repeat(np.arange(len(starts)), lengths)
    first = np.repeat(np.cumsum(lengths) - lengths, lengths)
    return owner, starts[owner] + np.arange(owner.size) - first


def _edges(topo: Topology) -> tuple[np.ndarray, ...]:
    """``i, j, g, f, boundary``: each edge, from its first half-edge (in the packed face
    order); ``f = -1`` on the boundary. Raises on edges used by more than two faces."""
    idx = topo.faces.indices.numpy().astype(np.int64)
    offsets = topo.faces.offsets.numpy().astype(np.int64)
    sizes = np.diff(offsets)
    face, corner = _ranges(offsets[:-1], sizes)
    nxt = np.where(corner + 1 == offsets[face + 1], offsets[face], corner + 1)
    src, dst = idx[corner], idx[nxt]
    nv = np.int64(topo.num_verts)
    key = np.minimum(src, dst) * nv + np.maximum(src, dst)
    order = np.argsort(key, kind="stable")
    _, first, counts = np.unique(key[order], return_index=True, return_counts=True)
    if counts.size and counts.max() > 2:
        bad = order[first[np.argmax(counts)]]
        raise ValueError(
            f"method='diamond' needs every edge shared by at most two faces; edge "
            f"({src[bad]}, {dst[bad]}) is used by {counts.max()} faces (e.g. face {face[bad]}). "
            "Split the mesh along such edges, or use another method."
        )
    h0 = order[first]
    second = np.where(counts == 2, order[np.minimum(first + 1, order.size - 1)], -1)
    other = np.where(second >= 0, face[np.maximum(second, 0)], -1)
    return src[h0], dst[h0], face[h0], other, second < 0


def _unique_inverse(keys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The sorted distinct ``keys`` and each key's index among them, by one sort (numpy's
    hashing ``unique`` is several times slower on the tens of millions of terms of a large
    mesh)."""
    order = np.argsort(keys, kind="stable")
    ordered = keys[order]
    new = np.empty(keys.size, bool)
    new[:1] = True
    np.not_equal(ordered[1:], ordered[:-1], out=new[1:])
    inverse = np.empty(keys.size, np.int64)
    inverse[order] = np.cumsum(new) - 1
    return ordered[new], inverse


def _build_plan(topo: Topology) -> DiamondPlan:
    V = topo.num_verts
    offsets = topo.faces.offsets.numpy().astype(np.int64)
    idx = topo.faces.indices.numpy().astype(np.int64)
    F = offsets.size - 1
    # corner weights live in the concatenation of the groups' (F_k, k) weight arrays
    packed_to_weight = np.empty(idx.size, np.int64)
    face_slot = np.empty(F, np.int64)
    base = fbase = 0
    groups = []
    for grp in topo.groups:
        fids = grp.face_ids.numpy().astype(np.int64)
        k = grp.k
        packed = offsets[fids][:, None] + np.arange(k)[None, :]
        packed_to_weight[packed.ravel()] = base + np.arange(fids.size * k)
        face_slot[fids] = fbase + np.arange(fids.size)
        base += fids.size * k
        fbase += fids.size
        groups.append((grp.corners_t, grp.face_ids))
    # factors: the corner weights, the constants 1, 1/2, -1, -1/2, the negated weights
    ONE, M_ONE, M_HALF = base, base + 2, base + 3
    NEG = base + 4

    ei, ej, eg, ef, bnd = _edges(topo)
    E = ei.size
    sizes = np.diff(offsets)
    # legs: (edge, vertex, weight factor, kind 0: alpha, 1: beta)
    a_edge = np.repeat(np.arange(E), 2)
    a_vert = np.stack([ej, ei], 1).ravel()
    a_src = np.tile([ONE, M_ONE], E)
    g_edge, g_pos = _ranges(offsets[eg], sizes[eg])
    inner = np.flatnonzero(~bnd)
    f_owner, f_pos = _ranges(offsets[ef[inner]], sizes[ef[inner]])
    f_edge = inner[f_owner]
    b = np.flatnonzero(bnd)
    leg_edge = np.concatenate([a_edge, g_edge, f_edge, b, b])
    leg_vert = np.concatenate([a_vert, idx[g_pos], idx[f_pos], ei[b], ej[b]])
    # each leg's factor, sign included: u_g - u_f puts -w on the corners of f
    leg_src = np.concatenate(
        [a_src, packed_to_weight[g_pos], NEG + packed_to_weight[f_pos], np.full(2 * b.size, M_HALF)]
    )
    leg_kind = (np.arange(leg_edge.size) >= a_edge.size).astype(np.int64)
    order = np.argsort(leg_edge, kind="stable")
    leg_edge, leg_vert, leg_src, leg_kind = (
        a[order] for a in (leg_edge, leg_vert, leg_src, leg_kind)
    )
    # every ordered pair of legs of one edge; the upper triangle and diagonal are kept and
    # mirrored at the end, so that L is exactly symmetric
    per_edge = np.bincount(leg_edge, minlength=E)
    start = np.cumsum(per_edge) - per_edge
    p, q = _ranges(np.zeros(leg_edge.size, np.int64), per_edge[leg_edge])
    q = start[leg_edge[p]] + q
    keep = leg_vert[p] <= leg_vert[q]
    p, q = p[keep], q[keep]
    s_coef = (leg_kind[p] + leg_kind[q]) * E + leg_edge[p]
    s_p, s_q = leg_src[p], leg_src[q]
    s_rows, s_cols = leg_vert[p], leg_vert[q]

    # mass: diag(m_V) + sum_f m_f w_f w_f^T
    mf, mp = _ranges(np.zeros(F, np.int64), sizes * sizes)
    ca = offsets[mf] + mp // sizes[mf]
    cb = offsets[mf] + mp % sizes[mf]
    keep = idx[ca] <= idx[cb]
    mf, ca, cb = mf[keep], ca[keep], cb[keep]
    m_rows = np.concatenate([idx[ca], np.arange(V)])
    m_cols = np.concatenate([idx[cb], np.arange(V)])
    m_node = np.concatenate([V + mf, np.arange(V)])
    m_p = np.concatenate([packed_to_weight[ca], np.full(V, ONE)])
    m_q = np.concatenate([packed_to_weight[cb], np.full(V, ONE)])

    keys = np.concatenate([s_rows * V + s_cols, m_rows * V + m_cols])
    upper, inverse = _unique_inverse(keys)
    rows, cols = upper // V, upper % V
    full = _unique_inverse(np.concatenate([upper, cols * V + rows]))[0]
    frow, fcol = full // V, full % V
    crow = np.concatenate([[0], np.cumsum(np.bincount(frow, minlength=V))])
    mirror = np.searchsorted(full, fcol * V + frow)
    pattern = SparsityPattern(torch.from_numpy(crow), torch.from_numpy(fcol), (V, V))
    pos = np.searchsorted(full, upper)[inverse]
    s_pos, m_pos = pos[: s_rows.size], pos[s_rows.size :]

    ef_slot = np.where(bnd, F, face_slot[np.maximum(ef, 0)])
    node_f = np.where(bnd, V + F, V + np.maximum(ef, 0))
    node_index = np.concatenate([ei, ej, V + eg, node_f])

    def t(a: np.ndarray) -> torch.Tensor:
        return torch.from_numpy(np.ascontiguousarray(a, dtype=np.int64))

    return DiamondPlan(
        pattern=pattern,
        groups=tuple(groups),
        face_slot=t(face_slot),
        edge_i=t(ei),
        edge_j=t(ej),
        edge_g=t(face_slot[eg]),
        edge_f=t(ef_slot),
        boundary=torch.from_numpy(bnd),
        node_index=t(node_index),
        s_coef=t(s_coef),
        s_p=t(s_p),
        s_q=t(s_q),
        s_pos=t(s_pos),
        m_node=t(m_node),
        m_p=t(m_p),
        m_q=t(m_q),
        m_pos=t(m_pos),
        mirror=t(mirror),
        off_diagonal=torch.from_numpy(frow != fcol),
    )


def diamond_values(
    verts: torch.Tensor, plan: DiamondPlan
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The values of ``L`` and ``M0`` on ``plan.pattern`` for ``verts`` ``(V, 3)``.

    Returns:
        ``L`` ``(nnz,)``, ``M0`` ``(nnz,)`` and ``(E,)`` twice each diamond's signed flattened
        area ``c`` (positive on a valid diamond; not differentiable), for the validation.
    """
    verts_t = verts.t()
    weights, points = [], []
    for corners_t, _ in plan.groups:
        x = verts_t[:, corners_t]
        w = virtual_vertices(x)
        weights.append(w.t().reshape(-1))
        points.append((x * w).sum(1))
    # face points in the groups' order, and a dummy row for the boundary's missing face (a
    # mesh without faces has no groups)
    w_all = torch.cat(weights) if weights else verts.new_zeros(0)
    points.append(verts.new_zeros(3, 1))
    xf = torch.cat(points, 1).t()
    factors = torch.cat([w_all, w_all.new_tensor([1.0, 0.5, -1.0, -0.5]), -w_all])

    xi, xj = verts[plan.edge_i], verts[plan.edge_j]
    xg = xf[plan.edge_g]
    xother = torch.where(plan.boundary[:, None], 0.5 * (xi + xj), xf[plan.edge_f])
    e, a, d = xj - xi, xg - xi, xg - xother
    ee = (e * e).sum(1)
    a_perp = a - ((a * e).sum(1) / ee)[:, None] * e
    ap2 = (a_perp * a_perp).sum(1)
    d_ap, d_e = (d * a_perp).sum(1), (d * e).sum(1)
    c = torch.sqrt(ee / ap2) * d_ap
    half_inv = 0.5 / c
    coef = torch.cat(
        [(d_ap * d_ap / ap2 + d_e * d_e / ee) * half_inv, -d_e * half_inv, ee * half_inv]
    )
    L = _symmetric_values(
        coef[plan.s_coef] * factors[plan.s_p] * factors[plan.s_q], plan.s_pos, plan
    )

    area_g = 0.5 * component_norm(*_cross(e, a).unbind(1))
    area_f = 0.5 * component_norm(*_cross(e, xother - xi).unbind(1))
    share = torch.where(plan.boundary, area_g / 3.0, 0.25 * (area_g + area_f))
    nodes = verts.shape[0] + plan.face_slot.shape[0] + 1
    node_mass = verts.new_zeros(nodes).index_add(0, plan.node_index, share.repeat(4))
    m_terms = node_mass[plan.m_node] * factors[plan.m_p] * factors[plan.m_q]
    return L, _symmetric_values(m_terms, plan.m_pos, plan), c.detach()


def _cross(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Row-wise cross product of ``(n, 3)`` tensors, written out (``torch.linalg.cross``
    checks shapes on every call and is slower on short rows)."""
    ax, ay, az = a.unbind(1)
    bx, by, bz = b.unbind(1)
    return torch.stack([ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx], 1)


def _symmetric_values(terms: torch.Tensor, pos: torch.Tensor, plan: DiamondPlan) -> torch.Tensor:
    """The upper triangle and diagonal summed from ``terms`` at ``pos``, mirrored below."""
    upper = terms.new_zeros(plan.mirror.shape[0]).index_add(0, pos, terms)
    return upper + torch.where(plan.off_diagonal, upper[plan.mirror], 0.0)

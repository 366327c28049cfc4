"""The Diamond Laplacian of Bunge, Botsch and Alexa 2021, surface version (``method="diamond"``).

"The Diamond Laplace for Polygonal and Polyhedral Meshes" (Comput. Graph. Forum 40(5)), 2-D
case. Unlike the other methods it is not a sum of per-face blocks: its stencil couples the two
faces at every edge, so it has its own pattern and index plan here.

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
from ..tracing import outside_transforms, run_eagerly, tracing
from .frames import component_norm
from .plms import virtual_vertices

__all__ = ["DiamondPlan", "diamond_plan", "diamond_values"]


@dataclass(frozen=True)
class DiamondPlan:
    """The index plan of the Diamond ``L`` and ``M0`` of one topology on one device.

    ``u^T L u`` is regrouped (see :func:`diamond_values`) into a block per face, a cross term
    per interior edge between the corners of its two faces, and terms on each edge's two
    endpoints; every term lands at a position of the upper triangle (or the diagonal), which
    is mirrored at the end so that ``L`` is exactly symmetric.

    Attributes:
        pattern: the ``V x V`` symmetric pattern of ``L`` (and ``M0``, a subset).
        groups: per degree group, ``(corners_t (k, F_k), face_ids (F_k,))``; corners and faces
            are numbered in the concatenation of the groups (``N`` corners, ``F`` faces).
        corner_face: ``(N + 1,)`` each corner's face (and ``F`` for a dummy corner).
        edge_i, edge_j, edge_g, edge_f: ``(E,)`` each diamond's edge ``i -> j`` (in face ``g``'s
            orientation), its first face ``g`` and other face ``f`` (``F``, a dummy, on the
            boundary).
        boundary: ``(E,)`` bool, edges with one face.
        edge_corners: ``(4 E,)`` the corners of ``i`` and ``j`` in ``g``, then in ``f`` (``N``,
            a dummy, on the boundary).
        node_index: ``(4 E,)`` the mass nodes of the diamonds' points: vertices ``i``, ``j``,
            then ``V +`` face ``g``, ``f`` (``V + F``, a dummy, on the boundary).
        face_a, face_b: the face blocks' terms: two corners of a face.
        cross_coef, cross_a, cross_b: the edges' cross terms: coefficient (index into
            ``[-c_bb, -2 c_bb]`` of the edges), a corner of ``g``, one of ``f``.
        stiffness_pos: the positions of the face terms, the cross terms, and the edges'
            ``(i, i)``, ``(j, j)`` and ``(i, j)`` terms, in that order.
        m_node, m_a, m_b, m_pos: the mass terms: node mass, two corners (``N``: the factor 1
            of a vertex's own mass), position.
        mirror: ``(nnz,)`` each position's transposed position.
        off_diagonal: ``(nnz,)`` bool.
    """

    pattern: SparsityPattern
    groups: tuple[tuple[torch.Tensor, torch.Tensor], ...]
    corner_face: torch.Tensor
    edge_i: torch.Tensor
    edge_j: torch.Tensor
    edge_g: torch.Tensor
    edge_f: torch.Tensor
    boundary: torch.Tensor
    edge_corners: torch.Tensor
    node_index: torch.Tensor
    face_a: torch.Tensor
    face_b: torch.Tensor
    cross_coef: torch.Tensor
    cross_a: torch.Tensor
    cross_b: torch.Tensor
    stiffness_pos: torch.Tensor
    m_node: torch.Tensor
    m_a: torch.Tensor
    m_b: torch.Tensor
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
        with outside_transforms():
            cpu = topo.derived.get(("diamond", torch.device("cpu")))
            plan = _build_plan(topo) if cpu is None else cpu
            if device.type != "cpu":
                plan = _plan_to(plan, device)
            # the pattern's derived indices now, as a topology view's: traced code reads them
            # and torch.compile guards on the pattern's attributes, which must not change then
            plan.pattern.row  # noqa: B018  (fills the cache)
            plan.pattern.diagonal_class()
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
    """``i, j, g, f, boundary`` and the packed corners of ``i`` and ``j`` in ``g`` and in ``f``:
    each edge, from its first half-edge (in the packed face order); ``f`` and its corners
    ``-1`` on the boundary. Raises on edges used by more than two faces."""
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
    h1 = np.maximum(second, 0)
    other = np.where(second >= 0, face[h1], -1)
    # the corners of i and j in f: h1 runs j -> i on an oriented mesh, i -> j otherwise
    forward = src[h1] == src[h0]
    fi = np.where(second >= 0, np.where(forward, h1, nxt[h1]), -1)
    fj = np.where(second >= 0, np.where(forward, nxt[h1], h1), -1)
    return src[h0], dst[h0], face[h0], other, second < 0, h0, nxt[h0], fi, fj


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
    sizes = np.diff(offsets)
    # corners and faces are numbered in the concatenation of the groups' (F_k, k) arrays
    corner_of = np.empty(idx.size, np.int64)
    face_slot = np.empty(F, np.int64)
    corner_face = np.empty(idx.size, np.int64)
    base = fbase = 0
    groups = []
    for grp in topo.groups:
        fids = grp.face_ids.numpy().astype(np.int64)
        k = grp.k
        packed = offsets[fids][:, None] + np.arange(k)[None, :]
        corner_of[packed.ravel()] = base + np.arange(fids.size * k)
        face_slot[fids] = fbase + np.arange(fids.size)
        corner_face[base : base + fids.size * k] = np.repeat(fbase + np.arange(fids.size), k)
        base += fids.size * k
        fbase += fids.size
        groups.append((grp.corners_t, grp.face_ids))
    N = base
    vertex_of = np.empty(N, np.int64)
    vertex_of[corner_of] = idx

    ei, ej, eg, ef, bnd, gi, gj, fi, fj = _edges(topo)
    E = ei.size
    inner = ~bnd
    # face blocks: every pair of corners of a face, the lower vertex first, and each corner
    face, pair = _ranges(np.zeros(F, np.int64), sizes * sizes)
    a = offsets[face] + pair // sizes[face]
    b = offsets[face] + pair % sizes[face]
    keep = idx[a] <= idx[b]
    face_a, face_b = corner_of[a[keep]], corner_of[b[keep]]
    # cross terms of interior edges: every corner of g with every corner of f
    e_in = np.flatnonzero(inner)
    owner, pair = _ranges(np.zeros(e_in.size, np.int64), sizes[eg[e_in]] * sizes[ef[e_in]])
    e = e_in[owner]
    kf = sizes[ef[e]]
    cross_a = corner_of[offsets[eg[e]] + pair // kf]
    cross_b = corner_of[offsets[ef[e]] + pair % kf]
    same = vertex_of[cross_a] == vertex_of[cross_b]
    cross_coef = e + E * same

    def upper(r: np.ndarray, c: np.ndarray) -> np.ndarray:
        return np.minimum(r, c) * V + np.maximum(r, c)

    keys = [
        upper(vertex_of[face_a], vertex_of[face_b]),
        upper(vertex_of[cross_a], vertex_of[cross_b]),
        upper(ei, ei),
        upper(ej, ej),
        upper(ei, ej),
        upper(np.arange(V), np.arange(V)),
    ]
    distinct, inverse = _unique_inverse(np.concatenate(keys))
    rows, cols = distinct // V, distinct % V
    full = _unique_inverse(np.concatenate([distinct, cols * V + rows]))[0]
    frow, fcol = full // V, full % V
    crow = np.concatenate([[0], np.cumsum(np.bincount(frow, minlength=V))])
    mirror = np.searchsorted(full, fcol * V + frow)
    pattern = SparsityPattern(torch.from_numpy(crow), torch.from_numpy(fcol), (V, V))
    pos = np.split(np.searchsorted(full, distinct)[inverse], np.cumsum([k.size for k in keys])[:-1])
    # mass: the vertices' own masses, and every face block prolonged (the same pairs)
    m_node = np.concatenate([V + corner_face[face_a], np.arange(V)])
    m_a = np.concatenate([face_a, np.full(V, N)])
    m_b = np.concatenate([face_b, np.full(V, N)])
    m_pos = np.concatenate([pos[0], pos[5]])

    def t(x: np.ndarray) -> torch.Tensor:
        return torch.from_numpy(np.ascontiguousarray(x, dtype=np.int64))

    slot_f = np.where(bnd, F, face_slot[np.maximum(ef, 0)])
    return DiamondPlan(
        pattern=pattern,
        groups=tuple(groups),
        corner_face=t(np.append(corner_face, F)),
        edge_i=t(ei),
        edge_j=t(ej),
        edge_g=t(face_slot[eg]),
        edge_f=t(slot_f),
        boundary=torch.from_numpy(bnd),
        edge_corners=t(
            np.concatenate(
                [
                    corner_of[gi],
                    corner_of[gj],
                    np.where(bnd, N, corner_of[fi]),
                    np.where(bnd, N, corner_of[fj]),
                ]
            )  # fmt: skip
        ),
        node_index=t(np.concatenate([ei, ej, V + face_slot[eg], V + slot_f])),
        face_a=t(face_a),
        face_b=t(face_b),
        cross_coef=t(cross_coef),
        cross_a=t(cross_a),
        cross_b=t(cross_b),
        stiffness_pos=t(np.concatenate(pos[:5])),
        m_node=t(m_node),
        m_a=t(m_a),
        m_b=t(m_b),
        m_pos=t(m_pos),
        mirror=t(mirror),
        off_diagonal=torch.from_numpy(frow != fcol),
    )


def diamond_values(
    verts: torch.Tensor, plan: DiamondPlan
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The values of ``L`` and ``M0`` on ``plan.pattern`` for ``verts`` ``(V, 3)``.

    With ``alpha = u_j - u_i`` and ``beta = w_g . u - w_f . u`` (``w_f . u`` the mean
    ``(u_i + u_j) / 2`` on the boundary), a diamond's energy
    ``c_aa alpha^2 + 2 c_ab alpha beta + c_bb beta^2`` is regrouped: ``(w_f . u)^2`` terms
    summed per face (``C_f``), ``alpha (w_f . u)`` terms likewise (the corner vector
    ``rho_f``), so each face has the block ``C_f w w^T + w rho^T + rho w^T``; the interior
    edges keep ``-2 c_bb (w_g . u)(w_f . u)``, and the rest falls on ``i`` and ``j``.

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
    # mesh without faces has no groups); the weights with a dummy 1 for the vertex masses
    weights.append(verts.new_ones(1))
    w_all = torch.cat(weights)
    points.append(verts.new_zeros(3, 1))
    xf = torch.cat(points, 1).t()

    xi, xj = verts.index_select(0, plan.edge_i), verts.index_select(0, plan.edge_j)
    xg = xf.index_select(0, plan.edge_g)
    xother = torch.where(plan.boundary[:, None], 0.5 * (xi + xj), xf.index_select(0, plan.edge_f))
    e, a, d = xj - xi, xg - xi, xg - xother
    ee = (e * e).sum(1)
    a_perp = a - ((a * e).sum(1) / ee)[:, None] * e
    ap2 = (a_perp * a_perp).sum(1)
    d_ap, d_e = (d * a_perp).sum(1), (d * e).sum(1)
    c = torch.sqrt(ee / ap2) * d_ap
    half_inv = 0.5 / c
    c_aa = (d_ap * d_ap / ap2 + d_e * d_e / ee) * half_inv
    c_ab = -d_e * half_inv
    c_bb = ee * half_inv
    bnd = plan.boundary.to(c.dtype)

    n_faces = xf.shape[0]
    C = c.new_zeros(n_faces).index_add(0, plan.edge_g, c_bb).index_add(0, plan.edge_f, c_bb)
    # rho: alpha's coefficients on the corners of g (+c_ab) and f (-c_ab); at a boundary
    # edge, -2 c_bb (w_g . u) (u_i + u_j) / 2 adds -c_bb / 2 at i and j in g
    half_b = 0.5 * c_bb * bnd
    rho_terms = torch.cat([-c_ab - half_b, c_ab - half_b, c_ab, -c_ab])
    rho = c.new_zeros(w_all.shape[0]).index_add(0, plan.edge_corners, rho_terms)
    r = rho + 0.5 * C.index_select(0, plan.corner_face) * w_all
    wa, wb = w_all.index_select(0, plan.face_a), w_all.index_select(0, plan.face_b)
    face_terms = r.index_select(0, plan.face_a) * wb + wa * r.index_select(0, plan.face_b)
    cross_terms = torch.cat([-c_bb, -2.0 * c_bb]).index_select(0, plan.cross_coef) * (
        w_all.index_select(0, plan.cross_a) * w_all.index_select(0, plan.cross_b)
    )
    # on i and j: c_aa alpha^2, and at a boundary edge -2 c_ab alpha m + c_bb m^2 (m the mean)
    quarter_b = 0.25 * c_bb * bnd
    vertex_terms = torch.cat(
        [c_aa + bnd * c_ab + quarter_b, c_aa - bnd * c_ab + quarter_b, quarter_b - c_aa]
    )
    terms = torch.cat([face_terms, cross_terms, vertex_terms])
    L = _symmetric_values(terms, plan.stiffness_pos, plan)

    area_g = 0.5 * component_norm(*_cross(e, a).unbind(1))
    area_f = 0.5 * component_norm(*_cross(e, xother - xi).unbind(1))
    share = torch.where(plan.boundary, area_g / 3.0, 0.25 * (area_g + area_f))
    nodes = verts.shape[0] + n_faces
    node_mass = verts.new_zeros(nodes).index_add(0, plan.node_index, share.repeat(4))
    m_terms = node_mass.index_select(0, plan.m_node) * (
        w_all.index_select(0, plan.m_a) * w_all.index_select(0, plan.m_b)
    )
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

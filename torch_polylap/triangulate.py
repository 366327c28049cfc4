"""Triangulation of polygon faces for libraries that only take triangles (trimesh, viewers).

Each face is projected onto the coordinate plane most orthogonal to its vector area
``a = 1/2 sum_i x_i x x_{i+1}`` (AW11 eq. 8), oriented so that it winds counter-clockwise
there.  Faces that are strictly convex in that projection get the fan ``(c0, c_j, c_{j+1})``;
the others are ear-clipped.  Both run vectorized over all faces of one degree, so the only
Python loops are over degrees and, for the ear clipping, over the ``k - 3`` clipping steps.
Every triangle keeps the polygon's orientation (its normal has a positive component along the
face's dominant axis), and for planar faces the triangles tile the polygon exactly.
"""

from __future__ import annotations

import numpy as np

from ._typing import ArrayLike
from .checks import check_verts_array
from .faces import FacesLike, as_faces

__all__ = ["triangulate_faces"]

# relative tolerance on 2D cross products, in units of the face's squared size
_EPS = 1e-12
# corners * corners * faces per vectorized ear-clipping chunk: bounds the (G, m, m) arrays
_CHUNK = 1 << 22


def triangulate_faces(verts: ArrayLike, faces: FacesLike) -> np.ndarray:
    """Triangles of every face, in face order, orientation-preserving even for non-convex faces.

    Args:
        verts: ``(V, 3)`` vertex positions.
        faces: anything :func:`~torch_polylap.faces.as_faces` accepts.

    Returns:
        ``(sum_f (k_f - 2), 3)`` int64 vertex indices; face ``f``'s ``k_f - 2`` triangles are
        consecutive, so ``np.repeat(np.arange(F), sizes - 2)`` maps triangles to faces.
    """
    v = check_verts_array(verts)
    pf = as_faces(faces)
    indices = pf.indices.cpu().numpy()
    sizes = pf.sizes.cpu().numpy()
    starts = pf.offsets.cpu().numpy()[:-1]
    per_face = sizes - 2
    tri_start = np.cumsum(per_face) - per_face
    tris = np.empty((int(per_face.sum()), 3), dtype=np.int64)
    for k in np.unique(sizes).tolist():
        sel = np.flatnonzero(sizes == k)
        corners = indices[starts[sel][:, None] + np.arange(k)]  # (F_k, k)
        local = _triangulate_degree(v[corners])  # (F_k, k - 2, 3) corner numbers
        rows = tri_start[sel][:, None] + np.arange(k - 2)
        tris[rows] = np.take_along_axis(corners[:, None, :], local, axis=2)
    return tris


def _triangulate_degree(points: np.ndarray) -> np.ndarray:
    """``(F, k - 2, 3)`` corner numbers triangulating ``F`` faces of ``k`` corners ``(F, k, 3)``."""
    f, k = points.shape[:2]
    fan = np.stack([np.zeros(k - 2, np.int64), np.arange(1, k - 1), np.arange(2, k)], axis=1)
    local = np.broadcast_to(fan, (f, k - 2, 3)).copy()
    if k == 3:
        return local
    q = projected(points)
    clip = np.flatnonzero(~strictly_convex(q))
    for chunk in np.array_split(clip, max(1, len(clip) * k * k // _CHUNK)):
        if len(chunk):
            local[chunk] = _ear_clip(q[chunk])
    return local


def projected(points: np.ndarray) -> np.ndarray:
    """``(F, k, 2)`` faces ``(F, k, 3)`` in their maximal-projection plane, counter-clockwise.

    The dropped axis is the largest component of the vector area; the remaining two are taken
    in cyclic order, swapped when that component is negative, so the projected signed area is
    positive.
    """
    centred = points - points.mean(axis=1, keepdims=True)  # cross products without cancellation
    area = 0.5 * np.cross(centred, np.roll(centred, -1, axis=1)).sum(axis=1)  # (F, 3)
    axis = np.abs(area).argmax(axis=1)
    first, second = (axis + 1) % 3, (axis + 2) % 3
    flip = np.take_along_axis(area, axis[:, None], axis=1)[:, 0] < 0
    first, second = np.where(flip, second, first), np.where(flip, first, second)
    gather = np.stack([first, second], axis=1)[:, None, :]
    return np.take_along_axis(centred, np.broadcast_to(gather, (*points.shape[:2], 2)), axis=2)


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]


def _tolerance(q: np.ndarray) -> np.ndarray:
    """``(F, 1)`` cross-product tolerance, relative to each face's squared size."""
    return _EPS * (q * q).sum(axis=2).max(axis=1, keepdims=True)


def strictly_convex(q: np.ndarray) -> np.ndarray:
    """``(F,)`` whether each counter-clockwise polygon ``(F, k, 2)`` turns left at every corner
    and winds exactly once (a pentagram turns left everywhere but winds twice)."""
    edges = np.roll(q, -1, axis=1) - q
    before = np.roll(edges, 1, axis=1)
    turn = _cross(before, edges)
    winding = np.arctan2(turn, (before * edges).sum(axis=2)).sum(axis=1)
    return (turn > _tolerance(q)).all(axis=1) & (np.abs(winding - 2 * np.pi) < 1e-6)


def _ear_clip(q: np.ndarray) -> np.ndarray:
    """``(G, k - 2, 3)`` ear-clipping triangulation of counter-clockwise polygons ``(G, k, 2)``.

    At each step every polygon loses one ear: a corner turning left whose triangle with its two
    neighbours contains no other remaining corner.  Among the ears, one whose removal leaves no
    straight corner (that could end as a degenerate triangle) is preferred, then the
    best-shaped one.  A polygon without an ear (self-intersecting in the projection) loses its
    most convex corner, so every face still gets ``k - 2`` triangles.
    """
    g, k = q.shape[:2]
    tol = _tolerance(q)
    rows = np.arange(g)[:, None]
    order = np.broadcast_to(np.arange(k), (g, k)).copy()  # remaining corners, in cyclic order
    triangles = []
    for m in range(k, 3, -1):
        a = q[rows, order]  # (G, m, 2)
        prev, after = np.roll(a, 1, axis=1), np.roll(a, -1, axis=1)
        turn = _cross(a - prev, after - a)
        ear = (turn > tol) & ~_holds_other_corner(prev, a, after, tol)
        # the corners next to the ear turn by these once it is clipped
        turn_prev = _cross(prev - np.roll(prev, 1, axis=1), after - prev)
        turn_after = _cross(after - prev, np.roll(after, -1, axis=1) - after)
        clean = ear & (np.abs(turn_prev) > tol) & (np.abs(turn_after) > tol)
        shape = _shape(prev, a, after)
        score = np.where(clean, 1.0 + shape, np.where(ear, shape, -1.0))
        fallback = turn - 4.0 * np.abs(turn).max(axis=1, keepdims=True)  # below every ear
        pick = np.where(ear.any(axis=1), score.argmax(axis=1), fallback.argmax(axis=1))
        r = np.arange(g)
        corners = [order[r, pick - 1], order[r, pick], order[r, (pick + 1) % m]]
        triangles.append(np.stack(corners, axis=1))
        keep = np.ones((g, m), dtype=bool)
        keep[r, pick] = False
        order = order[keep].reshape(g, m - 1)
    triangles.append(order)
    return np.stack(triangles, axis=1)


def _holds_other_corner(
    prev: np.ndarray, a: np.ndarray, after: np.ndarray, tol: np.ndarray
) -> np.ndarray:
    """``(G, m)``: whether triangle ``(prev_j, a_j, after_j)`` contains (or touches) a remaining
    corner other than its own three."""
    m = a.shape[1]
    p, c, n = prev[:, :, None, :], a[:, :, None, :], after[:, :, None, :]
    pts = a[:, None, :, :]  # (G, 1, m, 2): every remaining corner
    t = tol[:, :, None]
    inside = (
        (_cross(c - p, pts - p) >= -t)
        & (_cross(n - c, pts - c) >= -t)
        & (_cross(p - n, pts - n) >= -t)
    )
    j = np.arange(m)
    own = (j[None, :] == j[:, None]) | (j[None, :] == (j[:, None] - 1) % m)
    own |= j[None, :] == (j[:, None] + 1) % m
    return (inside & ~own).any(axis=2)


def _shape(p: np.ndarray, c: np.ndarray, n: np.ndarray) -> np.ndarray:
    """Triangle quality ``4 sqrt(3) area / sum of squared edges``: 1 equilateral, 0 degenerate."""
    area = 0.5 * np.abs(_cross(c - p, n - p))
    edges = ((c - p) ** 2).sum(-1) + ((n - c) ** 2).sum(-1) + ((p - n) ** 2).sum(-1)
    return 4.0 * np.sqrt(3.0) * area / np.maximum(edges, np.finfo(float).tiny)

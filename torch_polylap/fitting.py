"""Pieces of a mesh-fitting loop: surface samples, Chamfer distance, mesh-quality measures.

:func:`sample_points` draws points uniformly by area on polygon faces (a fan around each
face's centroid), as differentiable functions of the vertex positions.
:func:`chamfer_distance` is pytorch3d's ``chamfer_distance`` (same arguments, with its keyword
options in a :class:`ChamferOptions`; same reductions and ``(loss, loss_normals)`` result) on
nearest-neighbour searches (a KD-tree on the CPU, chunked ``torch.cdist`` elsewhere, so memory
stays ``O(chunk * M)``) whose autograd graph is ``O(N + M)``. :func:`mesh_quality` summarizes
what a regularizer is meant to protect: planar, convex, well-shaped, unfolded faces.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import Any

import torch

from ._typing import MeshFaces
from .checks import check_positive_int, check_verts
from .kernels.frames import corner_terms, gather_corners
from .measures import edge_lengths, face_nonplanarity, face_normals
from .topology import Topology, get_topology

__all__ = [
    "nearest_neighbors",
    "chamfer_distance",
    "ChamferOptions",
    "sample_points",
    "mesh_quality",
]


def _check_points(points: torch.Tensor, name: str) -> None:
    if points.dim() != 2 or points.shape[0] == 0:
        raise ValueError(
            f"{name} must be a non-empty (N, D) tensor, got shape {tuple(points.shape)}."
        )


def _nearest(
    query: torch.Tensor, points: torch.Tensor, norm: int, chunk_size: int, backend: str
) -> tuple[torch.Tensor, torch.Tensor]:
    """Distance (squared L2 for ``norm=2``, L1 for ``norm=1``) to the nearest of ``points``
    and its index; the search runs without autograd, the distance is recomputed from the pair."""
    if chunk_size < 1:
        raise ValueError(f"chunk_size must be positive, got {chunk_size}.")
    if backend == "auto":
        backend = "kdtree" if points.device.type == "cpu" else "cdist"
    if backend not in ("kdtree", "cdist"):
        raise ValueError(f"backend must be 'auto', 'kdtree' or 'cdist', got {backend!r}.")
    with torch.no_grad():
        qd, pd = query.detach(), points.detach()
        if backend == "kdtree":
            from scipy.spatial import cKDTree

            _, found = cKDTree(pd.cpu().numpy()).query(qd.cpu().numpy(), p=norm)
            index = torch.from_numpy(found).to(device=query.device, dtype=torch.int64)
        else:
            index = torch.cat(
                [torch.cdist(q, pd, p=norm).argmin(dim=1) for q in torch.split(qd, chunk_size)]
            )
    diff = query - points.index_select(0, index)
    dist = diff.square().sum(dim=1) if norm == 2 else diff.abs().sum(dim=1)
    return dist, index


def nearest_neighbors(
    query: torch.Tensor,
    points: torch.Tensor,
    *,
    chunk_size: int = 2048,
    backend: str = "auto",
) -> tuple[torch.Tensor, torch.Tensor]:
    """Squared distance from every query point to its nearest point of ``points``, and its index.

    Args:
        query: ``(N, D)`` points.
        points: ``(M, D)`` points of the same dtype and device.
        chunk_size: query points per ``torch.cdist`` block (``backend="cdist"``); memory is
            ``O(chunk_size * M)``.
        backend: ``"kdtree"`` (``scipy.spatial.cKDTree`` on the CPU, ``O((N + M) log M)``),
            ``"cdist"`` (chunked brute force on the points' device), or ``"auto"``: ``"kdtree"``
            for CPU tensors, ``"cdist"`` otherwise.

    Returns:
        ``sq_dist`` ``(N,)`` and ``index`` ``(N,)`` (int64). The search runs without autograd;
        ``sq_dist`` is recomputed from the gathered pairs, so it is differentiable in both inputs
        and its gradient is that of the distance to the (fixed) nearest point, which is the
        gradient of the minimum wherever the nearest point is unique.
    """
    _check_points(query, "query")
    _check_points(points, "points")
    if query.shape[1] != points.shape[1] or query.dtype != points.dtype:
        raise ValueError(
            f"query {tuple(query.shape)} {query.dtype} and points {tuple(points.shape)} "
            f"{points.dtype} must have the same dimension and dtype."
        )
    return _nearest(query, points, 2, chunk_size, backend)


def _clouds(
    points: Any, lengths: torch.Tensor | None, normals: torch.Tensor | None, name: str
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
    """``(padded (N, P, D), lengths (N,), normals (N, P, D) or None)`` of one chamfer input."""
    if hasattr(points, "points_padded") and hasattr(points, "num_points_per_cloud"):
        # a pytorch3d Pointclouds (duck-typed: pytorch3d is not imported)
        return points.points_padded(), points.num_points_per_cloud(), points.normals_padded()
    if not isinstance(points, torch.Tensor):
        raise ValueError(
            f"{name} must be a tensor (N, P, D) or (P, D), or a pytorch3d Pointclouds, got "
            f"{type(points).__name__}."
        )
    if points.dim() == 2:  # one cloud
        points = points[None]
        normals = None if normals is None else normals.reshape(1, *normals.shape[-2:])
    if points.dim() != 3:
        raise ValueError(f"{name} must have shape (N, P, D) or (P, D), got {tuple(points.shape)}.")
    n, p = points.shape[:2]
    if lengths is None:
        lengths = torch.full((n,), p, dtype=torch.int64, device=points.device)
    elif lengths.shape != (n,):
        raise ValueError(
            f"{name}_lengths must have shape ({n},), one count per cloud, got "
            f"{tuple(lengths.shape)}."
        )
    elif bool(((lengths < 0) | (lengths > p)).any()):
        raise ValueError(f"{name}_lengths must lie in [0, {p}], got {lengths.tolist()}.")
    if normals is not None and normals.shape != points.shape:
        raise ValueError(
            f"{name}_normals must have the shape of {name}, {tuple(points.shape)}, got "
            f"{tuple(normals.shape)}."
        )
    return points, lengths, normals


def _one_direction(
    x: torch.Tensor,
    y: torch.Tensor,
    x_lengths: list[int],
    y_lengths: list[int],
    x_normals: torch.Tensor | None,
    y_normals: torch.Tensor | None,
    weights: torch.Tensor | None,
    norm: int,
    *,
    abs_cosine: bool,
    chunk_size: int,
    backend: str,
) -> tuple[torch.Tensor, torch.Tensor | None]:
    """``(N, P1)`` distance of every point of ``x`` to its nearest point of ``y`` (0 past
    ``x_lengths``), and ``1 - |cos|`` (or ``1 - cos``) of their normals, or ``None``; each
    cloud's row times its weight."""
    p1 = x.shape[1]
    dist, cosine = [], []
    for i, (nx, ny) in enumerate(zip(x_lengths, y_lengths, strict=True)):
        if nx == 0:
            dist.append(x.new_zeros(p1))
            cosine.append(x.new_zeros(p1))
            continue
        if ny == 0:
            raise ValueError(
                f"chamfer_distance: cloud {i} has {nx} points on one side and none on the other; "
                "a point has no nearest neighbour in an empty cloud."
            )
        d, index = _nearest(x[i, :nx], y[i, :ny], norm, chunk_size, backend)
        dist.append(torch.nn.functional.pad(d, (0, p1 - nx)))
        if x_normals is not None and y_normals is not None:
            c = torch.nn.functional.cosine_similarity(
                x_normals[i, :nx], y_normals[i].index_select(0, index), dim=1, eps=1e-6
            )
            c = 1 - (c.abs() if abs_cosine else c)
            cosine.append(torch.nn.functional.pad(c, (0, p1 - nx)))
    out = [torch.stack(dist)]
    if x_normals is not None and y_normals is not None:
        out.append(torch.stack(cosine))
    if weights is not None:
        out = [t * weights[:, None] for t in out]
    return out[0], (out[1] if len(out) == 2 else None)


def _reduce(
    terms: torch.Tensor,
    lengths: torch.Tensor,
    weights: torch.Tensor | None,
    batch_reduction: str | None,
    point_reduction: str,
) -> torch.Tensor:
    """Point, then batch reduction of ``(N, P)`` weighted per-point terms."""
    if point_reduction == "max":
        per_cloud = terms.amax(dim=1) if terms.shape[1] else terms.new_zeros(terms.shape[0])
    else:
        per_cloud = terms.sum(dim=1)
        if point_reduction == "mean":
            per_cloud = per_cloud / lengths.clamp_min(1).to(terms.dtype)
    if batch_reduction is None:
        return per_cloud
    total = per_cloud.sum()
    if batch_reduction == "mean":
        total = total / (weights.sum() if weights is not None else max(terms.shape[0], 1))
    return total


@dataclass(frozen=True)
class ChamferOptions:
    """How :func:`chamfer_distance` measures and reduces: pytorch3d's keyword arguments after
    ``weights`` (same names, values and defaults), and the nearest-neighbour search.

    Attributes:
        batch_reduction: ``"mean"`` (default), ``"sum"`` or ``None`` (per cloud, ``(N,)``).
        point_reduction: ``"mean"`` (default) over each cloud's points, ``"sum"``, ``"max"``
            (the directed Hausdorff distance; no normals) or ``None``.
        norm: ``2`` (squared L2) or ``1`` (L1).
        single_directional: only the ``x -> y`` term.
        abs_cosine: the normal term is ``1 - |cos|`` (orientation ignored; default) or
            ``1 - cos``, of each point's normal and that of its nearest neighbour.
        chunk_size: the nearest-neighbour search's chunk size, see :func:`nearest_neighbors`.
        backend: the nearest-neighbour search's backend, see :func:`nearest_neighbors`.
    """

    batch_reduction: str | None = "mean"
    point_reduction: str | None = "mean"
    norm: int = 2
    single_directional: bool = False
    abs_cosine: bool = True
    chunk_size: int = 2048
    backend: str = "auto"


def chamfer_distance(
    x: torch.Tensor | Any,
    y: torch.Tensor | Any,
    x_lengths: torch.Tensor | None = None,
    y_lengths: torch.Tensor | None = None,
    x_normals: torch.Tensor | None = None,
    y_normals: torch.Tensor | None = None,
    weights: torch.Tensor | None = None,
    options: ChamferOptions | None = None,
) -> tuple[Any, Any]:
    """Chamfer distance between two batches of point clouds, pytorch3d's arguments and result.

    The first seven arguments, the reductions and the return values are those of
    ``pytorch3d.loss.chamfer_distance``; its keyword arguments after ``weights`` are the fields
    of ``options``: for every point of ``x`` the distance to its nearest point of ``y`` (the
    *squared* Euclidean distance for ``norm=2``, the L1 distance for ``norm=1``), reduced over
    the points of each cloud (``point_reduction``) and then over the batch
    (``batch_reduction``), plus the same from ``y`` to ``x`` unless ``single_directional``. The
    nearest-neighbour search is a KD-tree on the CPU and chunked ``torch.cdist`` elsewhere (see
    :func:`nearest_neighbors`); no ``P1 x P2`` matrix is held.

    Args:
        x: ``(N, P1, D)`` padded clouds, or a pytorch3d ``Pointclouds`` (read through
            ``points_padded``, ``num_points_per_cloud``, ``normals_padded``), or ``(P1, D)``:
            one cloud, the same as ``x[None]`` (an extension; pytorch3d wants 3-D input).
        y: ``(N, P2, D)``, a ``Pointclouds`` or ``(P2, D)``, like ``x``.
        x_lengths: ``(N,)`` int64 number of points in each cloud of ``x`` (the rest is
            padding); default: all ``P1``.
        y_lengths: the same for ``y``; default: all ``P2``.
        x_normals: ``(N, P1, D)`` normals of ``x`` (give both normals, or the normal term is
            not computed).
        y_normals: ``(N, P2, D)`` normals of ``y``.
        weights: ``(N,)`` non-negative weights of the clouds, multiplying their terms; the
            batch ``"mean"`` then divides by ``weights.sum()``.
        options: a :class:`ChamferOptions`: reductions, norm, direction, the normal term's
            cosine and the search; default ``ChamferOptions()``, pytorch3d's defaults.

    Returns:
        ``(loss, loss_normals)``: the reduced ``x -> y`` plus ``y -> x`` terms, and the same for
        the normals (``None`` without normals). With ``point_reduction=None`` (and then no batch
        reduction) each is the tuple of the per-point ``(N, P1)`` and ``(N, P2)`` terms (zero
        past the lengths), or the ``(N, P1)`` tensor alone if ``single_directional``.
        Differentiable in ``x``, ``y`` and the normals; the gradient is that of the distance
        to the (fixed) nearest point, exact wherever the nearest point is unique.

    Raises:
        ValueError: an unknown reduction or norm, ``"max"`` with normals, mismatched shapes,
            negative weights, or a non-empty cloud paired with an empty one.

    Examples:
        >>> import torch
        >>> from torch_polylap.fitting import ChamferOptions, chamfer_distance
        >>> x = torch.tensor([[0.0, 0, 0], [1, 0, 0]])
        >>> y = torch.tensor([[0.0, 0, 0], [1, 1, 0], [1, 0, 0]])
        >>> loss, _ = chamfer_distance(x, y)   # (0 + 0) / 2 + (0 + 1 + 0) / 3
        >>> round(float(loss), 6)
        0.333333
        >>> loss, _ = chamfer_distance(x, y, options=ChamferOptions(point_reduction="sum"))
        >>> round(float(loss), 6)  # (0 + 0) + (0 + 1 + 0)
        1.0
    """
    options = options or ChamferOptions()
    _check_chamfer_options(options)
    x, x_lengths, x_normals = _clouds(x, x_lengths, x_normals, "x")
    y, y_lengths, y_normals = _clouds(y, y_lengths, y_normals, "y")
    if options.point_reduction == "max" and (x_normals is not None or y_normals is not None):
        raise ValueError("point_reduction='max' takes no normals (as in pytorch3d).")
    n, _, dim = x.shape
    if y.shape[0] != n or y.shape[2] != dim or y.dtype != x.dtype:
        raise ValueError(
            f"x {tuple(x.shape)} {x.dtype} and y {tuple(y.shape)} {y.dtype} must have the same "
            "number of clouds, point dimension and dtype."
        )
    if weights is not None:
        _check_weights(weights, n)
        if float(weights.sum()) == 0.0:  # every cloud weighs nothing: a zero that keeps the graph
            zero = (x.sum((1, 2)) * weights) * 0.0
            zero = zero.sum() if options.batch_reduction is not None else zero
            with_normals = x_normals is not None and y_normals is not None
            return zero, (zero if with_normals else None)
    nx, ny = x_lengths.tolist(), y_lengths.tolist()
    one_direction = functools.partial(
        _one_direction,
        abs_cosine=options.abs_cosine,
        chunk_size=options.chunk_size,
        backend=options.backend,
    )
    forward = one_direction(x, y, nx, ny, x_normals, y_normals, weights, options.norm)
    directions = [(forward, x_lengths)]
    if not options.single_directional:
        backward = one_direction(y, x, ny, nx, y_normals, x_normals, weights, options.norm)
        directions.append((backward, y_lengths))
    if options.point_reduction is None:
        if options.single_directional:
            return forward
        return (forward[0], backward[0]), (
            None if forward[1] is None else (forward[1], backward[1])
        )
    return _reduced(directions, weights, options.batch_reduction, options.point_reduction)


def _check_chamfer_options(options: ChamferOptions) -> None:
    batch_reduction, point_reduction = options.batch_reduction, options.point_reduction
    if batch_reduction not in ("mean", "sum", None):
        raise ValueError(f"batch_reduction must be 'mean', 'sum' or None, got {batch_reduction!r}.")
    if point_reduction not in ("mean", "sum", "max", None):
        raise ValueError(
            f"point_reduction must be 'mean', 'sum', 'max' or None, got {point_reduction!r}."
        )
    if options.norm not in (1, 2):
        raise ValueError(f"norm must be 1 (L1) or 2 (squared L2), got {options.norm!r}.")


def _check_weights(weights: torch.Tensor, n: int) -> None:
    if weights.shape != (n,):
        raise ValueError(f"weights must have shape ({n},), got {tuple(weights.shape)}.")
    if bool((weights < 0).any()):
        raise ValueError("weights must be non-negative.")


def _reduced(
    directions: list[tuple[tuple[torch.Tensor, torch.Tensor | None], torch.Tensor]],
    weights: torch.Tensor | None,
    batch_reduction: str | None,
    point_reduction: str,
) -> tuple[Any, Any]:
    """``(loss, loss_normals)``: the sums over the directions of their reduced distance and
    normal terms (``loss_normals`` None without normals); each direction is its
    ``((distances, normal terms or None), lengths)``."""
    loss = sum(
        _reduce(d, lengths, weights, batch_reduction, point_reduction)
        for (d, _), lengths in directions
    )
    if directions[0][0][1] is None:
        return loss, None
    loss_normals = sum(
        _reduce(c, lengths, weights, batch_reduction, point_reduction)
        for (_, c), lengths in directions
        if c is not None  # every direction has them when the forward one has
    )
    return loss, loss_normals


def _fan_triangles(
    verts: torch.Tensor, topo: Topology
) -> list[tuple[int, torch.Tensor, torch.Tensor, torch.Tensor]]:
    """Per degree group: ``k``, face ids ``(F_k,)``, corners ``(3, k, F_k)`` and fan areas
    ``(T, F_k)``.

    Triangles are their own fan (``T = 1``); a ``k``-gon with ``k > 3`` is split into the
    ``T = k`` triangles ``(c, x_i, x_{i+1})`` around its corner centroid ``c``.
    """
    groups = topo.on(verts.device).groups
    verts_t = verts.t().contiguous()
    out = []
    for grp in groups:
        x = gather_corners(verts_t, grp.corners_t)
        if grp.k == 3:
            _, _, a = corner_terms(x)
            areas = torch.linalg.vector_norm(a, dim=0)[None]
        else:
            r = x - x.mean(dim=1, keepdim=True)
            areas = 0.5 * torch.linalg.vector_norm(
                torch.linalg.cross(r, torch.roll(r, -1, dims=1), dim=0), dim=0
            )
        out.append((grp.k, grp.face_ids, x, areas))
    return out


def sample_points(
    verts: torch.Tensor,
    faces: MeshFaces,
    num_samples: int,
    *,
    generator: torch.Generator | None = None,
    return_face_ids: bool = False,
) -> torch.Tensor | tuple[torch.Tensor, torch.Tensor]:
    """Points drawn uniformly by area from the surface of a polygon mesh.

    Every face is the fan of triangles ``(c, x_i, x_{i+1})`` around its corner centroid ``c``
    (triangles are used as they are); a fan triangle is drawn with probability proportional to
    its area, and a point uniformly inside it. For planar faces that are star-shaped with
    respect to ``c`` (all convex faces) this is the uniform distribution on the polygon; a
    non-planar face is represented by its centroid fan.

    Args:
        verts: ``(V, 3)`` vertex positions.
        faces: the faces (any form :func:`torch_polylap.laplacian` accepts).
        num_samples: number of points ``S``.
        generator: random generator (on ``verts``' device) for reproducible samples.
        return_face_ids: also return the face each point lies on.

    Returns:
        ``(S, 3)`` points, differentiable in ``verts`` (the choice of triangles and the
        barycentric coordinates are random constants; each point is a fixed convex combination
        of its face's corners), and ``(S,)`` face ids if asked for.
    """
    check_positive_int(num_samples, "num_samples")
    check_verts(verts, finite=False)
    topo = get_topology(faces, verts.shape[0])
    fans = _fan_triangles(verts, topo)
    weights = torch.cat([areas.detach().reshape(-1) for _, _, _, areas in fans])
    if not bool(torch.isfinite(weights).all()) or float(weights.sum()) <= 0:
        raise ValueError("sample_points: the mesh has no finite positive area to sample from.")
    tri = torch.multinomial(weights, num_samples, replacement=True, generator=generator)
    u, v = torch.rand(2, num_samples, dtype=verts.dtype, device=verts.device, generator=generator)
    # uniform barycentric coordinates in a triangle (Osada et al. 2002)
    su = u.sqrt()
    b = torch.stack((1 - su, su * (1 - v), su * v))  # (3, S): weights of (p0, p1, p2)

    points = verts.new_zeros(num_samples, 3)
    face_of = torch.empty(num_samples, dtype=torch.int64, device=verts.device)
    start = 0
    for k, face_ids, x, areas in fans:
        num_tri, nf = areas.shape
        mine = (tri >= start) & (tri < start + num_tri * nf)
        sel = mine.nonzero().squeeze(1)
        local = tri[sel] - start
        i, f = local // nf, local % nf  # fan triangle i of face f (areas is (T, F_k), row major)
        xf = x[:, :, f]  # (3, k, s)
        bs = b[:, sel]
        if k == 3:
            p = xf[:, 0] * bs[0] + xf[:, 1] * bs[1] + xf[:, 2] * bs[2]
        else:
            ar = torch.arange(sel.numel(), device=verts.device)
            xi = xf[:, i, ar]
            xj = xf[:, (i + 1) % k, ar]
            p = xf.mean(dim=1) * bs[0] + xi * bs[1] + xj * bs[2]
        points = points.index_copy(0, sel, p.t())
        face_of[sel] = face_ids[f]
        start += num_tri * nf
    return (points, face_of) if return_face_ids else points


def _corner_angles(x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Interior angle ``(k, F)`` at every corner of ``(3, k, F)`` faces and whether the corner turns
    the same way as the face's vector area (``False`` at reflex or folded corners)."""
    e, _, a = corner_terms(x)
    prev = -torch.roll(e, 1, dims=1)  # from corner i to corner i - 1
    cosine = (e * prev).sum(0) / (
        torch.linalg.vector_norm(e, dim=0) * torch.linalg.vector_norm(prev, dim=0)
    )
    angle = torch.arccos(cosine.clamp(-1.0, 1.0))
    turn = torch.linalg.cross(e, prev, dim=0)  # e_i x (x_{i-1} - x_i) points along a_f if convex
    convex = (turn * a[:, None]).sum(0) > 0
    return angle, convex


def mesh_quality(verts: torch.Tensor, faces: MeshFaces) -> dict[str, float]:
    """Summary measures of the shape of a mesh's faces (no gradients; for reports and tests).

    Returns a dict with:

    - ``nonplanarity_mean``, ``nonplanarity_max``: :func:`torch_polylap.face_nonplanarity`
      (corner distance from the face plane over the face diameter; 0 for triangles).
    - ``angle_error_deg``: mean ``|angle - pi (k - 2) / k|`` over all corners (0 for regular
      polygons), in degrees; ``min_angle_deg``: the smallest interior angle.
    - ``aspect``: mean over faces of longest edge / shortest edge (1 for equilateral faces).
    - ``edge_cv``: standard deviation / mean of the edge lengths.
    - ``nonconvex_faces``: fraction of faces with a corner turning against the face's vector
      area (reflex, folded or self-overlapping faces; never the case for triangles).
    - ``folded_edges``: fraction of interior edges (edges of exactly two faces) whose two
      faces' normals (AW11 vector-area directions) make an angle above 90 degrees: creases
      and fold-overs. Edges used by 3+ faces (non-manifold) are left out of it.

    Raises:
        ValueError: the faces are not consistently oriented (or the mesh is non-orientable):
            ``folded_edges`` would count every flipped face's edges as folds. The message names
            the first misoriented edges and the repair, ``torch_polylap.repair.orient_faces``.
    """
    with torch.no_grad():
        topo = get_topology(faces, verts.shape[0])
        topo.require_oriented("mesh_quality (its folded_edges measure)")
        groups = topo.on(verts.device).groups
        verts_t = verts.t().contiguous()
        angle_err, min_angle, aspects, nonconvex = [], [], [], 0
        for grp in groups:
            x = gather_corners(verts_t, grp.corners_t)
            angle, convex = _corner_angles(x)
            angle_err.append((angle - math.pi * (grp.k - 2) / grp.k).abs().reshape(-1))
            min_angle.append(angle.min())
            lengths = torch.linalg.vector_norm(torch.roll(x, -1, dims=1) - x, dim=0)
            aspects.append(lengths.amax(0) / lengths.amin(0))
            nonconvex += int((~convex).any(0).sum())
        nonplanar = face_nonplanarity(verts, topo)
        edge_len = edge_lengths(verts, topo, validate=False)
        # |n1 + n2|^2 = 2 + 2 n1.n2 < 2 exactly when the two unit normals are more than 90 deg apart
        he_edge = topo.half_edge_edge.to(verts.device)
        he_face = topo.faces.corner_face.to(verts.device)
        normal_sum = verts.new_zeros(edge_len.shape[0], 3).index_add(
            0, he_edge, face_normals(verts, topo)[he_face]
        )
        interior = topo.edge_faces.to(verts.device) == 2
        folded = (normal_sum[interior].square().sum(1) < 2).double().mean()
        return {
            "nonplanarity_mean": float(nonplanar.mean()),
            "nonplanarity_max": float(nonplanar.max()),
            "angle_error_deg": math.degrees(float(torch.cat(angle_err).mean())),
            "min_angle_deg": math.degrees(float(torch.stack(min_angle).min())),
            "aspect": float(torch.cat(aspects).mean()),
            "edge_cv": float(edge_len.std() / edge_len.mean()),
            "nonconvex_faces": nonconvex / topo.num_faces,
            "folded_edges": float(folded) if bool(interior.any()) else 0.0,
        }

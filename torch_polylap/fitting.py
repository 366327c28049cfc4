"""Pieces of a mesh-fitting loop: surface samples, Chamfer distance, mesh-quality measures.

:func:`sample_points` draws points uniformly by area on polygon faces (a fan around each
face's centroid), as differentiable functions of the vertex positions.
:func:`chamfer_distance` compares two point sets through nearest-neighbour searches (a KD-tree
on the CPU, chunked ``torch.cdist`` elsewhere, so memory stays ``O(chunk * M)``) whose autograd
graph is ``O(N + M)``. :func:`mesh_quality` summarizes what a regularizer is meant to protect:
planar, convex, well-shaped, unfolded faces.
"""

from __future__ import annotations

import math

import torch

from .faces import FacesLike
from .kernels.frames import corner_terms, gather_corners
from .measures import face_nonplanarity, face_normals
from .topology import Topology, get_topology

__all__ = ["nearest_neighbors", "chamfer_distance", "sample_points", "mesh_quality"]

MeshFaces = FacesLike | Topology


def _check_points(points: torch.Tensor, name: str) -> None:
    if points.dim() != 2 or points.shape[0] == 0:
        raise ValueError(
            f"{name} must be a non-empty (N, D) tensor, got shape {tuple(points.shape)}."
        )


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

            _, found = cKDTree(pd.cpu().numpy()).query(qd.cpu().numpy())
            index = torch.from_numpy(found).to(device=query.device, dtype=torch.int64)
        else:
            index = torch.cat(
                [torch.cdist(q, pd).argmin(dim=1) for q in torch.split(qd, chunk_size)]
            )
    sq_dist = (query - points.index_select(0, index)).square().sum(dim=1)
    return sq_dist, index


def chamfer_distance(
    points_a: torch.Tensor,
    points_b: torch.Tensor,
    *,
    chunk_size: int = 2048,
    backend: str = "auto",
    reduction: str = "mean",
) -> torch.Tensor:
    """Symmetric Chamfer distance ``mean_a min_b |a - b|^2 + mean_b min_a |a - b|^2``.

    Args:
        points_a: ``(N, D)`` points, e.g. samples of a mesh (:func:`sample_points`).
        points_b: ``(M, D)`` points, e.g. samples of the target.
        chunk_size, backend: the nearest-neighbour search (see :func:`nearest_neighbors`); no
            ``N x M`` matrix is ever held, and the autograd graph is ``O(N + M)``.
        reduction: ``"mean"`` (above) or ``"sum"`` (sums instead of means).

    Returns:
        A scalar, differentiable in both point sets.
    """
    if reduction not in ("mean", "sum"):
        raise ValueError(f"reduction must be 'mean' or 'sum', got {reduction!r}.")
    d_ab, _ = nearest_neighbors(points_a, points_b, chunk_size=chunk_size, backend=backend)
    d_ba, _ = nearest_neighbors(points_b, points_a, chunk_size=chunk_size, backend=backend)
    if reduction == "mean":
        return d_ab.mean() + d_ba.mean()
    return d_ab.sum() + d_ba.sum()


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
    if num_samples < 1:
        raise ValueError(f"num_samples must be positive, got {num_samples}.")
    if verts.dim() != 2 or verts.shape[1] != 3:
        raise ValueError(f"verts must have shape (V, 3), got {tuple(verts.shape)}.")
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
        edges = topo.edges.to(verts.device)
        edge_len = torch.linalg.vector_norm(verts[edges[:, 0]] - verts[edges[:, 1]], dim=1)
        # |n1 + n2|^2 = 2 + 2 n1.n2 < 2 exactly when the two unit normals are more than 90 deg apart
        he_edge = topo.half_edge_edge.to(verts.device)
        he_face = torch.repeat_interleave(
            torch.arange(topo.num_faces, device=verts.device), topo.faces.sizes.to(verts.device)
        )
        normal_sum = verts.new_zeros(edges.shape[0], 3).index_add(
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

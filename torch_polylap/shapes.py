"""Generated meshes: quad grids, cube-sphere quads, tori and the Schwarz lantern.

One implementation of the meshes that the tests, the examples and the benchmarks build, kept in
the package so that the examples run from a plain install. Every generator is deterministic
(random jitter and noise come from ``numpy.random.default_rng(seed)``), returns the vertices as
a ``(V, 3)`` tensor of the requested ``dtype`` and ``device`` and the faces as an int64 tensor
(or index lists, for mixed degrees) on the CPU, as :func:`~torch_polylap.read_mesh` does, with
every face counter-clockwise seen from outside (from ``+z`` for the grids).

Example:
    >>> import torch_polylap as tp
    >>> verts, faces = tp.shapes.quad_sphere(2)
    >>> verts.shape, faces.shape
    (torch.Size([26, 3]), torch.Size([24, 4]))
    >>> L, M0 = tp.laplacian(verts, faces)
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch

from .checks import check_int

__all__ = ["quad_grid", "quad_cube", "quad_sphere", "torus", "schwarz_lantern"]

Height = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]


def _grid_quads(rows: int, cols: int) -> np.ndarray:
    """Quads of a ``(rows + 1) x (cols + 1)`` vertex lattice numbered row-major: ``(rows, cols,
    4)`` with corners ``(i, j), (i + 1, j), (i + 1, j + 1), (i, j + 1)``."""
    idx = np.arange((rows + 1) * (cols + 1)).reshape(rows + 1, cols + 1)
    return np.stack([idx[:-1, :-1], idx[1:, :-1], idx[1:, 1:], idx[:-1, 1:]], -1)


def _verts(
    points: np.ndarray, dtype: torch.dtype, device: torch.device | str | None
) -> torch.Tensor:
    array = np.ascontiguousarray(points, dtype=np.float64)
    return torch.from_numpy(array).to(device=device, dtype=dtype)


def quad_grid(
    n: int,
    m: int | None = None,
    *,
    extent: tuple[float, float, float, float] = (0.0, 1.0, 0.0, 1.0),
    bump: float = 0.0,
    height: Height | None = None,
    seed: int | None = None,
    jitter: float = 0.25,
    dtype: torch.dtype = torch.float64,
    device: torch.device | str | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """An ``n x m`` grid of quads over the rectangle ``extent = (x0, x1, y0, y1)``.

    Vertex ``(i, j)`` (``0 <= i <= n`` along ``x``, ``0 <= j <= m`` along ``y``) has index
    ``i * (m + 1) + j``; quad ``(i, j)`` is ``(i, j), (i + 1, j), (i + 1, j + 1), (i, j + 1)``
    (row ``i * m + j``), counter-clockwise seen from ``+z``.

    Args:
        n: quads along ``x`` (at least 1).
        m: quads along ``y``; ``None`` means ``n``.
        extent: ``(x0, x1, y0, y1)``, the rectangle the grid covers before any jitter.
        bump: lifts each vertex by ``bump * sin(3 x + 0.5) * cos(2 y - 0.3)``, a smooth height
            field that makes the quads non-planar.
        height: a further height ``z += height(x, y)``, called with the (jittered) float64
            coordinates as ``(n + 1, m + 1)`` tensors.
        seed: when given, the interior vertices are moved in the plane by independent uniform
            offsets of at most ``jitter`` times the smaller cell side (``jitter < 0.5`` keeps
            the quads convex); the boundary stays straight.
        jitter: the largest in-plane offset, as a fraction of the smaller cell side.
        dtype: dtype of the vertices.
        device: device of the vertices.

    Returns:
        ``verts`` ``((n + 1) (m + 1), 3)`` and ``faces`` ``(n m, 4)`` int64.

    Examples:
        >>> verts, faces = quad_grid(2, 3, bump=0.1)
        >>> verts.shape, faces.shape, faces[0].tolist()
        (torch.Size([12, 3]), torch.Size([6, 4]), [0, 4, 5, 1])
    """
    m = n if m is None else m
    check_int(n, "n", least=1)
    check_int(m, "m", least=1)
    x0, x1, y0, y1 = (float(v) for v in extent)
    if not (x1 > x0 and y1 > y0):
        raise ValueError(f"extent must be (x0, x1, y0, y1) with x0 < x1 and y0 < y1, got {extent}.")
    xs, ys = np.meshgrid(np.linspace(x0, x1, n + 1), np.linspace(y0, y1, m + 1), indexing="ij")
    if seed is not None:
        rng = np.random.default_rng(seed)
        h = jitter * min((x1 - x0) / n, (y1 - y0) / m)
        inner = np.zeros(xs.shape, dtype=bool)
        inner[1:-1, 1:-1] = True
        xs = xs + inner * rng.uniform(-h, h, xs.shape)
        ys = ys + inner * rng.uniform(-h, h, ys.shape)
    zs = bump * np.sin(3 * xs + 0.5) * np.cos(2 * ys - 0.3)
    if height is not None:
        z = height(torch.from_numpy(xs), torch.from_numpy(ys))
        zs = zs + torch.as_tensor(z, dtype=torch.float64).expand(xs.shape).numpy()
    verts = np.stack([xs.ravel(), ys.ravel(), zs.ravel()], 1)
    return _verts(verts, dtype, device), torch.from_numpy(_grid_quads(n, m).reshape(-1, 4))


def _cube_lattice(n: int) -> tuple[np.ndarray, np.ndarray]:
    """Integer lattice points ``(V, 3)`` in ``{-n, -n + 2, ..., n}^3`` on the cube's surface
    (sorted lexicographically) and the quads ``(6 n^2, 4)`` of :func:`quad_cube`."""
    steps = 2 * np.arange(n + 1) - n
    u, v = np.meshgrid(steps, steps, indexing="ij")
    eye = np.eye(3, dtype=np.int64)
    points = []
    for axis in range(3):
        for sign in (1, -1):
            a, b = eye[(axis + 1) % 3], eye[(axis + 2) % 3]
            if sign < 0:
                a, b = b, a  # a x b points outwards on both sides
            points.append(sign * n * eye[axis] + u[..., None] * a + v[..., None] * b)
    lattice, inverse = np.unique(
        np.concatenate([p.reshape(-1, 3) for p in points]), axis=0, return_inverse=True
    )
    inverse = inverse.reshape(6, (n + 1) ** 2)
    quads = _grid_quads(n, n).reshape(-1, 4)
    return lattice, np.concatenate([side[quads] for side in inverse])


def quad_cube(
    n: int, *, dtype: torch.dtype = torch.float64, device: torch.device | str | None = None
) -> tuple[torch.Tensor, torch.Tensor]:
    """The surface of the cube ``[-1, 1]^3`` with ``n x n`` quads per side: closed, genus 0.

    The faces come side by side, in the order ``+x, -x, +y, -y, +z, -z``, each side's ``n x n``
    quads row-major in a frame ``(a, b)`` with ``a x b`` pointing outwards, corners ``(i, j),
    (i + 1, j), (i + 1, j + 1), (i, j + 1)``: ``faces.reshape(6, n, n, 4)`` is the grid of each
    side (what a tessellation that merges neighbouring quads needs). The vertices are shared
    between sides and sorted lexicographically by their coordinates.

    Args:
        n: quads per cube edge (at least 1).
        dtype: dtype of the vertices.
        device: device of the vertices.

    Returns:
        ``verts`` ``(6 n^2 + 2, 3)`` and ``faces`` ``(6 n^2, 4)`` int64.

    Examples:
        >>> verts, faces = quad_cube(1)
        >>> verts.shape, faces.shape, float(verts.abs().max())
        (torch.Size([8, 3]), torch.Size([6, 4]), 1.0)
    """
    check_int(n, "n", least=1)
    lattice, faces = _cube_lattice(n)
    return _verts(lattice / n, dtype, device), torch.from_numpy(faces)


def quad_sphere(
    n: int,
    *,
    radius: float = 1.0,
    noise: float = 0.0,
    seed: int = 0,
    dtype: torch.dtype = torch.float64,
    device: torch.device | str | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """The equi-angular cube sphere: :func:`quad_cube`'s quads on the sphere of ``radius``.

    Each cube coordinate ``c`` goes to ``tan(pi c / 4)`` before the projection onto the sphere,
    so that the quads along a cube edge subtend equal angles (the plain projection squeezes the
    quads near the cube's corners). Same connectivity and face order as :func:`quad_cube`.

    Args:
        n: quads per cube edge (``6 n^2`` quads in all).
        radius: the sphere's radius.
        noise: when positive, every vertex is moved radially by ``noise * radius`` times an
            independent standard normal draw (``numpy.random.default_rng(seed)``), which makes
            every quad non-planar.
        seed: the seed of the noise.
        dtype: dtype of the vertices.
        device: device of the vertices.

    Returns:
        ``verts`` ``(6 n^2 + 2, 3)`` and ``faces`` ``(6 n^2, 4)`` int64, outward oriented.

    Examples:
        >>> verts, faces = quad_sphere(3, radius=2.0)
        >>> torch.allclose(verts.norm(dim=1), torch.full((56,), 2.0, dtype=torch.float64))
        True
    """
    check_int(n, "n", least=1)
    lattice, faces = _cube_lattice(n)
    # tan(pi / 4) is 1 - 1e-16 in floating point: keep the cube's faces exactly at +-1
    cube = np.where(np.abs(lattice) == n, np.sign(lattice), np.tan(np.pi / 4 * lattice / n))
    points = cube / np.linalg.norm(cube, axis=1, keepdims=True)
    r = np.full(len(points), float(radius))
    if noise > 0:
        r = r * (1.0 + noise * np.random.default_rng(seed).standard_normal(len(points)))
    return _verts(points * r[:, None], dtype, device), torch.from_numpy(faces)


def torus(
    n_u: int,
    n_v: int,
    *,
    major: float = 1.0,
    minor: float = 0.4,
    dtype: torch.dtype = torch.float64,
    device: torch.device | str | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """A torus of quads around the ``z`` axis: closed, genus 1.

    Vertex ``(i, j)`` (index ``i * n_v + j``) sits at angle ``u = 2 pi i / n_u`` around the
    axis and ``v = 2 pi j / n_v`` around the tube: ``((major + minor cos v) cos u, (major +
    minor cos v) sin u, minor sin v)``. Quad ``(i, j)`` (row ``i * n_v + j``) is ``(i, j), (i +
    1, j), (i + 1, j + 1), (i, j + 1)``, indices modulo ``n_u`` and ``n_v``, so that
    ``faces.reshape(n_u, n_v, 4)`` is the periodic grid.

    Args:
        n_u: quads around the axis (at least 3).
        n_v: quads around the tube (at least 3).
        major: distance of the tube's centre line from the axis.
        minor: the tube's radius (less than ``major``).
        dtype: dtype of the vertices.
        device: device of the vertices.

    Returns:
        ``verts`` ``(n_u n_v, 3)`` and ``faces`` ``(n_u n_v, 4)`` int64, outward oriented.

    Examples:
        >>> verts, faces = torus(8, 4, major=2.0, minor=0.5)
        >>> verts.shape, faces.shape
        (torch.Size([32, 3]), torch.Size([32, 4]))
    """
    check_int(n_u, "n_u", least=3)
    check_int(n_v, "n_v", least=3)
    if not 0 < minor < major:
        raise ValueError(f"a torus needs 0 < minor < major, got minor={minor}, major={major}.")
    u, v = np.meshgrid(
        np.arange(n_u) * 2 * np.pi / n_u, np.arange(n_v) * 2 * np.pi / n_v, indexing="ij"
    )
    ring = major + minor * np.cos(v)
    verts = np.stack([ring * np.cos(u), ring * np.sin(u), minor * np.sin(v)], -1).reshape(-1, 3)
    idx = np.arange(n_u * n_v).reshape(n_u, n_v)
    nxt_u = np.roll(idx, -1, 0)
    quads = np.stack([idx, nxt_u, np.roll(nxt_u, -1, 1), np.roll(idx, -1, 1)], -1)
    return _verts(verts, dtype, device), torch.from_numpy(quads.reshape(-1, 4))


def schwarz_lantern(
    sides: int = 8,
    rings: int = 7,
    radius: float = 1.0,
    height: float = 1.0,
    triangulation: str = "quad",
    dtype: torch.dtype = torch.float64,
    device: torch.device | str | None = None,
) -> tuple[torch.Tensor, list[list[int]]]:
    """A Schwarz lantern: rings of ``sides`` points on a cylinder, each ring turned by ``pi/sides``.

    Vertex ``(i, j)`` (ring ``i``, ``0 <= j < sides``, index ``i * sides + j``) sits at angle
    ``(2 j + i) pi / sides`` and height ``i * height / (rings - 1)``. The quad version (AW11
    Fig. 2, top left) has the non-planar "diamond" quads ``(i, j), (i+1, j), (i+2, j-1), (i+1,
    j-1)`` (bottom, right, top, left) and half-diamond triangles along the two boundary rings.
    The triangulations split every diamond on the same vertices: ``"horizontal"`` along
    left-right (the classical Schwarz lantern), ``"vertical"`` along bottom-top,
    ``"alternating"`` by the parity of ``i + j``.

    Args:
        sides: points per ring (at least 3).
        rings: number of rings (at least 3).
        radius: the cylinder's radius.
        height: the cylinder's height.
        triangulation: ``"quad"``, ``"horizontal"``, ``"vertical"`` or ``"alternating"``.
        dtype: dtype of the vertices.
        device: device of the vertices.

    Returns:
        ``verts`` ``((rings * sides), 3)`` and faces as index lists, outward oriented; rotating by
        ``2 pi / sides`` about ``z`` maps vertex ``(i, j)`` to ``(i, j + 1)``. The quad version
        has ``(rings - 2) * sides`` quads and ``2 * sides`` triangles.

    Examples:
        >>> verts, faces = schwarz_lantern(6, 4)
        >>> verts.shape, sorted({len(f) for f in faces}), len(faces)
        (torch.Size([24, 3]), [3, 4], 24)
    """
    if sides < 3 or rings < 3:
        raise ValueError(f"a lantern needs sides >= 3 and rings >= 3, got {sides}, {rings}.")
    if triangulation not in ("quad", "horizontal", "vertical", "alternating"):
        raise ValueError(
            "triangulation must be 'quad', 'horizontal', 'vertical' or 'alternating', "
            f"got {triangulation!r}."
        )
    i, j = torch.meshgrid(torch.arange(rings), torch.arange(sides), indexing="ij")
    angle = (2 * j + i).to(dtype) * (torch.pi / sides)
    z = i.to(dtype) * (height / (rings - 1))
    verts = torch.stack([radius * angle.cos(), radius * angle.sin(), z], -1).reshape(-1, 3)

    def vid(ring: int, k: int) -> int:
        return ring * sides + k % sides

    faces: list[list[int]] = []
    for k in range(sides):  # boundary half-diamonds: (0, k), (0, k+1), (1, k) and the top ones
        faces.append([vid(0, k), vid(0, k + 1), vid(1, k)])
        faces.append([vid(rings - 2, k), vid(rings - 1, k), vid(rings - 1, k - 1)])
    for ring in range(rings - 2):
        for k in range(sides):
            b, r, t, l = vid(ring, k), vid(ring + 1, k), vid(ring + 2, k - 1), vid(ring + 1, k - 1)
            split = triangulation
            if split == "alternating":
                split = "horizontal" if (ring + k) % 2 == 0 else "vertical"
            if split == "quad":
                faces.append([b, r, t, l])
            elif split == "horizontal":
                faces += [[b, r, l], [r, t, l]]
            else:
                faces += [[b, r, t], [b, t, l]]
    return verts.to(device), faces

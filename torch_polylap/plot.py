"""Figures of polygon meshes and of per-face or per-vertex quantities on them (matplotlib).

matplotlib is imported inside the functions, so ``import torch_polylap`` never needs it.  The
figures are built with :class:`matplotlib.figure.Figure` directly instead of ``pyplot``: no
window opens, no global backend is switched, and nothing is kept alive after saving (PNG
through the Agg canvas).

Every polygon is drawn as it is (no triangulation), in 3D through
:class:`~mpl_toolkits.mplot3d.art3d.Poly3DCollection` and in 2D (parameterizations) through
:class:`~matplotlib.collections.PolyCollection`.
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Any, cast

import numpy as np
import torch

from ._typing import ArrayLike
from .checks import check_verts_array
from .faces import FacesLike, as_faces
from .measures import vector_area

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure
    from mpl_toolkits.mplot3d import Axes3D

__all__ = [
    "face_values",
    "new_figure",
    "plot_mesh",
    "PlotOptions",
    "plot_meshes",
    "plot_uv",
    "plot_lines",
    "save_figure",
]

# light direction for the gray shading of meshes drawn without values
# cyclic permutations of (x, y, z) that put the "up" axis last (matplotlib's vertical)
_UP = {"x": [1, 2, 0], "y": [2, 0, 1], "z": [0, 1, 2]}
_LIGHT = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])


def _numpy(x: ArrayLike) -> np.ndarray:
    if isinstance(x, torch.Tensor):
        return x.detach().cpu().to(torch.float64).numpy()
    return np.asarray(x, dtype=np.float64)


def face_values(values: ArrayLike, faces: FacesLike, num_verts: int) -> np.ndarray:
    """``(F,)`` per-face values: per-face input unchanged, per-vertex input averaged over each
    face's corners.

    Args:
        values: ``(F,)`` or ``(V,)`` values.
        faces: the mesh faces (anything :func:`~torch_polylap.as_faces` accepts).
        num_verts: ``V``, to tell the two cases apart.

    Raises:
        ValueError: ``values`` has neither ``F`` nor ``V`` entries (``F`` wins when ``F == V``).
    """
    pf = as_faces(faces)
    v = _numpy(values).reshape(-1)
    if v.shape[0] == pf.num_faces:
        return v
    if v.shape[0] != num_verts:
        raise ValueError(
            f"values has {v.shape[0]} entries; expected one per face ({pf.num_faces}) "
            f"or one per vertex ({num_verts})."
        )
    face_of_corner = np.repeat(np.arange(pf.num_faces), pf.sizes.cpu().numpy())
    sums = np.bincount(face_of_corner, weights=v[pf.indices.cpu().numpy()], minlength=pf.num_faces)
    return sums / pf.sizes.cpu().numpy()


def _polygons(points: np.ndarray, faces: FacesLike) -> np.ndarray:
    """``(F, k_max, d)`` corners of every face, a face of fewer corners padded by repeating its
    last one (the same polygon drawn). matplotlib pads ragged polygon lists with uninitialized
    memory and projects it in 3D, which overflows on some runs (matplotlib issue #32272)."""
    pf = as_faces(faces)
    offsets = pf.offsets.cpu().numpy()
    sizes = np.diff(offsets)
    if sizes.size == 0:
        return np.zeros((0, 3, points.shape[1]))
    local = np.minimum(np.arange(sizes.max())[None, :], sizes[:, None] - 1)  # (F, k_max)
    return points[pf.indices.cpu().numpy()[offsets[:-1, None] + local]]


def _face_colors(
    values: np.ndarray, cmap: str, clim: tuple[float, float] | None
) -> tuple[np.ndarray, Any]:
    """RGBA per face and the ScalarMappable for a colorbar."""
    from matplotlib import cm, colors

    finite = values[np.isfinite(values)]
    lo, hi = clim if clim is not None else (finite.min(), finite.max()) if finite.size else (0, 1)
    if hi <= lo:  # a constant field still needs a non-empty range
        lo, hi = lo - 0.5, hi + 0.5
    mappable = cm.ScalarMappable(norm=colors.Normalize(lo, hi), cmap=cmap)
    mappable.set_array(values)
    return mappable.to_rgba(values), mappable


@dataclass(frozen=True)
class PlotOptions:
    """How :func:`plot_mesh` draws: colors, colorbar, view and outlines.

    Attributes:
        cmap: colormap name.
        clim: color limits ``(low, high)``; default: the data range.
        colorbar: add a colorbar when values are given.
        label: the colorbar's label.
        elev: view elevation in degrees.
        azim: view azimuth in degrees.
        edges: draw the polygon outlines.
        up: the coordinate axis drawn vertically, ``"x"``, ``"y"`` (common for OBJ models) or
            ``"z"``; the axes are permuted cyclically, so the view is not mirrored.
    """

    cmap: str = "viridis"
    clim: tuple[float, float] | None = None
    colorbar: bool = True
    label: str | None = None
    elev: float = 20.0
    azim: float = -60.0
    edges: bool = True
    up: str = "z"


def plot_mesh(
    verts: ArrayLike,
    faces: FacesLike,
    values: ArrayLike | None = None,
    ax: Axes3D | None = None,
    path: str | os.PathLike | None = None,
    title: str | None = None,
    options: PlotOptions | None = None,
) -> Axes3D:
    """Draw a polygon mesh in 3D, faces colored by ``values`` (or gray-shaded without them).

    Args:
        verts: ``(V, 3)`` positions.
        faces: the polygons (any degree, mixed).
        values: ``(F,)`` per-face or ``(V,)`` per-vertex values (averaged to the faces).
        ax: a 3D axes to draw into (``projection="3d"``); a new figure when ``None``.
        path: save the figure there (PNG, or any format matplotlib infers from the suffix).
        title: axes title.
        options: a :class:`PlotOptions`: colormap and limits, colorbar and its label, view,
            outlines and the vertical axis; default ``PlotOptions()``.

    Returns:
        The axes drawn into.
    """
    import mpl_toolkits.mplot3d  # noqa: F401  (registers the "3d" projection)
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    options = options or PlotOptions()
    pts = check_verts_array(verts)
    if options.up not in _UP:
        raise ValueError(f"plot_mesh: up must be 'x', 'y' or 'z', got {options.up!r}.")
    pts = pts[:, _UP[options.up]]
    if ax is None:
        ax = cast("Axes3D", new_figure(1, 1, three_d=True)[1][0])  # new_figure types it as Axes
    pf = as_faces(faces)
    polys = _polygons(pts, pf)
    mappable = None
    if values is not None:
        rgba, mappable = _face_colors(face_values(values, pf, len(pts)), options.cmap, options.clim)
    else:
        # Lambert shading by the face normals (vector area, sign-free so back faces show too)
        normals = vector_area(torch.from_numpy(pts), pf).numpy()
        normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-300)
        shade = 0.35 + 0.6 * np.abs(normals @ _LIGHT)
        rgba = np.column_stack([shade, shade, shade, np.ones_like(shade)])
    collection = Poly3DCollection(
        polys,
        facecolors=rgba,
        edgecolors=(0.1, 0.1, 0.1, 0.35) if options.edges else "none",
        linewidths=0.3,
    )
    ax.add_collection3d(collection)
    lo, hi = pts.min(0), pts.max(0)
    center, half = (lo + hi) / 2, max(float((hi - lo).max()) / 2, 1e-12)
    ax.set_xlim(center[0] - half, center[0] + half)
    ax.set_ylim(center[1] - half, center[1] + half)
    ax.set_zlim(center[2] - half, center[2] + half)
    ax.set_box_aspect((1, 1, 1))  # equal aspect: the limits above are a cube
    ax.view_init(elev=options.elev, azim=options.azim)
    ax.set_axis_off()
    if title:
        ax.set_title(title, fontsize=10)
    if mappable is not None and options.colorbar:
        ax.figure.colorbar(mappable, ax=ax, shrink=0.6, pad=0.02, label=options.label)
    if path is not None:
        save_figure(ax.figure.figure, path)  # the whole figure, also from a subfigure
    return ax


def plot_meshes(
    panels: Sequence[Mapping[str, Any]],
    path: str | os.PathLike | None = None,
    ncols: int | None = None,
    *,
    shared_clim: bool = False,
    suptitle: str | None = None,
    panel_size: float = 4.0,
) -> Figure:
    """Several meshes side by side, one :func:`plot_mesh` call per panel.

    Args:
        panels: one mapping per panel with :func:`plot_mesh`'s keyword arguments (``verts``,
            ``faces``, and optionally ``values``, ``title`` and ``options``).
        path: save the figure there.
        ncols: panels per row (default: all in one row, at most 4).
        shared_clim: give every panel with values and no color limits of its own the same
            limits (the union of their ranges), so that before/after panels compare by color.
        suptitle: figure title.
        panel_size: inches per panel.

    Returns:
        The figure.
    """
    specs = [dict(p) for p in panels]  # copies: shared_clim adds to them
    ncols = ncols or min(len(specs), 4)
    nrows = -(-len(specs) // ncols)
    if shared_clim:
        ranges = [
            (np.nanmin(v), np.nanmax(v))
            for p in specs
            if p.get("values") is not None
            for v in [face_values(p["values"], p["faces"], len(_numpy(p["verts"])))]
        ]
        if ranges:
            clim = (min(r[0] for r in ranges), max(r[1] for r in ranges))
            for p in specs:
                options = p.get("options") or PlotOptions()
                if options.clim is None:
                    p["options"] = replace(options, clim=clim)
    fig, axes = new_figure(nrows, ncols, three_d=True, panel_size=panel_size)
    for ax, panel in zip(axes, specs, strict=False):
        plot_mesh(ax=ax, **panel)
    for ax in axes[len(specs) :]:
        # removed, not hidden: a hidden 3D axes has no extent, which breaks a tight bounding box
        ax.remove()
    if suptitle:
        fig.suptitle(suptitle)
    if path is not None:
        save_figure(fig, path)
    return fig


def plot_uv(
    uv: ArrayLike,
    faces: FacesLike,
    values: ArrayLike | None = None,
    ax: Axes | None = None,
    path: str | os.PathLike | None = None,
    title: str | None = None,
    cmap: str = "magma",
    clim: tuple[float, float] | None = None,
    label: str | None = None,
) -> Axes:
    """Draw a 2D mesh (a parameterization), polygons colored by ``values``.

    Args:
        uv: ``(V, 2)`` planar positions.
        faces: the polygons.
        values: ``(F,)`` or ``(V,)`` values; without them the polygons are white.
        ax: a 2D axes to draw into; a new figure when ``None``.
        path: save the figure there, as in :func:`plot_mesh`.
        title: axes title.
        cmap: colormap name.
        clim: color limits; default: the data range.
        label: the colorbar's label.

    Returns:
        The axes drawn into.
    """
    from matplotlib.collections import PolyCollection

    pts = _numpy(uv)
    if pts.ndim != 2 or pts.shape[1] != 2:
        raise ValueError(f"plot_uv: uv must have shape (V, 2), got {pts.shape}.")
    if ax is None:
        ax = new_figure(1, 1, three_d=False)[1][0]
    pf = as_faces(faces)
    mappable = None
    rgba: np.ndarray | str = "white"
    if values is not None:
        rgba, mappable = _face_colors(face_values(values, pf, len(pts)), cmap, clim)
    ax.add_collection(
        PolyCollection(
            list(_polygons(pts, pf)),
            facecolors=rgba,
            edgecolors=(0.1, 0.1, 0.1, 0.5),
            linewidths=0.3,
        )
    )
    ax.autoscale_view()
    ax.set_aspect("equal")
    if title:
        ax.set_title(title, fontsize=10)
    if mappable is not None:
        ax.figure.colorbar(mappable, ax=ax, shrink=0.8, label=label)
    if path is not None:
        save_figure(ax.figure.figure, path)  # the whole figure, also from a subfigure
    return ax


def plot_lines(
    series: Mapping[str, tuple[ArrayLike, ArrayLike]],
    ax: Axes | None = None,
    path: str | os.PathLike | None = None,
    title: str | None = None,
    xlabel: str | None = None,
    ylabel: str | None = None,
    *,
    logy: bool = False,
    marker: str = "o",
) -> Axes:
    """Line plot of named ``(x, y)`` series (eigenvalues against index, energy against step...).

    Returns:
        The axes drawn into.
    """
    if ax is None:
        ax = new_figure(1, 1, three_d=False)[1][0]
    for name, (x, y) in series.items():
        ax.plot(_numpy(x), _numpy(y), marker=marker, markersize=3, label=name)
    if logy:
        ax.set_yscale("log")
    ax.set_title(title or "", fontsize=10)
    ax.set_xlabel(xlabel or "")
    ax.set_ylabel(ylabel or "")
    ax.grid(True, alpha=0.3)
    if len(series) > 1:
        ax.legend()
    if path is not None:
        save_figure(ax.figure.figure, path)  # the whole figure, also from a subfigure
    return ax


def new_figure(
    nrows: int, ncols: int, *, three_d: Sequence[bool] | bool, panel_size: float = 4.0
) -> tuple[Figure, list[Axes]]:
    """A figure with an ``nrows x ncols`` grid of axes, 3D where ``three_d`` says so (one flag,
    or one per panel in row-major order), sized ``panel_size`` inches per panel."""
    import mpl_toolkits.mplot3d  # noqa: F401  (registers the "3d" projection)
    from matplotlib.figure import Figure

    fig = Figure(figsize=(panel_size * ncols, panel_size * nrows), layout="constrained")
    flags = [three_d] * (nrows * ncols) if isinstance(three_d, bool) else list(three_d)
    axes = [
        fig.add_subplot(nrows, ncols, i + 1, projection="3d" if flag else None)
        for i, flag in enumerate(flags)
    ]
    return fig, axes


def save_figure(fig: Figure, path: str | os.PathLike, dpi: int = 110) -> None:
    """Save ``fig`` (format from the suffix, PNG by default through the Agg canvas)."""
    fig.savefig(os.fspath(path), dpi=dpi)

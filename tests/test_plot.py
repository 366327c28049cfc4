"""Figure helpers: what is drawn (polygons, colors, limits) matches the mesh and the values."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
import torch
from conftest import mixed_mesh

import torch_polylap as tp
from torch_polylap.shapes import quad_grid

pytest.importorskip("matplotlib", reason='matplotlib not installed: pip install -e ".[plot]"')

from matplotlib import colormaps  # noqa: E402
from matplotlib.collections import PolyCollection  # noqa: E402
from mpl_toolkits.mplot3d.art3d import Poly3DCollection  # noqa: E402

from torch_polylap import plot  # noqa: E402

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def rows(colors: np.ndarray) -> np.ndarray:
    """RGBA rows in lexicographic order: 3D collections reorder their faces by depth."""
    colors = np.asarray(colors)
    return colors[np.lexsort(colors.T[::-1])]


def test_import_does_not_need_matplotlib():
    code = "import sys, torch_polylap, torch_polylap.plot; sys.exit('matplotlib' in sys.modules)"
    assert subprocess.run([sys.executable, "-c", code]).returncode == 0


def test_face_values_average_vertex_values_per_face():
    verts, faces = mixed_mesh()
    values = torch.arange(verts.shape[0], dtype=torch.float64) ** 2
    expected = [float(np.mean([values[i] for i in f])) for f in faces]
    assert plot.face_values(values, faces, verts.shape[0]) == pytest.approx(expected)
    per_face = np.linspace(0, 1, len(faces))
    assert np.array_equal(plot.face_values(per_face, faces, verts.shape[0]), per_face)
    with pytest.raises(ValueError, match="one per face \\(7\\) or one per vertex \\(12\\)"):
        plot.face_values(np.zeros(5), faces, verts.shape[0])


def test_plot_mesh_draws_every_polygon_with_its_color(tmp_path):
    verts, faces = mixed_mesh()
    values = np.array([0.0, 1, 2, 3, 4, 5, 6])
    style = plot.PlotOptions(cmap="viridis", clim=(0.0, 6.0))
    ax = plot.plot_mesh(verts, faces, values, options=style)
    (collection,) = [c for c in ax.collections if isinstance(c, Poly3DCollection)]
    # the face colors (matplotlib depth-sorts the faces, so compare as sorted rows)
    expected = colormaps["viridis"](values / 6.0)
    assert np.allclose(rows(collection.get_facecolor()), rows(expected))
    # each polygon keeps its corners (no triangulation); shorter ones repeat their last corner
    # up to the largest degree (matplotlib pads ragged lists with uninitialized memory)
    polys = plot._polygons(verts.numpy(), tp.as_faces(faces))
    k_max = max(len(f) for f in faces)
    assert polys.shape == (len(faces), k_max, 3)
    for p, f in zip(polys, faces, strict=True):
        assert np.array_equal(p[: len(f)], verts.numpy()[f])
        assert (p[len(f) :] == verts.numpy()[f[-1]]).all()
    # equal aspect: a cube of limits around the mesh, and one colorbar
    spans = [np.diff(lim)[0] for lim in (ax.get_xlim(), ax.get_ylim(), ax.get_zlim())]
    assert spans == pytest.approx([3.5] * 3)  # the largest extent: x from 0 to 3.5
    assert len(ax.figure.axes) == 2
    path = tmp_path / "mesh.png"
    plot.plot_mesh(verts, faces, path=path, title="gray")  # shaded, no colorbar
    assert path.read_bytes()[:8] == PNG_MAGIC


def test_up_axis_permutes_cyclically():
    verts = torch.tensor([[0.0, 0, 0], [1, 0, 0], [1, 2, 0], [0, 2, 0]]) + torch.tensor([0, 0, 5])
    faces = [[0, 1, 2, 3]]
    ax = plot.plot_mesh(verts, faces, options=plot.PlotOptions(up="y"))
    # y (0..2) is drawn vertically; x moves to the second axis, z to the first
    assert np.mean(ax.get_zlim()) == pytest.approx(1.0)
    assert np.mean(ax.get_ylim()) == pytest.approx(0.5)
    assert np.mean(ax.get_xlim()) == pytest.approx(5.0)
    with pytest.raises(ValueError, match="up must be"):
        plot.plot_mesh(verts, faces, options=plot.PlotOptions(up="w"))
    with pytest.raises(ValueError, match=r"\(V, 3\)"):
        plot.plot_mesh(verts[:, :2], faces)


def test_plot_uv_polygons_and_colors(tmp_path):
    verts, faces = quad_grid(3, 2)
    uv = verts[:, :2]
    values = uv[:, 0]  # per vertex: the face average is the face's x center
    path = tmp_path / "uv.png"
    ax = plot.plot_uv(uv, faces, values, path=path, cmap="magma")
    (collection,) = [c for c in ax.collections if isinstance(c, PolyCollection)]
    paths = collection.get_paths()
    assert len(paths) == faces.shape[0]
    for p, f in zip(paths, faces.tolist(), strict=True):
        assert np.allclose(p.vertices[:4], uv[f].numpy())
    centers = uv[faces].mean(1)[:, 0].numpy()
    lo, hi = centers.min(), centers.max()
    expected = colormaps["magma"]((centers - lo) / (hi - lo))
    assert np.allclose(collection.get_facecolor(), expected)
    assert ax.get_aspect() == 1.0 and path.read_bytes()[:8] == PNG_MAGIC
    with pytest.raises(ValueError, match=r"\(V, 2\)"):
        plot.plot_uv(verts, faces)


def test_plot_meshes_shares_color_limits(tmp_path):
    verts, faces = quad_grid(2)
    a = torch.zeros(faces.shape[0])
    b = torch.linspace(2.0, 5.0, faces.shape[0])
    panels = [dict(verts=verts, faces=faces, values=a), dict(verts=verts, faces=faces, values=b)]

    def colors(fig):
        return [
            c.get_facecolor()
            for ax in fig.axes
            for c in ax.collections
            if isinstance(c, Poly3DCollection)
        ]

    viridis = colormaps["viridis"]
    shared = colors(plot.plot_meshes(panels, shared_clim=True, path=tmp_path / "two.png"))
    # one scale 0..5 for both: the zeros take the bottom color, b runs from 2/5 to the top
    assert np.allclose(rows(shared[0]), viridis(np.zeros(4)))
    assert np.allclose(rows(shared[1]), rows(viridis(b.numpy() / 5.0)))
    own = colors(plot.plot_meshes(panels))
    # separately, a constant field sits in the middle of its own (widened) range
    assert np.allclose(rows(own[0]), viridis(np.full(4, 0.5)))
    assert np.allclose(rows(own[1]), rows(viridis((b.numpy() - 2.0) / 3.0)))
    assert (tmp_path / "two.png").read_bytes()[:8] == PNG_MAGIC
    # a panel's own limits win over the shared ones, and its other options stay
    own_limits = plot.PlotOptions(cmap="magma", clim=(0.0, 10.0))
    panels[1]["options"] = own_limits
    mixed = colors(plot.plot_meshes(panels, shared_clim=True))
    assert np.allclose(rows(mixed[0]), viridis(np.zeros(4)))
    assert np.allclose(rows(mixed[1]), rows(colormaps["magma"](b.numpy() / 10.0)))
    assert panels[1]["options"] is own_limits  # the caller's panels are not changed


def test_plot_lines_log_scale(tmp_path):
    ax = plot.plot_lines(
        {"a": ([0, 1, 2], [1.0, 1e-2, 1e-4]), "b": ([0, 1], [1.0, 0.5])},
        logy=True,
        path=tmp_path / "lines.png",
        xlabel="iteration",
    )
    assert ax.get_yscale() == "log" and len(ax.get_lines()) == 2
    assert ax.get_legend() is not None and ax.get_xlabel() == "iteration"
    assert np.allclose(ax.get_lines()[0].get_ydata(), [1.0, 1e-2, 1e-4])


def test_plot_meshes_saves_a_grid_with_empty_cells(tmp_path):
    """Three panels in two columns leave one cell empty; the saved figure has three axes."""
    verts, faces = quad_grid(3)
    panels = [dict(verts=verts, faces=faces, title=str(i)) for i in range(3)]
    fig = plot.plot_meshes(panels, path=tmp_path / "grid.png", ncols=2)
    assert (tmp_path / "grid.png").stat().st_size > 0
    assert [ax.get_title() for ax in fig.axes] == ["0", "1", "2"]

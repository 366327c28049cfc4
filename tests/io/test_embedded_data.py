"""The meshes shipped in ``torch_polylap/data``: read without a warning, and the geometry of the
upstream files they were cut from (see ``torch_polylap/data/README.md``)."""

from __future__ import annotations

import warnings
from pathlib import Path

import pytest
import torch
from conftest import DATA
from meshes import shared_path

import torch_polylap as tp
from torch_polylap.cli import main
from torch_polylap.data import DATA_DIR

EMBEDDED = sorted(DATA_DIR.glob("*.obj"))


def read_upstream(path: Path) -> tuple[torch.Tensor, tp.PolygonFaces]:
    """An unchanged upstream copy, with the content the package does not read."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", tp.io.SkippedContentWarning)
        return tp.read_mesh(path)


def test_all_embedded_meshes_are_covered():
    names = {path.name for path in EMBEDDED}
    assert {"spot_control_mesh.obj", "hex_hemisphere.obj", "grid_voronoi_1.obj"} <= names


@pytest.mark.parametrize("path", EMBEDDED, ids=lambda path: path.name)
def test_embedded_mesh_reads_without_warning(path):
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        verts, faces = tp.read_mesh(path)
    assert verts.shape[0] > 0 and faces.num_faces > 0


@pytest.mark.parametrize(
    "name,upstream",
    [
        ("spot_control_mesh.obj", lambda: DATA / "spot_control_mesh.obj"),
        ("grid_voronoi_1.obj", lambda: shared_path("grid/voronoi_1.obj")),
    ],
)
def test_embedded_mesh_has_the_upstream_geometry(name, upstream):
    """Removing the texture coordinates and materials left every coordinate and index as is."""
    verts, faces = tp.read_mesh(DATA_DIR / name)
    ref_verts, ref_faces = read_upstream(upstream())
    assert torch.equal(verts, ref_verts)
    assert torch.equal(faces.indices, ref_faces.indices)
    assert torch.equal(faces.offsets, ref_faces.offsets)


def test_info_on_the_embedded_mesh_warns_nothing(capsys):
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert main(["info"]) == 0
    captured = capsys.readouterr()
    assert "spot_control_mesh.obj (embedded default mesh)" in captured.out
    assert captured.err == ""

"""The free-boundary conformal map refuses every mesh that is not a topological disk.

Its area form sums over all boundary loops; on a mesh with holes or handles the top eigenpair of
AW11 eq. 14 need not be an embedding (corner angle errors of 250-285 degrees before the check). The
expected boundary loops, Euler characteristic and genus come from how each mesh is built here
(a grid is a disk, a cube sphere has genus 0, a torus genus 1; removing k faces that share no
vertex with each other or the boundary adds k loops and lowers V - E + F by k), not from the
package's topology code.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from torch_polylap.apps.conformal import angle_distortion, conformal_parameterization
from torch_polylap.cli import main
from torch_polylap.io import write_mesh
from torch_polylap.shapes import quad_sphere, torus


def grid(n: int, m: int, seed: int = 0) -> tuple[torch.Tensor, np.ndarray]:
    """An ``n x m`` quad grid on a bumpy height field (a disk: one loop, V - E + F = 1)."""
    x, y = np.meshgrid(np.arange(n + 1.0), np.arange(m + 1.0), indexing="ij")
    z = 0.3 * np.random.default_rng(seed).random(x.shape)
    idx = np.arange((n + 1) * (m + 1)).reshape(n + 1, m + 1)
    quads = np.stack([idx[:-1, :-1], idx[1:, :-1], idx[1:, 1:], idx[:-1, 1:]], -1).reshape(-1, 4)
    verts = torch.from_numpy(np.stack([x.ravel(), y.ravel(), z.ravel()], 1))
    return verts, quads


def punch(faces: np.ndarray, candidates: list[int], boundary_verts: set[int]) -> np.ndarray:
    """Remove the candidate faces, in order, that share no vertex with the boundary or with a
    face removed before (each one opens a hole of its own, every vertex stays manifold)."""
    used = set(boundary_verts)
    removed = []
    for f in candidates:
        corners = set(faces[f].tolist())
        if corners & used:
            continue
        used |= corners
        removed.append(f)
    return np.delete(faces, removed, axis=0)


def grid_boundary(n: int, m: int) -> set[int]:
    idx = np.arange((n + 1) * (m + 1)).reshape(n + 1, m + 1)
    return set(np.concatenate([idx[0], idx[-1], idx[:, 0], idx[:, -1]]).tolist())


# (mesh, expected boundary loops, Euler characteristic, genus)
Case = tuple[torch.Tensor, np.ndarray, int, int, int]


@st.composite
def surfaces(draw: st.DrawFn) -> Case:
    """A grid (disk), cube sphere (genus 0, closed) or torus (genus 1, closed) with 0-4 holes."""
    kind = draw(st.sampled_from(["grid", "sphere", "torus"]))
    if kind == "grid":
        n, m = draw(st.integers(3, 8)), draw(st.integers(3, 8))
        verts, faces = grid(n, m, draw(st.integers(0, 9)))
        loops0, chi0, genus, boundary = 1, 1, 0, grid_boundary(n, m)
    elif kind == "sphere":
        verts, f = quad_sphere(draw(st.integers(2, 3)))
        faces, loops0, chi0, genus, boundary = f.numpy(), 0, 2, 0, set()
    else:
        verts, f = torus(draw(st.integers(6, 9)), draw(st.integers(4, 6)))
        faces, loops0, chi0, genus, boundary = f.numpy(), 0, 0, 1, set()
    candidates = draw(st.lists(st.integers(0, len(faces) - 1), max_size=4, unique=True))
    punched = punch(faces, candidates, boundary)
    holes = len(faces) - len(punched)
    return verts, punched, loops0 + holes, chi0 - holes, genus


@settings(max_examples=40, deadline=None)
@given(case=surfaces())
def test_free_boundary_maps_disks_and_refuses_the_rest(case: Case) -> None:
    verts, faces, loops, chi, genus = case
    faces_t = torch.from_numpy(faces)
    if loops == 0:
        with pytest.raises(ValueError, match=rf"no boundary \(closed, Euler characteristic "
                           rf"{chi}, genus {genus}\)"):  # fmt: skip
            conformal_parameterization(verts, faces_t, free_boundary=True)
    elif (loops, chi) != (1, 1):
        message = (
            rf"needs a topological disk .* has {loops} boundary loops? and Euler "
            rf"characteristic {chi} \(genus {genus}\)"
        )
        with pytest.raises(ValueError, match=message):
            conformal_parameterization(verts, faces_t, free_boundary=True)
    else:
        uv = conformal_parameterization(verts, faces_t, free_boundary=True)
        assert uv.shape == (verts.shape[0], 2) and bool(torch.isfinite(uv).all())


def test_non_disks_are_refused_and_disks_still_map(device: torch.device) -> None:
    """A torus with one hole (one loop, but genus 1) used to be mapped silently with angle
    errors of 260 degrees. A grid with three holes is refused too: nearly flat, it happened to
    map well, but the same area form folds curved meshes with holes (a cube sphere with five
    holes: 250 degrees). The grid itself, a disk, maps cleanly."""
    verts, faces = grid(9, 9)
    verts = verts.to(device)
    holes = punch(faces, [10, 14, 46], grid_boundary(9, 9))
    assert len(faces) - len(holes) == 3
    with pytest.raises(ValueError, match="4 boundary loops and Euler characteristic -2"):
        conformal_parameterization(verts, torch.from_numpy(holes), free_boundary=True)
    tv, tf = torus(8, 6, device=device)
    with pytest.raises(ValueError, match="1 boundary loop and Euler characteristic -1 .genus 1"):
        conformal_parameterization(tv, tf[1:], free_boundary=True)
    uv = conformal_parameterization(verts, torch.from_numpy(faces), free_boundary=True)
    assert uv.device.type == device.type
    assert math.degrees(angle_distortion(uv, verts, faces).max) < 10  # a fold-over: 250-285


def test_cli_reports_a_non_disk_in_one_line_and_writes_nothing(tmp_path, capsys) -> None:
    verts, faces = grid(9, 9)
    mesh = tmp_path / "holes.obj"
    write_mesh(mesh, verts, punch(faces, [10, 14, 46], grid_boundary(9, 9)))
    out = tmp_path / "out"
    assert main(["param", str(mesh), "--free-boundary", "--no-plot", "-o", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("polylap: error: free_boundary=True needs")
    assert "4 boundary loops and Euler characteristic -2 (genus 0)" in err
    assert list(out.iterdir()) == []

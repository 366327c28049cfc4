"""The polylap command, run as a user would: in a subprocess (one per command), and in-process
through ``main`` for option variations and errors (no interpreter start per case).

The expected values are recomputed here from the files the commands write, with numpy/scipy
formulas independent of the package where one exists (shoelace areas, corner angles, plane fits).
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import math
import os
import re
import subprocess
import sys

import numpy as np
import pytest
import scipy.linalg
import scipy.sparse.linalg
import torch
from conftest import DATA, ROOT
from meshes import dumbbell, read_mesh

import torch_polylap as tp
from torch_polylap.cli import COMMANDS, build_parser, main
from torch_polylap.cli.common import Result
from torch_polylap.data import DATA_DIR, DEFAULT_MESH, DISK_MESH
from torch_polylap.timing import pinned_threads

# The commands read the test meshes, whose texture coordinates, normals, object names and
# smoothing groups the readers report with a SkippedContentWarning: expected here (the readers'
# own tests assert it); every other warning stays an error.
pytestmark = pytest.mark.filterwarnings("ignore::torch_polylap.io.SkippedContentWarning")

COMMAND = [sys.executable, "-m", "torch_polylap.cli"]
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
# one torch thread: on a busy machine every tiny parallel kernel otherwise waits for its threads
ENV = {**os.environ, "OMP_NUM_THREADS": "1"}


def run(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([*COMMAND, *args], capture_output=True, text=True, timeout=120, env=ENV)


def field(out: str, label: str) -> str:
    match = re.search(rf"^  {re.escape(label)}\s+(.*)$", out, re.MULTILINE)
    assert match, f"{label!r} missing from:\n{out}"
    return match.group(1)


def numbers(text: str) -> list[float]:
    return [float(x) for x in re.findall(r"[-+]?\d+(?:\.\d*)?(?:e[-+]?\d+)?", text)]


def is_png(path) -> bool:
    return path.is_file() and path.read_bytes()[:8] == PNG_MAGIC and path.stat().st_size > 1000


def polygons(verts: np.ndarray, faces: tp.PolygonFaces) -> list[np.ndarray]:
    return np.split(verts[faces.indices.numpy()], faces.offsets.numpy()[1:-1])


def shoelace_normal(poly: np.ndarray) -> np.ndarray:
    """Vector area 1/2 sum p_i x p_{i+1} of a (possibly non-planar) polygon."""
    return 0.5 * np.cross(poly, np.roll(poly, -1, axis=0)).sum(0)


def corner_angles(poly: np.ndarray) -> np.ndarray:
    """Interior angles of a convex polygon (2D or 3D), by arccos of the edge vectors."""
    a = np.roll(poly, 1, axis=0) - poly
    b = np.roll(poly, -1, axis=0) - poly
    cos = (a * b).sum(1) / np.linalg.norm(a, axis=1) / np.linalg.norm(b, axis=1)
    return np.arccos(np.clip(cos, -1, 1))


def plane_fit_nonplanarity(poly: np.ndarray) -> float:
    """Largest distance from the least-squares plane over the diameter (an independent measure;
    the package uses the plane of the maximal projection instead)."""
    c = poly - poly.mean(0)
    normal = np.linalg.svd(c)[2][-1]
    diameter = max(np.linalg.norm(p - q) for p in poly for q in poly)
    return float(np.abs(c @ normal).max() / diameter)


# ------------------------------------------------------------------------------------------
# info (the first command; its behaviour is kept)
# ------------------------------------------------------------------------------------------


def test_info_on_embedded_mesh():
    result = run("info")
    assert result.returncode == 0, result.stderr
    out = result.stdout
    assert "spot_control_mesh.obj (embedded default mesh)" in out
    assert field(out, "vertices / faces / edges") == "188 / 180 / 366"
    assert field(out, "face degrees (k:count)") == "3:4 4:160 5:16"
    assert field(out, "genus (closed, orientable)") == "0"
    assert float(field(out, "L symmetry |L - L^T| / max|L|")) == 0.0
    assert float(field(out, "L row sums / max|L|")) < 1e-14
    assert field(out, "zero eigenvalues / components") == "1 / 1"
    assert "first assembly" in out and result.stderr == ""


def test_info_without_command_defaults_to_info(capsys, one_thread):
    assert main([]) == 0
    assert capsys.readouterr().out.startswith("polylap")
    assert main(["--threads", "1"]) == 0  # a global option alone still runs info
    assert "(embedded default mesh)" in capsys.readouterr().out


def test_info_on_a_file_with_options(capsys, one_thread):
    assert main(["info", str(DATA / "tetris.obj"), "--lam", "2", "--dtype", "float32"]) == 0
    out = capsys.readouterr().out
    assert "lambda = 2.0, float32" in out
    assert field(out, "vertices / faces / edges").startswith("52 / 16 /")


def test_info_reports_topology_defects(capsys, one_thread):
    """A Moebius band is not an error: L and M0 are defined; info lists what it found."""
    assert main(["info", str(DATA / "moebius.obj"), "--eigs", "2"]) == 0
    captured = capsys.readouterr()
    out = captured.out
    assert field(out, "manifold / oriented / orientable") == "yes / no / no"
    defects = [line for line in out.splitlines() if "topology defect" in line]
    assert len(defects) == 2
    assert "inconsistent orientation (first: [[77, 102]" in defects[0]
    assert "1 non-orientable component(s)" in defects[1]
    assert "genus" not in out and "orient_faces" in out
    assert "zero eigenvalues / components" in out
    assert "not a consistently oriented" not in captured.err  # listed, not warned
    assert main(["info", str(DATA / "dodecahedron_poly.obj"), "--eigs", "2"]) == 0
    out = capsys.readouterr().out
    assert field(out, "manifold / oriented / orientable") == "yes / yes / yes"
    assert "topology defect" not in out and field(out, "genus (closed, orientable)") == "0"


def test_info_output_dir_writes_its_report_with_the_eigenvalues_of_eigs(
    tmp_path, capsys, one_thread
):
    """``info -o DIR`` writes ``<mesh>_info.json``; its eigenvalues are those of ``tp.eigs`` and,
    independently, of scipy's ARPACK on the generalized problem ``L phi = mu M0 phi``."""
    out = tmp_path / "report"  # created by the command
    assert main(["info", "-o", str(out), "--eigs", "8"]) == 0
    stdout = capsys.readouterr().out
    path = out / "spot_control_mesh_info.json"
    assert f"wrote {path}" in stdout
    report = json.loads(path.read_text())
    assert report["vertices"] == 188 and report["faces"] == 180 and report["edges"] == 366
    assert report["embedded"] and report["zero_eigenvalues"] == 1 and report["components"] == 1
    assert report["threads"] == 1 and set(report["timings_s"]) == {
        "first_assembly",
        "reassembly",
        "forward_backward",
    }
    mesh_table = dict(map(tuple, report["tables"]["mesh"]))
    assert mesh_table["vertices / faces / edges"] == field(stdout, "vertices / faces / edges")
    evals = np.array(report["eigenvalues"])
    assert evals.shape == (8,)

    verts, faces = read_mesh(DEFAULT_MESH)
    L, M0 = tp.laplacian(verts, faces)
    assert evals == pytest.approx(tp.eigs(L, M0, 8)[0].numpy(), rel=1e-12, abs=1e-12)
    Ls, Ms = tp.sparse.to_scipy(L), tp.sparse.to_scipy(M0)
    shift = -1e-3 * np.abs(Ls).max() / Ms.diagonal().max()
    arpack = np.sort(scipy.sparse.linalg.eigsh(Ls, k=8, M=Ms, sigma=shift, which="LM")[0])
    assert evals == pytest.approx(arpack, abs=1e-9 * arpack[-1])
    printed = numbers(field(stdout, "smallest 8 eigenvalues of L = mu M0"))
    assert printed == pytest.approx(evals, rel=1e-3, abs=1e-9)


def test_info_writes_nothing_without_output_option(tmp_path, monkeypatch, capsys, one_thread):
    monkeypatch.chdir(tmp_path)
    assert main(["info", "--eigs", "2"]) == 0
    assert "wrote" not in capsys.readouterr().out and not list(tmp_path.iterdir())
    assert main(["info", "--eigs", "2", "--json"]) == 0  # --json: to the default directory
    assert (tmp_path / "polylap_out" / "spot_control_mesh_info.json").is_file()


# the Moebius band warns that it is not oriented: expected
@pytest.mark.filterwarnings("ignore:the mesh .* is not a consistently oriented:UserWarning")
def test_smooth_runs_on_a_moebius_band_without_a_volume_row(tmp_path, capsys, one_thread):
    argv = ["smooth", str(DATA / "moebius.obj"), "--steps", "2", "--no-plot", "--no-progress"]
    assert main([*argv, "-o", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "total area before / after" in out and "enclosed volume" not in out
    assert (tmp_path / "moebius_smooth.obj").is_file()


def _dumbbell(path):
    """The dumbbell of ``meshes.dumbbell`` written to ``path``."""
    tp.write_mesh(path, *dumbbell())
    return path


def _largest_scaled_curvature(path):
    verts, faces = read_mesh(path, dtype=torch.float64)
    L, M0 = tp.laplacian(verts, faces)
    h = tp.strong_laplacian(L, M0, verts).norm(dim=1) / 2
    return float(h.max()) * math.sqrt(float(tp.face_areas(verts, faces).sum()) / (4 * math.pi))


@pytest.mark.parametrize("dt", [None, "0.05"])
def test_smooth_stops_before_the_neck_pinches(tmp_path, capsys, one_thread, dt):
    mesh = _dumbbell(tmp_path / "dumbbell.obj")
    argv = ["smooth", str(mesh), "--steps", "20", "--no-plot", "--no-progress"]
    argv += [] if dt is None else ["--dt", dt]
    assert main([*argv, "-o", str(tmp_path / "out")]) == 0
    captured = capsys.readouterr()
    before = _largest_scaled_curvature(mesh)
    after = _largest_scaled_curvature(tmp_path / "out" / "dumbbell_smooth.obj")
    assert after <= 4.0 * before  # the bound the command keeps, recomputed from the file
    if dt is not None:  # a chosen step is kept: the flow stops and says where and why
        assert "stopped after" in captured.err and "pinching off" in captured.err
        assert "--dt" in captured.err  # the advice names the command's options
        taken = int(re.search(r"stopped after (\d+) of 20", captured.err)[1])
        assert 0 < taken < 20
    # that the unguarded flow pinches this dumbbell is tested with the library's guard
    # (tests/apps/test_apps_flow.py); here: the command turns the guard on and says where it stopped


def test_bad_files_give_one_line_errors(tmp_path, capsys, one_thread):
    assert main(["info", str(tmp_path / "nope.obj")]) == 2
    assert "No such file" in capsys.readouterr().err
    broken = tmp_path / "broken.off"
    broken.write_text("OFF\n4 1 0\n0 0 0\n1 0 0\n")
    assert main(["info", str(broken)]) == 2
    assert capsys.readouterr().err.startswith("polylap: error:")


# ------------------------------------------------------------------------------------------
# demo: smooth, param and planarize on their default meshes plus the plate, in one process
# ------------------------------------------------------------------------------------------


def test_demo_writes_report_meshes_and_figures(tmp_path):
    out = tmp_path / "report"
    result = run("demo", "-o", str(out), "--no-progress")
    assert result.returncode == 0, result.stderr
    assert result.stderr == ""
    stdout = result.stdout
    report = (out / "report.md").read_text()
    figures = re.findall(r"!\[[^\]]*\]\(([^)]+)\)", report)
    assert len(figures) == 4 and all(is_png(out / f) for f in figures)
    assert report.count("## ") == 4 and "| --" not in report.splitlines()[0]

    # mean-curvature flow with area normalization: same connectivity, same total area
    v0, f0 = read_mesh(DEFAULT_MESH)
    v1, f1 = read_mesh(out / "spot_control_mesh_smooth.obj")
    assert torch.equal(f1.indices, f0.indices) and torch.equal(f1.sizes, f0.sizes)
    area = [
        sum(np.linalg.norm(shoelace_normal(p)) for p in polygons(v.numpy(), f0)) for v in (v0, v1)
    ]
    assert area[1] == pytest.approx(area[0], rel=1e-9)
    assert numbers(field(stdout, "total area before / after")) == pytest.approx(area, rel=1e-4)
    # the flow spreads curvature out: the (scale-free) curvature varies less afterwards
    std = numbers(field(stdout, "|H| sqrt(A/4pi) std before / after"))
    assert std[1] < 0.7 * std[0]

    # conformal map of the hemisphere: a flat (z = 0) copy, no flipped polygon, angles kept
    vd, fd = read_mesh(DISK_MESH)
    uv, fu = read_mesh(out / "hex_hemisphere_param.obj")
    assert uv.shape == vd.shape and torch.equal(fu.indices, fd.indices)
    assert torch.all(uv[:, 2] == 0)
    flat, curved = polygons(uv.numpy(), fd), polygons(vd.numpy(), fd)
    assert all(shoelace_normal(p)[2] > 0 for p in flat)
    err = np.concatenate(
        [corner_angles(p[:, :2]) - corner_angles(q) for p, q in zip(flat, curved, strict=True)]
    )
    mean_deg = math.degrees(np.abs(err).mean())
    # a hemisphere cannot be flattened isometrically, but conformally up to discretization
    assert mean_deg < 5.0
    printed = numbers(field(stdout, "angle error mean / rms / max (deg)"))
    assert printed[0] == pytest.approx(mean_deg, abs=0.05)  # faces are planar to ~2e-3
    assert field(stdout, "flipped faces") == "0"

    # planarization: every face planar by an independent least-squares plane fit
    vp, fp = read_mesh(out / "spot_control_mesh_planar.obj")
    before = max(plane_fit_nonplanarity(p) for p in polygons(v0.numpy(), f0))
    after = max(plane_fit_nonplanarity(p) for p in polygons(vp.numpy(), fp))
    assert before > 0.1 and after < 1e-3
    assert field(stdout, "converged") == "yes"

    # plate: the deflection mesh is the plate with z = u, close to Navier's series solution
    vg, fg = read_mesh(DATA_DIR / "grid_voronoi_1.obj")
    plate, _ = read_mesh(out / "plate_deflection.obj")
    assert torch.allclose(plate[:, :2], vg[:, :2] + 0.5, atol=1e-15)
    ours, navier = numbers(field(stdout, "max deflection: ours / Navier"))
    assert float(plate[:, 2].max()) == pytest.approx(ours, rel=1e-3)
    # Navier's double series (Timoshenko & Woinowsky-Krieger eq. 134), summed here directly
    m = np.arange(1, 120, 2)[:, None, None]
    n = np.arange(1, 120, 2)[None, :, None]
    x, y = vg[:, 0].numpy() + 0.5, vg[:, 1].numpy() + 0.5
    terms = np.sin(m * np.pi * x) * np.sin(n * np.pi * y) / (m * n * (m**2 + n**2) ** 2)
    assert navier == pytest.approx(16 / np.pi**6 * terms.sum((0, 1)).max(), rel=1e-3)
    errors = numbers(field(stdout, "relative L2 error, lambda = 0.5 / 1 / 2"))
    assert errors[1] < 0.05


# ------------------------------------------------------------------------------------------
# spectrum (in-process) and bench (subprocess)
# ------------------------------------------------------------------------------------------


def test_spectrum_default_output_directory_and_npz(tmp_path, monkeypatch, capsys, one_thread):
    monkeypatch.chdir(tmp_path)
    assert main(["spectrum", "-k", "8", "--npz", "--show", "3"]) == 0
    stdout = capsys.readouterr().out
    out = tmp_path / "polylap_out"  # the documented default output directory
    assert is_png(out / "spot_control_mesh_spectrum.png")
    data = np.load(out / "spot_control_mesh_spectrum.npz")
    verts, faces = read_mesh(DEFAULT_MESH)
    L, M0 = tp.laplacian(verts, faces)
    Ld, Md = tp.sparse.to_scipy(L).toarray(), tp.sparse.to_scipy(M0).toarray()
    expected = scipy.linalg.eigh(Ld, Md, eigvals_only=True)[:8]
    assert data["eigenvalues"] == pytest.approx(expected, abs=1e-9 * expected[-1])
    phi = data["eigenvectors"]
    assert phi.shape == (188, 8)
    assert np.abs(Ld @ phi - Md @ phi * data["eigenvalues"]).max() < 1e-9 * np.abs(Ld).max()
    # lumped masses add up to the total area (shoelace, independent of the package)
    area = sum(np.linalg.norm(shoelace_normal(p)) for p in polygons(verts.numpy(), faces))
    assert data["mass"].sum() == pytest.approx(area, rel=1e-12)
    printed = numbers(" ".join(re.findall(r"\d+: (\S+)", stdout)))
    assert printed == pytest.approx(expected, rel=1e-5, abs=1e-9)


def test_bench_json(tmp_path):
    result = run(
        "bench", str(DATA / "dodecahedron_poly.obj"), "--repeat", "1", "-k", "4", "--json",
        "--no-progress", "-o", str(tmp_path),
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    data = json.loads((tmp_path / "dodecahedron_poly_bench.json").read_text())
    rows = {r["operation"]: r for r in data["results"]}
    assert len(rows) == 7 and data["faces"] == 12 and data["verts"] == 20
    for r in rows.values():
        assert r["torch_polylap_s"] > 0
        if r["reference_s"] is not None:
            assert r["ratio"] == pytest.approx(r["torch_polylap_s"] / r["reference_s"])
    assert rows["spmm(L, X), X (V, 3)"]["reference"] == "scipy CSR @ X"
    assert result.stdout.count("\n| ") == 8  # header and 7 rows
    assert data["threads"] == 1 and "1 torch thread (pinned" in result.stdout


def test_bench_pins_torch_threads_for_its_timings(tmp_path, monkeypatch, capsys):
    """Without --threads the timings run on one torch thread (a busy machine otherwise makes
    tiny multi-threaded kernels wait for descheduled threads); the caller's count comes back."""
    import torch_polylap.cli.bench as bench

    seen = []

    def spy(A, B):
        seen.append(torch.get_num_threads())
        return tp.solve(A, B)

    monkeypatch.setattr(bench, "solve", spy)
    before = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        argv = ["bench", str(DATA / "dodecahedron_poly.obj"), "--repeat", "1", "-k", "2"]
        assert main([*argv, "--no-progress", "-o", str(tmp_path)]) == 0
        assert seen and set(seen) == {1}
        assert torch.get_num_threads() == 2  # restored after the timings
        out = capsys.readouterr().out
        assert "1 torch thread (pinned; polylap bench --threads N to change)" in out
        data = json.loads((tmp_path / "dodecahedron_poly_bench.json").read_text())
        assert data["threads"] == 1

        seen.clear()
        assert main(["--threads", "2", *argv, "--no-progress"]) == 0  # asked for: used as is
        assert seen and set(seen) == {2}
        out = capsys.readouterr().out
        assert "2 torch threads" in out and "pinned" not in out
    finally:
        torch.set_num_threads(before)


def test_pinned_threads_restores_and_checks():
    before = torch.get_num_threads()
    with pytest.raises(RuntimeError), pinned_threads(1) as threads:
        assert threads == 1 and torch.get_num_threads() == 1
        raise RuntimeError
    assert torch.get_num_threads() == before
    with pytest.raises(ValueError, match="at least 0"), pinned_threads(-1):
        pass


# ------------------------------------------------------------------------------------------
# option variations in-process
# ------------------------------------------------------------------------------------------


def test_smooth_frozen_volume_on_a_file(tmp_path, capsys, one_thread):
    mesh = DATA / "dodecahedron_poly.obj"
    argv = ["smooth", str(mesh), "--steps", "3", "--frozen", "--normalize", "volume"]
    assert main([*argv, "--no-plot", "--no-progress", "-o", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    v0, f0 = read_mesh(mesh)
    v1, _ = read_mesh(tmp_path / "dodecahedron_poly_smooth.obj")
    # divergence theorem: V = 1/3 sum_f c_f . a_f for the closed, outward-oriented mesh
    vol = [
        sum(p.mean(0) @ shoelace_normal(p) for p in polygons(v.numpy(), f0)) / 3 for v in (v0, v1)
    ]
    assert vol[1] == pytest.approx(vol[0], rel=1e-9)
    assert numbers(field(out, "enclosed volume before / after")) == pytest.approx(vol, rel=1e-4)
    assert not list(tmp_path.glob("*.png"))  # --no-plot


def test_param_free_boundary_and_pins(tmp_path, capsys, one_thread):
    assert main(["param", "--free-boundary", "--no-plot", "-o", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    uv, faces = read_mesh(tmp_path / "hex_hemisphere_param.obj")
    verts, _ = read_mesh(DISK_MESH)
    # the free-boundary map is scaled to the source's total area (AW11 eq. 13-15)
    flat = sum(shoelace_normal(p)[2] for p in polygons(uv.numpy(), faces))
    area = sum(np.linalg.norm(shoelace_normal(p)) for p in polygons(verts.numpy(), faces))
    assert flat == pytest.approx(area, rel=1e-6)
    assert "free boundary" in field(out, "mode")

    boundary = tp.build_topology(faces, verts.shape[0]).boundary_edges
    i, j = (int(boundary[0, 0]), int(boundary[5, 1]))
    assert main(["param", "--pins", str(i), str(j), "--no-plot", "-o", str(tmp_path)]) == 0
    uv, _ = read_mesh(tmp_path / "hex_hemisphere_param.obj")
    # the pins land at (0, 0) and (|x_i - x_j|, 0)
    assert uv[i].tolist() == pytest.approx([0.0, 0.0, 0.0], abs=1e-12)
    d = float(torch.linalg.vector_norm(verts[i] - verts[j]))
    assert uv[j].tolist() == pytest.approx([d, 0.0, 0.0], abs=1e-12)


def test_planarize_on_a_file_without_convergence(tmp_path, capsys, one_thread):
    argv = ["planarize", str(DATA / "spot_control_mesh.obj"), "--max-iter", "1", "--tol", "1e-9"]
    assert main([*argv, "--no-plot", "--no-progress", "-o", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert field(out, "converged").startswith("no")
    assert field(out, "iterations / time").startswith("1 /")
    v, f = read_mesh(tmp_path / "spot_control_mesh_planar.obj")
    assert v.shape == (188, 3) and f.num_faces == 180


# the Moebius band warns that it is not oriented: expected
@pytest.mark.filterwarnings("ignore:the mesh .* is not a consistently oriented:UserWarning")
def test_argument_and_input_errors_are_one_line(tmp_path, capsys, one_thread):
    cases = [
        (["smooth", "--dt", "-1"], "argument --dt: expected a positive number"),
        (["spectrum", "-k", "0"], "expected a positive integer"),
        (["planarize", "--tol", "nan"], "expected a positive number"),
        (["frobnicate"], "invalid choice"),
        (["--threads", "-1", "info"], "expected a whole number of threads"),
        (["info", "--threads", "two"], "expected a whole number of threads"),
    ]
    for argv, message in cases:
        with pytest.raises(SystemExit) as exit_info:
            main(argv)
        assert exit_info.value.code == 2
        err = capsys.readouterr().err
        assert len(err.strip().splitlines()) == 1 and message in err, err
    errors = [
        (["param", str(DEFAULT_MESH)], "no boundary"),  # a closed mesh cannot be flattened
        (["spectrum", "-k", "500"], "too large"),
        (
            ["smooth", str(DATA / "moebius.obj"), "--normalize", "volume", "--no-plot"],
            "normalize='volume' needs an oriented mesh, but 1 of its components cannot be oriented",
        ),
        (["param", str(DATA / "moebius.obj"), "--no-plot"], "cannot be oriented"),
        (["param", "--pins", "0", "1", "--free-boundary"], "exclude each other"),
    ]
    for argv, message in errors:
        assert main([*argv, "-o", str(tmp_path)]) == 2
        err = capsys.readouterr().err
        assert err.startswith("polylap: error:") and message in err, err
        assert len(err.strip().splitlines()) == 1
    not_a_dir = tmp_path / "file"
    not_a_dir.write_text("")
    assert main(["spectrum", "-o", str(not_a_dir)]) == 2
    assert "not a directory" in capsys.readouterr().err


def subcommands() -> list[str]:
    """The command names, as the parser knows them."""
    (action,) = [a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction)]
    return list(action.choices)


def test_every_command_has_help(capsys):
    assert subcommands() == [
        "info",
        "smooth",
        "param",
        "planarize",
        "spectrum",
        "precompute",
        "bench",
        "demo",
    ]
    for command in subcommands():
        with pytest.raises(SystemExit) as exit_info:
            main([command, "--help"])
        assert exit_info.value.code == 0
        assert f"usage: polylap {command}" in capsys.readouterr().out


def test_every_command_follows_the_protocol():
    """SUMMARY / DESCRIPTION / add_arguments / compute / run in every module; the parser
    dispatches to run and compute."""
    parser = build_parser()
    names = subcommands()
    assert len(COMMANDS) == len(names)
    for module, name in zip(COMMANDS, names, strict=True):
        assert all(callable(getattr(module, f, None)) for f in ("add_arguments", "compute", "run"))
        assert isinstance(module.SUMMARY, str) and isinstance(module.DESCRIPTION, str)
        args = parser.parse_args([name])
        assert args.func is module.run and args.compute is module.compute


# quick options of each command (the demo runs in test_demo_writes_report_meshes_and_figures)
QUICK = {
    "info": ["--eigs", "2"],
    "smooth": ["--steps", "1", "--no-plot", "--no-progress"],
    "param": ["--no-plot"],
    "planarize": ["--max-iter", "1", "--no-plot", "--no-progress"],
    "spectrum": ["-k", "2", "--no-plot", "--npz"],
    "bench": [str(DATA / "dodecahedron_poly.obj"), "--repeat", "1", "-k", "2", "--no-progress"],
}


@pytest.mark.parametrize("command", subcommands())
def test_every_command_accepts_output_dir(command, tmp_path, capsys, one_thread):
    out = tmp_path / "out"
    args = build_parser().parse_args([command, "-o", str(out)])
    assert args.output == str(out)
    if command not in QUICK:
        return
    assert main([command, *QUICK[command], "-o", str(out)]) == 0
    written = sorted(p.name for p in out.iterdir())
    assert written, f"polylap {command} -o DIR wrote nothing"
    stdout = capsys.readouterr().out
    assert all(f"wrote {out / name}" in stdout for name in written)


def test_compute_prints_and_writes_nothing(tmp_path, capsys, one_thread):
    """compute returns the result; files are written by Result.write (run does both)."""
    out = tmp_path / "out"
    args = build_parser().parse_args(["spectrum", "-k", "3", "--npz", "-o", str(out)])
    result = args.compute(args)
    assert isinstance(result, Result) and capsys.readouterr().out == ""
    assert not out.exists()
    names = [o.name for o in result.outputs]
    assert names == ["spot_control_mesh_spectrum.npz", "spot_control_mesh_spectrum.png"]
    out.mkdir()
    assert result.write(out) == [out / name for name in names]
    assert np.load(out / names[0])["eigenvalues"] == pytest.approx(result.data["eigenvalues"])


def test_benchmarks_share_the_timing_helpers():
    """benchmarks/common.py imports the package's timing helpers instead of keeping a copy."""
    from torch_polylap import timing

    path = ROOT / "benchmarks" / "common.py"
    spec = importlib.util.spec_from_file_location("benchmarks_common", path)
    common = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(common)
    for name in ("median_time", "timed", "pinned_threads", "markdown_table", "fmt_time"):
        assert getattr(common, name) is getattr(timing, name)


def test_console_script_entry_point():
    """The installed ``polylap`` is the launcher setup.py declares, which runs ``main`` after
    importing the package (it catches Ctrl-C during those imports, see
    tests/cli/test_reliability_cli.py)."""
    from importlib.metadata import entry_points

    import _polylap_launcher

    setup = (ROOT / "setup.py").read_text()
    assert '"polylap=_polylap_launcher:main"' in setup
    (script,) = [e for e in entry_points(group="console_scripts") if e.name == "polylap"]
    if script.value != "_polylap_launcher:main":
        pytest.skip(f"the installed metadata predates setup.py ({script.value}): pip install -e .")
    assert script.load() is _polylap_launcher.main

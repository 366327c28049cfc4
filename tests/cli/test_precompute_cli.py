"""``polylap precompute``: folders in, JSON out, exit codes, and runs ended by SIGKILL and Ctrl-C.

The killed runs are real processes (``python -m torch_polylap.cli``) in their own process
group, signalled as a terminal or a batch system would signal them; the cache they leave is
checked entry by entry with the reader the dataset uses.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

import torch_polylap as tp
from torch_polylap.cli import main
from torch_polylap.shapes import quad_grid
from torch_polylap.spectral import load_cached_eigs

K = 32
# the command of this checkout, installed or not
ENV = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[2])}


def write_meshes(folder: Path, count: int, n: int, device) -> list[Path]:
    """``count`` bumpy quad grids of ``n x n`` faces, as OBJ files in subfolders of ``folder``."""
    paths = []
    for i in range(count):
        path = folder / f"part{i % 3}" / f"grid{i:03}.obj"
        path.parent.mkdir(parents=True, exist_ok=True)
        verts, faces = quad_grid(n, bump=0.2, seed=i, device=device)
        tp.write_mesh(path, verts.cpu(), faces.cpu())
        paths.append(path)
    return paths


def valid_entries(cache: Path, num_verts: int) -> int:
    """How many entries of ``cache`` read back whole (shape, dtype, checksum); a damaged one
    (the reader warns) fails the test under ``filterwarnings = error``."""
    return sum(load_cached_eigs(p, K, num_verts) is not None for p in cache.glob("eigs-*.npz"))


def test_folders_json_and_exit_codes(tmp_path, capsys, device):
    write_meshes(tmp_path / "meshes", 3, 6, device)
    (tmp_path / "meshes" / "notes.txt").write_text("not a mesh: skipped by the folder search")
    cache = tmp_path / "cache"
    argv = ["precompute", str(tmp_path / "meshes"), "--cache", str(cache), "-k", "5"]
    assert main([*argv, "--workers", "2", "--json", "--no-progress"]) == 0
    report = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert (report["computed"], report["reused"], report["failed"]) == (3, 0, 0)
    assert report["seconds"] > 0

    bad = tmp_path / "meshes" / "bad.off"
    bad.write_text("OFF\n1 1 0\n0 0 0\n3 0 1 2\n")
    assert main([*argv, "--workers", "1", "--json", "--no-progress"]) == 1
    out, err = capsys.readouterr()
    report = json.loads(out.strip().splitlines()[-1])
    assert (report["computed"], report["reused"], report["failed"]) == (0, 3, 1)
    assert report["failures"][0]["item"] == str(bad)
    assert f"failed: {bad}" in err and "line 4" in err

    # no INPUT: the embedded default mesh, as for every command
    assert main(["precompute", "--cache", str(tmp_path / "default"), "--json", "-k", "4"]) == 0
    assert json.loads(capsys.readouterr().out.strip().splitlines()[-1])["computed"] == 1
    assert main(["precompute", str(tmp_path / "missing"), "--cache", str(cache)]) == 2
    assert "no such file or folder" in capsys.readouterr().err


def _start(meshes: Path, cache: Path) -> subprocess.Popen:
    command = [sys.executable, "-m", "torch_polylap.cli", "precompute", str(meshes)]
    command += ["--cache", str(cache), "-k", str(K), "--workers", "1", "--json", "--no-progress"]
    return subprocess.Popen(
        command,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=ENV,
        start_new_session=True,  # its own process group, signalled as a whole
    )


# the interrupted runs: TOTAL meshes of N x N faces, enough that a signal lands mid-run
TOTAL, N = 30, 40


def _signal_mid_run(tmp_path: Path, device, signum: int) -> tuple[subprocess.Popen, str, Path]:
    """Write the meshes, start the command on them and send ``signum`` to its group once a few
    entries exist; the process (ended), its stderr and the cache folder, checked to hold only
    entries that read back whole."""
    meshes, cache = tmp_path / "meshes", tmp_path / "cache"
    write_meshes(meshes, TOTAL, N, device)
    process = _start(meshes, cache)
    deadline = time.monotonic() + 120
    while len(list(cache.glob("eigs-*.npz"))) < 3:
        assert process.poll() is None, process.communicate()
        assert time.monotonic() < deadline, "no entry written in 120 s"
        time.sleep(0.02)
    os.killpg(process.pid, signum)
    _, err = process.communicate(timeout=60)
    done = len(list(cache.glob("eigs-*.npz")))
    assert done < TOTAL, "the run ended before the signal: use more or larger meshes"
    assert valid_entries(cache, (N + 1) ** 2) == done  # no entry that reads as invalid
    return process, err, cache


@pytest.mark.slow  # two runs of the command on 30 meshes: about 10 s
def test_a_run_killed_outright_resumes_computing_only_what_is_missing(tmp_path, device):
    killed, _, cache = _signal_mid_run(tmp_path, device, signal.SIGKILL)
    assert killed.returncode == -signal.SIGKILL
    complete = len(list(cache.glob("eigs-*.npz")))

    again = _start(tmp_path / "meshes", cache)
    out, err = again.communicate(timeout=300)
    assert again.returncode == 0, err
    report = json.loads(out.strip().splitlines()[-1])
    # every entry complete before the rerun is reused, never computed again
    assert (report["reused"], report["computed"], report["failed"]) == (
        complete,
        TOTAL - complete,
        0,
    )
    assert valid_entries(cache, (N + 1) ** 2) == TOTAL


@pytest.mark.slow  # one run of the command on 30 meshes: about 6 s
def test_ctrl_c_ends_with_one_line_exit_130_and_only_whole_entries(tmp_path, device):
    process, err, cache = _signal_mid_run(tmp_path, device, signal.SIGINT)
    assert process.returncode == 130, err
    assert err.strip().splitlines()[-1] == "polylap: interrupted"
    assert "Traceback" not in err
    assert not [p for p in cache.iterdir() if p.name.endswith(".tmp")]  # temporaries removed

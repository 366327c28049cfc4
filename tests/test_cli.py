"""The polylap command, run as a user would: in a subprocess."""

from __future__ import annotations

import re
import subprocess
import sys

from conftest import DATA

COMMAND = [sys.executable, "-m", "torch_polylap.cli"]


def run(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([*COMMAND, *args], capture_output=True, text=True, timeout=120)


def field(out: str, label: str) -> str:
    match = re.search(rf"^  {re.escape(label)}\s+(.*)$", out, re.MULTILINE)
    assert match, f"{label!r} missing from:\n{out}"
    return match.group(1)


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


def test_info_without_command_defaults_to_info():
    assert run().stdout.startswith("polylap")


def test_info_on_a_file_with_options():
    result = run("info", str(DATA / "tetris.obj"), "--lam", "2", "--dtype", "float32")
    assert result.returncode == 0, result.stderr
    assert "lambda = 2.0, float32" in result.stdout
    assert field(result.stdout, "vertices / faces / edges").startswith("52 / 16 /")


def test_bad_files_give_one_line_errors(tmp_path):
    result = run("info", str(DATA / "moebius.obj"))
    assert result.returncode == 2
    assert result.stderr.startswith("polylap: error: faces ")
    assert "not consistently oriented" in result.stderr
    assert len(result.stderr.strip().splitlines()) == 1 and "Traceback" not in result.stderr
    missing = run("info", str(tmp_path / "nope.obj"))
    assert missing.returncode == 2 and "No such file" in missing.stderr
    broken = tmp_path / "broken.off"
    broken.write_text("OFF\n4 1 0\n0 0 0\n1 0 0\n")
    result = run("info", str(broken))
    assert result.returncode == 2 and result.stderr.startswith("polylap: error:")


def test_help():
    result = run("info", "--help")
    assert result.returncode == 0 and "--lam" in result.stdout

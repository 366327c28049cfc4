"""The examples run as a user would run them, and say what they claim."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


def run(name: str, *args: str) -> str:
    result = subprocess.run(
        [sys.executable, str(EXAMPLES / name), *args], capture_output=True, text=True, timeout=300
    )
    assert result.returncode == 0, result.stderr
    return result.stdout


def test_quickstart():
    out = run("quickstart.py")
    pattern = r"X\^T L0 X\) = ([\d.]+)\s+vs\s+total area = ([\d.]+)"
    dirichlet, area = re.search(pattern, out).groups()
    assert dirichlet == area  # equal to the printed 6 decimals (Lemma 3)
    assert "symmetric: True" in out


def test_denoising_reduces_radial_error():
    out = run("denoise_by_gradient_descent.py", "--n", "8", "--steps", "150")
    errors = [float(m) for m in re.findall(r"^\S.*?\s([\d.]+e[-+]\d+)\s+[\d.]+$", out, re.M)]
    noisy, weak, strong = errors
    assert strong < weak < noisy and strong < 0.6 * noisy

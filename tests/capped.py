"""Run a script on a 62,500-vertex grid under a 4 GB address-space cap (shared by the O(nnz)
memory tests, not a test itself).

A dense V x V float64 tensor on that grid is 31 GB, so any code path that builds one fails under
the cap; the tests run the script in a child process so that the cap does not bind pytest itself.
"""

from __future__ import annotations

import subprocess
import sys
import textwrap

_PREAMBLE = textwrap.dedent(
    """
    import resource, sys
    import numpy as np
    import torch
    import torch_polylap as tp

    torch.set_num_threads(1)
    n = 250  # 62,500 vertices: a dense V x V float64 matrix is 31 GB
    xs, ys = np.meshgrid(np.arange(n) / n, np.arange(n) / n, indexing="ij")
    verts = torch.tensor(np.stack([xs.ravel(), ys.ravel(), 0.05 * np.sin(7 * xs.ravel())], 1))
    i, j = (a.ravel() for a in np.meshgrid(np.arange(n - 1), np.arange(n - 1), indexing="ij"))
    corners = [i * n + j, (i + 1) * n + j, (i + 1) * n + j + 1, i * n + j + 1]
    faces = torch.tensor(np.stack(corners, 1))
    topo = tp.build_topology(faces, verts.shape[0])
    cap = 4 * 2**30
    resource.setrlimit(resource.RLIMIT_AS, (cap, cap))
    """
)


def run_capped(body: str) -> subprocess.CompletedProcess[str]:
    """Run ``body`` (dedented) in a fresh interpreter after the preamble, which defines ``np``,
    ``torch``, ``tp``, ``sys``, the grid's ``verts`` (V x 3 float64), ``faces`` (F x 4) and
    ``topo``, and caps the address space at 4 GB. Returns the finished process (stdout, stderr
    and return code captured as text)."""
    script = _PREAMBLE + textwrap.dedent(body)
    return subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, timeout=600
    )

"""Where the test meshes live, and cached loading (shared by the test modules, not a test itself).

Two sources:

* ``tests/data/`` -- small copies inside the repository (see ``tests/data/LICENSES.md``); tests
  over them always run.
* ``../shared/data/meshes/`` next to the repository (override with ``POLYLAP_SHARED_MESHES``) --
  the full refinement families (levels 1..5) and the big real meshes. Tests that need it skip
  with :data:`SHARED_SKIP_REASON` when it is absent.
"""

from __future__ import annotations

import functools
import os
from pathlib import Path

import pytest
import torch

import torch_polylap as tp

DATA_DIR = Path(__file__).resolve().parent / "data"

SHARED_SKIP_REASON = (
    "../shared/data/meshes not found: the refinement families live outside the repository "
    "(set POLYLAP_SHARED_MESHES to its location to run this test)"
)


def shared_meshes_dir() -> Path | None:
    """``../shared/data/meshes`` (or ``$POLYLAP_SHARED_MESHES``), or ``None`` when absent."""
    env = os.environ.get("POLYLAP_SHARED_MESHES")
    root = (
        Path(env)
        if env
        else Path(__file__).resolve().parents[1].parent / "shared" / "data" / "meshes"
    )
    return root if root.is_dir() else None


def require_shared() -> Path:
    """The shared mesh directory; ``pytest.skip`` when it is absent."""
    root = shared_meshes_dir()
    if root is None:
        pytest.skip(SHARED_SKIP_REASON)
    return root


def shared_path(rel: str) -> Path:
    """``rel`` (e.g. ``"sphere/hex_5.obj"``) inside the shared directory, skipping when absent."""
    path = require_shared() / rel
    if not path.is_file():
        pytest.skip(f"{path} is missing from the shared mesh directory")
    return path


@functools.cache
def load(path: str | Path) -> tuple[torch.Tensor, tp.PolygonFaces]:
    """``read_mesh`` in float64, cached per path (tests must not modify the returned tensors)."""
    return tp.read_mesh(path, dtype=torch.float64)

"""An eigenpair cache that cannot be written never loses the eigenpairs just computed.

Every way a write can fail (the tests run as root, which ignores permissions, so they are
simulated: a path through a regular file, symbolic link loops, and ``os`` functions made to fail
with EACCES, EROFS or ENOSPC) must return the same eigenpairs as :func:`torch_polylap.eigs`
without the cache, with one :class:`~torch_polylap.spectral.CacheWriteWarning` per folder that
names it and the reason, and leave no temporary behind.
"""

from __future__ import annotations

import errno
import os
import tempfile
import warnings
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

import torch_polylap as tp
from torch_polylap.shapes import quad_grid

spectral = tp.spectral


@pytest.fixture(autouse=True)
def fresh_reports(monkeypatch):
    """Each test starts with no folder reported as unwritable."""
    monkeypatch.setattr(spectral, "_UNWRITABLE_REPORTED", set(), raising=False)


MESH = quad_grid(4, bump=0.2, seed=1)


def reference(k: int) -> tuple[torch.Tensor, torch.Tensor]:
    V, F = MESH
    return tp.eigs(*tp.laplacian(V, F), k)


def _failing(name: str, code: int, inside: Path) -> Callable[..., object]:
    real = getattr(os, name)

    def fail(path, *args, **kwargs):
        if isinstance(path, int):  # fsync(fd): only called while the cache writes
            raise OSError(code, os.strerror(code))
        if str(inside) in os.fsdecode(path):
            raise OSError(code, os.strerror(code), path)
        return real(path, *args, **kwargs)

    return fail


@contextmanager
def failure(mode: str, root: Path) -> Iterator[tuple[Path, str]]:
    """``(cache_dir, the errno name the warning must give)`` for one way of failing."""
    saved = {}

    def patch(name: str, code: int, inside: Path) -> None:
        saved[name] = getattr(os, name)
        setattr(os, name, _failing(name, code, inside))

    if mode == "parent is a file":
        (root / "file").write_text("not a folder")
        cache, code = root / "file" / "cache", "ENOTDIR"
    elif mode == "symlink loop":
        (root / "loop").symlink_to(root / "loop")
        cache, code = root / "loop", "ELOOP"
    elif mode == "symlink loop above":
        (root / "a").symlink_to(root / "b")
        (root / "b").symlink_to(root / "a")
        cache, code = root / "a" / "cache", "ELOOP"
    elif mode == "no permission (mkdir)":
        cache, code = root / "cache", "EACCES"
        patch("mkdir", errno.EACCES, cache)
    elif mode == "read-only (temporary)":
        cache, code = root / "cache", "EROFS"
        cache.mkdir()
        patch("open", errno.EROFS, cache)
    elif mode == "read-only (rename)":
        cache, code = root / "cache", "EROFS"
        cache.mkdir()
        patch("replace", errno.EROFS, cache)
    elif mode == "disk full":
        cache, code = root / "cache", "ENOSPC"
        cache.mkdir()
        patch("fsync", errno.ENOSPC, cache)
    else:
        raise AssertionError(mode)
    try:
        yield cache, code
    finally:
        for name, real in saved.items():
            setattr(os, name, real)


MODES = [
    "parent is a file",
    "symlink loop",
    "symlink loop above",
    "no permission (mkdir)",
    "read-only (temporary)",
    "read-only (rename)",
    "disk full",
]


def check_unwritable(mode: str, k: int, root: Path) -> None:
    V, F = MESH
    expected = reference(k)
    with failure(mode, root) as (cache, code):
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            first = tp.cached_eigs(V, F, k, cache)
            second = tp.cached_eigs(V, F, k, cache)  # recomputed, not reported again
    for evals, evecs in (first, second):
        torch.testing.assert_close(evals, expected[0], rtol=1e-9, atol=1e-10)
        torch.testing.assert_close(evecs.abs(), expected[1].abs(), rtol=1e-6, atol=1e-8)
    messages = [str(w.message) for w in caught]
    assert [w.category for w in caught] == [tp.spectral.CacheWriteWarning], messages
    message = str(caught[0].message)
    assert f"folder {cache} cannot be written" in message and code in message, message
    assert "returned" in message
    if cache.is_dir():  # no temporary, no partial file
        assert list(cache.iterdir()) == []


@pytest.mark.parametrize("mode", MODES)
def test_unwritable_cache_returns_the_eigenpairs_with_one_warning(mode, tmp_path):
    check_unwritable(mode, 4, tmp_path)


@settings(max_examples=20, deadline=None)
@given(mode=st.sampled_from(MODES), k=st.integers(1, 6))
def test_every_failure_mode_and_k(mode, k):
    getattr(spectral, "_UNWRITABLE_REPORTED", set()).clear()
    with tempfile.TemporaryDirectory() as root:
        check_unwritable(mode, k, Path(root))


def test_one_warning_per_folder_then_the_cache_works_again(tmp_path):
    """A second unwritable folder gets its own warning; a writable one caches silently."""
    V, F = MESH
    (tmp_path / "file").write_text("")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        tp.cached_eigs(V, F, 3, tmp_path / "file" / "a")
        tp.cached_eigs(V, F, 3, tmp_path / "file" / "b")
        tp.cached_eigs(V, F, 3, tmp_path / "file" / "a")
    assert len(caught) == 2
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        tp.cached_eigs(V, F, 3, tmp_path / "ok")
    assert len(list((tmp_path / "ok").glob("eigs-*.npz"))) == 1

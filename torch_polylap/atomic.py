"""Atomic file replacement: a file is either the old one or the complete new one.

Mesh writers (:func:`torch_polylap.io.write_mesh`), the eigenpair cache
(:func:`torch_polylap.cached_eigs`, :func:`torch_polylap.interop.to_diffusionnet`) and the
command line's outputs all write through :func:`atomic_write`, so an interrupted or concurrent
writer never leaves a truncated file where a reader expects a complete one.
"""

from __future__ import annotations

import os
import re
import secrets
import stat
import time
from collections.abc import Callable
from pathlib import Path
from typing import BinaryIO

__all__ = ["atomic_write", "remove_stale_temporaries"]

PathLike = str | os.PathLike


def atomic_write(path: PathLike, write: Callable[[BinaryIO], object]) -> None:
    """Replace ``path`` by what ``write`` writes, all or nothing.

    ``write`` fills a new temporary file in the target's folder, named
    ``.<name>.<pid>-<8 hex digits>.tmp`` (hidden, ``.tmp``: no reader mistakes it for the file;
    ``pid`` is the writing process); it is flushed and fsynced, then moved onto ``path`` with
    :func:`os.replace`, atomic on POSIX and Windows.  Readers and concurrent writers thus only
    ever see the old file or a complete new one; on any exception (``KeyboardInterrupt`` and
    ``SystemExit`` included, so also a signal turned into one) the temporary is removed and the
    old file is left as it was.  The new file keeps the old one's permissions (or gets the usual
    ``0o666 & ~umask`` for a new file).

    A process killed outright (SIGKILL, power loss) cannot remove its temporary: each write
    first removes the temporaries of the same target that such a writer left, see
    :func:`remove_stale_temporaries`.

    Args:
        path: the file to replace (created if missing; its folder must exist).
        write: called once with the temporary file, opened for binary writing (``np.savez``,
            ``Figure.savefig(f, format=...)``, ``f.write(data)``...).

    Raises:
        OSError: the folder cannot be written (permissions, read-only file system, disk full,
            a path through a regular file or a symbolic link loop); nothing was changed.
    """
    path = Path(path)
    remove_stale_temporaries(path)
    tmp, fd = _create_temporary(path)
    try:
        with os.fdopen(fd, "wb") as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp, _file_mode(path))
        os.replace(tmp, path)
    except BaseException:
        # BaseException: a KeyboardInterrupt mid-write must not leave the temporary behind either
        tmp.unlink(missing_ok=True)
        raise
    _fsync_folder(path.parent)


# A temporary of a writer that was killed outright is removed by the next write of its target
# once it is this old (seconds since it was last written) and no process of its pid runs here...
STALE_TEMPORARY_S = 600.0
# ... or once it is this old whatever the pid says (pids are reused; a writer on another machine
# of a shared file system has a pid that means nothing here)
ABANDONED_TEMPORARY_S = 86400.0

# file names are limited to 255 bytes: the temporary's name keeps at most this much of the target's
_NAME_KEPT = 200


def _temporary_stem(path: Path) -> str:
    return f".{path.name[:_NAME_KEPT]}."


def _create_temporary(path: Path) -> tuple[Path, int]:
    """A new, empty ``.<name>.<pid>-<hex>.tmp`` next to ``path`` and its open descriptor."""
    stem = _temporary_stem(path)
    for _ in range(100):
        tmp = path.parent / f"{stem}{os.getpid()}-{secrets.token_hex(4)}.tmp"
        try:
            return tmp, os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | _O_BINARY, 0o600)
        except FileExistsError:
            continue
    raise FileExistsError(f"{path}: no free temporary file name next to it after 100 tries.")


_O_BINARY = getattr(os, "O_BINARY", 0)  # Windows: no newline translation


def remove_stale_temporaries(path: PathLike, now: float | None = None) -> list[Path]:
    """Remove the temporaries of :func:`atomic_write` that killed writers of ``path`` left.

    A temporary ``.<name>.<pid>-<hex>.tmp`` of the same target is removed when it was last
    written more than :data:`STALE_TEMPORARY_S` (10 minutes) ago and no process ``pid`` runs on
    this machine, or more than :data:`ABANDONED_TEMPORARY_S` (a day) ago.  A live writer's
    temporary is thus never touched, nor one of a writer on another machine sharing the folder
    unless it is a day old.  Other files, and temporaries of other targets, are left alone.

    Args:
        path: the target file whose folder is searched.
        now: the current time (``time.time()``), for tests.

    Returns:
        The temporaries removed. Folders that cannot be listed and files that cannot be removed
        are skipped silently: the write that follows reports a folder it cannot write.
    """
    path = Path(path)
    pattern = re.compile(re.escape(_temporary_stem(path)) + r"(\d{1,10})-[0-9a-f]{8}\.tmp")
    now = time.time() if now is None else now
    removed = []
    try:
        entries = list(os.scandir(path.parent))
    except OSError:
        return []
    for entry in entries:
        match = pattern.fullmatch(entry.name)
        if match is None:
            continue
        try:
            info = entry.stat(follow_symlinks=False)
        except OSError:
            continue
        if not stat.S_ISREG(info.st_mode):
            continue
        age = now - info.st_mtime
        if age > ABANDONED_TEMPORARY_S or (
            age > STALE_TEMPORARY_S and not _process_running(int(match.group(1)))
        ):
            try:
                os.unlink(entry.path)
            except OSError:
                continue
            removed.append(Path(entry.path))
    return removed


def _process_running(pid: int) -> bool:
    """Whether a process ``pid`` exists on this machine (True when that cannot be told)."""
    if os.name == "nt":  # os.kill would terminate the process there: no harmless probe
        return True
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OverflowError:  # no pid is that large
        return False
    except OSError:  # EPERM: it exists, owned by someone else
        return True
    return True


def _file_mode(path: Path) -> int:
    try:
        return stat.S_IMODE(os.stat(path).st_mode)
    except FileNotFoundError:
        umask = os.umask(0)  # the only portable way to read the umask is to set it
        os.umask(umask)
        return 0o666 & ~umask


def _fsync_folder(folder: Path) -> None:
    """Make the rename itself durable (POSIX); folders cannot be opened on Windows."""
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)

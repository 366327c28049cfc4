"""atomic_write's temporaries: recognisable names, removed on every exception, and the ones a
killed writer left removed by the next write of the same target once they are stale."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from conftest import ROOT

from torch_polylap import atomic
from torch_polylap.atomic import atomic_write

# the documented ages: a killed writer's temporary is stale after 10 minutes, any after a day
STALE, ABANDONED = 10 * 60, 24 * 3600


def temporary_name(target: str, pid: int) -> re.Pattern[str]:
    return re.compile(rf"\.{re.escape(target)}\.{pid}-[0-9a-f]{{8}}\.tmp")


def no_such_pid() -> int:
    """A pid no process can have: above the kernel's limit (Linux), else far above usual ones."""
    try:
        return int(Path("/proc/sys/kernel/pid_max").read_text()) + 1
    except OSError:
        return 2**22 + 1


def test_temporary_is_named_for_target_and_process(tmp_path):
    target = tmp_path / "mesh.obj"
    seen = []
    atomic_write(target, lambda f: seen.extend(p.name for p in tmp_path.iterdir()))
    (name,) = seen
    assert temporary_name("mesh.obj", os.getpid()).fullmatch(name), name
    assert [p.name for p in tmp_path.iterdir()] == ["mesh.obj"]


@pytest.mark.parametrize("error", [OSError, KeyboardInterrupt, SystemExit])
def test_exception_mid_write_keeps_the_old_file_and_no_temporary(tmp_path, error):
    target = tmp_path / "report.json"
    target.write_bytes(b"old")

    def fail(f):
        f.write(b"half of the new con")
        raise error()

    with pytest.raises(error):
        atomic_write(target, fail)
    assert target.read_bytes() == b"old"
    assert [p.name for p in tmp_path.iterdir()] == ["report.json"]


def _age(path: Path, seconds: float) -> None:
    t = time.time() - seconds
    os.utime(path, (t, t))


def test_stale_temporaries_of_the_same_target_are_removed(tmp_path):
    target = tmp_path / "a.png"
    dead, alive = no_such_pid(), os.getppid()
    old = STALE + 60
    files = {
        # (name, age in seconds): removed?
        (f".a.png.{dead}-0123abcd.tmp", old): True,  # killed writer, stale
        (f".a.png.{alive}-0123abcd.tmp", ABANDONED + 60): True,  # a day old
        (f".a.png.{dead}-89abcdef.tmp", 5.0): False,  # too young: maybe another machine's
        (f".a.png.{alive}-0123abcd.tmp.keep", old): False,  # not a temporary's name
        (f".a.png.{alive}-456789ab.tmp", old): False,  # its writer still runs
        (f".b.png.{dead}-0123abcd.tmp", old): False,  # another target's
        (f".a.png.{dead}-0123ABCD.tmp", old): False,  # not our hex digits
        ("a.png.tmp", old): False,
    }
    for name, age in files:
        (tmp_path / name).write_bytes(b"partial")
        _age(tmp_path / name, age)
    atomic_write(target, lambda f: f.write(b"new"))
    left = {p.name for p in tmp_path.iterdir()}
    assert left == {"a.png"} | {name for (name, _), removed in files.items() if not removed}
    assert target.read_bytes() == b"new"


def test_stale_symlink_or_folder_with_a_temporary_name_is_left_alone(tmp_path):
    name = f".x.obj.{no_such_pid()}-0123abcd.tmp"
    (tmp_path / "elsewhere").write_text("keep me")
    (tmp_path / name).symlink_to(tmp_path / "elsewhere")
    os.utime(tmp_path / name, (0, 0), follow_symlinks=False)
    assert atomic.remove_stale_temporaries(tmp_path / "x.obj") == []
    assert (tmp_path / "elsewhere").read_text() == "keep me"


WRITER = """
import os, sys, time
from torch_polylap.atomic import atomic_write

def fill(f):
    f.write(b"x" * 100000)
    f.flush()
    print("writing", flush=True)
    time.sleep(600)

atomic_write(sys.argv[1], fill)
"""


@pytest.mark.skipif(not hasattr(signal, "SIGKILL"), reason="needs POSIX signals (SIGKILL)")
def test_temporary_of_a_sigkilled_writer_is_removed_by_the_next_write_once_stale(tmp_path):
    target = tmp_path / "big.obj"
    target.write_bytes(b"old")
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    proc = subprocess.Popen(
        [sys.executable, "-c", WRITER, str(target)], stdout=subprocess.PIPE, text=True, env=env
    )
    try:
        assert proc.stdout.readline().strip() == "writing"
    finally:
        proc.kill()  # no cleanup can run
        proc.wait()
        proc.stdout.close()
    (left,) = [p for p in tmp_path.iterdir() if p != target]
    assert temporary_name("big.obj", proc.pid).fullmatch(left.name)
    atomic_write(target, lambda f: f.write(b"new 1"))  # young: it could be a live writer's
    assert left.exists()
    _age(left, STALE + 1)
    atomic_write(target, lambda f: f.write(b"new 2"))
    assert sorted(tmp_path.iterdir()) == [target] and target.read_bytes() == b"new 2"

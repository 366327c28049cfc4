"""The polylap command under interruption, and its defaults.

* Every file a command writes goes through a temporary next to it and ``os.replace``.
* SIGINT, SIGTERM and SIGHUP at any point (during the imports, the computation, the drawing of
  a figure, the last moment of a write) end the command with one line on stderr and status
  ``128 + signal``, the previous files intact and no temporary left. The moments are made
  deterministic by a hook in the child process that announces on stdout where it is blocked
  and then waits; the signal is sent only after that line arrived.
* Every command runs on one torch thread unless ``--threads`` says otherwise.
* ``info`` and ``spectrum`` report the same first-assembly time, checked with a fake clock.
"""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import pytest
import torch
from conftest import DATA, ROOT

from torch_polylap import atomic, timing
from torch_polylap.cli import COMMANDS, build_parser, main
from torch_polylap.cli import common as cli_common
from torch_polylap.cli import timing as cli_timing
from torch_polylap.cli.common import Output

# The commands read the test meshes, whose object names and smoothing groups the readers report
# with a SkippedContentWarning: expected here (the readers' own tests assert it); every other
# warning stays an error.
pytestmark = pytest.mark.filterwarnings("ignore::torch_polylap.io.SkippedContentWarning")

ENV = {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1"}
TEMPORARY = re.compile(r"\.(.+)\.(\d+)-[0-9a-f]{8}\.tmp")

needs_posix_signals = pytest.mark.skipif(
    not hasattr(signal, "SIGHUP"), reason="needs POSIX signals (SIGTERM, SIGHUP)"
)

# --------------------------------------------------------------------------------------------
# every output is written through a temporary and os.replace
# --------------------------------------------------------------------------------------------

SPOT, DISK = "spot_control_mesh", "hex_hemisphere"  # the commands' embedded default meshes
WRITING = {
    "spectrum": (["-k", "2", "--npz"], [f"{SPOT}_spectrum.npz", f"{SPOT}_spectrum.png"]),
    "info": (["--eigs", "2", "--json"], [f"{SPOT}_info.json"]),
    "param": ([], [f"{DISK}_param.obj", f"{DISK}_param.png"]),
    "smooth": (["--steps", "1", "--no-progress"], [f"{SPOT}_smooth.obj", f"{SPOT}_smooth.png"]),
    "planarize": (
        ["--max-iter", "1", "--no-progress"],
        [f"{SPOT}_planar.obj", f"{SPOT}_planar.png"],
    ),
}


@pytest.mark.parametrize("command", sorted(WRITING))
def test_every_file_is_moved_into_place_from_a_temporary(
    command, tmp_path, monkeypatch, one_thread
):
    options, names = WRITING[command]
    replaced = []
    real_replace = os.replace

    def spy(src, dst):
        replaced.append((Path(src), Path(dst)))
        real_replace(src, dst)

    monkeypatch.setattr(atomic.os, "replace", spy)
    assert main([command, *options, "-o", str(tmp_path)]) == 0
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(names)
    assert sorted(dst.name for _, dst in replaced) == sorted(names)
    for src, dst in replaced:
        match = TEMPORARY.fullmatch(src.name)
        assert src.parent == dst.parent == tmp_path and match, src
        assert match[1] == dst.name and int(match[2]) == os.getpid()


def test_output_takes_exactly_one_content():
    with pytest.raises(TypeError, match="exactly one of fill and mesh"):
        Output("x.obj")
    with pytest.raises(TypeError, match="exactly one of fill and mesh"):
        Output("x.obj", fill=lambda f: None, mesh=(torch.zeros(3, 3), None))  # type: ignore[arg-type]


# --------------------------------------------------------------------------------------------
# signals
# --------------------------------------------------------------------------------------------

CHILD = """
import os, sys, time

hook, argv = sys.argv[1], sys.argv[2:]


def block(where):
    print("blocked in " + where, flush=True)
    time.sleep(600)


if hook == "fsync":  # the temporary is complete, not yet moved into place
    os.fsync = lambda fd: block("fsync")
elif hook == "savefig":  # a figure half written (the 0-124 byte PNGs of old)
    import matplotlib.figure

    def savefig(self, f, *args, **kwargs):
        f.write(b"\\x89PNG\\r\\n\\x1a\\n" + b"x" * 100)
        f.flush()
        block("savefig")

    matplotlib.figure.Figure.savefig = savefig
elif hook == "compute":  # the eigensolver of polylap spectrum
    import torch_polylap.cli.spectrum as spectrum

    spectrum.eigs = lambda *args, **kwargs: block("eigs")
elif hook == "flow":  # the solve of a step of polylap smooth, its progress bar drawn
    import torch_polylap.apps.flow as flow

    flow.solve = lambda *args, **kwargs: block("flow")

from torch_polylap.cli import main

sys.exit(main(argv))
"""

ENDINGS = {
    "SIGINT": (130, "polylap: interrupted"),
    "SIGTERM": (143, "polylap: terminated (SIGTERM)"),
    "SIGHUP": (129, "polylap: terminated (SIGHUP)"),
}

# (hook, command line, the files it would write)
MOMENTS = {
    "drawing the figure": ("savefig", ["spectrum", "-k", "3"], [f"{SPOT}_spectrum.png"]),
    "finishing the npz": (
        "fsync",
        ["spectrum", "-k", "3", "--npz", "--no-plot"],
        [f"{SPOT}_spectrum.npz"],
    ),
    "finishing the json": ("fsync", ["info", "--eigs", "2", "--json"], [f"{SPOT}_info.json"]),
    "finishing the mesh": ("fsync", ["param", "--no-plot"], [f"{DISK}_param.obj"]),
    "smoothing": ("flow", ["smooth", "--no-plot"], [f"{SPOT}_smooth.obj"]),
    "computing": (
        "compute",
        ["spectrum", "-k", "3", "--npz"],
        [f"{SPOT}_spectrum.npz", f"{SPOT}_spectrum.png"],
    ),
}

# the late moments take 12-16 s each (the figure is drawn first): the default run keeps the two
# early ones, the full run (--runslow, as CI) all of them
_LATE = pytest.mark.slow
CASES = [
    pytest.param("drawing the figure", "SIGINT", marks=_LATE),
    pytest.param("drawing the figure", "SIGTERM", marks=_LATE),
    pytest.param("finishing the npz", "SIGINT", marks=_LATE),
    pytest.param("finishing the json", "SIGTERM", marks=_LATE),
    pytest.param("finishing the mesh", "SIGHUP", marks=_LATE),
    ("computing", "SIGINT"),
    ("smoothing", "SIGINT"),
]


def _default_ending_signals() -> None:
    """In the child, before it starts: the ending signals at their default disposition.

    A test run started under ``nohup`` (SIGHUP ignored) or as a background job of a shell
    without job control (SIGINT ignored) hands those ignored dispositions to its children, and
    the command rightly keeps an ignored signal ignored; the tests are about the default case.
    """
    for name in ("SIGINT", "SIGTERM", "SIGHUP"):
        signal.signal(getattr(signal, name), signal.SIG_DFL)


def interrupt(argv: list[str], marker: str, signame: str, **popen) -> subprocess.CompletedProcess:
    """Run ``argv``, wait for the line starting with ``marker`` on stdout, send the signal."""
    proc = subprocess.Popen(
        argv,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=ENV,
        preexec_fn=_default_ending_signals,
        **popen,
    )
    try:
        line = proc.stdout.readline()
        assert line.startswith(marker), (line, proc.stderr.read() if proc.poll() else "")
        proc.send_signal(getattr(signal, signame))
        out, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    return subprocess.CompletedProcess(argv, proc.returncode, line + out, err)


@needs_posix_signals
@pytest.mark.parametrize(("moment", "signame"), CASES)
def test_signal_leaves_previous_files_and_one_line(moment, signame, tmp_path):
    hook, argv, names = MOMENTS[moment]
    for name in names:
        (tmp_path / name).write_bytes(f"previous {name}".encode())
    cmd = [sys.executable, "-c", CHILD, hook, *argv, "-o", str(tmp_path)]
    result = interrupt(cmd, "blocked in", signame)
    status, line = ENDINGS[signame]
    if hook == "flow":  # the progress bar, closed, then the message on a line of its own
        bar = result.stderr.lstrip()
        assert result.returncode == status and bar.startswith("mean curvature flow:"), bar
        assert result.stderr.endswith(f"\n{line}\n") and result.stderr.count(line) == 1
    else:
        assert (result.returncode, result.stderr) == (status, line + "\n")
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(names), "a temporary was left"
    for name in names:
        assert (tmp_path / name).read_bytes() == f"previous {name}".encode()


def console_script() -> tuple[str, str]:
    """``(module, function)`` of the polylap console script that setup.py declares."""
    match = re.search(r'"polylap=([\w.]+):(\w+)"', (ROOT / "setup.py").read_text())
    assert match, "setup.py declares no polylap console script"
    return match[1], match[2]


# what pip's console-script wrapper runs, with the import of torch blocked until a signal comes
WRAPPER = """
import sys
import time


class BlockTorch:
    def find_spec(self, name, path=None, target=None):
        if name == "torch":
            print("importing torch", flush=True)
            time.sleep(600)
        return None


sys.meta_path.insert(0, BlockTorch())
sys.argv = ["polylap", "info"]
from {module} import {function}

sys.exit({function}())
"""


@needs_posix_signals
@pytest.mark.parametrize("signame", ["SIGINT", "SIGTERM"])
def test_signal_during_the_imports_of_the_console_script(signame, tmp_path):
    module, function = console_script()
    code = WRAPPER.format(module=module, function=function)
    result = interrupt([sys.executable, "-c", code], "importing torch", signame, cwd=tmp_path)
    status, line = ENDINGS[signame]
    assert (result.returncode, result.stderr) == (status, line + "\n")


# the console script with an atexit callback that blocks: the process is ending (its command
# done, its files written and its table printed) when the signal comes. The table goes to
# /dev/null so that the marker is the first line on stdout.
ENDING_SCRIPT = """
import atexit
import os
import sys
import time


def block():
    print("blocked in shutdown", file=sys.__stdout__, flush=True)
    time.sleep(600)


atexit.register(block)
sys.stdout = open(os.devnull, "w")
sys.argv = ["polylap", *sys.argv[1:]]
from {module} import {function}

sys.exit({function}())
"""

# a quick run of every command that writes files, with the figure where it has one
AFTER_WRITING = {
    "smooth": ["--steps", "2", "--no-progress"],
    "info": ["--eigs", "2", "--json"],
    "param": [],
    "planarize": ["--max-iter", "1", "--no-progress"],
    "spectrum": ["-k", "2", "--npz"],
    "bench": [str(DATA / "dodecahedron_poly.obj"), "--repeat", "1", "-k", "2", "--json"],
    "demo": ["--no-plot", "--no-progress"],
}


def _signal_while_ending(command: str, signame: str, out: Path) -> None:
    module, function = console_script()
    code = ENDING_SCRIPT.format(module=module, function=function)
    argv = [sys.executable, "-c", code, command, *AFTER_WRITING[command], "-o", str(out)]
    result = interrupt(argv, "blocked in shutdown", signame)
    status, line = ENDINGS[signame]
    # what the command itself wrote to stderr (bench: its progress bar) comes first
    assert result.returncode == status, result.stderr
    assert result.stderr.endswith(f"{line}\n") and result.stderr.count("polylap:") == 1
    assert "Traceback" not in result.stderr
    assert any(out.iterdir()) and not [p for p in out.iterdir() if TEMPORARY.fullmatch(p.name)]


@needs_posix_signals
def test_ctrl_c_after_the_command_wrote_its_files(tmp_path):
    """Ctrl-C once ``polylap smooth`` wrote its PNG: Python's shutdown used to print a
    KeyboardInterrupt traceback from an atexit callback and exit with status 0."""
    _signal_while_ending("smooth", "SIGINT", tmp_path)


@pytest.mark.slow
@needs_posix_signals
@pytest.mark.parametrize("signame", sorted(ENDINGS))
@pytest.mark.parametrize("command", sorted(AFTER_WRITING))
def test_signal_after_every_command_wrote_its_files(command, signame, tmp_path):
    _signal_while_ending(command, signame, tmp_path)


def test_console_script_runs_the_command():
    """The launcher setup.py names runs torch_polylap.cli.main with the process's arguments,
    and ends the process with its status (argparse's exits included)."""
    module, function = console_script()
    runs = {
        ("info", "--help"): (0, "stdout", "usage: polylap info"),
        ("info", "--eigs", "x"): (2, "stderr", "invalid int value: 'x'"),
    }
    for args, (status, stream, text) in runs.items():
        argv = ["polylap", *args]
        code = f"import sys; sys.argv = {argv!r}; from {module} import {function}"
        code += f"; sys.exit({function}())"
        result = subprocess.run(
            [sys.executable, "-c", code], capture_output=True, text=True, env=ENV
        )
        assert result.returncode == status and text in getattr(result, stream), result.stderr


@needs_posix_signals
def test_ctrl_c_while_ending_after_help(tmp_path):
    """argparse ends ``--help`` with SystemExit: that process too ends with the one line."""
    module, function = console_script()
    code = ENDING_SCRIPT.format(module=module, function=function)
    result = interrupt([sys.executable, "-c", code, "info", "--help"], "blocked in", "SIGINT")
    assert (result.returncode, result.stderr) == (130, "polylap: interrupted\n")


# --------------------------------------------------------------------------------------------
# threads
# --------------------------------------------------------------------------------------------

QUICK = {
    "info": ["--eigs", "2"],
    "smooth": ["--steps", "1", "--no-plot", "--no-progress"],
    "param": ["--no-plot"],
    "planarize": ["--max-iter", "1", "--no-plot", "--no-progress"],
    "spectrum": ["-k", "2", "--no-plot"],
    "bench": [str(DATA / "dodecahedron_poly.obj"), "--repeat", "1", "-k", "2", "--no-progress"],
    "demo": ["--no-plot", "--no-progress"],
}


def test_every_command_documents_threads(capsys):
    for command in QUICK:
        with pytest.raises(SystemExit):
            main([command, "--help"])
        text = " ".join(capsys.readouterr().out.split())
        assert "--threads N" in text and "(default 1; 0: torch's own default" in text, command


@pytest.fixture
def two_threads():
    before = torch.get_num_threads()
    torch.set_num_threads(2)
    yield
    torch.set_num_threads(before)


def _spy_threads(monkeypatch) -> list[int]:
    """The torch thread count at every mesh load of every command (demo: of its parts)."""
    seen: list[int] = []
    # the commands that need the topology load through common.load_mesh_topology
    for module in (*COMMANDS, cli_common):
        if hasattr(module, "load_mesh"):
            real = module.load_mesh

            def spy(*args, real=real, **kwargs):
                seen.append(torch.get_num_threads())
                return real(*args, **kwargs)

            monkeypatch.setattr(module, "load_mesh", spy)
    return seen


@pytest.mark.parametrize("command", sorted(QUICK))
def test_every_command_runs_on_one_thread_unless_told(command, tmp_path, monkeypatch, two_threads):
    seen = _spy_threads(monkeypatch)
    out = ["-o", str(tmp_path)]
    assert main([command, *QUICK[command], *out]) == 0
    assert seen and set(seen) == {1}, seen
    assert torch.get_num_threads() == 2  # the caller's count is back
    seen.clear()
    assert main([command, *QUICK[command], "--threads", "2", *out]) == 0
    assert set(seen) == {2}


def test_threads_zero_is_torchs_own_default(tmp_path, monkeypatch, two_threads):
    seen = _spy_threads(monkeypatch)
    assert main(["--threads", "0", "spectrum", *QUICK["spectrum"], "-o", str(tmp_path)]) == 0
    assert set(seen) == {timing.TORCH_DEFAULT_THREADS}
    seen.clear()  # after the command, as before it
    argv = ["--threads", "3", "spectrum", *QUICK["spectrum"], "--threads", "1", "-o", str(tmp_path)]
    assert main(argv) == 0
    assert set(seen) == {1}


def test_info_and_spectrum_report_the_same_first_assembly(tmp_path, monkeypatch, capsys):
    """A fake clock that the topology build advances by 0.25 s and the first Laplacian by
    0.0625 s: both commands report their sum, 312.50 ms, under the same label."""
    clock = SimpleNamespace(now=0.0)
    monkeypatch.setattr(timing, "time", SimpleNamespace(perf_counter=lambda: clock.now))
    for name, seconds in (("build_topology", 0.25), ("laplacian", 0.0625)):
        real = getattr(cli_timing, name)

        def slow(*args, real=real, seconds=seconds, **kwargs):
            clock.now += seconds
            return real(*args, **kwargs)

        monkeypatch.setattr(cli_timing, name, slow)
    assert main(["spectrum", "-k", "2", "--no-plot", "-o", str(tmp_path)]) == 0
    assert main(["info", "--eigs", "2"]) == 0
    label = re.escape(cli_timing.FIRST_ASSEMBLY)
    rows = re.findall(rf"^  {label}\s+(.*)$", capsys.readouterr().out, re.M)
    assert rows == ["312.50 ms", "312.50 ms"]


def test_parser_keeps_the_global_threads_option():
    assert build_parser().parse_args(["--threads", "4", "info"]).threads == 4
    assert build_parser().parse_args(["info"]).threads is None

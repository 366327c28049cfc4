"""The ``polylap`` console script: :func:`torch_polylap.cli.main`, with the seconds of importing
torch_polylap (torch, scipy) and of ending the process covered too.

A module outside the package because importing anything inside it runs
``torch_polylap/__init__.py`` first: a Ctrl-C during those imports would end in Python's
traceback before any code of the command could catch it. Here it ends like a Ctrl-C later on:
one line on stderr and exit status 130 (SIGTERM and SIGHUP: ``128 + signal``).

The same holds after the command returned (:func:`_exit`): Python's own shutdown takes about a
second after a command that imported torch, and a Ctrl-C in it used to end in a traceback and
exit status 0 (raised inside an ``atexit`` callback) or, later in the teardown, to kill the
process without a word.
"""

from __future__ import annotations

import atexit
import os
import signal
import sys
from types import FrameType
from typing import NoReturn, TextIO

__all__ = ["main"]

_ENDING = tuple(
    getattr(signal, name) for name in ("SIGINT", "SIGTERM", "SIGHUP") if hasattr(signal, name)
)


class _Ended(SystemExit):
    """SIGTERM or SIGHUP during the imports."""

    def __init__(self, signum: int) -> None:
        super().__init__(128 + signum)
        self.signum = signum


def _raise_ended(signum: int, frame: FrameType | None) -> None:
    raise _Ended(signum)


def _message(signum: int) -> str:
    if signum == signal.SIGINT:
        return "interrupted"
    return f"terminated ({signal.Signals(signum).name})"


def _end(signum: int) -> int:
    """One line for a process ended by ``signum``; its exit status ``128 + signum``."""
    for ending in _ENDING:  # ending already: a second signal is moot
        signal.signal(ending, signal.SIG_IGN)
    _flush(sys.stdout)
    try:
        print(f"polylap: {_message(signum)}", file=sys.stderr)
    except OSError:  # SIGHUP: the terminal may be gone
        pass
    return 128 + signum


def _end_now(signum: int, frame: FrameType | None) -> None:
    """The handler while the process ends: the one line, then out with ``128 + signum``."""
    status = _end(signum)
    _flush(sys.stderr)
    os._exit(status)


def _flush(stream: TextIO | None) -> None:
    if stream is None:  # pythonw: no console
        return
    try:
        stream.flush()
    except (OSError, ValueError):  # a closed pipe or stream
        pass


def main() -> NoReturn:
    """Import the command, run it (:func:`torch_polylap.cli.main`) and end the process with its
    exit status."""
    _exit(_run())


def _run() -> int:
    """The imports and the command, each signal during them turned into its one line; the exit
    status."""
    ending = [getattr(signal, n) for n in ("SIGTERM", "SIGHUP") if hasattr(signal, n)]
    # a signal the parent set to be ignored (nohup) stays ignored
    replaced = [s for s in ending if signal.getsignal(s) is signal.SIG_DFL]
    try:
        for signum in replaced:
            signal.signal(signum, _raise_ended)
        from torch_polylap.cli import main as run
        from torch_polylap.cli.interrupts import Terminated, raise_terminated

        # the command's own handler, swapped in without a moment at the default (which would
        # kill the process silently); the command keeps a handler it finds installed
        for signum in replaced:
            signal.signal(signum, raise_terminated)
    except KeyboardInterrupt:
        return _end(signal.SIGINT)
    except _Ended as ended:
        return _end(ended.signum)
    try:
        return run()
    except KeyboardInterrupt:  # between the command's handlers and the end of the process
        return _end(signal.SIGINT)
    except Terminated as ended:
        return _end(ended.signum)
    except SystemExit as done:  # argparse: --help, --version, a bad argument
        return _status(done.code)


def _status(code: object) -> int:
    """The exit status of ``SystemExit(code)``, as Python gives it (a message: printed, 1)."""
    if code is None:
        return 0
    if isinstance(code, int):
        return code
    print(code, file=sys.stderr)
    return 1


def _exit(status: int) -> NoReturn:
    """End the process with ``status``; a signal until then ends it with its one line and
    ``128 + signal`` (none after a command that a signal ended: it printed its line).

    The ``atexit`` callbacks run as in Python's own shutdown, but the teardown of the modules
    after them is skipped: it has nothing to do for a finished command, and Python runs it with
    the signals at their default, where Ctrl-C kills the process without its line. The command
    wrote every file whole and closed it (:mod:`torch_polylap.atomic`).
    """
    signalled = status - 128 in _ENDING
    for signum in _ENDING:
        if signal.getsignal(signum) is not signal.SIG_IGN:  # what the parent ignored stays so
            signal.signal(signum, signal.SIG_IGN if signalled else _end_now)
    atexit._run_exitfuncs()
    _flush(sys.stdout)
    _flush(sys.stderr)
    os._exit(status)


if __name__ == "__main__":
    main()

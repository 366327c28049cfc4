"""The ``polylap`` console script: :func:`torch_polylap.cli.main`, with the seconds of importing
torch_polylap (torch, scipy) covered too.

A module outside the package because importing anything inside it runs
``torch_polylap/__init__.py`` first: a Ctrl-C during those imports would end in Python's
traceback before any code of the command could catch it. Here it ends like a Ctrl-C later on:
one line on stderr and exit status 130 (SIGTERM and SIGHUP: ``128 + signal``).
"""

from __future__ import annotations

import signal
import sys
from types import FrameType

__all__ = ["main"]


class _Ended(SystemExit):
    """SIGTERM or SIGHUP during the imports."""

    def __init__(self, signum: int) -> None:
        super().__init__(128 + signum)
        self.signum = signum


def _raise_ended(signum: int, frame: FrameType | None) -> None:
    raise _Ended(signum)


def _end(message: str, status: int) -> int:
    for name in ("SIGINT", "SIGTERM", "SIGHUP"):  # ending already: a second signal is moot
        if hasattr(signal, name):
            signal.signal(getattr(signal, name), signal.SIG_IGN)
    try:
        print(f"polylap: {message}", file=sys.stderr)
    except OSError:  # SIGHUP: the terminal may be gone
        pass
    return status


def main() -> int:
    """Import the command, then run it (:func:`torch_polylap.cli.main`); the exit status."""
    ending = [getattr(signal, n) for n in ("SIGTERM", "SIGHUP") if hasattr(signal, n)]
    # a signal the parent set to be ignored (nohup) stays ignored
    replaced = [s for s in ending if signal.getsignal(s) is signal.SIG_DFL]
    try:
        for signum in replaced:
            signal.signal(signum, _raise_ended)
        from torch_polylap.cli import main as run

        for signum in replaced:  # the command installs its own
            signal.signal(signum, signal.SIG_DFL)
    except KeyboardInterrupt:
        return _end("interrupted", 130)
    except _Ended as ended:
        return _end(f"terminated ({signal.Signals(ended.signum).name})", 128 + ended.signum)
    try:
        return run()
    except KeyboardInterrupt:  # between the command's handlers and the end of the process
        return _end("interrupted", 130)


if __name__ == "__main__":
    sys.exit(main())

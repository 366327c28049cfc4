"""Signals that end a ``polylap`` command, turned into exceptions so that it ends cleanly.

Python turns SIGINT (Ctrl-C) into :class:`KeyboardInterrupt`; by default SIGTERM (``kill``) and
SIGHUP (the terminal closed) end the process on the spot, so no ``finally`` block runs and a
file being written stays behind as a temporary. :func:`signals_as_exceptions` turns them into
:class:`Terminated` (a :class:`SystemExit`), which unwinds the stack like Ctrl-C does: every
atomic write (:func:`torch_polylap.atomic.atomic_write`) removes its temporary and the
previous file stays as it was. ``main`` then prints one line and exits with ``128 + signal``.

A signal the parent process set to be ignored (``nohup``, SIGINT of a background job) stays
ignored, and a handler someone else installed is kept.
"""

from __future__ import annotations

import signal
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from types import FrameType

__all__ = ["Terminated", "raise_terminated", "signals_as_exceptions", "ignore_signals"]

# the signals that end a command, as exceptions (SIGHUP does not exist on Windows)
_ENDING = tuple(
    getattr(signal, name) for name in ("SIGINT", "SIGTERM", "SIGHUP") if hasattr(signal, name)
)


class Terminated(SystemExit):
    """SIGTERM or SIGHUP arrived; ``code`` is the shell's ``128 + signal number``."""

    def __init__(self, signum: int) -> None:
        super().__init__(128 + signum)
        self.signum = signum

    @property
    def name(self) -> str:
        return signal.Signals(self.signum).name


def raise_terminated(signum: int, frame: FrameType | None) -> None:
    """The handler :func:`signals_as_exceptions` installs for SIGTERM and SIGHUP."""
    raise Terminated(signum)


@contextmanager
def signals_as_exceptions() -> Iterator[None]:
    """Within the block, SIGINT raises :class:`KeyboardInterrupt` and SIGTERM and SIGHUP raise
    :class:`Terminated`, in the main thread; every handler is restored after it (also one that
    :func:`ignore_signals` changed).

    Only handlers left at the default are replaced; outside the main thread (where Python
    cannot set handlers) the block runs unchanged.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = {signum: signal.getsignal(signum) for signum in _ENDING}
    for signum, current in previous.items():
        if current is signal.SIG_DFL:  # not ignored, not Python's KeyboardInterrupt, no user's
            ours = signal.default_int_handler if signum == signal.SIGINT else raise_terminated
            signal.signal(signum, ours)
    try:
        yield
    finally:
        for signum, before in previous.items():
            if before is not None:  # None: a handler not installed from Python, left alone
                signal.signal(signum, before)


def ignore_signals() -> None:
    """Ignore further ending signals that raise (main thread only): the command is already
    ending, and a second Ctrl-C must not turn its one-line message into a traceback."""
    if threading.current_thread() is not threading.main_thread():
        return
    for signum in _ENDING:
        if signal.getsignal(signum) in (signal.default_int_handler, raise_terminated):
            signal.signal(signum, signal.SIG_IGN)

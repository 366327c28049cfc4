"""What the benchmark scripts share: the CPU's name, the peak resident memory of one step
(Linux ``/proc``; an upper bound from ``ru_maxrss`` elsewhere), and the timing and table
helpers of the ``polylap`` command (median timing, thread pinning, Markdown tables), imported
from the package (:mod:`torch_polylap.cli.timing`) rather than kept here as a second copy.
Imported by the ``bench_*.py`` scripts (run from this folder, or with it on ``sys.path``)."""

from __future__ import annotations

import ctypes
import gc
import platform
import resource
from collections.abc import Callable

from torch_polylap.timing import (
    DEFAULT_THREADS,
    fmt_time,
    markdown_table,
    median_time,
    pinned_threads,
    synchronizer,
    timed,
)

__all__ = [
    "cpu_model",
    "rss_bytes",
    "reset_peak_rss",
    "trim_heap",
    "peak_rss_growth",
    "DEFAULT_THREADS",
    "fmt_time",
    "markdown_table",
    "median_time",
    "pinned_threads",
    "synchronizer",
    "timed",
]


def cpu_model() -> str:
    """The CPU's model name from ``/proc/cpuinfo`` (``platform``'s guess elsewhere)."""
    try:
        with open("/proc/cpuinfo") as info:
            return next(line.split(":", 1)[1].strip() for line in info if "model name" in line)
    except (OSError, StopIteration):
        return platform.processor() or platform.machine()


def rss_bytes(field: str) -> int | None:
    """``VmRSS`` / ``VmHWM`` of this process from ``/proc/self/status`` (None off Linux)."""
    try:
        with open("/proc/self/status") as status:
            for line in status:
                if line.startswith(field + ":"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return None


def reset_peak_rss() -> bool:
    """Reset the kernel's peak-RSS counter (``VmHWM``) to the current RSS; False if unsupported."""
    try:
        with open("/proc/self/clear_refs", "w") as clear_refs:
            clear_refs.write("5")
        return True
    except OSError:
        return False


def trim_heap() -> None:
    """Return freed heap memory to the OS (glibc), so that a step's peak is not hidden in it."""
    try:
        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):
        pass


def peak_rss_growth(step: Callable[[], object]) -> dict:
    """Run ``step`` once and report how far the resident memory rose above where it started.

    The heap is trimmed and the peak counter reset first, so the baseline is what the setup
    left resident. Where ``/proc/self/clear_refs`` cannot be written the peak is ``ru_maxrss``
    since process start (an upper bound).
    """
    gc.collect()
    trim_heap()
    exact = reset_peak_rss()
    baseline = rss_bytes("VmRSS")
    step()
    peak = (
        rss_bytes("VmHWM") if exact else resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
    )
    return {
        "method": "VmHWM after clear_refs" if exact else "ru_maxrss since start",
        "rss_baseline_bytes": baseline,
        "rss_peak_bytes": peak,
        "rss_delta_bytes": None if baseline is None else peak - baseline,
    }

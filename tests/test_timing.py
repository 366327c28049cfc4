"""torch_polylap.timing on a fake clock: what the medians measure, how many calls they make, and
at which torch thread count (no real time is measured here; benchmarks/ does that)."""

from __future__ import annotations

from types import SimpleNamespace

import pytest
import torch

from torch_polylap import timing


@pytest.fixture
def clock(monkeypatch):
    """A clock that only the timed work advances: every call of ``work`` takes ``step`` s."""
    state = SimpleNamespace(now=0.0, calls=0, threads=[], step=1e-3)
    monkeypatch.setattr(timing, "time", SimpleNamespace(perf_counter=lambda: state.now))

    def work():
        state.now += state.step
        state.calls += 1
        state.threads.append(torch.get_num_threads())

    state.work = work
    return state


def test_median_time_measures_with_the_given_clock(clock):
    syncs = []
    seconds = timing.median_time(clock.work, 3, sync=lambda: syncs.append(1))
    assert seconds == pytest.approx(clock.step)
    assert syncs  # the clock waits for the device before every reading
    # torch's Timer warms up before each sample: more calls than samples
    assert clock.calls > 3


def test_median_time_doubles_the_calls_until_a_sample_is_long_enough(clock):
    seconds = timing.median_time(clock.work, 2, sync=lambda: None, min_sample_s=0.01)
    assert seconds == pytest.approx(clock.step)
    # 16 calls (0.016 s) are the first power of two that lasts 0.01 s; 2 samples of 16 at least
    assert clock.calls >= 32


def test_cold_samples_make_exactly_the_calls_asked(clock):
    assert timing.median_time(clock.work, 4, warmup=False) == pytest.approx(clock.step)
    assert clock.calls == 4
    seconds, result = timing.timed(lambda: (clock.work(), "last")[1], 1)
    assert seconds == pytest.approx(clock.step) and result == "last" and clock.calls == 5


@pytest.mark.parametrize("threads", [1, 2])
def test_median_time_runs_at_the_pinned_thread_count(clock, threads):
    """torch's Timer would run on one thread unless told otherwise; the pinned count holds."""
    before = torch.get_num_threads()
    with timing.pinned_threads(threads):
        timing.median_time(clock.work, 2, sync=lambda: None)
    assert set(clock.threads) == {threads}
    assert torch.get_num_threads() == before


def test_bad_repeat_and_thread_counts_are_refused(clock):
    with pytest.raises(ValueError, match="repeat must be at least 1"):
        timing.median_time(clock.work, 0)
    with pytest.raises(ValueError, match="repeat must be at least 1"):
        timing.timed(clock.work, 0)
    with pytest.raises(ValueError, match="thread count"), timing.pinned_threads(-1):
        pass


def test_markdown_table_escapes_bars_and_pads_columns():
    table = timing.markdown_table(["name", "|H|"], [["a", 1.5], ["long name", 2]])
    lines = table.splitlines()
    assert lines[0] == "| name      | \\|H\\| |"
    assert lines[1] == "|-----------|-------|"
    assert lines[3] == "| long name | 2     |"
    assert len({len(line) for line in lines}) == 1


def test_fmt_time_picks_the_unit():
    assert [timing.fmt_time(s) for s in (2e-6, 2.5e-3, 3.0)] == ["2 us", "2.50 ms", "3.00 s"]

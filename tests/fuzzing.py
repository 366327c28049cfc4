"""What the fuzz tests share (not a test itself): Hypothesis, skipping the importing module when
it is not installed, settings that replay the same examples on every run, and a tally of the
inputs tried per category, printed after the module.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable, Iterator

import pytest

pytest.importorskip("hypothesis", reason="hypothesis not installed: pip install .[test]")
from hypothesis import HealthCheck, settings  # noqa: E402


def fuzz_settings(max_examples: int) -> settings:
    """``max_examples`` derandomized examples without a deadline: the same inputs in CI and
    locally, however slow the machine (slow examples are the point, not a health problem)."""
    return settings(
        max_examples=max_examples,
        deadline=None,
        suppress_health_check=[HealthCheck.too_slow],
        derandomize=True,
    )


def tally_fixture(counts: Counter, what: str) -> Callable[[], Iterator[None]]:
    """A module-scoped autouse fixture (assign it to a module-level name) that prints ``counts``,
    the ``what`` per category, once the module's tests have run."""

    @pytest.fixture(scope="module", autouse=True)
    def _print_tally() -> Iterator[None]:
        yield
        print(f"\n{what} per category:", dict(sorted(counts.items())))

    return _print_tally

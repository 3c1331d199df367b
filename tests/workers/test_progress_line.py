"""The throughput a training loop reports: env steps/s between reads, split into trained and
explored steps for UED (both in TensorBoard and on the progress line), the old total kept."""

from __future__ import annotations

import io
import math

import pytest

from workers.progress import Progress, ThroughputClock


class FakeNow:
    """A clock's notion of now (seconds), set by calling it; no compilation happens."""

    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self, seconds: float) -> None:
        self.now = seconds

    def clock(self, start_update: int, steps_per_update: int) -> ThroughputClock:
        return ThroughputClock(start_update, steps_per_update, seconds=lambda: self.now,
                               compile_seconds=lambda: 0.0)


@pytest.fixture
def clock_at():
    return FakeNow()


def test_ued_rate_splits_into_trained_and_explored(clock_at):
    clock = clock_at.clock(start_update=10, steps_per_update=100)
    clock_at(5.0)
    timing, rate = clock.read(11, trained=0)  # the first read: compilation included
    assert timing == {"time/first_update_s": 5.0} and math.isnan(rate)
    clock_at(7.0)  # 4 steps in 2 s, 1 of them trained
    timing, rate = clock.read(15, trained=1)
    assert rate == 200.0
    assert timing == {"time/trained_steps_per_s": 50.0, "time/explored_steps_per_s": 150.0}
    clock_at(8.0)  # 2 steps in 1 s, both trained
    timing, rate = clock.read(17, trained=3)
    assert (rate, timing["time/trained_steps_per_s"], timing["time/explored_steps_per_s"]) == (
        200.0, 200.0, 0.0)


def test_marl_rate_is_all_trained(clock_at):
    clock = clock_at.clock(start_update=0, steps_per_update=10)
    clock_at(1.0)
    clock.read(1)
    clock_at(2.0)
    timing, rate = clock.read(5)
    assert rate == 40.0 and timing == {"time/trained_steps_per_s": 40.0}


def test_progress_line_shows_the_split_only_when_given():
    out = io.StringIO()
    bar = Progress(100, out, every_s=0.0)
    bar.show(3, 300, 1234.4, 60.0, 0.5, extra="new 2, replay 1")
    bar.show(4, 400, 1234.4, 60.0, 0.5, trained_per_s=1000.2, explored_per_s=234.2)
    bar.show(5, 500, 1234.4, 60.0, 0.5, trained_per_s=1234.4)
    first, second, third = out.getvalue().splitlines()
    assert first == ("update 3/100  300 steps  1,234 steps/s  ETA 1m00s  win 0.50  "
                     "(new 2, replay 1)")
    assert "1,234 steps/s (trained 1,000 + explored 234)  ETA 1m00s" in second
    assert "1,234 steps/s  ETA" in third and "explored" not in third


def test_a_line_off_a_terminal_splits_the_steps_since_the_previous_line(clock_at):
    """Off a terminal a line is shown every `every_s` seconds: its rate and its split cover
    every step since the previous line, not only the last logged one. Robust PLR's steps
    alternate here: a new-level step (1 s, explored) and a replay step (3 s, trained); the line
    after four of them lands on a replay step, which alone would read `explored 0`."""
    from workers.progress import log_update

    clock = clock_at.clock(start_update=0, steps_per_update=100)
    out = io.StringIO()
    bar = Progress(100, out, every_s=3600.0)  # the first and the final line only
    trained = 0
    for update, (seconds, trains) in enumerate([(5, False), (1, False), (3, True), (1, False),
                                                (3, True)], start=1):
        clock_at(clock_at.now + seconds)
        trained += trains
        timing, rate = clock.read(update, trained)
        log_update(None, bar, None, update, None, timing, 100, rate, 100, update == 5,
                   played=clock.played)
    first, line = out.getvalue().splitlines()
    assert "first update 5.0 s" in first
    # Updates 2-5 in 8 s: 2 trained (200 env steps), 2 explored (200): 25 + 25 steps/s.
    assert "50 steps/s (trained 25 + explored 25)" in line, line

"""The progress line's ETA leaves compilation out: the first update (compiled) is reported on
its own, and a later compilation (a UED branch's first step) does not inflate the estimate."""

from __future__ import annotations

import io
import math

import jax
import jax.numpy as jnp

from tabx.compile_counter import compile_seconds
from workers.progress import Progress, ThroughputClock, log_update


class FakeTime:
    """A clock and a compile-time total that the test moves by hand."""

    def __init__(self) -> None:
        self.now = 0.0
        self.compiling = 0.0

    def run(self, seconds: float, compiling: float = 0.0) -> None:
        self.now += seconds + compiling
        self.compiling += compiling


class NullWriter:
    def scalars(self, values, step):
        self.last = (values, step)


def test_eta_rate_leaves_intervals_that_compiled_out():
    t = FakeTime()
    clock = ThroughputClock(0, 100, seconds=lambda: t.now, compile_seconds=lambda: t.compiling,
                            min_clean_updates=1)
    t.run(1.0, compiling=20.0)  # update 1: compiled
    timing, rate = clock.read(1)
    assert timing == {"time/first_update_s": 21.0} and math.isnan(rate)
    assert math.isnan(clock.eta_steps_per_s)  # nothing to estimate from yet
    t.run(1.0, compiling=30.0)  # update 2: another program compiled (a replay step, say)
    timing, rate = clock.read(2)
    assert timing == {"time/trained_steps_per_s": rate} and rate == 100 / 31.0  # wall-clock
    assert math.isnan(clock.eta_steps_per_s)  # no compile-free interval yet: no ETA
    for update in range(3, 6):
        t.run(2.0)
        clock.read(update)
    assert clock.eta_steps_per_s == 3 * 100 / 6.0  # updates 3-5 only


def test_eta_waits_for_min_clean_updates():
    t = FakeTime()
    clock = ThroughputClock(0, 100, seconds=lambda: t.now, compile_seconds=lambda: t.compiling)
    t.run(1.0, compiling=20.0)
    clock.read(1)
    for update in (2, 3):
        t.run(1.0)
        clock.read(update)
        assert math.isnan(clock.eta_steps_per_s)  # 1, then 2 compile-free updates: too few
    t.run(1.0)
    clock.read(4)
    assert clock.eta_steps_per_s == 100.0


def test_first_run_of_a_new_program_does_not_inflate_the_eta():
    """A new program's first run costs time that no compile event reports (measured on the
    quickstart: the replay branch's first step at update 2, the buffer's larger shapes
    later); the interval holding it is left out whole, so the first ETA is the steady one."""
    t = FakeTime()
    clock = ThroughputClock(0, 100, seconds=lambda: t.now, compile_seconds=lambda: t.compiling,
                            min_clean_updates=1)
    t.run(1.0, compiling=20.0)
    clock.read(1)
    t.run(1.0 + 12.0, compiling=15.0)  # update 2: compiled, and 12 s unreported beside it
    clock.read(2)
    t.run(1.0)
    clock.read(3)
    assert clock.eta_steps_per_s == 100.0  # not 2 * 100 / 14 (ETA 14 times too long)
    t.run(1.0 + 5.0, compiling=4.0)  # the buffer grows: a larger shape compiles
    clock.read(4)
    t.run(1.0)
    clock.read(5)
    assert clock.eta_steps_per_s == 100.0


def test_eta_falls_back_when_every_interval_compiles():
    t = FakeTime()
    clock = ThroughputClock(0, 100, seconds=lambda: t.now, compile_seconds=lambda: t.compiling,
                            fallback_after=3)
    t.run(1.0, compiling=20.0)
    clock.read(1)
    for update in (2, 3):
        t.run(1.0, compiling=1.0)
        clock.read(update)
        assert math.isnan(clock.eta_steps_per_s)
    t.run(1.0, compiling=1.0)
    clock.read(4)
    assert clock.eta_steps_per_s == 3 * 100 / 3.0  # since update 1, compile time left out


def test_progress_line_eta_uses_the_compile_free_rate():
    t = FakeTime()
    clock = ThroughputClock(0, 100, seconds=lambda: t.now, compile_seconds=lambda: t.compiling,
                            min_clean_updates=1)
    stream = io.StringIO()
    bar = Progress(100, stream, every_s=0.0)
    writer = NullWriter()
    for update, (seconds, compiling) in enumerate([(1, 20), (1, 30), (1, 0), (1, 0)], start=1):
        t.run(seconds, compiling)
        timing, rate = clock.read(update)
        log_update(writer, bar, None, update, None, timing, 100, rate, 100, False,
                   eta_steps_per_s=clock.eta_steps_per_s)
    first, second, third, fourth = stream.getvalue().splitlines()
    assert "first update 21.0 s (compilation included)" in first and "ETA" not in first
    assert "ETA ?" in second  # its interval compiled: not 98 updates at 31 s (50m38s)
    assert "ETA 1m37s" in third  # 97 updates at 1 s each
    assert "ETA 1m36s" in fourth
    assert writer.last[0]["time/steps_per_s"] == 100.0  # the last interval, wall-clock


def test_compile_seconds_counts_a_real_compilation():
    before = compile_seconds()
    jax.jit(lambda x: jnp.sin(x) * 3.0 + jnp.cos(x))(jnp.arange(7.0)).block_until_ready()
    assert compile_seconds() > before
    again = compile_seconds()
    jnp.arange(7.0).block_until_ready()  # no new program
    assert compile_seconds() == again


def test_env_steps_explored_beside_the_steps_count_as_explored():
    """The continuous schedule trains at every step while Explorers score levels beside it:
    their env steps (`background`) are explored steps/s and part of the sum; the ETA counts
    the loop's steps only."""
    t = FakeTime()
    clock = ThroughputClock(0, 100, seconds=lambda: t.now, compile_seconds=lambda: t.compiling,
                            min_clean_updates=1)
    t.run(1.0)
    clock.read(1, trained=1, background=50)  # the first read: its background is the origin
    t.run(2.0)
    timing, rate = clock.read(3, trained=3, background=50 + 600)
    assert timing["time/trained_steps_per_s"] == 2 * 100 / 2.0
    assert timing["time/explored_steps_per_s"] == 600 / 2.0
    assert rate == (2 * 100 + 600) / 2.0
    assert clock.eta_steps_per_s == 2 * 100 / 2.0

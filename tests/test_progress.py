"""The progress line's ETA leaves compilation out: the first update (compiled) is reported on
its own, and a later compilation (a UED branch's first step) does not inflate the estimate."""

from __future__ import annotations

import io
import math

import jax
import jax.numpy as jnp

from tabx.compile_counter import compile_seconds
from ued.progress import Progress, ThroughputClock, log_update


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


def test_eta_rate_leaves_compilation_out():
    t = FakeTime()
    clock = ThroughputClock(0, 100, seconds=lambda: t.now, compile_seconds=lambda: t.compiling)
    t.run(1.0, compiling=20.0)  # update 1: compiled
    timing, rate = clock.read(1)
    assert timing == {"time/first_update_s": 21.0} and math.isnan(rate)
    assert math.isnan(clock.eta_steps_per_s)  # nothing to estimate from yet
    t.run(1.0, compiling=30.0)  # update 2: another program compiled (a replay step, say)
    timing, rate = clock.read(2)
    assert timing == {"time/trained_steps_per_s": rate} and rate == 100 / 31.0  # wall-clock
    assert clock.eta_steps_per_s == 100 / 1.0  # the ETA's rate is not
    for update in range(3, 6):
        t.run(2.0)
        clock.read(update)
    assert clock.eta_steps_per_s == 4 * 100 / 7.0  # since the first update, compiles left out


def test_progress_line_eta_uses_the_compile_free_rate():
    t = FakeTime()
    clock = ThroughputClock(0, 100, seconds=lambda: t.now, compile_seconds=lambda: t.compiling)
    stream = io.StringIO()
    bar = Progress(100, stream, every_s=0.0)
    writer = NullWriter()
    for update, (seconds, compiling) in enumerate([(1, 20), (1, 30), (1, 0)], start=1):
        t.run(seconds, compiling)
        timing, rate = clock.read(update)
        log_update(writer, bar, None, update, None, timing, 100, rate, 100, False,
                   eta_steps_per_s=clock.eta_steps_per_s)
    first, second, third = stream.getvalue().splitlines()
    assert "first update 21.0 s (compilation included)" in first and "ETA" not in first
    assert "ETA 1m38s" in second  # 98 updates at 1 s each, not at 31 s (50m38s)
    assert "ETA 1m37s" in third
    assert writer.last[0]["time/steps_per_s"] == 100.0  # the last interval, wall-clock


def test_compile_seconds_counts_a_real_compilation():
    before = compile_seconds()
    jax.jit(lambda x: jnp.sin(x) * 3.0 + jnp.cos(x))(jnp.arange(7.0)).block_until_ready()
    assert compile_seconds() > before
    again = compile_seconds()
    jnp.arange(7.0).block_until_ready()  # no new program
    assert compile_seconds() == again

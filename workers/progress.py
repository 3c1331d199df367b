"""Reporting a training loop as it goes: the progress line, throughput and the log of an update.

Both drivers (`workers.local`, and the Ray driver) report through these, so a run reads the
same on the terminal and in TensorBoard wherever it ran.
"""

from __future__ import annotations

import math
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, TextIO

from tabx.compile_counter import compile_seconds
from ued.learners.ppo import TrainState
from ued.tensorboard import SummaryWriter


class Progress:
    """A one-line progress report on a stream: updates, env steps/s, ETA and the win rate.
    On a terminal the line is rewritten in place; otherwise a line is printed at most every
    `every_s` seconds (and at the end)."""

    def __init__(self, total: int, stream: TextIO | None = None, every_s: float = 10.0):
        self.total = total
        self.stream = sys.stderr if stream is None else stream
        self.tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self.every_s = every_s
        self._last = -math.inf
        self._shown: Played | None = None  # the env steps played when the last line was shown

    def show(self, update: int, steps: int, steps_per_s: float, eta_s: float,
             win_rate: float, final: bool = False, first_update_s: float | None = None,
             extra: str = "", trained_per_s: float | None = None,
             explored_per_s: float | None = None, played: Played | None = None) -> None:
        """`trained_per_s` and `explored_per_s` (UED: env steps that trained the policy, and
        those played only to score levels) split `steps_per_s`, their sum, on the line.
        `played` (`ThroughputClock.played`): the line's rate and its split then cover the env
        steps played since the previous line shown, whatever number of logged steps that
        spans (a line every `every_s` seconds off a terminal would otherwise show one step's
        rate: a replay step's, all trained, or a new-level step's, all explored)."""
        now = time.monotonic()
        if not (self.tty or final or now - self._last >= self.every_s):
            return
        self._last = now
        if played is not None:
            since, self._shown = self._shown, played
            if since is not None and played.seconds > since.seconds and first_update_s is None:
                trained_per_s, explored_per_s = played.rates_since(since)
                steps_per_s = trained_per_s + (explored_per_s or 0.0)
        win = "-" if not math.isfinite(win_rate) else f"{win_rate:.2f}"
        if first_update_s is not None:
            rate = f"first update {first_update_s:.1f} s (compilation included)"
        else:
            split = ""
            if trained_per_s is not None and explored_per_s is not None:
                split = f" (trained {trained_per_s:,.0f} + explored {explored_per_s:,.0f})"
            rate = f"{steps_per_s:,.0f} steps/s{split}  ETA {format_duration(eta_s)}"
        line = f"update {update}/{self.total}  {steps:,} steps  {rate}  win {win}"
        if extra:
            line += f"  ({extra})"
        if self.tty:
            self.stream.write("\r" + line.ljust(110) + ("\n" if final else ""))
        else:
            self.stream.write(line + "\n")
        self.stream.flush()


@dataclass(frozen=True)
class Played:
    """Env steps played by a training loop so far (from any fixed origin), at a clock's read:
    `trained` trained the policy, `explored` only scored levels (None: every step trains)."""

    seconds: float
    trained: float
    explored: float | None

    def rates_since(self, before: Played) -> tuple[float, float | None]:
        """(trained, explored) env steps/s between `before` and this."""
        span = self.seconds - before.seconds
        explored = (None if self.explored is None or before.explored is None
                    else (self.explored - before.explored) / span)
        return (self.trained - before.trained) / span, explored


class ThroughputClock:
    """Wall-clock bookkeeping of a training loop: the first update's seconds (compilation
    included), then env steps/s between reads. Read it only after the device has finished the
    updates being timed (e.g. after `jax.device_get` of their metrics).

    A UED loop also says how many of its steps trained the policy (`read(done, trained)`); the
    rate then splits into trained and explored env steps/s (steps played only to score levels:
    Robust PLR's and ACCEL's new and mutated levels), logged as `time/trained_steps_per_s` and
    `time/explored_steps_per_s`; `time/steps_per_s` stays their sum. Without `trained` every
    step trained. Env steps played beside the loop's steps (`background`: the Ray driver's
    continuous schedule, whose Explorers score levels while the learner trains) count as
    explored, and in the sum; the ETA counts the loop's steps only. `played` holds the running
    totals of the newest read, for a rate over any window (`Progress.show`).

    `eta_steps_per_s` is the rate an ETA should use: env steps per second over the intervals
    between reads (after the first) in which nothing compiled. A run compiles more than its
    first update (a UED curriculum's replay and mutation steps are programs of their own,
    compiled the first time each branch runs, and again when the level buffer grows into a
    larger shape; an evaluation's first run). Leaving out only the compile time those events
    report is not enough: the first run of a new program also costs time that no compile
    event reports (e.g. the persistent cache's key and write, the program's first dispatch),
    enough to make the quickstart's first ETA read about twice the real remaining time
    (docs/cli.md has the measurements). So an interval that compiled is left out whole, and
    until the compile-free intervals hold `min_clean_updates` updates the rate is NaN (no ETA
    yet: one interval on a shared machine is too noisy), unless `fallback_after` intervals
    have all compiled: then it is the rate since the first read with the compile time left
    out. `seconds` and `compile_seconds` (the process's running totals,
    `tabx.compile_counter.compile_seconds`)
    can be replaced to test it."""

    def __init__(self, start_update: int, steps_per_update: int,
                 seconds: Callable[[], float] = time.perf_counter,
                 compile_seconds: Callable[[], float] = compile_seconds,
                 fallback_after: int = 3, min_clean_updates: int = 3):
        self.steps_per_update = steps_per_update
        self.min_clean_updates = min_clean_updates
        self.fallback_after = fallback_after
        self.first_update_s: float | None = None
        self.eta_steps_per_s = math.nan
        self._seconds, self._compile_seconds = seconds, compile_seconds
        self._t, self._update, self._trained = seconds(), start_update, None
        self._background = 0
        self._since: tuple[float, float, int] | None = None  # (time, compile time, update)
        self._compiled_at = 0.0  # the compile-time total at the previous read
        self._clean = [0, 0.0]  # updates and seconds of the compile-free intervals
        self._intervals = 0  # intervals since the first read
        self.played: Played | None = None

    @property
    def first_pending(self) -> bool:
        return self.first_update_s is None

    def read(self, done: int, trained: int | None = None, background: int = 0
             ) -> tuple[dict[str, float], float]:
        """(metrics to log, steps/s) at update `done`: {"time/first_update_s": s} and NaN on
        the first read, then the trained (and, given `trained`, explored) steps/s since the
        previous read and their sum. `trained`: how many of the loop's steps so far trained
        the policy; `background`: env steps explored beside the loop's steps so far; both
        counted from any fixed origin."""
        now, compiling = self._seconds(), self._compile_seconds()
        played_beside, self._background = background - self._background, background
        if self.first_update_s is None:
            self.first_update_s = now - self._t
            out, rate = {"time/first_update_s": self.first_update_s}, math.nan
            self._since = (now, compiling, done)
        else:
            seconds = max(now - self._t, 1e-9)
            rate = (done - self._update) * self.steps_per_update / seconds
            if trained is None or self._trained is None:
                out = {"time/trained_steps_per_s": rate} if trained is None else {}
            else:
                trained_rate = (trained - self._trained) * self.steps_per_update / seconds
                rate += played_beside / seconds
                out = {"time/trained_steps_per_s": trained_rate,
                       "time/explored_steps_per_s": rate - trained_rate}
            self._intervals += 1
            if compiling == self._compiled_at:
                self._clean[0] += done - self._update
                self._clean[1] += now - self._t
            if self._clean[0] >= self.min_clean_updates and self._clean[1] > 0:
                self.eta_steps_per_s = self._clean[0] * self.steps_per_update / self._clean[1]
            elif self._intervals >= self.fallback_after:  # something compiles every time
                t0, c0, u0 = self._since
                running = (now - t0) - (compiling - c0)
                if running > 0:
                    self.eta_steps_per_s = (done - u0) * self.steps_per_update / running
        self._t, self._update, self._trained = now, done, trained
        self._compiled_at = compiling
        loop = done * self.steps_per_update
        self.played = (Played(now, loop, None) if trained is None else
                       Played(now, trained * self.steps_per_update,
                              loop - trained * self.steps_per_update + background))
        return out, rate


def format_duration(seconds: float) -> str:
    if not math.isfinite(seconds):
        return "?"
    seconds = int(round(seconds))
    h, rest = divmod(seconds, 3600)
    m, s = divmod(rest, 60)
    return f"{h}h{m:02d}m" if h else f"{m}m{s:02d}s"


def logged_scalars(metrics: dict[str, Any], steps_per_s: float) -> dict[str, float]:
    """The scalars an update logs: its metrics as floats, and `time/steps_per_s` once there
    is a rate (none on the first update, whose time is `time/first_update_s`)."""
    values = {k: float(v) for k, v in metrics.items()}
    if math.isfinite(steps_per_s):
        values["time/steps_per_s"] = steps_per_s
    return values


def log_update(writer: SummaryWriter | None, bar: Progress | None, callback, done: int,
               train_state: TrainState, metrics: dict[str, Any], steps_per_update: int,
               steps_per_s: float, num_updates: int, last: bool, extra: str = "",
               eta_steps_per_s: float | None = None, played: Played | None = None) -> None:
    """One logged update: TensorBoard scalars, the progress line (its ETA from
    `eta_steps_per_s` where given: `ThroughputClock.eta_steps_per_s`; its rate over the steps
    since the previous line with `played`: `ThroughputClock.played`), the callback. No
    `writer`: the caller writes the scalars (a multi-seed run: one writer per seed)."""
    values = logged_scalars(metrics, steps_per_s)
    steps = done * steps_per_update
    if writer is not None:
        writer.scalars(values, step=steps)
    if bar is not None:
        rate = steps_per_s if math.isfinite(steps_per_s) and steps_per_s > 0 else math.nan
        eta_rate = rate if eta_steps_per_s is None else eta_steps_per_s
        eta = (num_updates - done) * steps_per_update / eta_rate if eta_rate > 0 else math.nan
        bar.show(done, steps, rate, eta, values.get("episode/win_rate", math.nan), final=last,
                 first_update_s=values.get("time/first_update_s"), extra=extra,
                 trained_per_s=values.get("time/trained_steps_per_s"),
                 explored_per_s=values.get("time/explored_steps_per_s"), played=played)
    if callback is not None:
        callback(done, train_state, values)


__all__ = ["Played", "Progress", "ThroughputClock", "format_duration", "log_update",
           "logged_scalars"]

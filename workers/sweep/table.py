"""The live table of a sweep: one row per trial (state, steps, rate, latest win rate, ETA).

`SweepTable` keeps the rows and draws them: on a terminal it redraws the table in place
(cursor up over the previous drawing), elsewhere (a log, a pipe) it prints the table at most
every `every_s` seconds and when a trial changes state. It knows nothing of Ray: the sweep
(`workers.sweep.tune`) feeds it Tune's events.
"""

from __future__ import annotations

import math
import sys
import time
from dataclasses import dataclass
from typing import TextIO

from workers.progress import format_duration


@dataclass
class Row:
    """One trial's line."""

    name: str
    state: str = "pending"  # pending, running, finished, failed, done before (skipped)
    steps: int = 0
    total_steps: int = 0
    steps_per_s: float = math.nan
    win_rate: float = math.nan
    reported_eta_s: float = math.nan  # the trial's own estimate (its mean rate), if it gave one
    error: str = ""

    @property
    def eta_s(self) -> float:
        if self.state != "running":
            return math.nan
        if math.isfinite(self.reported_eta_s):
            return self.reported_eta_s
        if not self.steps_per_s > 0:
            return math.nan
        return max(self.total_steps - self.steps, 0) / self.steps_per_s


def _num(value: float, fmt: str) -> str:
    return "-" if not math.isfinite(value) else format(value, fmt)


class SweepTable:
    """Rows of a sweep's trials, drawn on `stream`."""

    def __init__(self, names: list[str], stream: TextIO | None = None, every_s: float = 30.0):
        self.rows = {name: Row(name) for name in names}
        self.stream = sys.stderr if stream is None else stream
        self.tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self.every_s = every_s
        self._drawn_lines = 0
        self._last = -math.inf
        self.started = time.monotonic()

    def __getstate__(self) -> dict:
        # Tune pickles its callbacks (this table's) with its experiment state: not the stream.
        return {**self.__dict__, "stream": None}

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        self.stream = sys.stderr if self.stream is None else self.stream

    def update(self, name: str, **values: object) -> None:
        """Set fields of a trial's row; a change of state draws the table at once."""
        row = self.rows.setdefault(name, Row(name))
        changed = "state" in values and values["state"] != row.state
        for key, value in values.items():
            setattr(row, key, value)
        self.draw(force=changed)

    def lines(self) -> list[str]:
        width = max([5, *(len(n) for n in self.rows)])
        counts = {}
        for row in self.rows.values():
            counts[row.state] = counts.get(row.state, 0) + 1
        summary = ", ".join(f"{n} {s}" for s, n in counts.items())
        out = [f"sweep: {len(self.rows)} trials ({summary}); "
               f"{format_duration(time.monotonic() - self.started)} elapsed",
               f"{'trial':<{width}}  {'state':<9} {'steps':>13} {'steps/s':>9} {'win':>5} "
               f"{'ETA':>7}"]
        for row in self.rows.values():
            steps = (f"{row.steps / row.total_steps:6.1%} of {_short(row.total_steps)}"
                     if row.total_steps else "-")
            line = (f"{row.name:<{width}}  {row.state:<9} {steps:>13} "
                    f"{_num(row.steps_per_s, ',.0f'):>9} {_num(row.win_rate, '.2f'):>5} "
                    f"{format_duration(row.eta_s) if math.isfinite(row.eta_s) else '-':>7}")
            if row.error:
                line += f"  {row.error[:100]}"
            out.append(line)
        return out

    def draw(self, force: bool = False) -> None:
        now = time.monotonic()
        if not force and now - self._last < (1.0 if self.tty else self.every_s):
            return
        self._last = now
        lines = self.lines()
        if self.tty and self._drawn_lines:
            self.stream.write(f"\x1b[{self._drawn_lines}F\x1b[J")
        self.stream.write("\n".join(lines) + "\n")
        self.stream.flush()
        self._drawn_lines = len(lines) if self.tty else 0


def _short(steps: int) -> str:
    for unit, size in (("G", 1e9), ("M", 1e6), ("k", 1e3)):
        if steps >= size:
            return f"{steps / size:.3g}{unit}"
    return str(steps)


__all__ = ["Row", "SweepTable"]

"""What a Ray run reports about itself: rates over a sliding window, the actors alive, and the
`ray/*` statistics written to TensorBoard and ray.json."""

from __future__ import annotations

import time
from collections import Counter, deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from workers.ray.actor_manager import ActorManager

RATE_WINDOW_S = 60.0  # rates in ray.json, `tabx runs status` and ray/*_per_s: over this window


class RateWindow:
    """Rates of running counts averaged over the last `window_s` seconds (the whole session
    while it is younger): the rate a run holds, not one step's burst."""

    def __init__(self, window_s: float = RATE_WINDOW_S,
                 clock: Callable[[], float] = time.perf_counter, start: tuple = ()):
        self.window_s, self.clock = window_s, clock
        self.samples: deque[tuple[float, tuple[float, ...]]] = deque()
        if start:
            self.samples.append((clock(), tuple(start)))

    def add(self, *counts: float) -> tuple[float, ...]:
        """Record `counts` now; their rates per second over the window (0 until there are two
        readings)."""
        now = self.clock()
        self.samples.append((now, counts))
        while len(self.samples) > 2 and self.samples[1][0] <= now - self.window_s:
            self.samples.popleft()
        t0, base = self.samples[0]
        span = now - t0
        return tuple((c - b) / span if span > 0 else 0.0 for c, b in zip(counts, base,
                                                                         strict=True))

    @property
    def span_s(self) -> float:
        """Seconds the last rates were averaged over."""
        return self.samples[-1][0] - self.samples[0][0] if self.samples else 0.0


def live_actors(ray: Any, actors: ActorManager, names: list[str]) -> int:
    """Of `names`, the actors answering: not given up by the ActorManager and alive in Ray's
    actor table (one dead or restarting is not)."""
    from ray._private import state

    live = 0
    for name in names:
        if not actors.available(name):
            continue
        actor_id = actors.members[name].actor_id()
        try:
            info = state.actors(actor_id=actor_id) if actor_id else {}
        except Exception:  # the table unreadable: count on the manager's word
            info = {"State": "ALIVE"}
        live += info.get("State") == "ALIVE"
    return live


@dataclass
class RayStats:
    """What the progress line and `ray/*` scalars report."""

    trained_steps: int = 0
    explored_steps: int = 0
    committed: int = 0
    rescored: int = 0
    reissued: int = 0  # batches submitted again after their Explorer died
    evaluations_rerun: int = 0  # evaluations run again after their Evaluator died
    evaluations_lost: int = 0  # evaluations given up
    staleness: Counter = field(default_factory=Counter)  # version lag at commit -> batches
    learner_busy_s: float = 0.0
    wait_for_levels_s: float = 0.0
    t0: float = field(default_factory=time.perf_counter)
    window: RateWindow = field(default_factory=lambda: RateWindow(start=(0, 0)))
    rates: tuple[float, ...] = (0.0, 0.0)  # trained, explored env steps/s over the window

    def scalars(self, live_explorers: int, inflight: int) -> dict[str, float]:
        """The `ray/*` scalars of a logged step (reads the rates: once per logged step)."""
        elapsed = max(time.perf_counter() - self.t0, 1e-9)
        self.rates = self.window.add(self.trained_steps, self.explored_steps)
        lags = list(self.staleness.elements())
        out = {"ray/trained_steps_per_s": self.rates[0],
               "ray/explored_steps_per_s": self.rates[1],
               "ray/rate_window_s": self.window.span_s,
               "ray/live_explorers": float(live_explorers),
               "ray/inflight_batches": float(inflight),
               "ray/committed_batches": float(self.committed),
               "ray/rescored": float(self.rescored),
               "ray/reissued": float(self.reissued),
               "ray/learner_busy_fraction": self.learner_busy_s / elapsed,
               "ray/wait_for_levels_s": self.wait_for_levels_s}
        if lags:
            out["ray/staleness_mean"] = float(np.mean(lags))
            out["ray/staleness_max"] = float(max(lags))
        return out

    def text(self, live_explorers: int, buffer_size: int | None) -> str:
        """The progress line's part (after `scalars`: its rates)."""
        lags = list(self.staleness.elements())
        parts = [f"trained {self.rates[0]:,.0f}/s",
                 f"explored {self.rates[1]:,.0f}/s over {self.window.span_s:.0f} s",
                 f"explorers {live_explorers} live"]
        if buffer_size is not None:
            parts.append(f"buffer {buffer_size}")
        if lags:
            parts.append(f"lag {np.mean(lags):.1f}")
        return ", ".join(parts)


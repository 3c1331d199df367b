"""Deaths and restarts of a Ray run's actors, as the driver sees them.

Ray restarts a dead actor by running its constructor again (`max_restarts`); calls sent while it
restarts fail, and a call Ray retried would reuse its original arguments, so the driver never
lets Ray retry (`max_task_retries=0`): it waits for the restart and sends the call again itself,
with what the schedule asks for now. What a restart loses depends on the actor:

    Explorer, Evaluator  nothing (their parameters come with each call): calls run again
    LevelService         nothing acknowledged: it replays its commit log on restart
                         (`workers.durable_service`); its state-changing calls are numbered
                         (`RemoteService`), so one it had logged before dying is not applied
                         twice
    Learner              not restarted: its death stops the run (resume from a checkpoint)
"""

from __future__ import annotations

import time
from collections import Counter
from collections.abc import Callable
from typing import Any, TextIO

from workers.driver import RunStopped
from workers.durable_service import MUTATING

MAX_CALL_FAILURES = 5  # one call failing this often in a row stops the run


def death_cause(err: Exception) -> str:
    """The first line of an actor error: what Ray says killed it."""
    text = str(err).strip()
    return text.splitlines()[0] if text else type(err).__name__


class ActorDeaths:
    """Deaths of the restartable actors (Explorers, the Evaluator): counted by name and
    logged with their cause on the run's stream."""

    def __init__(self, stream: TextIO | None):
        self.stream, self.count = stream, Counter()

    def saw(self, name: str, err: Exception, then: str) -> None:
        self.count[name] += 1
        if self.stream is not None:
            self.stream.write(f"ray: {name} died ({death_cause(err)}); {then}\n")
            self.stream.flush()


RESTART_TIMEOUT_S = 300.0  # an actor not back after this long stops the run


def wait_restarted(ray: Any, actor: Any, name: str,
                   timeout_s: float = RESTART_TIMEOUT_S) -> None:
    """Wait until a restarting actor answers again: calls sent while it restarts fail ("the
    actor is restarting") rather than wait for it."""
    deadline = time.perf_counter() + timeout_s
    while True:
        try:
            ray.get(actor.ready.remote(), timeout=max(deadline - time.perf_counter(), 0.1))
            return
        except ray.exceptions.ActorUnavailableError:
            if time.perf_counter() > deadline:
                break
            time.sleep(0.2)
        except (ray.exceptions.ActorDiedError, ray.exceptions.GetTimeoutError) as err:
            raise RunStopped(f"{name} did not come back ({death_cause(err)}); raise "
                             f"ray.actor_restarts (-1: no limit)") from err
    raise RunStopped(f"{name} did not come back within {timeout_s:.0f} s")


def call_restarting(ray: Any, actor: Any, name: str, method: str, args: tuple,
                    deaths: ActorDeaths | None) -> Any:
    """`actor.method(*args)`, waited for; where the actor dies (and `deaths` says it may be
    restarted) the same call runs again on its restart. Without `deaths` an error raises."""
    for _ in range(MAX_CALL_FAILURES):
        try:
            return ray.get(getattr(actor, method).remote(*args))
        except ray.exceptions.RayActorError as err:
            if deaths is None:
                raise
            deaths.saw(name, err, f"{method} runs again on its restart")
            wait_restarted(ray, actor, name)
            error = err
    raise RunStopped(f"{name}: {method} failed {MAX_CALL_FAILURES} times in a row "
                     f"({death_cause(error)})")


def is_actor(err: Exception, actor: Any) -> bool:
    """Whether an actor error is about `actor` (a call that needed one of its results fails
    with the error of the actor that should have produced it)."""
    return getattr(err, "actor_id", None) == actor._actor_id.hex()


class RemoteService:
    """The LevelService actor behind `LevelService`'s interface: every call waits. A call that
    finds the service dead waits for its restart (which restores every logged commit), runs the
    `on_restart` hooks (the asynchronous schedule asks again for levels that died with it), and
    is sent again. State-changing calls carry a sequence number (`apply`), so that one the
    service had logged before it died is answered, not applied again."""

    def __init__(self, ray: Any, actor: Any, deaths: ActorDeaths):
        self._ray, self.actor, self._deaths = ray, actor, deaths
        self.seq = 0
        self.incarnation = 0  # restarts seen
        self.on_restart: list[Callable[[], None]] = []

    def __getattr__(self, name: str) -> Callable[..., Any]:
        if name.startswith("_"):
            raise AttributeError(name)
        if name in MUTATING:
            def numbered(*args: Any, **kwargs: Any) -> Any:
                self.seq += 1
                return self.call("apply", self.seq, name, *args, **kwargs)
            return numbered
        return lambda *args, **kwargs: self.call(name, *args, **kwargs)

    def call(self, method: str, *args: Any, **kwargs: Any) -> Any:
        error: Exception | None = None
        for _ in range(MAX_CALL_FAILURES):
            incarnation = self.incarnation
            try:
                return self._ray.get(getattr(self.actor, method).remote(*args, **kwargs))
            except self._ray.exceptions.RayActorError as err:
                if not is_actor(err, self.actor):
                    raise
                self.restarted(err, incarnation)
                error = err
        raise RunStopped(f"service: {method} failed {MAX_CALL_FAILURES} times in a row "
                         f"({death_cause(error)})")

    def restarted(self, err: Exception, incarnation: int) -> None:
        """Handle a death seen by something sent at `incarnation`: once per death, wait for
        the restart and run the hooks."""
        if incarnation != self.incarnation:
            return  # an echo of a death already handled
        self._deaths.saw("service", err, "it restarts from its snapshot and commit log")
        wait_restarted(self._ray, self.actor, "service")
        self.incarnation += 1
        for hook in self.on_restart:
            hook()


class Chaos:
    """`ray.chaos_*`: kill the run's restartable actors on a schedule (every N steps and/or
    every N seconds, the roles of `ray.chaos_roles` in turn), so that users can check their
    own cluster the way the tests check this one. Never after the last step."""

    def __init__(self, ray: Any, section: Any, actors: list[tuple[str, Any]],
                 stream: TextIO | None):
        roles = {r.strip() for r in section.chaos_roles.split(",")}
        self.ray, self.stream = ray, stream
        self.targets = [(name, actor) for name, actor in actors
                        if name.split("-")[0] in roles]
        self.every_steps, self.every_s = section.chaos_kill_every, section.chaos_kill_every_s
        self.kills = 0
        self.last_s = time.perf_counter()

    def after_step(self, done: int, last: bool) -> None:
        if last or not self.targets:
            return
        now = time.perf_counter()
        if self.every_steps and done % self.every_steps == 0:
            why = f"ray.chaos_kill_every={self.every_steps}"
        elif self.every_s and now - self.last_s >= self.every_s:
            why = f"ray.chaos_kill_every_s={self.every_s:g}"
        else:
            return
        name, actor = self.targets[self.kills % len(self.targets)]
        self.ray.kill(actor, no_restart=False)
        self.kills += 1
        self.last_s = now
        if self.stream is not None:
            self.stream.write(f"ray: chaos: killed {name} after step {done} ({why})\n")
            self.stream.flush()


__all__ = ["Chaos", "MAX_CALL_FAILURES", "ActorDeaths", "RemoteService", "call_restarting",
           "death_cause", "is_actor", "wait_restarted"]

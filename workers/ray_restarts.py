"""What a restart of each actor of a Ray run loses, the level service's numbered calls, and chaos
kills to check a cluster's restarts.

Every call to an actor goes through the run's `workers.actor_manager.ActorManager`, which waits
for a restart once per death and sends lost calls again. What a restart loses depends on the
actor:

    Explorer, Evaluator  nothing (their parameters come with each call): calls run again
    LevelService         nothing acknowledged: it replays its commit log on restart
                         (`workers.durable_service`); its state-changing calls are numbered
                         (`RemoteService`), so one it had logged before dying is not applied
                         twice
    Learner              not restarted: its death stops the run (resume from a checkpoint)
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any, TextIO

from workers.actor_manager import ActorDeaths, ActorManager
from workers.durable_service import MUTATING

SERVICE = "service"  # the level service's name in the run's ActorManager


class RemoteService:
    """The LevelService actor behind `LevelService`'s interface: every call waits. A call that
    finds the service dead waits for its restart (which restores every logged commit), runs the
    `on_restart` hooks (the asynchronous schedule asks again for levels that died with it), and
    is sent again (`ActorManager`). State-changing calls carry a sequence number (`apply`), so
    that one the service had logged before it died is answered, not applied again.

    `actors`: the run's ActorManager, or an ActorDeaths for a manager of the service alone."""

    def __init__(self, ray: Any, actor: Any, actors: ActorManager | ActorDeaths):
        self.actors = actors if isinstance(actors, ActorManager) else ActorManager(ray, actors)
        self.actor = actor
        self._member = self.actors.add(SERVICE, actor, restarts=True, then=(
            "it restarts from its snapshot and commit log"))
        self.seq = 0

    @property
    def incarnation(self) -> int:
        """Restarts of the service handled so far."""
        return self._member.incarnation

    @property
    def on_restart(self) -> list[Callable[[], None]]:
        return self._member.on_restart

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
        return self.actors.call(SERVICE, method, *args, **kwargs)


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


__all__ = ["SERVICE", "Chaos", "RemoteService"]

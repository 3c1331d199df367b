"""What a restart of each actor of a Ray run loses, the level service's numbered calls, and chaos
kills to check a cluster's restarts.

Every call to an actor goes through the run's `workers.ray.actor_manager.ActorManager`, which waits
for a restart once per death and sends lost calls again. What a restart loses depends on the
actor:

    Explorer, Evaluator  nothing (their parameters come with each call): calls run again
    LevelService         nothing acknowledged: it replays its commit log on restart
                         (`workers.ray.durable_service`); its state-changing calls are numbered
                         (`RemoteService`), so one it had logged before dying is not applied
                         twice
    Learner              not restarted as an actor: the run restarts from its newest intact
                         checkpoint, up to `ray.learner_restarts` times
                         (`workers.ray.learner_group.Restarts`), then stops
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any, TextIO

from workers.ray.actor_manager import ActorManager, Call
from workers.ray.durable_service import MUTATING

SERVICE = "service"  # the level service's name in the run's ActorManager


class RemoteService:
    """The LevelService actor behind `LevelService`'s interface: every call waits. A call that
    finds the service dead waits for its restart (which restores every logged commit), runs the
    `on_restart` hooks (the asynchronous schedule asks again for levels that died with it), and
    is sent again (`ActorManager`). State-changing calls carry a sequence number (`apply`), so
    that one the service had logged before it died is answered, not applied again.

    `actors`: the run's ActorManager."""

    def __init__(self, ray: Any, actor: Any, actors: ActorManager):
        self.actors = actors
        self.actor = actor
        self._member = self.actors.add(SERVICE, actor, restarts=True, then=(
            "it restarts from its snapshot and commit log"))
        self.seq = 0
        # Numbered calls sent and not yet answered, in number order: after a restart the
        # lost ones are sent again in that order, before anything else (the service applies
        # call n + 1 only after call n).
        self.unanswered: list[Call] = []
        self.by_ref: set[Call] = set()  # of them, those whose answer goes to another actor
        self.on_restart.append(self._send_lost_again)

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
            return lambda *args, **kwargs: self.get(self.send(name, *args, **kwargs))
        return lambda *args, **kwargs: self.call(name, *args, **kwargs)

    def call(self, method: str, *args: Any, **kwargs: Any) -> Any:
        return self.actors.call(SERVICE, method, *args, **kwargs)

    def send(self, method: str, *args: Any, by_ref: bool = False, **kwargs: Any) -> Call:
        """Send the state-changing call `method(*args, **kwargs)`, numbered, without waiting:
        its answer is awaited with `get` (or `settle`). `by_ref`: its answer goes by ref to
        another actor and is never fetched here; the caller `forget`s it once that actor's
        call succeeded (which proves it answered)."""
        self.seq += 1
        call = self._track(Call.of(SERVICE, "apply", self.seq, method, *args, **kwargs))
        if by_ref:
            self.by_ref.add(call)
        return call

    def forget(self, call: Call) -> None:
        """`call` (sent `by_ref`) was answered: stop tracking it."""
        self.by_ref.discard(call)
        if call in self.unanswered:
            self.unanswered.remove(call)

    def send_group(self, calls: list[tuple[str, tuple, dict]], values: tuple[Any, ...] = ()
                   ) -> Call:
        """A group commit (`DurableLevelService.apply_many`): the state-changing calls
        `calls` ([method, args, kwargs]; an argument `Slot(i)` stands for `values[i]`: the
        result of the service's call `values[i]`, levels it made, or levels an Explorer made,
        held by the driver), numbered, applied in order and made durable with one fsync; not
        waited for. After a restart the service's levels are asked for again before the group
        is sent again."""
        numbered = []
        for method, args, kwargs in calls:
            self.seq += 1
            numbered.append((self.seq, method, tuple(args), dict(kwargs)))
        made_here = tuple(c for c in values if isinstance(c, Call))
        return self._track(Call(SERVICE, "apply_many",
                                lambda: (numbered, *(c.ref if isinstance(c, Call) else c
                                                     for c in values)), after=made_here))

    def _track(self, call: Call) -> Call:
        self.actors.send(call)
        self.unanswered.append(call)
        return call

    def get(self, call: Call) -> Any:
        """The answer to a numbered call (sent again, with the lost ones before it, after a
        restart of the service)."""
        result = self.actors.get(call)
        if call in self.unanswered:
            self.unanswered.remove(call)
        return result

    def settle(self, block: bool = False) -> None:
        """Take the answers of the numbered calls that are answered (all of them, waiting,
        with `block`): an answer is the service's acknowledgement that the call is durable."""
        for call in list(self.unanswered):
            if call in self.by_ref:
                continue
            if not block:
                ready, _ = self.actors.ray.wait([call.ref], timeout=0)
                if not ready:
                    return
            self.get(call)

    def _send_lost_again(self) -> None:
        self.actors.send_lost_again(list(self.unanswered))


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

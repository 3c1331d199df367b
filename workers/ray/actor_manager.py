"""The calls a Ray run sends to its actors, and what happens when an actor or its node is lost.

Ray restarts a dead actor by running its constructor again (`max_restarts`); calls sent while it
restarts fail, and a call Ray retried would reuse its original arguments, so the driver never
lets Ray retry (`max_task_retries=0`). Every call goes through one `ActorManager` instead: it
knows which actor each call went to and which incarnation of that actor it reached, waits for a
restart once per death (however many calls the death took), and sends a lost call again with
arguments its caller rebuilds then (`Call.args`: the current policy, levels asked for again).
It plays the part RLlib's FaultTolerantActorManager plays for RLlib's env runners, and like it
keeps the calls in flight: a schedule `submit`s a call with a tag of its own (a batch, an
evaluation), asks how many are in flight to an actor (`in_flight`), and takes the finished ones
with `fetch_ready` as values or, for an optional call given up, errors (`Result`). A call lost on
the way is recovered and sent again inside `fetch_ready` (with the arguments its `args` give
then, after its `before_send` hook); the schedules keep no in-flight bookkeeping of their own and
write no retry of their own.

A call is lost when `ray.get` raises one of these (`is_lost`):

    RayActorError       the actor died (ActorDiedError) or is unreachable for now
                        (ActorUnavailableError, e.g. while it restarts)
    OutOfMemoryError    Ray's memory monitor killed the actor's process (not a RayActorError)
    NodeDiedError       the actor's node died or cannot be reached
    ObjectLostError     a result the call needed is gone with its node, or with its owner
                        (OwnerDiedError, ObjectReconstructionFailedError); not the subclasses
                        that mean a bug of the caller (a freed or deleted reference)

Anything else (an exception in the actor's own code, a timeout) raises as it is. The error names
the actor it is about where Ray knows it (`actor_id`, or the actor's id in the message, as in
the memory monitor's); else it is the actor the call went to. A call that took another actor's
result as an argument (`Call.after`: an Explorer's levels, made by the level service) fails
with that actor's error when that actor died first, so the loss is that actor's.

What a loss does depends on the actor (`Member.restarts`) and the call (`Call.optional`):

    restartable actor   the death is logged once (`ray: NAME died (CAUSE); THEN`) and counted
                        (`ActorDeaths`, `restarts` in `ray.json`; a lost result is logged
                        as `NAME lost a result` and not counted); the manager waits until the
                        actor answers again, runs its restart hooks, and the caller sends the
                        call again (`send`)
    actor not restarted the learner: RunStopped (the driver adds the resume command)
    failure budget      a call lost `MAX_CALL_FAILURES` times in a row: RunStopped, or for an
                        optional call (an evaluation) given up while training goes on
    not back            an actor that does not answer within `RESTART_TIMEOUT_S`, or that Ray
                        gave up: RunStopped, or for an optional call the actor is given up
                        (`Member.gone`) and so is all its later work
"""

from __future__ import annotations

import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, TextIO

from workers.driver import RunStopped

MAX_CALL_FAILURES = 5  # one call lost this often in a row stops the run (or is given up)
RESTART_TIMEOUT_S = 300.0  # an actor not back after this long stops the run
RESULT_WAIT_S = 30.0  # for a result asked of an actor that then died to report its fate


def lost_errors(ray: Any) -> tuple[type[BaseException], ...]:
    """The error classes of `ray` that can mean a call was lost with its actor or node."""
    e = ray.exceptions
    return (e.RayActorError, e.OutOfMemoryError, e.NodeDiedError, e.ObjectLostError)


def is_lost(ray: Any, err: BaseException) -> bool:
    """Whether `err` means a call's work was lost with an actor or a node (the module doc)."""
    e = ray.exceptions
    if isinstance(err, e.ReferenceCountingAssertionError | e.ObjectFreedError):
        return False  # a reference used after it was released: a bug, not a loss
    return isinstance(err, lost_errors(ray))


def death_cause(err: BaseException) -> str:
    """The first line of an error: what Ray says killed the actor."""
    text = str(err).strip()
    return text.splitlines()[0] if text else type(err).__name__


class ActorDeaths:
    """Deaths of the restartable actors: counted by name and logged with their cause on the
    run's stream (None: counted only)."""

    def __init__(self, stream: TextIO | None):
        self.stream, self.count = stream, Counter()

    def saw(self, name: str, err: BaseException, then: str, *, died: bool = True) -> None:
        if died:
            self.count[name] += 1
        self.say(f"{name} {'died' if died else 'lost a result'} ({death_cause(err)}); {then}")

    def say(self, text: str) -> None:
        if self.stream is not None:
            self.stream.write(f"ray: {text}\n")
            self.stream.flush()


@dataclass
class Member:
    """One actor of the group."""

    name: str
    handle: Any
    restarts: bool  # whether Ray restarts it (and the run waits for that)
    then: str = ""  # what its restart restores, logged with its death (else the call's `then`)
    incarnation: int = 0  # deaths handled so far
    gone: bool = False  # given up: it did not come back, and only optional work went to it
    on_restart: list[Callable[[], None]] = field(default_factory=list)

    def actor_id(self) -> str | None:
        actor_id = getattr(self.handle, "_actor_id", None)
        return None if actor_id is None else actor_id.hex()


@dataclass(eq=False)
class Call:
    """One piece of work for an actor: how to (re)build its arguments, and its fate so far."""

    actor: str  # the member it goes to
    method: str
    args: Callable[[], tuple[Any, ...]]  # called at every sending: what to send now
    then: str = ""  # what happens to it after its actor's death (the death's log line)
    optional: bool = False  # the run goes on without it (given up rather than stopping)
    after: tuple[Call, ...] = ()  # calls whose results are among its arguments
    kwargs: dict[str, Any] = field(default_factory=dict)
    ref: Any = None  # of the newest sending
    incarnation: int = 0  # of its actor at the newest sending
    failures: int = 0  # sendings lost in a row
    # Runs just before every sending (the caller's record of what it sends: a batch's policy
    # version goes with the parameters `args` gives).
    before_send: Callable[[], None] | None = None
    sendings: int = 0  # how often it was sent

    @classmethod
    def of(cls, actor: str, method: str, *args: Any, then: str = "", **kwargs: Any) -> Call:
        """A call whose arguments are the same at every sending."""
        return cls(actor, method, lambda: args, then=then, kwargs=kwargs)


def names_actor(err: BaseException, actor_id: str) -> bool:
    """Whether Ray's error `err` is about the actor with this id (hex): its `actor_id` where
    Ray sets one, else the id in its message."""
    named = getattr(err, "actor_id", None)
    return named == actor_id if named is not None else actor_id in str(err)


@dataclass
class Result:
    """A call taken back by `ActorManager.fetch_ready`: its value, or the error that ended it
    (an optional call given up after its actor's loss)."""

    call: Call
    tag: Any
    value: Any = None
    error: BaseException | None = None


class ActorManager:
    """Calls to the actors of one run (module doc). Members are added by the clients that call
    them; the first `add` of a name decides whether it restarts."""

    def __init__(self, ray: Any, deaths: ActorDeaths | None = None,
                 max_failures: int = MAX_CALL_FAILURES):
        self.ray = ray
        self.deaths = ActorDeaths(None) if deaths is None else deaths
        self.max_failures = max_failures
        self.members: dict[str, Member] = {}
        self.flying: dict[Call, Any] = {}  # submitted and not taken back: call -> tag
        self.resent: Counter[str] = Counter()  # calls sent again after a loss, by actor

    def add(self, name: str, handle: Any, *, restarts: bool, then: str = "") -> Member:
        """The member `name`, added with these settings where it is new."""
        member = self.members.get(name)
        if member is None:
            member = self.members[name] = Member(name, handle, restarts, then)
        elif member.handle is not handle:
            raise ValueError(f"two actors are called {name!r}")
        return member

    def incarnation(self, name: str) -> int:
        return self.members[name].incarnation

    def available(self, name: str) -> bool:
        """Whether `name` is in the group and not given up."""
        return name in self.members and not self.members[name].gone

    # --- sending and waiting ---------------------------------------------------------------

    def send(self, call: Call) -> Call:
        """Send `call` (again), with its arguments as `call.args()` gives them now. A result it
        needs (`call.after`) that was lost with a restart of its actor is asked for again
        first."""
        for needed in call.after:
            if self.lost_with_restart(needed):
                self.send(needed)
        member = self.members[call.actor]
        if call.before_send is not None:
            call.before_send()
        call.incarnation = member.incarnation
        call.ref = getattr(member.handle, call.method).remote(*call.args(), **call.kwargs)
        call.sendings += 1
        return call

    # --- calls in flight -------------------------------------------------------------------

    def submit(self, call: Call, tag: Any = None) -> Call:
        """Send `call` and keep it in flight, with the caller's `tag`, until `fetch_ready`
        hands it back."""
        self.send(call)
        self.flying[call] = tag
        return call

    def in_flight(self, actors: Any = None) -> list[Call]:
        """The calls in flight (to the actors named in `actors`; default: all), oldest
        first."""
        return [c for c in self.flying if actors is None or c.actor in actors]

    def has_room(self, actor: str, limit: int) -> bool:
        """Whether `actor` has fewer than `limit` calls in flight (a cap per actor)."""
        return sum(c.actor == actor for c in self.flying) < limit

    def tags(self, actors: Any = None) -> list[Any]:
        """The tags of the calls in flight (to `actors`), oldest first."""
        return [self.flying[c] for c in self.in_flight(actors)]

    def fetch_ready(self, actors: Any = None, *, block: bool = False) -> list[Result]:
        """Take back the calls in flight (to `actors`) that are done, without waiting or, with
        `block`, after waiting for the first of them: the ones that block waited for first,
        then in the order they were submitted. A call lost with its actor is recovered
        (`recover`) and sent again, and stays in flight; an optional call given up comes back
        with its error; an error that is no loss raises."""
        calls = self.in_flight(actors)
        if not calls:
            return []
        by_ref = {c.ref: c for c in calls}
        first: list[Any] = []
        if block:
            first, _ = self.ray.wait(list(by_ref), num_returns=1)
        ready, _ = self.ray.wait(list(by_ref), num_returns=len(by_ref), timeout=0)
        ready = [*first, *(ref for ref in ready if ref not in first)]
        try:  # one fetch for all of them; where one failed, each on its own
            values: list[Any] | None = self.ray.get(ready)
        except Exception:  # noqa: BLE001 - each is fetched again below, its error handled
            values = None
        out = []
        for i, ref in enumerate(ready):
            call = by_ref[ref]
            if values is not None:
                call.failures = 0
                out.append(Result(call, self.flying.pop(call), values[i]))
                continue
            try:
                value = self.ray.get(ref)
            except Exception as err:  # noqa: BLE001 - `recover` raises what is no loss
                if self.recover(call, err):
                    if call.ref is ref:  # not sent again meanwhile (by a restart hook)
                        self.send(call)
                    self.resent[call.actor] += 1
                    continue
                out.append(Result(call, self.flying.pop(call), error=err))
                continue
            call.failures = 0
            out.append(Result(call, self.flying.pop(call), value))
        return out

    def get(self, call: Call) -> Any:
        """The result of a sent `call`, waited for; sent again after each loss."""
        while True:
            try:
                return self.ray.get(call.ref)
            except Exception as err:
                lost = call.ref
                if not self.recover(call, err):
                    raise RunStopped(f"{call.actor}: {call.method} was given up "
                                     f"({death_cause(err)})") from err
                if call.ref is lost:  # not sent again meanwhile (by a restart hook)
                    self.send(call)

    def call(self, actor: str, method: str, *args: Any, then: str = "", **kwargs: Any) -> Any:
        """`actor.method(*args, **kwargs)`, waited for; after a restart of `actor` the same call
        runs again."""
        return self.get(self.send(Call.of(actor, method, *args, then=then, **kwargs)))

    def send_lost_again(self, calls: list[Call]) -> None:
        """Send again, in the order given, each of `calls` whose result died with a restart of
        its actor (a restart hook: before anything else reaches the restarted actor)."""
        for call in calls:
            if self.lost_with_restart(call):
                self.send(call)

    def lost_with_restart(self, call: Call) -> bool:
        """Whether `call` was sent before its actor's newest restart and its result died with
        the old process (waited for up to `RESULT_WAIT_S`: Ray reports that late). A result
        made before the death is kept (the call counts as sent to the new incarnation)."""
        member = self.members[call.actor]
        if call.incarnation == member.incarnation:
            return False
        self.ray.wait([call.ref], timeout=RESULT_WAIT_S)
        try:
            self.ray.get(call.ref, timeout=0)
        except self.ray.exceptions.RayError:
            return True
        call.incarnation = member.incarnation
        return False

    # --- losses ----------------------------------------------------------------------------

    def culprit(self, err: BaseException, call: Call) -> Member:
        """The member `err` is about: the one it names, else the one `call` went to."""
        for member in self.members.values():
            mine = member.actor_id()
            if mine is not None and names_actor(err, mine):
                return member
        return self.members[call.actor]

    def recover(self, call: Call, err: BaseException) -> bool:
        """Handle the loss of `call` with `err` (module doc). True: send it again (`send`);
        False: an optional call given up. Raises `err` where it is no loss, RunStopped where
        the run cannot go on without the call."""
        if not is_lost(self.ray, err):
            raise err
        member = self.culprit(err, call)
        if not member.restarts:
            raise RunStopped(f"{member.name} died ({death_cause(err)}); it is not "
                             f"restarted", lost=member.name) from err
        call.failures += 1
        spent = call.failures >= self.max_failures  # the call's failure budget
        # The incarnation the call met: of its own actor, or of the one whose result it took.
        met = next((c.incarnation for c in (call, *call.after) if c.actor == member.name),
                   member.incarnation)
        if met == member.incarnation and not member.gone:  # a new death, not its echo
            then = member.then or (f"{call.method} is given up" if spent else call.then)
            died = not isinstance(err, self.ray.exceptions.ObjectLostError)
            self.deaths.saw(member.name, err, then, died=died)
            if not spent or call.optional:  # someone will call it again: wait for it
                try:
                    self.wait_back(member.name)
                except RunStopped as stopped:
                    if not call.optional:
                        raise
                    member.gone = True
                    self.deaths.say(f"{member.name} is given up ({stopped}); the run goes on "
                                    f"without it")
                else:
                    member.incarnation += 1
                    for hook in member.on_restart:
                        hook()
        if call.optional and (spent or member.gone):
            return False
        if member.gone:
            raise RunStopped(f"{member.name} is gone; {call.method} cannot run") from err
        if spent:
            raise RunStopped(f"{call.actor}: {call.method} was lost {self.max_failures} times "
                             f"in a row ({death_cause(err)})") from err
        return True

    def wait_back(self, name: str, timeout_s: float = RESTART_TIMEOUT_S) -> None:
        """Wait until `name` answers again: calls sent while it restarts fail rather than wait
        for it. RunStopped where Ray gave it up or it is not back within `timeout_s`."""
        ray, handle = self.ray, self.members[name].handle
        deadline = time.perf_counter() + timeout_s
        while True:
            try:
                ray.get(handle.ready.remote(), timeout=max(deadline - time.perf_counter(), 0.1))
                return
            except (ray.exceptions.ActorDiedError, ray.exceptions.GetTimeoutError) as err:
                raise RunStopped(f"{name} did not come back ({death_cause(err)}); raise "
                                 f"ray.actor_restarts (-1: no limit)") from err
            except Exception as err:
                if not is_lost(ray, err):
                    raise
                # Still restarting (unavailable), or its new process was lost too: try again.
                if time.perf_counter() > deadline:
                    break
                time.sleep(0.2)
        raise RunStopped(f"{name} did not come back within {timeout_s:.0f} s")


__all__ = ["MAX_CALL_FAILURES", "ActorDeaths", "ActorManager", "Call", "Member", "Result",
           "death_cause", "is_lost", "lost_errors"]

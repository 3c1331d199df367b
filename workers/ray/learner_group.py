"""A learner group on Ray (`ray.learners: N`): N learner actors that run one update together.

    driver                      one placement group of N bundles (a CPU, or the learner's GPUs,
                                each), SPREAD over CPU nodes, PACKed on GPU nodes
      learner 0  (bundle 0)     hosts JAX's coordinator at HOST:PORT of its node (the driver
                                picks the port with a task in bundle 0 and hands it to all)
      learner i  (bundle i)     joins it (`ued.learners.distributed.join`) in its constructor,
                                pinned to its share of its node's cores where asked (`share_cores`)

Every member holds the same train state and receives the same calls with the same arguments
(`init`, `train`, `train_scored`, `set_train_state`): each puts only its share of the envs on
its devices, and the update is one jitted program over the devices of all members, its
gradients reduced by XLA's collectives (ued/learners/distributed.py). The results are whole
in every member; the driver reads them from learner 0 alone (metrics, scores, parameters, the
train state for checkpoints), which also scores levels where the run has no Explorers.

`LearnerGroup` stands where the one learner actor's handle stood: `group.METHOD.remote(...)`
sends a call to every member that must run it and returns learner 0's ref. A member's death
ends the others within JAX's heartbeat timeout (no collective waits for ever); learner 0's
ref then fails and the run stops as it does when its one learner dies.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any, TextIO

# Calls every member runs together (they run the update, or change the state it starts from).
COLLECTIVE = frozenset({"init", "train", "train_scored", "set_train_state"})


class _Method:
    def __init__(self, group: LearnerGroup, name: str):
        self.group, self.name = group, name

    def remote(self, *args: Any, **kwargs: Any) -> Any:
        members = self.group.members if self.name in COLLECTIVE else self.group.members[:1]
        refs = [getattr(m, self.name).remote(*args, **kwargs) for m in members]
        # Only the newest call of the others is held: their results equal learner 0's.
        self.group.others = refs[1:] or self.group.others
        return refs[0]


class LearnerGroup:
    """N learner actors behind the handle of one (module doc)."""

    def __init__(self, members: list[Any], placement_group: Any, coordinator: str):
        self.members = members
        self.placement_group = placement_group
        self.coordinator = coordinator
        self.others: list[Any] = []

    @property
    def _actor_id(self) -> Any:  # the ActorManager names a death by it: learner 0's
        return self.members[0]._actor_id

    def __getattr__(self, name: str) -> _Method:
        if name.startswith("_"):
            raise AttributeError(name)
        return _Method(self, name)

    def nodes(self, ray: Any) -> list[str]:
        """The id of each member's node, in member order."""
        return ray.get([member.node.remote() for member in self.members])

    def kill(self, ray: Any) -> None:
        """Kill every member and release their placement group."""
        for member in self.members:
            ray.kill(member)
        ray.util.remove_placement_group(self.placement_group)


class Restarts:
    """A run's restarts after a stop that starting its actors again cures (its lost learner or
    learner-group member: the group stops as a whole; an actor lost while the actors
    started), up to `limit` (`ray.learner_restarts`), from its newest intact checkpoint, or
    from step 0 where it has none: each is logged with what died and the steps it loses
    (done since that checkpoint, played again) and counted in `ray.json` (`learner_restarts`,
    `steps_lost`)."""

    def __init__(self, limit: int):
        self.limit, self.done, self.steps_lost = limit, 0, 0

    def left(self) -> bool:
        return self.done < self.limit

    def fields(self) -> dict[str, int]:
        return {"learner_restarts": self.done, "steps_lost": self.steps_lost}

    def restart(self, reason: str, latest: int | None, session: tuple[int, int] | None,
                max_updates: int | None, stream: TextIO) -> int | None:
        """Count a restart after `reason` (what died) from checkpoint `latest` (None: from
        step 0) of a session that ran from step `session[0]` to `session[1]` (None: it stopped
        before its first step) in a call that asked for `max_updates` more; return the steps
        the next session runs (None: to the end)."""
        back = 0 if latest is None else latest
        lost = 0 if session is None else max(session[1] - back, 0)
        self.done += 1
        self.steps_lost += lost
        where = (f"continues from its checkpoint at step {latest}" if latest is not None else
                 "has no checkpoint yet: it starts again from step 0")
        stream.write(f"ray: {reason}: restart {self.done} of {self.limit} "
                     f"(ray.learner_restarts): the run {where}; {lost} steps lost "
                     f"({self.steps_lost} in all)\n")
        stream.flush()
        if max_updates is None or session is None:
            return max_updates
        return session[0] + max_updates - back


def coordinator_address(ray: Any, placement_group: Any) -> str:
    """HOST:PORT free on the node of the group's bundle 0 (where learner 0 will run)."""
    from ray.util.scheduling_strategies import PlacementGroupSchedulingStrategy

    def pick() -> str:
        import ray as ray_here

        from ued.learners.distributed import free_address

        return free_address(ray_here.util.get_node_ip_address())

    strategy = PlacementGroupSchedulingStrategy(placement_group, placement_group_bundle_index=0)
    return ray.get(ray.remote(pick).options(num_cpus=0, scheduling_strategy=strategy).remote())


def start_group(ray: Any, count: int, gpus: float,
                spawn: Callable[[int, tuple[str, int, int, int, int], Any], Any],
                timeout_s: float) -> LearnerGroup:
    """`count` learner actors in one placement group; `spawn(i, (coordinator, count, i,
    rank on its node, members on its node), scheduling_strategy)` starts member i. The group
    waits at most `timeout_s` to be placed (the cluster may hold enough in all while other
    jobs reserve it), then fails in one line naming the resource it lacks."""
    from ray.util.placement_group import placement_group
    from ray.util.scheduling_strategies import PlacementGroupSchedulingStrategy

    from ued.config import ConfigError

    resource, each = ("GPU", gpus) if gpus else ("CPU", 1.0)
    group = placement_group([{resource: each} for _ in range(count)],
                            strategy="PACK" if gpus else "SPREAD")
    t0 = time.monotonic()
    placed, _ = ray.wait([group.ready()], timeout=timeout_s)
    if not placed:
        ray.util.remove_placement_group(group)
        free = ray.available_resources().get(resource, 0)
        total = ray.cluster_resources().get(resource, 0)
        raise ConfigError(f"ray.placement_timeout_s: after {time.monotonic() - t0:.0f} s the "
                          f"learner group ({count} learners x {each:g} {resource}) is not "
                          f"placed: the cluster has {free:g} {resource} free of {total:g}; "
                          f"add nodes with {resource}, or ask for less (ray.learners, "
                          f"ray.learner_gpus)")
    coordinator = coordinator_address(ray, group)
    # Members on one node may split its cores (`ray.learner_share_cores`: each pins itself to
    # its share, `distributed.share_cores`), so they need their rank among the node's members.
    where = ray.util.placement_group_table(group).get("bundles_to_node_id", {})
    nodes = [where.get(i, where.get(str(i), i)) for i in range(count)]
    members = [spawn(i, (coordinator, count, i, nodes[:i].count(node), nodes.count(node)),
                     PlacementGroupSchedulingStrategy(group, placement_group_bundle_index=i))
               for i, node in enumerate(nodes)]
    return LearnerGroup(members, group, coordinator)


__all__ = ["COLLECTIVE", "LearnerGroup", "Restarts", "coordinator_address", "start_group"]

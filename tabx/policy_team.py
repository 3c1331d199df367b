"""A team played by a trained policy in an episode of `tabx.rollout`.

The simulator trains and loads no policy (its layer imports no learner), yet its episodes can
play one: a layer above hands in a `PolicyTeam` (`ued.evaluate.policy_team`): a traceable action
function with its parameters and recurrent state, the unit slots it drives, and the EnvConfig it
plays (a policy's observation size is fixed). The rollout compiles the policy's step into its
own episode scan, beside the scripted controllers of the other team:

    team = ued.evaluate.load_policy_team("runs/mappo_crossfire-...", C.ENEMY, greedy=False)
    hidden = team.initial_hidden()
    actions, hidden = team.act(team.params, obs, mask, hidden, key)    # inside jit
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import jax

from tabx.params import EnvConfig

# act(params, obs (N, obs_size), mask (N, num_actions), hidden, key) -> (actions (end - first,)
# int32 of the team's slots, new hidden); traceable, for one env (no batch axis).
PolicyAct = Callable[[Any, jax.Array, jax.Array, Any, jax.Array], tuple[jax.Array, Any]]


@dataclass(frozen=True)
class PolicyTeam:
    """A trained policy seated on one team of a rollout.

    `act` and `initial_hidden` decide what the compiled episode computes: give the same objects
    for the same network (and seat) so that repeated rollouts reuse one compilation; `params`
    is data (a pytree of arrays), passed to the program as an argument."""

    label: str  # how the outcome names it, e.g. "runs/x (mappo, update 40)"
    title: str  # a short name for a GIF's title
    env_config: EnvConfig  # the only EnvConfig it plays: the scenario is padded into it
    slots: tuple[int, int]  # (first, end) unit slots it drives
    act: PolicyAct
    initial_hidden: Callable[[], Any]  # its recurrent state at the start of an episode
    params: Any = field(default=None, compare=False, repr=False)
    matmul_dtype: str = "float32"  # its networks' matmul inputs (tabx.jit_options.learner_jit)
    scenario: str | None = None  # its first training scenario (the rollout's default)
    opponent: str | None = None  # its training opponent, a controller (the other team's default)
    profile: str | None = None  # its behaviour profile (the rollout's default)

    def __str__(self) -> str:
        return self.label


__all__ = ["PolicyAct", "PolicyTeam"]

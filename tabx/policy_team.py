"""A team played by a trained policy in an episode of `tabx.rollout`.

The simulator trains and loads no policy (its layer imports no learner), yet its episodes can
play one: a layer above hands in a `PolicyTeam` (`ued.evaluate.policy_team`): the policy as
the episode player takes it (`tabx.episodes.Policy`: a traceable action function with its
recurrent state and the unit slots it drives), its parameters, and the EnvConfig it plays (a
policy's observation size is fixed). The rollout compiles the policy's step into its own
episode, beside the scripted controllers of the other team:

    team = ued.evaluate.load_policy_team("runs/mappo_crossfire-...", C.ENEMY, greedy=False)
    hidden = team.policy.initial_hidden(num_envs)
    actions, hidden = team.policy.act(team.params, key, obs, mask, states, levels, hidden)
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from tabx.episodes import Policy
from tabx.params import EnvConfig


@dataclass(frozen=True)
class PolicyTeam:
    """A trained policy seated on one team of a rollout.

    `policy` decides what the compiled episode computes: give the same object for the same
    network (and seat) so that repeated rollouts reuse one compilation; `params` is data (a
    pytree of arrays), passed to the program as an argument."""

    label: str  # how the outcome names it, e.g. "runs/x (mappo, update 40)"
    title: str  # a short name for a GIF's title
    env_config: EnvConfig  # the only EnvConfig it plays: the scenario is padded into it
    policy: Policy
    params: Any = field(default=None, compare=False, repr=False)
    matmul_dtype: str = "float32"  # its networks' matmul inputs (tabx.jit_options.learner_jit)
    scenario: str | None = None  # its first training scenario (the rollout's default)
    opponent: str | None = None  # its training opponent, a controller (the other team's default)
    profile: str | None = None  # its behaviour profile (the rollout's default)

    @property
    def slots(self) -> tuple[int, int]:
        """(first, end) unit slots it drives."""
        return self.policy.slots

    def __str__(self) -> str:
        return self.label


__all__ = ["PolicyTeam"]

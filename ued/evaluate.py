"""`tabx eval`: play trained policies against the heuristic, random, idle or each other.

Each team is played by a *side*: a trained policy (a run folder: its config and newest
checkpoint) or a controller (`heuristic[:TIER]`, `random`, `idle`). Episodes run in parallel
through the episode player (`tabx.episodes.play`), one env per episode, for the episode limit
of the policies' EnvConfig (a finished episode is frozen, so the scan simply runs to the
limit). Policies act with their recurrent state carried over the episode, sampling from the
masked policy (or its argmax with `greedy`).

A policy only plays levels of the EnvConfig it was trained on (its observation size is fixed):
the scenario is padded into that config, and two policies must share one. Observations are
ego-centric, so a policy plays either team: one trained as the allies takes the enemy slots
(the team swap of `tabx.marl`'s `team="enemy"`) when that team has as many slots as it has
agents. Tiers named by a controller are written into the level (`with_tiers`); a bare
`heuristic` plays the level's own heuristic settings. The compiled program depends only on
the policies' learners, which slots they take, the controllers' kinds and the episode count,
so a table of many pairings (`ued.payoff`) compiles once per combination of learners.

Results per team: win rate with a 95 % Wilson interval (exactly one team wins an episode: a
time-out goes to the higher health ratio, ties to the enemy), mean undiscounted return and
mean episode length with 95 % normal intervals.

Zero-shot evaluation on a whole suite of held-out scenarios and opponents (`tabx eval RUN_DIR
--suite NAME`) is `workers.roles.evaluator.Evaluator` on `ued.suites` files (docs/evaluation.md); it
shares `wilson` and `mean_ci` with this module.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from tabx import constants as C
from tabx.controllers import Controller, with_tiers
from tabx.env import TabxEnv
from tabx.episodes import EVAL_KEYS, Policy, sample
from tabx.episodes import play as play_episodes
from tabx.intervals import mean_ci, wilson
from tabx.jit_options import learner_jit
from tabx.params import EnvConfig, EnvParams, repeat_level
from tabx.policy_team import PolicyTeam
from ued.config import TEAMS, ConfigError
from ued.learners.ppo import PPOLearner, masked_logits
from ued.run_folder import TrainedPolicy, load_policy

TEAM_NAMES = TEAMS  # index = team code (C.ALLY, C.ENEMY)

Side = TrainedPolicy | Controller


def parse_side(text: str) -> Side:
    """A run folder (it holds a config.yaml) or a controller spec."""
    path = Path(text)
    if path.is_dir():
        return load_policy(path)
    try:
        return Controller.parse_scripted(text, "a side (give a run folder or a controller)")
    except ValueError as err:
        raise ConfigError(f"{text!r} is neither a run folder nor a controller ({err})") from None


@dataclass
class EvalResult:
    episodes: int
    won: np.ndarray  # (K, 2) bool
    returns: np.ndarray  # (K, 2) float
    lengths: np.ndarray  # (K,) int
    states: Any = None  # EnvState of episode 0 with a time axis (for --gif)
    infos: Any = None

    def win_rate(self, team: int) -> tuple[float, float, float]:
        return wilson(int(self.won[:, team].sum()), self.episodes)

    def mean_return(self, team: int) -> tuple[float, float]:
        return mean_ci(self.returns[:, team])

    def mean_length(self) -> tuple[float, float]:
        return mean_ci(self.lengths.astype(np.float64))


def team_slots(env_config: EnvConfig, team: int) -> tuple[int, int]:
    """(first, end) unit slots of a team: the allies first, then the enemies."""
    if team == C.ALLY:
        return 0, env_config.max_allies
    return env_config.max_allies, env_config.num_units


def seat(policy: TrainedPolicy, team: int, env_config: EnvConfig) -> tuple[int, int]:
    """The slots `policy` takes when it plays `team`: its own team's, or the other team's
    (the team swap) if that has as many slots as the policy has agents; ConfigError if not."""
    if policy.learner.env_config != env_config:
        raise ConfigError(f"{policy.run_dir} was trained with {policy.learner.env_config}, "
                          f"this evaluation needs {env_config}")
    first, end = team_slots(env_config, team)
    if end - first != policy.learner.num_agents:
        agents, slots = policy.learner.num_agents, end - first
        raise ConfigError(f"{policy.run_dir} was trained as the {TEAM_NAMES[policy.team]} "
                          f"team ({agents} agent{'s' * (agents != 1)}); the "
                          f"{TEAM_NAMES[team]} team has {slots} unit slot{'s' * (slots != 1)}, "
                          f"so it cannot play that team")
    return first, end


@functools.lru_cache(maxsize=64)
def learner_policy(learner: PPOLearner, slots: tuple[int, int], greedy: bool = False) -> Policy:
    """The policy of `learner`'s networks on unit `slots` as the episode player takes it
    (`tabx.episodes.Policy`): it samples from the masked policy (`greedy`: its argmax) with its
    recurrent state carried over the episode. One object per learner (process-cached), seat
    and mode, so that programs of runs of one config share their compilation."""
    take = slice(*slots)

    def act(params, key, obs, mask, states, levels, hidden):
        x = learner.agent_inputs(obs[:, take])
        hidden, logits = learner.policy_step(params, x, hidden)
        logits = masked_logits(logits, mask[:, take])
        if greedy:
            return jnp.argmax(logits, -1).astype(jnp.int32), hidden
        return sample(key, logits), hidden

    return Policy(act, learner.initial_hidden, slots)


def policy_team(policy: TrainedPolicy, team: int, greedy: bool = False) -> PolicyTeam:
    """`policy` seated on `team` (its own, or the other through the team swap: `seat`) for
    `tabx rollout` (`tabx.policy_team`): it acts as in `play`."""
    env_config = policy.learner.env_config
    slots = seat(policy, team, env_config)
    return PolicyTeam(label=str(policy), title=f"{policy.run_dir.name} ({policy.config.algorithm})",
                      env_config=env_config, policy=learner_policy(policy.learner, slots, greedy),
                      params=policy.params, matmul_dtype=policy.learner.ppo.matmul_dtype,
                      scenario=policy.config.env.scenario[0],
                      opponent=policy.config.env.opponent, profile=policy.config.env.profile)


def load_policy_team(run_dir: str, team: int, greedy: bool = False) -> PolicyTeam:
    """The newest checkpoint of `run_dir` seated on `team` (`tabx rollout --ally RUN_DIR`).
    ConfigError (a CheckpointError for a damaged checkpoint) naming the folder when it
    cannot."""
    return policy_team(load_policy(run_dir), team, greedy)


def play(env_config: EnvConfig, level: EnvParams, ally: Side, enemy: Side, episodes: int,
         seed: int = 0, greedy: bool = False, record: bool = False) -> EvalResult:
    """Play `episodes` episodes of one level (EnvParams without a batch axis). A policy may
    play either team (`seat`)."""
    sides = (ally, enemy)
    seats = tuple(seat(s, team, env_config) if isinstance(s, TrainedPolicy) else None
                  for team, s in enumerate(sides))
    controllers = tuple(Controller("external") if isinstance(s, TrainedPolicy) else s
                        for s in sides)
    level = with_tiers(level, controllers)
    params = [s.params if isinstance(s, TrainedPolicy) else None for s in sides]
    levels = jax.tree.map(jnp.asarray, repeat_level(level, episodes))
    # The program sees the learners and the controllers' kinds; tiers are data in the level.
    learners = tuple(s.learner if isinstance(s, TrainedPolicy) else None for s in sides)
    kinds = tuple(Controller(c.kind) for c in controllers)
    run = _play_program(env_config, learners, seats, kinds, greedy, record)
    won, returns, lengths, trace = jax.device_get(run(params, levels, jax.random.key(seed)))
    states, infos = trace if record else (None, None)
    return EvalResult(episodes, np.asarray(won), np.asarray(returns), np.asarray(lengths),
                      states, infos)


@functools.lru_cache(maxsize=32)
def _play_program(env_config: EnvConfig, learners: tuple, seats: tuple, controllers: tuple,
                  greedy: bool, record: bool) -> Any:
    """The compiled episodes of `play` for these static settings (`learners`: per team the
    (process-cached) learner of its policy or None; `seats`: its slots); one compilation per
    episode count."""
    env = TabxEnv(env_config)
    policies = tuple(None if learner is None else learner_policy(learner, slots, greedy)
                     for learner, slots in zip(learners, seats, strict=True))
    # Compiled for the networks' matmul dtype (bfloat16 if either policy multiplies in it).
    dtypes = {learner.ppo.matmul_dtype for learner in learners if learner is not None}
    matmul_dtype = "bfloat16" if "bfloat16" in dtypes else "float32"
    # Episode 0's states and infos, per step (`--gif`).
    first = (lambda states, info, levels: jax.tree.map(lambda x: x[0], (states, info))
             ) if record else None

    @functools.partial(learner_jit, matmul_dtype=matmul_dtype)
    def run(params, levels, key):
        out = play_episodes(env, levels, key, env_config.max_steps, controllers, policies,
                            tuple(params), keys=EVAL_KEYS, record=first)
        return out.states.won, out.returns, out.length, out.record

    return run


def describe(side: Side) -> str:
    return str(side)


def format_result(result: EvalResult, sides: tuple[Side, Side], scenario: str,
                  greedy: bool, profile: str | None = None) -> str:
    lines = [f"scenario {scenario}: {result.episodes} episodes, "
             f"{'greedy' if greedy else 'sampled'} policies"
             + (f", profile {profile}" if profile else "")]
    for team, side in enumerate(sides):
        rate, low, high = result.win_rate(team)
        ret, ret_ci = result.mean_return(team)
        lines.append(f"  {TEAM_NAMES[team]:5s} {describe(side)}")
        lines.append(f"        win rate {rate:.3f} [{low:.3f}, {high:.3f}]   "
                     f"return {ret:+.3f} ± {ret_ci:.3f}")
    length, length_ci = result.mean_length()
    lines.append(f"  episode length {length:.1f} ± {length_ci:.1f} steps "
                 f"(95 % intervals: Wilson for rates, normal for means)")
    return "\n".join(lines)


__all__ = ["TEAM_NAMES", "EvalResult", "Side", "TrainedPolicy", "format_result",
           "learner_policy", "load_policy", "load_policy_team", "mean_ci", "parse_side", "play",
           "policy_team", "seat", "team_slots", "wilson"]

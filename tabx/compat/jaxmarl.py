"""`TabxJaxMARLEnv`: the TABX battle as a `jaxmarl.environments.MultiAgentEnv`.

It *is* a JaxMARL environment (a subclass, with JaxMARL's own `Box` / `Discrete` spaces), shaped
like JaxMARL's SMAX with a scripted enemy (`HeuristicEnemySMAX`), so SMAX code runs on it
unmodified:

- `reset(key) -> (obs, state)`, `step_env` (one step, no reset) and JaxMARL's own `step`, which
  resets a finished episode with a fresh `reset` (new randomised start, new sampled level);
- `obs[agent]` (ego-centric, `obs_size` long) and `obs["world_state"]` (`state_size` long), as
  SMAX names them; `get_obs(state)`, `get_world_state(state)`, `get_avail_actions(state)`;
- `num_allies` (the learner's agents), `num_enemies` (the other team's slots), `state_size`;
- per-agent rewards (the team's) and per-agent `infos` (each of shape `(num_agents,)`), so
  `SMAXLogWrapper(env)` works without `replace_info=True` and the baseline scripts' reshape of
  `traj_batch.info` to `(steps, envs, agents)` holds;
- `name` contains "smax", the hook by which JaxMARL's `CTRolloutManager` (IQL / VDN / QMIX)
  takes `obs["world_state"]` as the global state, the first agent's reward as the team reward
  and `get_avail_actions` as the legal actions.

Agents, teams and opponents are those of `tabx.marl.TabxMarlEnv` (which this wraps for its
levels and controllers): `team="ally"` learns the ally slots against `opponent`.

`make_env(name_or_path, **kwargs)` builds one from a scenario name (or composition, or file)
and keyword arguments, so a JaxMARL baseline's env line becomes
`env = make_env(config["MAP_NAME"], **config["ENV_KWARGS"])` and `MAP_NAME=crossfire` /
`ENV_KWARGS.opponent=heuristic:expert` are hydra overrides. SMAX's own `ENV_KWARGS` keys (as
the baselines' configs ship them) have no meaning here: they are ignored with a warning.

`infos["won"]` is the battle's outcome: at the end of an episode, a time-out included, the team
with the higher rounded health ratio wins (ties to the enemy), as in the reference; see
docs/ecosystem.md for how `SMAXLogWrapper`'s reward-based win count relates to it.

Needs jaxmarl (the `peers` extra); importing this module without it raises ImportError naming
the extra.
"""

from __future__ import annotations

import math
import numbers
import warnings
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

try:
    from jaxmarl.environments.multi_agent_env import MultiAgentEnv, State
    from jaxmarl.environments.spaces import Box, Discrete
except ImportError as err:  # pragma: no cover - depends on the environment
    raise ImportError("tabx.compat.jaxmarl needs jaxmarl: pip install 'tabx-ued[peers]' "
                      f"({err})") from err

from tabx import constants as C
from tabx.controllers import controlled_actions, with_tiers
from tabx.env import TabxEnv
from tabx.marl import TabxMarlEnv
from tabx.params import EnvConfig, EnvParams, level_config
from tabx.scenarios import load_named
from tabx.scenarios.format import START_NOISE_RANGE
from tabx.state import EnvState

# Keyword arguments of JaxMARL's SMAX / HeuristicEnemySMAX that the baselines' configs put in
# ENV_KWARGS: accepted by `make_env` (so such a config runs) and ignored with a warning.
SMAX_ONLY_KWARGS = frozenset({
    "see_enemy_actions", "walls_cause_death", "attack_mode", "enemy_shoots", "scenario",
    "num_allies", "num_enemies", "map_width", "map_height", "world_steps_per_env_step",
    "time_per_step", "use_self_play_reward", "won_battle_bonus", "smacv2_position_generation",
    "smacv2_unit_type_generation", "observation_type", "action_type"})


@struct.dataclass
class TabxJaxMARLState(State):
    """JaxMARL's `State` (`done`, `step`) with the battle's state and the level it plays."""

    env_state: EnvState
    level: EnvParams


class TabxJaxMARLEnv(MultiAgentEnv):
    """The TABX battle as a JaxMARL `MultiAgentEnv`; see the module docstring."""

    name = "TABX-SMAX"  # "smax" in the name: CTRolloutManager's SMAX handling applies

    def __init__(self, config: EnvConfig, level: EnvParams | None = None,
                 level_sampler: Callable[[jax.Array], EnvParams] | None = None,
                 team: str = "ally", opponent: str = "heuristic:medium"):
        self.marl = TabxMarlEnv(config, level, level_sampler, team, opponent)
        self.map_name: str | None = None  # the scenario's name where `make_env` built it
        super().__init__(num_agents=self.marl.num_agents)
        self.config = config
        self.env = TabxEnv(config)
        self.agents = list(self.marl.agents)
        self.agent_slots = self.marl.agent_slots
        self.slots = [int(i) for i in self.agent_slots]  # the agents' unit slots, in order
        learners = {"ally": config.max_allies, "enemy": config.max_enemies,
                    "both": config.max_allies}[team]
        self.num_allies = learners
        self.num_enemies = config.num_units - learners if team != "both" else config.max_enemies
        self.obs_size = config.obs_size
        self.state_size = config.state_size
        self.num_actions = C.NUM_ACTIONS
        self.learner_team = C.ENEMY if team == "enemy" else C.ALLY
        self.observation_spaces = {a: Box(-jnp.inf, jnp.inf, (config.obs_size,))
                                   for a in self.agents}
        self.action_spaces = {a: Discrete(C.NUM_ACTIONS) for a in self.agents}

    # --- JaxMARL's interface -----------------------------------------------------------------

    def reset(self, key: jax.Array) -> tuple[dict[str, jax.Array], TabxJaxMARLState]:
        """A new episode: a level (the fixed one, or the sampler's) and its start drawn from
        `key` (randomised where the level asks for it)."""
        key_level, key_start = jax.random.split(key)
        level = self.marl.level
        if self.marl.level_sampler is not None:
            level = with_tiers(self.marl.level_sampler(key_level), self.marl.controllers)
        env_state = self.env.start_state(key_start, level)
        state = TabxJaxMARLState(done=jnp.zeros((), bool), step=jnp.zeros((), jnp.int32),
                                 env_state=env_state, level=level)
        return self.get_obs(state), state

    def step_env(self, key: jax.Array, state: TabxJaxMARLState, actions: dict[str, jax.Array]
                 ) -> tuple[dict, TabxJaxMARLState, dict, dict, dict]:
        """One step of every unit (the agents' actions, the opponent controller's for the
        rest), without reset; JaxMARL's `step` adds the reset."""
        key_other, key_step = jax.random.split(key)
        external = jnp.full((self.config.num_units,), C.IDLE, jnp.int32)
        chosen = jnp.stack([jnp.asarray(actions[a], jnp.int32) for a in self.agents])
        external = external.at[self.agent_slots].set(chosen)
        slot_actions, env_state = controlled_actions(key_other, state.env_state, state.level,
                                                     external, self.marl.controllers)
        _, env_state, reward, done, info = self.env.step(key_step, env_state, slot_actions,
                                                         state.level)
        state = state.replace(env_state=env_state, done=done, step=env_state.step)
        teams = [C.ALLY if a.startswith("ally") else C.ENEMY for a in self.agents]
        rewards = {a: reward[t] for a, t in zip(self.agents, teams, strict=True)}
        dones = {a: done for a in self.agents}
        dones["__all__"] = done
        per_agent = lambda x: jnp.broadcast_to(x, (self.num_agents,))
        alive = env_state.alive[self.agent_slots]
        infos = {"won": per_agent(info["won"][self.learner_team]),
                 "terminated": per_agent(info["terminated"]),
                 "truncated": per_agent(info["truncated"]),
                 "alive": alive}
        return self.get_obs(state), state, rewards, dones, infos

    def get_obs(self, state: TabxJaxMARLState) -> dict[str, jax.Array]:
        obs = self.env.observe(state.env_state, state.level)
        out = {a: obs[slot] for a, slot in zip(self.agents, self.slots, strict=True)}
        out["world_state"] = jax.lax.stop_gradient(self.get_world_state(state))
        return out

    def get_world_state(self, state: TabxJaxMARLState) -> jax.Array:
        """The global state (`state_size`,), one per env, as SMAX's `obs["world_state"]`."""
        return self.env.world_state(state.env_state, state.level)

    def get_avail_actions(self, state: TabxJaxMARLState) -> dict[str, jax.Array]:
        mask = self.env.action_mask(state.env_state, state.level)
        return {a: mask[slot] for a, slot in zip(self.agents, self.slots, strict=True)}

    def observation_space(self, agent: str) -> Box:
        return self.observation_spaces[agent]

    def action_space(self, agent: str) -> Discrete:
        return self.action_spaces[agent]

    @property
    def agent_classes(self) -> dict[str, Any]:
        return {"ally": [a for a in self.agents if a.startswith("ally")],
                "enemy": [a for a in self.agents if a.startswith("enemy")]}


def _check_arguments(max_steps: Any, start_noise: Any, shuffle_positions: Any) -> None:
    """ValueError naming the argument of `make_env` that is out of its range: `max_steps` an
    integer in [1, 2**31 - 1] (10.7 is not 10), `start_noise` a finite number in the range a
    scenario file allows, `shuffle_positions` true or false (the string "no" is not false)."""
    integral = (isinstance(max_steps, numbers.Integral) or isinstance(max_steps, float)
                and max_steps.is_integer()) and not isinstance(max_steps, bool | np.bool_)
    if not integral or not 1 <= max_steps <= C.MAX_STEPS:
        raise ValueError(f"make_env: max_steps must be an integer in [1, 2**31 - 1], got "
                         f"{max_steps!r}")
    if start_noise is not None:
        ok = (isinstance(start_noise, numbers.Real) and not isinstance(start_noise, bool | np.bool_)
              and math.isfinite(start_noise) and START_NOISE_RANGE.contains(float(start_noise)))
        if not ok:
            raise ValueError(f"make_env: start_noise must be a number of world units in "
                             f"[{START_NOISE_RANGE.lo:g}, {START_NOISE_RANGE.hi:g}], got "
                             f"{start_noise!r}")
    if shuffle_positions is not None and not isinstance(shuffle_positions, bool | np.bool_):
        raise ValueError(f"make_env: shuffle_positions must be True or False, got "
                         f"{shuffle_positions!r}")


def make_env(name_or_path: str, opponent: str = "heuristic:medium",
             max_steps: int = C.DEFAULT_MAX_STEPS, team: str = "ally",
             start_noise: float | None = None, shuffle_positions: bool | None = None,
             **smax_kwargs: Any) -> TabxJaxMARLEnv:
    """A `TabxJaxMARLEnv` on one scenario (`load_named`: a name, a composition `UNITS_ZONES`
    or a file path), its config the tightest for the scenario with `max_steps`.

    `start_noise` (world units) and `shuffle_positions`, where given, replace the scenario's
    own randomised-start settings (docs/environment.md). Keys of SMAX's own ENV_KWARGS
    (`SMAX_ONLY_KWARGS`) are ignored with a warning; any other key is a TypeError naming the
    accepted ones."""
    unknown = sorted(set(smax_kwargs) - SMAX_ONLY_KWARGS)
    if unknown:
        raise TypeError(f"make_env got unknown keyword arguments {unknown}; it takes opponent, "
                        "max_steps, team, start_noise, shuffle_positions (and ignores SMAX's "
                        f"{sorted(SMAX_ONLY_KWARGS)})")
    if smax_kwargs:
        warnings.warn(f"make_env ignores SMAX-only keyword arguments {sorted(smax_kwargs)}: "
                      "TABX has no counterpart for them", stacklevel=2)
    _check_arguments(max_steps, start_noise, shuffle_positions)
    level = load_named(name_or_path).to_level()
    if start_noise is not None:
        level = level.replace(start_noise=jnp.float32(start_noise))
    if shuffle_positions is not None:
        level = level.replace(shuffle_positions=jnp.bool_(shuffle_positions))
    env = TabxJaxMARLEnv(level_config(level, max_steps=int(max_steps)), level, team=team,
                         opponent=opponent)
    env.map_name = name_or_path
    return env


__all__ = ["SMAX_ONLY_KWARGS", "TabxJaxMARLEnv", "TabxJaxMARLState", "make_env"]

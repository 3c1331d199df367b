"""One episode of one level, played by a *side* per team, in one jitted program.

A side is a controller (tabx.controllers: random, idle, heuristic (the level's own parameters)
or heuristic:TIER) or a trained policy, which a layer above hands in as a
`tabx.policy_team.PolicyTeam`. The episode is the episode player's (`tabx.episodes.play`, a
batch of one); a finished episode is frozen, so the scan can run the full horizon. `summarise`
reports when and how it ended, the winner, and each team's remaining units and health;
`write_gif` and `render_gif` draw every step. The `tabx rollout` command (tabx_ued.rollout)
plays through here.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp

from tabx import constants as C
from tabx.controllers import Controller, with_tiers
from tabx.env import TabxEnv
from tabx.episodes import EPISODE_KEYS, play
from tabx.jit_options import learner_jit, simulator_jit
from tabx.params import EnvConfig, EnvParams
from tabx.policy_team import PolicyTeam
from tabx.state import EnvState

Side = Controller | PolicyTeam
DEFAULT_CONTROLLERS = (Controller("random"), Controller("heuristic", "medium"))


def play_episode(config: EnvConfig, level: EnvParams, steps: int, seed: int,
                 controllers: tuple[Side, Side] = DEFAULT_CONTROLLERS,
                 trajectory: bool = False
                 ) -> tuple[EnvState, jax.Array, jax.Array, tuple[EnvState, dict] | None]:
    """(final state, total reward per team, step the episode ended at (0: not ended), and
    per-step (states, infos) when `trajectory`) of one episode with a controller or a policy
    (`PolicyTeam`) per team. No controller may be external. `level` must already carry the
    controllers' tiers (`with_tiers`)."""
    if any(isinstance(c, Controller) and c.kind == "external" for c in controllers):
        raise ValueError("a rollout needs a controller for both teams (not external)")
    teams = tuple(c if isinstance(c, PolicyTeam) else None for c in controllers)
    # The program sees what each policy computes (`Policy`); its parameters are an argument.
    policies = tuple(None if t is None else t.policy for t in teams)
    params = tuple(None if t is None else t.params for t in teams)
    dtypes = {t.matmul_dtype for t in teams if t is not None}
    compiled = _play(None if not dtypes else "bfloat16" if "bfloat16" in dtypes else "float32")
    return compiled(env_for(config), level, jax.random.key(seed), steps,
                    scripted_controllers(controllers), trajectory, policies, params)


@functools.lru_cache(maxsize=16)
def env_for(config: EnvConfig) -> TabxEnv:
    """One env object per config, so that jit caches keyed on it are reused across calls."""
    return TabxEnv(config)


def episode(env: TabxEnv, level: EnvParams, key: jax.Array, steps: int,
            controllers: tuple[Controller, Controller], trajectory: bool = False,
            policies: tuple = (None, None), params: tuple = (None, None)):
    """The traceable body of `play_episode`: one episode of `level` (no batch axis) through
    the episode player (`tabx.episodes.play`, a batch of one). A team with a `Policy` (its
    controller external) acts with it on `params`, its recurrent state carried over the
    episode."""
    record = ((lambda states, info, levels: (states, {k: info[k] for k in ("attacking", "hit")}))
              if trajectory else None)
    out = play(env, jax.tree.map(lambda x: x[None], level), key[None], steps, controllers,
               policies, params, keys=EPISODE_KEYS, record=record)
    state, total, length = jax.tree.map(lambda x: x[0], (out.states, out.returns, out.length))
    # The episode ended at the step it was done after: the steps it played.
    ended_at = jnp.where(state.done, length, 0)
    frames = None if out.record is None else jax.tree.map(lambda x: x[:, 0], out.record)
    return state, total, ended_at, frames


@functools.cache
def _play(matmul_dtype: str | None):
    """The compiled `episode`: with the simulator's compiler options, or with a learner's
    (`matmul_dtype`) when a policy plays. Made on first use: choosing the options asks JAX for
    its backend, which an import must not start."""
    static = dict(static_argnums=(0, 3, 4, 5, 6))
    if matmul_dtype is None:
        return simulator_jit(episode, **static)
    return learner_jit(episode, matmul_dtype, **static)


def run_episode(config: EnvConfig, level: EnvParams, steps: int, seed: int,
                controllers: tuple[Side, Side] = DEFAULT_CONTROLLERS) -> dict:
    """Play up to `steps` steps and summarise the outcome as plain Python values."""
    level = with_tiers(level, scripted_controllers(controllers))
    state, total, ended_at, _ = jax.device_get(
        play_episode(config, level, steps, seed, controllers))
    return summarise(level, state, total, ended_at)


def summarise(level: EnvParams, state: EnvState, total: jax.Array, ended_at: jax.Array
              ) -> dict:
    """The outcome of an episode of `level` (`play_episode`'s results) as plain values: its
    steps, whether and when it ended, the winner, and per team the units alive, health and
    total reward."""
    state, total, ended_at, u = jax.device_get((state, total, ended_at, level.units))
    teams = []
    for team in (C.ALLY, C.ENEMY):
        member = (u.team == team) & u.active
        teams.append(dict(
            units=int(member.sum()),
            alive=int((member & state.alive).sum()),
            health=float(state.health[member].sum()),
            max_health=float(u.max_health[member].sum()),
            hp_ratio=float(state.hp_ratio[team]),
            total_reward=float(total[team]),
        ))
    return dict(steps=int(state.step), done=bool(state.done), ended_at=int(ended_at),
                won=[bool(w) for w in state.won], teams=teams,
                truncated=bool(state.done and all(t["alive"] > 0 for t in teams)))


def scripted_controllers(sides: tuple[Side, Side]) -> tuple[Controller, Controller]:
    """The controllers of `sides`, a policy's team as external (for `with_tiers`)."""
    return tuple(Controller("external") if isinstance(s, PolicyTeam) else s for s in sides)


def write_gif(config: EnvConfig, level: EnvParams, steps: int, seed: int,
              controllers: tuple[Side, Side], path: str, fps: float = 10.0) -> None:
    """Play the episode and render it (the start state, then every step until it ends) as a
    GIF."""
    _, _, _, (states, infos) = jax.device_get(
        play_episode(config, level, steps, seed, controllers, trajectory=True))
    render_gif(config, level, states, infos, controllers, path, fps)


def render_gif(config: EnvConfig, level: EnvParams, states: EnvState, infos: dict,
               controllers: tuple[Side, Side], path: str, fps: float = 10.0) -> None:
    """Render a recorded episode (`play_episode(..., trajectory=True)`'s per-step states and
    infos) as a GIF: the start state, then every step until it ends."""
    from tabx.render import render_level, render_trajectory, save_gif

    title = " v ".join(c.title if isinstance(c, PolicyTeam) else str(c) for c in controllers)
    frames = [render_level(config, level, title=title)]
    frames += render_trajectory(config, level, states, infos, title=title)
    save_gif(frames, path, fps=fps)


__all__ = ["DEFAULT_CONTROLLERS", "Side", "play_episode", "render_gif", "run_episode",
           "scripted_controllers", "summarise", "write_gif"]

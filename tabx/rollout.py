"""`tabx rollout NAME`: play one scenario and print the outcome (optionally render a GIF).

Each team has a controller (tabx.controllers): `--ally random --enemy heuristic:medium` by
default, any of random, idle, heuristic (the scenario's own parameters) or heuristic:TIER. The
episode runs as one jitted `lax.scan` (a finished episode is frozen, so the scan can run the
full horizon); the summary reports when and how it ended, the winner, and each team's
remaining units and health. `--gif out.gif` renders every step.
"""

from __future__ import annotations

import argparse
import functools
import time

import jax
import jax.numpy as jnp

from tabx import constants as C
from tabx.controllers import Controller, controlled_actions, with_tiers
from tabx.env import TabxEnv
from tabx.jit_options import simulator_jit
from tabx.params import EnvConfig, EnvParams
from tabx.profiles import DEFAULT_PROFILE, add_profile_argument, with_profile
from tabx.state import EnvState

DEFAULT_CONTROLLERS = (Controller("random"), Controller("heuristic", "medium"))


def play_episode(config: EnvConfig, level: EnvParams, steps: int, seed: int,
                 controllers: tuple[Controller, Controller] = DEFAULT_CONTROLLERS,
                 trajectory: bool = False
                 ) -> tuple[EnvState, jax.Array, jax.Array, tuple[EnvState, dict] | None]:
    """(final state, total reward per team, step the episode ended at (0: not ended), and
    per-step (states, infos) when `trajectory`) of one episode under `controllers`. No team
    may be external. `level` must already carry the controllers' tiers (`with_tiers`)."""
    if any(c.kind == "external" for c in controllers):
        raise ValueError("a rollout needs a controller for both teams (not external)")
    return _play()(env_for(config), level, jax.random.key(seed), steps, tuple(controllers),
                   trajectory)


@functools.lru_cache(maxsize=16)
def env_for(config: EnvConfig) -> TabxEnv:
    """One env object per config, so that jit caches keyed on it are reused across calls."""
    return TabxEnv(config)


def episode(env: TabxEnv, level: EnvParams, key: jax.Array, steps: int,
            controllers: tuple[Controller, Controller], trajectory: bool = False):
    """The traceable body of `play_episode` (one env; vmap it for a batch of episodes)."""
    _, state = env.reset(key, level)

    def body(carry, key):
        state, total, ended_at = carry
        was_done = state.done
        actions, state = controlled_actions(key, state, level, None, controllers)
        _, state, reward, done, info = env.step(key, state, actions, level)
        ended_at = jnp.where(done & ~was_done, state.step, ended_at)
        out = (state, {k: info[k] for k in ("attacking", "hit")}) if trajectory else None
        return (state, total + reward, ended_at), out

    init = (state, jnp.zeros(C.NUM_TEAMS), jnp.zeros((), jnp.int32))
    (state, total, ended_at), frames = jax.lax.scan(body, init, jax.random.split(key, steps))
    return state, total, ended_at, frames


@functools.cache
def _play():
    # Made on first use: choosing the compiler options asks JAX for its backend, which an
    # import must not start.
    return simulator_jit(episode, static_argnums=(0, 3, 4, 5))


def run_episode(config: EnvConfig, level: EnvParams, steps: int, seed: int,
                controllers: tuple[Controller, Controller] = DEFAULT_CONTROLLERS) -> dict:
    """Play up to `steps` steps and summarise the outcome as plain Python values."""
    level = with_tiers(level, controllers)
    state, total, ended_at, _ = jax.device_get(
        play_episode(config, level, steps, seed, controllers))
    u = jax.device_get(level.units)
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


def cmd_rollout(args: argparse.Namespace) -> int:
    from tabx.errors import UserError
    from tabx.scenarios import ScenarioError, config_for, load_named

    if args.steps < 1:
        raise UserError(f"--steps must be >= 1, got {args.steps}")
    try:
        scenario = load_named(args.name)
    except ScenarioError as err:
        raise UserError(str(err)) from None
    if not scenario.units:
        raise UserError(f"scenario {scenario.name!r} has no units (a zone layout): compose it "
                        f"with units, e.g. 3F_vs_3F_{scenario.name}")
    controllers = []
    for flag, text in (("--ally", args.ally), ("--enemy", args.enemy)):
        try:
            controllers.append(Controller.parse_scripted(text))
        except ValueError as err:
            raise UserError(f"{flag}: {err}") from None
    controllers = tuple(controllers)
    if args.gif is not None and not args.gif.endswith(".gif"):
        raise UserError(f"--gif: expected a file name ending in .gif, got {args.gif!r}")
    config = config_for([scenario], max_steps=args.max_steps)
    profile = args.profile or DEFAULT_PROFILE
    level = with_profile(with_tiers(scenario.to_level(config), controllers), profile)
    t0 = time.perf_counter()
    result = run_episode(config, level, args.steps, args.seed, controllers)
    elapsed = time.perf_counter() - t0
    print(f"scenario {scenario.name}: {len(scenario.allies)} allies v {len(scenario.enemies)} "
          f"enemies, {len(scenario.zones)} zones; allies {controllers[0]}, enemies "
          f"{controllers[1]}, seed {args.seed}, profile {profile}")
    for name, team in zip(("allies", "enemies"), result["teams"], strict=True):
        print(f"  {name:8s} alive {team['alive']}/{team['units']}  health "
              f"{team['health']:.0f}/{team['max_health']:.0f} (ratio {team['hp_ratio']:.3f})  "
              f"return {team['total_reward']:+.3f}")
    if result["done"]:
        how = "time limit" if result["truncated"] else "elimination"
        winner = "allies" if result["won"][C.ALLY] else "enemies"
        print(f"outcome: {winner} win by {how} at step {result['ended_at']}")
    else:
        print(f"outcome: still running after {result['steps']} steps "
              f"(episode limit {args.max_steps})")
    print(f"({elapsed:.1f} s including compilation)")
    if args.gif is not None:
        write_gif(config, level, args.steps, args.seed, controllers, args.gif, args.fps)
        print(f"wrote {args.gif}")
    return 0


def write_gif(config: EnvConfig, level: EnvParams, steps: int, seed: int,
              controllers: tuple[Controller, Controller], path: str, fps: float = 10.0) -> None:
    """Render the episode (the start state, then every step until it ends) as a GIF."""
    from tabx.render import render_level, render_trajectory, save_gif

    _, _, _, (states, infos) = jax.device_get(
        play_episode(config, level, steps, seed, controllers, trajectory=True))
    title = f"{controllers[0]} v {controllers[1]}"
    frames = [render_level(config, level, title=title)]
    frames += render_trajectory(config, level, states, infos, title=title)
    save_gif(frames, path, fps=fps)


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("rollout", help="play a scenario (heuristic/random teams)")
    p.add_argument("name", help="scenario name (tabx scenarios list), composition or file")
    p.add_argument("--steps", type=int, default=512, help="steps to play (default 512)")
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument("--max-steps", type=int, default=C.DEFAULT_MAX_STEPS,
                   help="episode limit (default 512)")
    p.add_argument("--ally", default="random",
                   help="ally controller: random, idle, heuristic or heuristic:TIER "
                        "(default random)")
    p.add_argument("--enemy", default="heuristic:medium",
                   help="enemy controller (default heuristic:medium)")
    p.add_argument("--gif", metavar="OUT.gif", help="render the episode to a GIF")
    p.add_argument("--fps", type=float, default=10.0, help="GIF frames per second (default 10)")
    add_profile_argument(p)
    p.set_defaults(func=cmd_rollout)


__all__ = ["DEFAULT_CONTROLLERS", "play_episode", "run_episode", "write_gif"]

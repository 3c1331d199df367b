"""`tabx rollout [NAME]`: play one scenario and print the outcome (optionally render a GIF).

Each team is played by a *side*: a controller (tabx.controllers: random, idle, heuristic (the
scenario's own parameters) or heuristic:TIER; `--ally random --enemy heuristic:medium` by
default) or, from the full command line, a trained policy given as its run folder
(`tabx.policy_team`: the layer above loads it; the simulator alone refuses a folder). A policy
plays the EnvConfig it was trained on (the scenario is padded into it), the team it was trained
for or, through the team swap, the other one when that has as many slots; the scenario defaults
to its first training scenario, and the team nobody names to its training opponent.

The episode runs as one jitted `lax.scan` (a finished episode is frozen, so the scan can run the
full horizon); the summary reports when and how it ended, the winner, and each team's remaining
units and health. `--gif out.gif` renders every step.
"""

from __future__ import annotations

import argparse
import functools
import time
from pathlib import Path

import jax
import jax.numpy as jnp

from tabx import constants as C
from tabx.controllers import Controller, controlled_actions, with_tiers
from tabx.env import TabxEnv
from tabx.errors import UserError
from tabx.jit_options import learner_jit, simulator_jit
from tabx.params import EnvConfig, EnvParams
from tabx.policy_team import PolicyLoader, PolicyTeam
from tabx.profiles import DEFAULT_PROFILE, add_profile_argument, with_profile
from tabx.state import EnvState

Side = Controller | PolicyTeam
DEFAULT_CONTROLLERS = (Controller("random"), Controller("heuristic", "medium"))
TEAM_FLAGS = ("--ally", "--enemy")


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
    policies = tuple(c if isinstance(c, PolicyTeam) else None for c in controllers)
    scripted = tuple(Controller("external") if p is not None else c
                     for c, p in zip(controllers, policies, strict=True))
    # The program sees what each policy computes (its functions and slots); its parameters
    # are an argument.
    networks = tuple(None if p is None else (p.act, p.initial_hidden, p.slots)
                     for p in policies)
    params = tuple(None if p is None else p.params for p in policies)
    dtypes = {p.matmul_dtype for p in policies if p is not None}
    compiled = _play(None if not dtypes else "bfloat16" if "bfloat16" in dtypes else "float32")
    return compiled(env_for(config), level, jax.random.key(seed), steps, scripted, trajectory,
                    networks, params)


@functools.lru_cache(maxsize=16)
def env_for(config: EnvConfig) -> TabxEnv:
    """One env object per config, so that jit caches keyed on it are reused across calls."""
    return TabxEnv(config)


def episode(env: TabxEnv, level: EnvParams, key: jax.Array, steps: int,
            controllers: tuple[Controller, Controller], trajectory: bool = False,
            networks: tuple = (None, None), params: tuple = (None, None)):
    """The traceable body of `play_episode` (one env; vmap it for a batch of episodes). A team
    with a network (`(act, initial_hidden, slots)` of a `PolicyTeam`, its controller
    external) acts with `act` on `params`, its recurrent state carried over the episode."""
    obs, state = env.reset(key, level)
    playing = [team for team in range(C.NUM_TEAMS) if networks[team] is not None]

    def policy_actions(key, obs, state, hidden):
        if not playing:
            return None, hidden
        mask = env.action_mask(state, level)
        external = jnp.zeros((env.config.num_units,), jnp.int32)
        hidden = list(hidden)
        for team in playing:
            act, _, slots = networks[team]
            # Keys of their own, so that the scripted team's draws are those of a rollout
            # without a policy.
            acts, hidden[team] = act(params[team], obs, mask, hidden[team],
                                     jax.random.fold_in(key, 1 + team))
            external = external.at[slice(*slots)].set(acts)
        return external, tuple(hidden)

    def body(carry, key):
        obs, state, hidden, total, ended_at = carry
        was_done = state.done
        external, hidden = policy_actions(key, obs, state, hidden)
        actions, state = controlled_actions(key, state, level, external, controllers)
        obs, state, reward, done, info = env.step(key, state, actions, level)
        ended_at = jnp.where(done & ~was_done, state.step, ended_at)
        out = (state, {k: info[k] for k in ("attacking", "hit")}) if trajectory else None
        # Observations are carried only for a policy (scripted teams do without them).
        return (obs if playing else None, state, hidden, total + reward, ended_at), out

    hidden = tuple(None if n is None else n[1]() for n in networks)
    init = (obs if playing else None, state, hidden, jnp.zeros(C.NUM_TEAMS),
            jnp.zeros((), jnp.int32))
    (_, state, _, total, ended_at), frames = jax.lax.scan(body, init,
                                                          jax.random.split(key, steps))
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


def parse_side(text: str, team: int, greedy: bool, loader: PolicyLoader | None) -> Side:
    """A team's side from its flag's text: a run folder (through `loader`) or a controller."""
    flag = TEAM_FLAGS[team]
    if Path(text).is_dir():
        if loader is None:
            raise UserError(f"{flag}: {text} is a folder: playing a trained policy (a run "
                            f"folder) needs the full command line (`tabx`, tabx_ued.cli); the "
                            f"simulator's own (`python -m tabx.cli`) plays controllers only")
        try:
            return loader(text, team, greedy)
        except UserError as err:
            raise UserError(f"{flag}: {err}") from None
    if Path(text).exists():
        raise UserError(f"{flag}: {text}: not a folder (expected a run folder or a controller)")
    if "/" in text or "\\" in text:
        raise UserError(f"{flag}: {text}: no such run folder")
    try:
        return Controller.parse_scripted(text)
    except ValueError as err:
        folder = " or a run folder" if loader is not None else ""
        raise UserError(f"{flag}: {text!r} is not a controller{folder} ({err})") from None


def resolve_sides(args: argparse.Namespace, loader: PolicyLoader | None
                  ) -> tuple[tuple[Side, Side], PolicyTeam | None]:
    """(the sides of both teams, the first policy among them or None). A team nobody names
    plays the policy's training opponent, or the default controller when no policy plays."""
    texts = (args.ally, args.enemy)
    sides: list[Side | None] = [None if text is None else
                                parse_side(text, team, args.greedy, loader)
                                for team, text in enumerate(texts)]
    policies = [s for s in sides if isinstance(s, PolicyTeam)]
    reference = policies[0] if policies else None
    if len(policies) == 2 and policies[0].env_config != policies[1].env_config:
        raise UserError(f"{policies[1].label} was trained with {policies[1].env_config}, "
                        f"{policies[0].label} with {policies[0].env_config}: two policies "
                        f"play each other on one EnvConfig")
    if args.greedy and reference is None:
        raise UserError("--greedy picks a trained policy's most likely action: give a run "
                        "folder as --ally or --enemy")
    for team in range(C.NUM_TEAMS):
        if sides[team] is None:
            if reference is not None and reference.opponent is not None:
                sides[team] = Controller.parse_scripted(reference.opponent)
            else:
                sides[team] = DEFAULT_CONTROLLERS[team]
    return (sides[0], sides[1]), reference


def cmd_rollout(args: argparse.Namespace, loader: PolicyLoader | None = None) -> int:
    from tabx.scenarios import ScenarioError, config_for, load_named

    if args.steps < 1:
        raise UserError(f"--steps must be >= 1, got {args.steps}")
    if args.gif is not None and not args.gif.endswith(".gif"):
        raise UserError(f"--gif: expected a file name ending in .gif, got {args.gif!r}")
    controllers, policy = resolve_sides(args, loader)
    name = args.name or (policy.scenario if policy is not None else None)
    if name is None:
        raise UserError("give a scenario NAME (tabx scenarios list)")
    try:
        scenario = load_named(name)
    except ScenarioError as err:
        raise UserError(str(err)) from None
    if not scenario.units:
        raise UserError(f"scenario {scenario.name!r} has no units (a zone layout): compose it "
                        f"with units, e.g. 3F_vs_3F_{scenario.name}")
    if policy is None:
        config = config_for([scenario], max_steps=(C.DEFAULT_MAX_STEPS if args.max_steps is None
                                                   else args.max_steps))
    else:
        config = policy.env_config
        if args.max_steps is not None and args.max_steps != config.max_steps:
            raise UserError(f"--max-steps: {policy.label} plays episodes of "
                            f"{config.max_steps} steps (its EnvConfig); drop --max-steps")
    try:
        level = scenario.to_level(config)
    except ScenarioError as err:
        if policy is None:
            raise UserError(str(err)) from None
        raise UserError(f"{policy.label} cannot play {scenario.name!r}: {err} (the policy's "
                        f"EnvConfig: {config})") from None
    profile = args.profile or (policy.profile if policy is not None else None) or DEFAULT_PROFILE
    level = with_profile(with_tiers(level, scripted_controllers(controllers)), profile)
    t0 = time.perf_counter()
    # One episode: with --gif it also records every step, to render after the summary.
    state, total, ended_at, frames = play_episode(config, level, args.steps, args.seed,
                                                  controllers, trajectory=args.gif is not None)
    result = summarise(level, state, total, ended_at)
    elapsed = time.perf_counter() - t0
    acting = "" if policy is None else (", greedy policies" if args.greedy
                                        else ", sampled policies")
    print(f"scenario {scenario.name}: {len(scenario.allies)} allies v {len(scenario.enemies)} "
          f"enemies, {len(scenario.zones)} zones; allies {controllers[0]}, enemies "
          f"{controllers[1]}, seed {args.seed}, profile {profile}{acting}")
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
              f"(episode limit {config.max_steps})")
    print(f"({elapsed:.1f} s including compilation)")
    if args.gif is not None:
        render_gif(config, level, *jax.device_get(frames), controllers, args.gif, args.fps)
        print(f"wrote {args.gif}")
    return 0


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


def add_parser(subparsers: argparse._SubParsersAction, loader: PolicyLoader | None = None
               ) -> None:
    """`tabx rollout`; `loader` lets `--ally`/`--enemy` name a run folder (tabx.policy_team)."""
    side = ("a controller: random, idle, heuristic or heuristic:TIER"
            + (", or a run folder (a trained policy)" if loader is not None else ""))
    p = subparsers.add_parser(
        "rollout", help="play a scenario (scripted teams"
                        + (" or trained policies)" if loader is not None else ")"))
    p.add_argument("name", nargs="?",
                   help="scenario name (tabx scenarios list), composition or file"
                        + (" (default: the policy's first training scenario)"
                           if loader is not None else ""))
    p.add_argument("--steps", type=int, default=512, help="steps to play (default 512)")
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument("--max-steps", type=int,
                   help=f"episode limit (default {C.DEFAULT_MAX_STEPS}; a policy's own "
                        f"EnvConfig sets it)")
    p.add_argument("--ally", help=f"who plays the ally team: {side} (default random, or a "
                                  f"policy's training opponent)")
    p.add_argument("--enemy", help=f"who plays the enemy team: {side} (default "
                                   f"heuristic:medium, or a policy's training opponent)")
    p.add_argument("--greedy", action="store_true",
                   help="a trained policy takes its most likely action instead of sampling")
    p.add_argument("--gif", metavar="OUT.gif", help="render the episode to a GIF")
    p.add_argument("--fps", type=float, default=10.0, help="GIF frames per second (default 10)")
    add_profile_argument(p)
    p.set_defaults(func=functools.partial(cmd_rollout, loader=loader))


__all__ = ["DEFAULT_CONTROLLERS", "Side", "parse_side", "play_episode", "render_gif",
           "resolve_sides", "run_episode", "scripted_controllers", "summarise", "write_gif"]

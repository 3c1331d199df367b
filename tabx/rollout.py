"""`tabx rollout NAME`: play one scenario with random legal actions and print the outcome.

The episode runs as one jitted `lax.scan` (a finished episode is frozen, so the scan can run
the full horizon); the summary reports when and how it ended, the winner, and each team's
remaining units and health.
"""

from __future__ import annotations

import argparse
import time

import jax
import jax.numpy as jnp

from tabx import constants as C
from tabx.env import TabxEnv, random_legal_actions
from tabx.params import EnvConfig, EnvParams


def run_episode(config: EnvConfig, level: EnvParams, steps: int, seed: int) -> dict:
    """Play up to `steps` steps with uniform random legal actions for every unit."""
    env = TabxEnv(config)

    @jax.jit
    def play(level: EnvParams, key: jax.Array):
        _, state = env.reset(key, level)

        def body(carry, _):
            key, state, total, ended_at = carry
            key, k_act = jax.random.split(key)
            actions = random_legal_actions(k_act, env.action_mask(state, level))
            was_done = state.done
            _, state, reward, done, info = env.step(k_act, state, actions, level)
            ended_at = jnp.where(done & ~was_done, state.step, ended_at)
            return (key, state, total + reward, ended_at), info["damage_dealt"]

        init = (key, state, jnp.zeros(C.NUM_TEAMS), jnp.zeros((), jnp.int32))
        (_, state, total, ended_at), _ = jax.lax.scan(body, init, None, length=steps)
        return state, total, ended_at

    state, total, ended_at = jax.device_get(play(level, jax.random.key(seed)))
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
    from tabx.cli import UserError
    from tabx.scenarios import ScenarioError, config_for, load_named

    if args.steps < 1:
        raise UserError(f"--steps must be >= 1, got {args.steps}")
    try:
        scenario = load_named(args.name)
    except ScenarioError as err:
        raise UserError(str(err)) from None
    config = config_for([scenario], max_steps=args.max_steps)
    level = scenario.to_level(config)
    t0 = time.perf_counter()
    result = run_episode(config, level, args.steps, args.seed)
    elapsed = time.perf_counter() - t0
    print(f"scenario {scenario.name}: {len(scenario.allies)} allies v {len(scenario.enemies)} "
          f"enemies, {len(scenario.zones)} zones; random actions, seed {args.seed}")
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
    return 0


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("rollout", help="play a scenario with random actions")
    p.add_argument("name", help="scenario name (tabx scenarios list), composition or file")
    p.add_argument("--steps", type=int, default=512, help="steps to play (default 512)")
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument("--max-steps", type=int, default=C.DEFAULT_MAX_STEPS,
                   help="episode limit (default 512)")
    p.set_defaults(func=cmd_rollout)


__all__ = ["run_episode"]

"""Heuristic tier tournaments: `tabx eval heuristics NAME`, a tier-vs-tier win-rate table.

Row tier plays the allies, column tier the enemies, both with the scripted policy; each cell is
`episodes` full episodes on the scenario. The tiers are data in the level, so the whole table
runs through one compiled function: each row is one batch of (columns x episodes) envs stepped
until every episode has ended (a `lax.while_loop`, so short battles finish early).

A draw (time limit with equal team health ratios) counts as an enemy win, as in the reward's
tie-break; the table reports ally wins, so the diagonal of a mirror scenario sits a little
below one half when draws happen.
"""

from __future__ import annotations

import argparse
import functools
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np

from tabx import constants as C
from tabx.controllers import Controller, controlled_actions
from tabx.env import TabxEnv
from tabx.jit_options import simulator_jit
from tabx.params import HEURISTIC_TIERS, EnvConfig, EnvParams, heuristic_params, stack_levels

BOTH_HEURISTIC = (Controller("heuristic"), Controller("heuristic"))


@dataclass
class TierTable:
    """Results per (ally tier, enemy tier): win rate of the allies, mean episode length and
    mean ally return."""

    ally_tiers: list[str]
    enemy_tiers: list[str]
    episodes: int
    win_rate: np.ndarray  # (A, E)
    length: np.ndarray  # (A, E)
    ally_return: np.ndarray  # (A, E)

    def ci95(self) -> np.ndarray:
        """Half-width of the normal 95% interval of each win rate."""
        p = self.win_rate
        return 1.96 * np.sqrt(p * (1 - p) / self.episodes)

    def to_json(self) -> dict:
        return dict(ally_tiers=self.ally_tiers, enemy_tiers=self.enemy_tiers,
                    episodes=self.episodes, win_rate=self.win_rate.tolist(),
                    ci95=self.ci95().tolist(), length=self.length.tolist(),
                    ally_return=self.ally_return.tolist())

    def format(self) -> str:
        width = max(9, *(len(t) for t in self.enemy_tiers)) + 2
        lines = ["ally \\ enemy".ljust(12) + "".join(t.rjust(width) for t in self.enemy_tiers)]
        ci = self.ci95()
        for i, tier in enumerate(self.ally_tiers):
            cells = [f"{self.win_rate[i, j]:.2f}±{ci[i, j]:.2f}".rjust(width)
                     for j in range(len(self.enemy_tiers))]
            lines.append(tier.ljust(12) + "".join(cells))
        return "\n".join(lines)


@functools.lru_cache(maxsize=8)
def make_batch_runner(config: EnvConfig):
    """A jitted `run(levels, keys) -> (ally_won, length, ally_return)` over a batch of envs,
    each playing one episode with the heuristic on both teams until all have ended."""
    env = TabxEnv(config)

    def act(key, state, level):
        actions, state = controlled_actions(key, state, level, None, BOTH_HEURISTIC)
        _, state, reward, _, _ = env.step(key, state, actions, level)
        return state, reward

    def run(levels: EnvParams, keys: jax.Array):
        states = jax.vmap(env.initial_state)(levels)
        batch = keys.shape[0]

        def cond(carry):
            states, _, _, t = carry
            return jnp.any(~states.done) & (t < config.max_steps)

        def body(carry):
            states, total, key, t = carry
            key, sub = jax.random.split(key)
            states, reward = jax.vmap(act)(jax.random.split(sub, batch), states, levels)
            return states, total + reward[:, C.ALLY], key, t + 1

        init = (states, jnp.zeros(batch), keys[0], jnp.zeros((), jnp.int32))
        states, total, _, _ = jax.lax.while_loop(cond, body, init)
        return states.won[:, C.ALLY], states.step, total

    return simulator_jit(run)


def tier_table(config: EnvConfig, level: EnvParams, episodes: int, seed: int = 0,
               ally_tiers: Sequence[str] = tuple(HEURISTIC_TIERS),
               enemy_tiers: Sequence[str] = tuple(HEURISTIC_TIERS),
               progress: bool = False) -> TierTable:
    """Play `episodes` episodes for every (ally tier, enemy tier) pair on one level."""
    for tier in (*ally_tiers, *enemy_tiers):
        if tier not in HEURISTIC_TIERS:
            raise ValueError(f"unknown heuristic tier {tier!r}; expected one of "
                             f"{', '.join(HEURISTIC_TIERS)}")
    run = make_batch_runner(config)
    shape = (len(ally_tiers), len(enemy_tiers))
    win, length, ret = (np.zeros(shape) for _ in range(3))
    key = jax.random.key(seed)
    start = time.perf_counter()
    for i, ally in enumerate(ally_tiers):
        levels = stack_levels([level.replace(heuristic=heuristic_params(ally, enemy))
                               for enemy in enemy_tiers for _ in range(episodes)])
        key, sub = jax.random.split(key)
        won, steps, total = jax.device_get(run(levels, jax.random.split(sub, len(enemy_tiers)
                                                                          * episodes)))
        win[i] = won.reshape(len(enemy_tiers), episodes).mean(-1)
        length[i] = steps.reshape(len(enemy_tiers), episodes).mean(-1)
        ret[i] = total.reshape(len(enemy_tiers), episodes).mean(-1)
        if progress:
            elapsed = time.perf_counter() - start
            eta = elapsed / (i + 1) * (len(ally_tiers) - i - 1)
            print(f"  row {i + 1}/{len(ally_tiers)} ({ally}) done: {elapsed:.0f} s elapsed, "
                  f"ETA {eta:.0f} s", file=sys.stderr, flush=True)
    return TierTable(list(ally_tiers), list(enemy_tiers), episodes, win, length, ret)


def cmd_eval_heuristics(args: argparse.Namespace) -> int:
    from tabx.errors import UserError
    from tabx.files import atomic_write_json
    from tabx.scenarios import ScenarioError, config_for, load_named

    if args.episodes < 1:
        raise UserError(f"--episodes must be >= 1, got {args.episodes}")
    try:
        scenario = load_named(args.name)
    except ScenarioError as err:
        raise UserError(str(err)) from None
    if not scenario.units:
        raise UserError(f"scenario {scenario.name!r} has no units (a zone layout)")
    tiers = args.tiers.split(",") if args.tiers else list(HEURISTIC_TIERS)
    bad = [t for t in tiers if t not in HEURISTIC_TIERS]
    if bad:
        raise UserError(f"--tiers: unknown tier(s) {', '.join(bad)}; expected a comma "
                        f"separated subset of {','.join(HEURISTIC_TIERS)}")
    config = config_for([scenario], max_steps=args.max_steps)
    level = scenario.to_level(config)
    print(f"{scenario.name}: heuristic tier v tier, {args.episodes} episodes per cell, "
          f"max {args.max_steps} steps, seed {args.seed}", file=sys.stderr)
    t0 = time.perf_counter()
    table = tier_table(config, level, args.episodes, args.seed, tiers, tiers, progress=True)
    elapsed = time.perf_counter() - t0
    print(f"ally win rate (row tier = allies, column tier = enemies; ±95% CI), "
          f"{scenario.name}, {args.episodes} episodes per cell:")
    print(table.format())
    print(f"({elapsed:.1f} s, {len(tiers) ** 2 * args.episodes} episodes, compile included)")
    if args.json:
        atomic_write_json(args.json, dict(scenario=scenario.name, seed=args.seed,
                                          max_steps=args.max_steps, **table.to_json()))
        print(f"wrote {args.json}")
    return 0


def add_route_parser(sub: argparse._SubParsersAction) -> None:
    """`heuristics` under `tabx eval` (a route of tabx.cli)."""
    p = sub.add_parser("heuristics", help="tier-vs-tier win-rate table of the scripted policy")
    p.add_argument("name", help="scenario name, composition or file")
    p.add_argument("--episodes", type=int, default=64, help="episodes per cell (default 64)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--max-steps", type=int, default=C.DEFAULT_MAX_STEPS)
    p.add_argument("--tiers", help=f"comma separated tiers (default all: "
                                   f"{','.join(HEURISTIC_TIERS)})")
    p.add_argument("--json", metavar="FILE", help="also write the table as JSON")
    p.set_defaults(func=cmd_eval_heuristics)


__all__ = ["TierTable", "make_batch_runner", "tier_table", "add_route_parser"]


"""`tabx eval heuristics NAME`: the scripted policy's tier-vs-tier table on one scenario
(`tabx.tournament.tier_table`), printed and optionally written as JSON."""

from __future__ import annotations

import argparse
import sys
import time

from tabx import constants as C
from tabx.errors import UserError
from tabx.files import atomic_write_json
from tabx.params import HEURISTIC_TIERS
from tabx.profiles import DEFAULT_PROFILE
from tabx.scenarios import ScenarioError, config_for, load_named
from tabx.tournament import tier_table
from tabx_ued.arguments import add_profile_argument


def cmd_eval_heuristics(args: argparse.Namespace) -> int:
    """Play the tier table of one scenario; print it (and write it as JSON)."""
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
    profile = args.profile or DEFAULT_PROFILE
    print(f"{scenario.name}: heuristic tier v tier, {args.episodes} episodes per cell, "
          f"max {args.max_steps} steps, seed {args.seed}, profile {profile}", file=sys.stderr)
    t0 = time.perf_counter()
    table = tier_table(config, level, args.episodes, args.seed, tiers, tiers, progress=True,
                       profile=profile)
    elapsed = time.perf_counter() - t0
    print(f"ally win rate (row tier = allies, column tier = enemies; [95% Wilson interval]), "
          f"{scenario.name}, {args.episodes} episodes per cell, profile {profile}:")
    print(table.format())
    print(f"({elapsed:.1f} s, {len(tiers) ** 2 * args.episodes} episodes, compile included)")
    if args.json:
        atomic_write_json(args.json, dict(scenario=scenario.name, seed=args.seed,
                                          max_steps=args.max_steps, **table.to_json()))
        print(f"wrote {args.json}")
    return 0


def add_route_parser(sub: argparse._SubParsersAction) -> None:
    """`heuristics` under `tabx eval` (a route of `tabx_ued.commands`)."""
    p = sub.add_parser("heuristics", help="tier-vs-tier tables of the scripted policy")
    p.add_argument("name", help="scenario name, composition or file")
    p.add_argument("--episodes", type=int, default=64, help="episodes per cell (default 64)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--max-steps", type=int, default=C.DEFAULT_MAX_STEPS)
    p.add_argument("--tiers", help=f"comma separated tiers (default all: "
                                   f"{','.join(HEURISTIC_TIERS)})")
    p.add_argument("--json", metavar="FILE", help="also write the table as JSON")
    add_profile_argument(p)
    p.set_defaults(func=cmd_eval_heuristics)


__all__ = ["add_route_parser", "cmd_eval_heuristics"]

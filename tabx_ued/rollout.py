"""`tabx rollout [NAME]`: play one scenario and print the outcome (optionally render a GIF).

Each team is played by a *side*: a controller (tabx.controllers: random, idle, heuristic (the
scenario's own parameters) or heuristic:TIER; `--ally random --enemy heuristic:medium` by
default) or a trained policy given as its run folder (`ued.evaluate.load_policy_team`). A
policy plays the EnvConfig it was trained on (the scenario is padded into it), the team it was
trained for or, through the team swap, the other one when that has as many slots; the scenario
defaults to its first training scenario, and the team nobody names to its training opponent.

The episode is `tabx.rollout.play_episode` (one jitted program); the summary reports when and
how it ended, the winner, and each team's remaining units and health. `--gif out.gif` renders
every step.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import jax

from tabx import constants as C
from tabx.controllers import Controller, with_tiers
from tabx.errors import UserError
from tabx.policy_team import PolicyTeam
from tabx.profiles import DEFAULT_PROFILE, with_profile
from tabx.rollout import (
    DEFAULT_CONTROLLERS,
    Side,
    play_episode,
    render_gif,
    scripted_controllers,
    summarise,
)
from tabx.scenarios import ScenarioError, config_for, load_named
from tabx_ued.arguments import add_profile_argument
from ued.evaluate import load_policy_team

TEAM_FLAGS = ("--ally", "--enemy")


def parse_side(text: str, team: int, greedy: bool) -> Side:
    """A team's side from its flag's text: a run folder (its newest checkpoint's policy,
    `ued.evaluate.load_policy_team`) or a controller."""
    flag = TEAM_FLAGS[team]
    if Path(text).is_dir():
        try:
            return load_policy_team(text, team, greedy)
        except UserError as err:
            raise UserError(f"{flag}: {err}") from None
    if Path(text).exists():
        raise UserError(f"{flag}: {text}: not a folder (expected a run folder or a controller)")
    if "/" in text or "\\" in text:
        raise UserError(f"{flag}: {text}: no such run folder")
    try:
        return Controller.parse_scripted(text)
    except ValueError as err:
        raise UserError(f"{flag}: {text!r} is not a controller or a run folder ({err})"
                        ) from None


def resolve_sides(args: argparse.Namespace) -> tuple[tuple[Side, Side], PolicyTeam | None]:
    """(the sides of both teams, the first policy among them or None). A team nobody names
    plays the policy's training opponent, or the default controller when no policy plays."""
    texts = (args.ally, args.enemy)
    sides: list[Side | None] = [None if text is None else
                                parse_side(text, team, args.greedy)
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


def cmd_rollout(args: argparse.Namespace) -> int:
    """Play the scenario and print its outcome (and write the GIF)."""
    if args.steps < 1:
        raise UserError(f"--steps must be >= 1, got {args.steps}")
    if args.gif is not None and not args.gif.endswith(".gif"):
        raise UserError(f"--gif: expected a file name ending in .gif, got {args.gif!r}")
    controllers, policy = resolve_sides(args)
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


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    """Add `tabx rollout`."""
    side = ("a controller: random, idle, heuristic or heuristic:TIER, or a run folder (a "
            "trained policy)")
    p = subparsers.add_parser("rollout",
                              help="play a scenario (scripted teams or trained policies)")
    p.add_argument("name", nargs="?",
                   help="scenario name (tabx scenarios list), composition or file (default: "
                        "the policy's first training scenario)")
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
    p.set_defaults(func=cmd_rollout)


__all__ = ["add_parser", "cmd_rollout", "parse_side", "resolve_sides"]

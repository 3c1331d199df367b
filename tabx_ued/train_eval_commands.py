"""`tabx train` and `tabx eval`: runs on the command line (a registrar of `tabx_ued.cli`).

    tabx train configs/marl/mappo_crossfire.yaml [KEY=VALUE ...]
    tabx train quickstart | ued/accel_zone [KEY=VALUE ...]       (a shipped config, by name)
    tabx train --list-configs
    tabx train --resume RUN_DIR [--ray [--address A] [ray.KEY=VALUE ...]]
    tabx eval RUN_DIR [--scenario NAME] [--enemy heuristic:medium] [--episodes K] [--gif PATH]
    tabx eval --ally RUN_A --enemy RUN_B [--scenario NAME]
    tabx eval RUN_DIR --suite NAME_OR_FILE [--episodes K] [--json OUT] [--seed S]
    tabx eval RUN_DIR --suite NAME_OR_FILE --ray [--address auto|HOST:PORT]
    tabx eval --list-suites

A side of `tabx eval` (`--ally`, `--enemy`) is a run folder or a controller
(`heuristic[:TIER]`, `random`, `idle`); the positional RUN_DIR plays the team it was trained
for, and the team nobody names plays the run's training opponent. `--suite` evaluates the
run zero-shot on every entry of an evaluation suite (`ued.suites`, `workers.roles.evaluator`);
with `--ray` on a Ray actor (`workers.ray.remote_eval`), here or on a cluster.
Training goes through `workers.train.train`, which picks the driver.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path
from typing import Any

from tabx.errors import UserError
from tabx_ued.arguments import add_profile_argument

DEFAULT_EPISODES = 100  # of `tabx eval` without --suite


def cmd_train(args: argparse.Namespace) -> int:
    from ued.config import ConfigError, check_ray_overrides, load_config
    from workers.driver import RunStopped
    from workers.train import train

    if args.list_configs:
        from ued.config_files import list_configs

        print("\n".join(list_configs()))
        return 0
    positional = list(args.items)
    config_path = None
    if positional and "=" not in positional[0]:
        config_path = positional.pop(0)
    overrides = positional
    bad = [o for o in overrides if "=" not in o]
    if bad:
        raise UserError(f"expected KEY=VALUE overrides after the config, got {bad[0]!r}")
    if args.max_updates is not None and args.max_updates < 1:
        raise UserError(f"--max-updates must be >= 1, got {args.max_updates}")
    if args.address is not None and not args.ray:
        raise UserError("--address joins a Ray cluster: give --ray too")
    if args.address is not None and not args.address.strip():
        raise UserError("--address: empty; give auto or HOST:PORT (or leave --address out to "
                        "start Ray here)")
    ray_overrides = []
    if args.ray:
        ray_overrides.append("ray.enabled=true")
    if args.address is not None:  # a string as given (YAML would read `host:` as a mapping)
        ray_overrides.append(f"ray.address={json.dumps(args.address)}")
    try:
        if args.resume:
            if config_path and Path(config_path).is_dir():
                raise UserError(f"--resume takes one run folder; {config_path} is another "
                                f"(did a pattern match several runs?)")
            if config_path or any(not o.startswith("ray.") for o in overrides):
                raise UserError("--resume continues a run with its own config.yaml: give no "
                                "config file, and overrides of the ray: section only "
                                "(e.g. --ray ray.explorers=4)")
            run_dir = train(run_dir=args.resume, resume=True, max_updates=args.max_updates,
                            progress=not args.quiet,
                            ray=resume_ray(args.resume, overrides, ray_overrides))
        else:
            if config_path is None:
                raise UserError("give a config file or a shipped config's name (e.g. "
                                "quickstart, marl/mappo_crossfire; --list-configs) or "
                                "--resume RUN_DIR")
            config = load_config(config_path, [*overrides, *ray_overrides])
            check_ray_overrides(config, overrides)
            run_dir = train(config, run_dir=args.run_dir, max_updates=args.max_updates,
                            progress=not args.quiet)
    except (ConfigError, RunStopped) as err:
        raise UserError(str(err)) from None
    if not args.quiet:
        print(run_summary_lines(Path(run_dir)), file=sys.stderr)
    print(run_dir)
    return 0


def resume_ray(run_dir: str, overrides: list[str], flags: list[str]) -> Any:
    """The `ray:` section `tabx train --resume RUN_DIR` continues with (None: the run's own).
    Without `--ray` the run resumes on the local driver, whichever driver trained it (the run
    folder is the same): its own section with `ray.enabled: false`, which may be said. With
    `--ray` (`flags`: `ray.enabled=true`, and `ray.address` of `--address`) its own section with
    the `ray.*` `overrides`, on Ray."""
    from ued.config import apply_overrides, config_from_dict
    from ued.run_folder import read_run_config

    on_ray = bool(flags)
    if not on_ray:
        stray = [o for o in overrides if o.split("=", 1)[0].strip() != "ray.enabled"]
        if stray:
            raise UserError(f"ray.* overrides on --resume go with --ray (got {stray[0]!r}); "
                            f"without --ray the run resumes on the local driver")
    own = read_run_config(run_dir)
    if not overrides and not on_ray:
        return dataclasses.replace(own.ray, enabled=False) if own.ray.enabled else None
    source = f"{run_dir} with {' '.join([*overrides, *flags])}"
    asked = config_from_dict(apply_overrides(own.to_dict(), overrides), source=source).ray
    if on_ray and not asked.enabled:
        raise UserError("ray.enabled=false: --ray resumes the run on Ray; give one of them")
    if not on_ray:
        if asked.enabled:
            raise UserError("ray.enabled=true on --resume: give --ray to resume on Ray")
        return asked
    return config_from_dict(apply_overrides(own.to_dict(), [*overrides, *flags]),
                            source=source).ray


def run_summary_lines(run_dir: Path) -> str:
    """What a run ended with, for the terminal: the last logged win rate, the last zero-shot
    mean win rate of each suite, and where its checkpoints are. Best effort: a part that
    cannot be read is left out (the run itself is complete)."""
    from ued.run_folder import CHECKPOINT_DIR, EVENTS_DIR

    lines = [f"summary of {run_dir}:"]
    try:
        from ued.tensorboard import read_scalars

        scalars = read_scalars(run_dir / EVENTS_DIR)
    except Exception:  # noqa: BLE001 (no events/, a multi-seed run, unreadable files)
        scalars = {}
    lines += _training_win_rate(scalars)
    for tag in sorted(t for t in scalars if t.startswith("eval/") and
                      t.endswith("/mean_win_rate")):
        step, value = scalars[tag][-1]
        lines.append(f"  zero-shot mean win rate, {tag.split('/')[1]} (env step {step}): "
                     f"{value:.3f}")
    folder = run_dir / CHECKPOINT_DIR
    steps = sorted(int(p.name) for p in folder.iterdir() if p.name.isdigit()) \
        if folder.is_dir() else []
    if steps:
        lines.append(f"  checkpoints: {folder} (steps {', '.join(map(str, steps))}); "
                     f"evaluate with tabx eval {run_dir}")
    return "\n".join(lines)


def _training_win_rate(scalars: dict[str, list[tuple[int, float]]]) -> list[str]:
    """The training win rate of the last logged update, with the episodes it is over (an
    update whose rollouts ended no episode logs none: `learner.num_steps` below
    `env.max_steps` ends one only by an elimination)."""
    counts = dict(scalars.get("episode/count", []))
    rates = scalars.get("episode/win_rate", [])
    if not counts and not rates:
        return []
    last = max(counts) if counts else rates[-1][0]
    if rates and rates[-1][0] == last:
        step, value = rates[-1]
        return [f"  win rate (training, at env step {step}): {value:.3f}"
                + (f" over {_episodes(counts[step])}" if step in counts else "")]
    line = (f"  win rate (training): none; no episode ended within the rollouts of the last "
            f"logged update (env step {last})")
    if rates:
        step, value = rates[-1]
        line += (f"; the last that had one, at env step {step}: {value:.3f}"
                 + (f" over {_episodes(counts[step])}" if step in counts else ""))
    return [line]


def _episodes(count: float) -> str:
    return f"{count:.0f} episode{'' if count == 1 else 's'}"


def cmd_eval(args: argparse.Namespace) -> int:
    from tabx import constants as C
    from tabx.controllers import Controller
    from tabx.profiles import DEFAULT_PROFILE, with_profile
    from tabx.scenarios import ScenarioError, config_for, load_named
    from ued import compile_cache
    from ued.config import ConfigError
    from ued.evaluate import format_result, parse_side, play
    from ued.run_folder import TrainedPolicy, load_policy

    if args.list_suites:
        return _list_suites()
    if args.episodes is not None and args.episodes < 1:
        raise UserError(f"--episodes must be >= 1, got {args.episodes}")
    if args.address is not None and not args.ray:
        raise UserError("--address joins a Ray cluster: give --ray too")
    if args.ray and args.suite is None:
        raise UserError("--ray plays an evaluation suite on a Ray actor: give --suite")
    if args.max_steps is not None and not 1 <= args.max_steps <= C.MAX_STEPS:
        raise UserError(f"--max-steps must be an integer in [1, {C.MAX_STEPS}] (steps per "
                        f"episode), got {args.max_steps}")
    compile_cache.enable()
    if args.suite is not None:
        return _eval_suite(args)
    if args.json:
        raise UserError("--json goes with --suite")
    episodes = DEFAULT_EPISODES if args.episodes is None else args.episodes
    try:
        sides: list = [None, None]
        run = load_policy(args.run_dir, args.checkpoint) if args.run_dir else None
        if run is not None:
            sides[run.team] = run
        for team, text in enumerate((args.ally, args.enemy)):
            if text is None:
                continue
            if sides[team] is not None:
                raise UserError(f"the {('ally', 'enemy')[team]} team is already played by "
                                f"{args.run_dir}; name only the other team")
            sides[team] = parse_side(text)
        if args.max_steps is not None:
            sides = [s.with_episode_limit(args.max_steps) if isinstance(s, TrainedPolicy) else s
                     for s in sides]
            run = sides[run.team] if run is not None else None
        policies = [s for s in sides if isinstance(s, TrainedPolicy)]
        reference = run or (policies[0] if policies else None)
        for team in range(2):
            if sides[team] is None:
                if reference is None:
                    raise UserError("give a run folder, or both --ally and --enemy")
                sides[team] = Controller.parse(reference.config.env.opponent)
        name = args.scenario or (reference.config.env.scenario[0] if reference else None)
        if name is None:
            raise UserError("--scenario is needed when no run folder is given")
        try:
            scenario = load_named(name)
        except ScenarioError as err:
            raise UserError(str(err)) from None
        if reference is not None:
            env_config = reference.learner.env_config
        else:
            env_config = config_for([scenario], max_steps=args.max_steps or C.DEFAULT_MAX_STEPS)
        try:
            level = scenario.to_level(env_config)
        except ScenarioError as err:
            raise UserError(f"{err} (the policy's EnvConfig: {env_config})") from None
        profile = args.profile or (reference.config.env.profile if reference
                                   else DEFAULT_PROFILE)
        level = with_profile(level, profile)
        result = play(env_config, level, sides[0], sides[1], episodes, seed=args.seed,
                      greedy=args.greedy, record=bool(args.gif))
    except ConfigError as err:
        raise UserError(str(err)) from None
    print(format_result(result, (sides[0], sides[1]), scenario.name, args.greedy, profile))
    if args.gif:
        _write_gif(args.gif, env_config, level, sides, result)
    return 0


def _list_suites() -> int:
    from ued.suites import list_suites, load_suite

    for name in list_suites():
        suite = load_suite(name)
        print(f"{name:30s} {len(suite.entries)} entries  {suite.description}")
    return 0


def _eval_suite(args: argparse.Namespace) -> int:
    """`tabx eval RUN_DIR --suite NAME_OR_FILE`: a table per suite, JSON with --json."""
    import jax

    from tabx.files import atomic_write_json
    from ued.config import ConfigError
    from ued.run_folder import load_policy
    from ued.suites import load_suite
    from workers.roles.evaluator import Evaluator, format_table, to_json

    clash = [flag for flag, value in (("--scenario", args.scenario), ("--ally", args.ally),
                                      ("--enemy", args.enemy), ("--gif", args.gif)) if value]
    if clash:
        raise UserError(f"--suite names the scenarios and opponents itself; drop {clash[0]}")
    if not args.run_dir:
        raise UserError("--suite evaluates a run folder: give RUN_DIR")
    try:
        suite = load_suite(args.suite)
        policy = load_policy(args.run_dir, args.checkpoint)
        if args.max_steps is not None:
            policy = policy.with_episode_limit(args.max_steps)
        profile = args.profile or policy.config.env.profile
        key = jax.random.key(args.seed)
        if args.ray:
            from workers.ray.remote_eval import evaluate_on_ray

            result = evaluate_on_ray(policy, suite, key, episodes=args.episodes,
                                     greedy=args.greedy, address=args.address or "",
                                     profile=profile)
        else:
            evaluator = Evaluator(policy.learner, suite, episodes=args.episodes,
                                  greedy=args.greedy, profile=profile)
            result = evaluator.evaluate(policy.params, key)
    except ConfigError as err:
        raise UserError(str(err)) from None
    print(f"policy {policy}, profile {profile}")
    print(format_table(result))
    if args.json:
        data = {"run_dir": str(policy.run_dir), "algorithm": policy.config.algorithm,
                "update": policy.update, "seed": args.seed, "profile": profile,
                **to_json(result)}
        atomic_write_json(args.json, data)
        print(f"wrote {args.json}")
    return 0


def _write_gif(path: str, env_config, level, sides, result) -> None:
    import jax
    import jax.numpy as jnp
    import numpy as np

    from tabx.controllers import Controller, with_tiers
    from tabx.env import TabxEnv

    try:
        from tabx.render import render_trajectory, save_gif
    except ImportError:  # the renderer is optional
        raise UserError("--gif needs tabx.render, which this install lacks") from None
    controllers = tuple(s if isinstance(s, Controller) else Controller("external")
                        for s in sides)
    start = TabxEnv(env_config).initial_state(with_tiers(level, controllers))
    states = jax.tree.map(lambda s, x: jnp.concatenate([s[None], x]), start, result.states)
    infos = {k: np.concatenate([np.zeros_like(v[:1]), v]) for k, v in result.infos.items()}
    frames = render_trajectory(env_config, level, states, infos)
    save_gif(frames, path)
    print(f"wrote {path} ({len(frames)} frames, episode 0)")


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    train = subparsers.add_parser(
        "train", help="train MAPPO or IPPO from a YAML config (UED if ued.method is set)",
        description="Train MAPPO or IPPO from a YAML config (configs/marl/; with ued.method "
                    "set, a UED curriculum: configs/ued/, docs/ued.md), given as a file or as "
                    "a shipped config's name (quickstart, ued/accel_zone). Overrides: "
                    "KEY=VALUE with KEY a section.field (learner.lr) or an unambiguous field "
                    "name (lr). The run folder (config.yaml, events/, checkpoints/) is printed "
                    "at the end.")
    train.add_argument("items", nargs="*", metavar="CONFIG [KEY=VALUE ...]",
                       help="config file or shipped config name, then overrides")
    train.add_argument("--list-configs", action="store_true",
                       help="list the shipped configs' names and exit")
    train.add_argument("--resume", metavar="RUN_DIR",
                       help="continue a run from its newest checkpoint")
    train.add_argument("--run-dir", help="the run folder (default: run.dir/NAME-TIMESTAMP)")
    train.add_argument("--max-updates", type=int,
                       help="stop after this many updates (resume later with --resume)")
    train.add_argument("--quiet", action="store_true", help="no progress line")
    train.add_argument("--ray", action="store_true",
                       help="run the UED workers as Ray actors (ray.enabled=true; needs the "
                            "ray extra): on this machine, or on a cluster with --address")
    train.add_argument("--address", metavar="ADDRESS",
                       help="with --ray: join a running Ray cluster (auto, or HOST:PORT)")
    train.set_defaults(func=cmd_train)

    ev = subparsers.add_parser(
        "eval", help="evaluate trained policies (win rate, return, episode length)",
        description="Play episodes with trained policies and print win rate, return and "
                    "episode length with 95% confidence intervals.")
    ev.add_argument("run_dir", nargs="?", help="run folder of the policy to evaluate")
    ev.add_argument("--scenario", help="scenario name or file (default: the run's first)")
    ev.add_argument("--ally", help="who plays the ally team: a run folder or a controller")
    ev.add_argument("--enemy", help="who plays the enemy team: a run folder or a controller "
                                    "(heuristic:TIER, random, idle)")
    ev.add_argument("--episodes", type=int,
                    help=f"episodes (default {DEFAULT_EPISODES}; with --suite: per entry, "
                         f"default the suite's)")
    ev.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    ev.add_argument("--greedy", action="store_true",
                    help="take the most likely action instead of sampling")
    ev.add_argument("--checkpoint", type=int,
                    help="checkpoint (update number) of RUN_DIR (default: newest)")
    ev.add_argument("--max-steps", type=int,
                    help="episode limit (default: the run's env.max_steps; without a run "
                         "folder 512). With a run folder, its policy plays episodes of this "
                         "length: observations carry no clock")
    ev.add_argument("--gif", metavar="PATH", help="also render episode 0 as an animated GIF")
    ev.add_argument("--suite", metavar="NAME_OR_FILE",
                    help="evaluate RUN_DIR on every entry of an evaluation suite (a shipped "
                         "suite's name, see --list-suites, or a .yaml file)")
    ev.add_argument("--json", metavar="OUT", help="with --suite: also write the results as JSON")
    ev.add_argument("--list-suites", action="store_true",
                    help="list the shipped evaluation suites and exit")
    ev.add_argument("--ray", action="store_true",
                    help="with --suite: play the suite on a Ray actor (needs the ray extra): "
                         "on this machine, or on a cluster with --address")
    ev.add_argument("--address", metavar="ADDRESS",
                    help="with --ray: join a running Ray cluster (auto, or HOST:PORT)")
    add_profile_argument(ev, "the run's env.profile, else tabx-ued")
    ev.set_defaults(func=cmd_eval)

__all__ = ["add_parser", "cmd_eval", "cmd_train"]

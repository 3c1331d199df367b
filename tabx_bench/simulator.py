"""`tabx bench env`: simulator throughput and compile time. `tabx bench scale | reconfig |
compare` build on the machinery here (tabx_bench/suite.py); the command line is
tabx_bench/cli.py.

`--ally` / `--enemy` choose each team's controller (tabx.controllers): the scripted-enemy
benchmark is `--enemy heuristic:medium` (random allies, scripted enemies).

Protocol: random legal actions for every unit slot; `jit` of a 128-step `lax.scan`
over `vmap(step_autoreset)`; the batch of levels is a jit *argument* (never a baked-in
constant); one warm-up call, then 3 timed calls (median, `block_until_ready`). Env steps/s =
num_envs x steps / seconds, compile excluded; compile time (lower + compile) reported
separately. By default the observation is carried through the scan, so it is computed every
step as a policy would need it; with `--no-obs` it is dropped (a random policy never reads it,
and XLA then skips computing it), which is what a plain random-action benchmark measures.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import time
from dataclasses import asdict, dataclass

import jax
import jax.numpy as jnp
import numpy as np

from tabx.controllers import (
    Controller,
    controlled_actions_from_words,
    controller_words,
    with_tiers,
)
from tabx.devices import env_devices, env_sharding
from tabx.env import TabxEnv, random_legal_actions
from tabx.jit_options import simulator_jit
from tabx.native_lib import native_available
from tabx.params import EnvConfig, EnvParams, make_level, repeat_level

RANDOM_BOTH = (Controller("random"), Controller("random"))

TEAM_SIZES = (3, 5, 10)
NUM_ENVS = (1, 16, 128, 1024)
UNIT_CYCLE = ("farmer", "archer", "theking", "healer", "assassin", "deadeye", "cannon",
              "paladin", "mammoth")


@dataclass
class BenchResult:
    team_size: int
    zones: int
    num_envs: int
    with_obs: bool
    steps: int
    compile_s: float
    run_s: float
    steps_per_s: float
    controllers: str = "random/random"
    load_avg: float | None = None  # 1-minute load average when the run started (shared machines)
    devices: int = 1  # devices the envs were split over (tabx.devices)


@dataclass
class ReconfigResult:
    simulator: str
    scenarios: int  # scenarios the result speaks for
    num_envs: int
    steps: int
    total_s: float  # first call to last result, compilation included (extrapolated if flagged)
    first_s: float  # first scenario: trace + compile + run
    compile_s: float  # trace, lowering and XLA compile seconds, all scenarios (measured ones)
    compilations: int  # XLA compilations while timing (measured scenarios)
    recompilations: int  # compilations after the first scenario
    effective_steps_per_s: float  # scenarios x num_envs x steps / total_s
    measured_scenarios: int = 0  # scenarios really run (< scenarios when extrapolated)
    extrapolated: bool = False
    generate_s: float = 0.0  # building and validating the levels (not in total_s)
    load_avg: float | None = None

    @property
    def env_steps(self) -> int:
        return self.scenarios * self.num_envs * self.steps


def bench_level(team_size: int, num_zones: int) -> tuple[EnvConfig, EnvParams]:
    """A team_size v team_size battle in lines facing each other, with num_zones zones."""
    config = EnvConfig(max_allies=team_size, max_enemies=team_size, max_zones=max(num_zones, 1))
    ys = np.linspace(-30, 30, team_size) if team_size > 1 else np.zeros(1)
    allies = [dict(unit=UNIT_CYCLE[i % 9], position=(-12.0, float(y)), heading=0.0)
              for i, y in enumerate(ys)]
    enemies = [dict(unit=UNIT_CYCLE[(i + 4) % 9], position=(12.0, float(y)), heading=np.pi)
               for i, y in enumerate(ys)]
    kinds = ("lava", "bush", "swamp")
    zones = [dict(type=kinds[i % 3], centre=(-40.0 + 16.0 * i, 10.0 * (-1) ** i),
                  semi_axes=(6.0, 5.0), effect=(10.0, 0.0, 0.4)[i % 3])
             for i in range(num_zones)]
    return config, make_level(config, allies, enemies, zones)


def make_rollout(env: TabxEnv, steps: int, with_obs: bool = True,
                 controllers: tuple[Controller, Controller] = RANDOM_BOTH):
    """jit(levels, key) -> final carry of a `steps`-long scan over all envs, each team driven
    by its controller (random legal actions by default).

    With `with_obs`, every step starts by computing the observation of the state it acts on,
    where a policy would consume it, and carries it out of the scan so that XLA keeps it: one
    observation per step taken, none for a start state (the auto-reset's start states are
    passed in, so the step itself needs no observation). Random and scripted controllers draw
    their randomness for the whole batch from one key per step (`random_legal_actions`,
    `tabx.controllers.controller_words`), not from a key per env. Compiled with
    `tabx.jit_options.simulator_jit`."""
    plain_random = all(c.kind == "random" for c in controllers)

    def rollout(levels: EnvParams, key: jax.Array):
        num_envs = levels.reward_mode.shape[0]
        states = jax.vmap(env.initial_state)(levels)
        start_states = states  # auto-reset into the same levels
        observe = jax.vmap(env.observe)

        def body(carry, _):
            key, states, obs, total = carry
            if with_obs:
                obs = observe(states, levels)
            key, k_act = jax.random.split(key)
            if plain_random:
                masks = jax.vmap(env.action_mask)(states, levels)
                actions = random_legal_actions(k_act, masks)
            else:
                words = controller_words(k_act, num_envs, env.num_units)
                actions, states = jax.vmap(
                    lambda w, s, p: controlled_actions_from_words(w, s, p, None, controllers))(
                    words, states, levels)
            _, states, reward, done, _ = jax.vmap(env.step_autoreset)(
                jax.random.split(key, num_envs), states, actions, levels, start_states)
            # Per-env sums: a batch split over devices then needs no exchange between them.
            return (key, states, obs, total + reward.sum(-1) + done), None

        if with_obs:
            spec = jax.eval_shape(observe, states, levels)
            obs = jnp.zeros(spec.shape, spec.dtype)
        else:
            obs = jnp.zeros((num_envs, 0), jnp.float32)
        carry, _ = jax.lax.scan(body, (key, states, obs, jnp.zeros(num_envs)), None,
                                length=steps)
        return carry

    return simulator_jit(rollout)


def run_one(team_size: int, num_zones: int, num_envs: int, steps: int = 128,
            repeats: int = 3, with_obs: bool = True,
            controllers: tuple[Controller, Controller] = RANDOM_BOTH,
            devices: int = 0) -> BenchResult:
    """One configuration, its envs split over `devices` local devices (0: all that split
    them evenly; `tabx.devices.env_devices`)."""
    config, level = bench_level(team_size, num_zones)
    env = TabxEnv(config)
    placed = env_devices(num_envs, devices)
    levels = repeat_level(with_tiers(level, controllers), num_envs)
    # Materialised on the devices: a real argument, never a constant of the program.
    levels = jax.device_put(jax.tree.map(np.asarray, levels), env_sharding(placed))
    fn = make_rollout(env, steps, with_obs, controllers)
    load_avg = load_average()
    compile_s, run_s = time_compiled(fn, lambda key: (levels, key), repeats)
    return BenchResult(team_size, num_zones, num_envs, with_obs, steps, compile_s, run_s,
                       num_envs * steps / run_s, "/".join(map(str, controllers)), load_avg,
                       len(placed))


def time_compiled(fn, make_args, repeats: int = 3) -> tuple[float, float]:
    """(compile seconds, median run seconds) of a jitted fn: lower + compile timed, one warm-up
    call, then `repeats` timed calls; `make_args(key)` gives the arguments of each call. The
    native kernels are built (or found cached) first, outside the compile time."""
    native_available()
    t0 = time.perf_counter()
    compiled = fn.lower(*make_args(jax.random.key(0))).compile()
    compile_s = time.perf_counter() - t0
    jax.block_until_ready(compiled(*make_args(jax.random.key(0))))  # warm-up
    times = []
    for i in range(repeats):
        args = make_args(jax.random.key(i + 1))
        t0 = time.perf_counter()
        jax.block_until_ready(compiled(*args))
        times.append(time.perf_counter() - t0)
    return compile_s, statistics.median(times)


def load_average() -> float | None:
    """The 1-minute load average (None where the OS has none): next to every timing, since
    the benchmark machines are often shared."""
    try:
        return round(os.getloadavg()[0], 2)
    except OSError:
        return None


class Progress:
    """`[i/n, eta Ns]` suffixes for progress lines: eta from the mean time per item so far."""

    def __init__(self, total: int):
        self.total, self.done, self.start = total, 0, time.perf_counter()

    def step(self) -> str:
        self.done += 1
        elapsed = time.perf_counter() - self.start
        eta = elapsed / self.done * (self.total - self.done)
        return f"[{self.done}/{self.total}, eta {eta:.0f}s]"


def machine_summary() -> str:
    return (f"{platform.node()} {platform.machine()}, {jax.device_count()}x "
            f"{jax.devices()[0].device_kind}, jax {jax.__version__}, python "
            f"{platform.python_version()}")


def bench_env(args: argparse.Namespace) -> int:
    from tabx.errors import UserError

    try:
        controllers = (Controller.parse_scripted(args.ally), Controller.parse_scripted(args.enemy))
    except ValueError as err:
        raise UserError(f"--ally/--enemy: {err}") from None
    check_devices(args.devices, args.num_envs)
    print(f"# tabx bench env on {machine_summary()}; observations "
          f"{'computed every step' if args.obs else 'not computed (--no-obs)'}; allies "
          f"{controllers[0]}, enemies {controllers[1]}", flush=True)
    print(f"{'units':>6} {'zones':>5} {'envs':>6} {'devices':>7} {'compile s':>9} {'run s':>8} "
          f"{'steps/s':>12}", flush=True)
    results = []
    configs = [(t, z, n) for t in args.team_sizes for z in args.zones for n in args.num_envs]
    progress = Progress(len(configs))
    for team, zones, envs in configs:
        r = run_one(team, zones, envs, steps=args.steps, repeats=args.repeats, with_obs=args.obs,
                    controllers=controllers, devices=args.devices)
        results.append(r)
        print(f"{f'{team}v{team}':>6} {zones:>5} {envs:>6} {r.devices:>7} {r.compile_s:>9.2f} "
              f"{r.run_s:>8.3f} {r.steps_per_s:>12,.0f}   {progress.step()}", flush=True)
    if args.json:
        write_results(args.json, results)
    return 0


def check_devices(devices: int, env_counts: list[int]) -> None:
    """UserError naming --devices unless every env count splits over `devices` devices."""
    from tabx.errors import UserError

    for num_envs in env_counts:
        try:
            env_devices(num_envs, devices)
        except ValueError as err:
            raise UserError(f"--devices: {err}") from None


def write_results(path: str, results: list) -> None:
    """Benchmark results (dataclasses or dicts) as JSON lines with the machine summary,
    atomically."""
    from tabx.files import atomic_write_text

    machine = machine_summary()
    atomic_write_text(path, "".join(
        json.dumps({**(r if isinstance(r, dict) else asdict(r)), "machine": machine}) + "\n"
        for r in results))
    print(f"wrote {path}")

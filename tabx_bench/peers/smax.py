"""SMAX (JaxMARL 0.2.0) under our benchmark protocols, for `tabx bench compare`.

Fixed configuration: an N v N SMAX scenario (unit types cycling through SMAX's six: marine,
marauder, stalker, zealot, zergling, hydralisk), random legal actions for every agent (the same
sampler as ours, `tabx.env.random_legal_actions` over SMAX's avail-action masks), `jit` of a
`steps`-long `lax.scan` over `vmap(step)` with auto-reset into the start states
(`env.step_env`, then a select of the start state and observation where the episode ended:
what SMAX's `step(..., reset_state)` does, and what our `step_autoreset` does), observations
carried in the scan
(or dropped with `with_obs=False`), one warm-up call and `repeats` timed calls: the protocol of
`tabx_bench.simulator.run_one`.

Reconfiguration: in SMAX a scenario's unit counts are array shapes and its unit types are
constants of the environment object, so a new scenario (new types and counts) is a new
`SMAX(scenario=...)` and a new compilation. Each scenario: build the environment, jit the same
rollout, run `num_envs` x `steps`, wait for the result. `measure` < `scenarios` runs only the
first `measure` scenarios and extrapolates linearly (flagged `extrapolated` in the result).

Needs jaxmarl (`pip install -e ".[peers]"`); importing this module without it raises
`tabx_bench.peers.PeerUnavailable` with the install command.
"""

from __future__ import annotations

import time
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np

from tabx.compile_counter import CompileCounter
from tabx.devices import env_devices, env_sharding
from tabx.env import random_legal_actions
from tabx_bench.peers import INSTALL_HINT, PeerUnavailable
from tabx_bench.simulator import BenchResult, Progress, ReconfigResult, load_average, time_compiled

try:
    import jaxmarl
    from jaxmarl.environments.smax import SMAX, Scenario
except ImportError as err:  # pragma: no cover - depends on the optional extra
    raise PeerUnavailable(f"SMAX needs jaxmarl, which is not installed ({err}); "
                          f"{INSTALL_HINT}") from None

SMAX_UNIT_TYPES = 6  # marine, marauder, stalker, zealot, zergling, hydralisk


def smax_env(ally_types: list[int], enemy_types: list[int]) -> SMAX:
    scenario = Scenario(jnp.asarray(list(ally_types) + list(enemy_types), jnp.uint8),
                        len(ally_types), len(enemy_types), False, False)
    return SMAX(scenario=scenario)


def mixed_types(team_size: int, offset: int = 0) -> list[int]:
    return [(i + offset) % SMAX_UNIT_TYPES for i in range(team_size)]


def make_smax_rollout(env: SMAX, num_envs: int, steps: int, with_obs: bool = True,
                      devices: int = 0):
    """jit(key) -> final carry of a `steps`-long scan of `num_envs` SMAX envs, random legal
    actions, auto-reset into the start states. (SMAX has no level argument: the scenario is
    part of the environment object.)"""
    agents = env.agents

    def step_autoreset(key, state, actions, reset_state, reset_obs):
        # MultiAgentEnv.step with a reset state, minus its get_obs of the reset state (which in
        # jaxmarl 0.2.0 lacks "world_state" and fails): the select that ours does too.
        obs, state, reward, done, info = env.step_env(key, state, actions)
        pick = lambda reset, new: jax.lax.select(done["__all__"], reset, new)
        return (jax.tree.map(pick, reset_obs, obs), jax.tree.map(pick, reset_state, state),
                reward, done, info)

    # The envs split over the devices as ours are (`tabx.devices`): the keys they start from
    # are placed there, and everything per env follows them.
    placement = env_sharding(env_devices(num_envs, devices))

    def rollout(key: jax.Array):
        key, k_reset = jax.random.split(key)
        reset_keys = jax.lax.with_sharding_constraint(jax.random.split(k_reset, num_envs),
                                                      placement)
        obs, states = jax.vmap(env.reset)(reset_keys)
        start_states, start_obs = states, obs

        def body(carry, _):
            key, states, obs, total = carry
            key, k_act, k_step = jax.random.split(key, 3)
            avail = jax.vmap(env.get_avail_actions)(states)
            # (E, N, A): allies have 5 + enemies actions, enemies 5 + allies; pad with illegal.
            width = max(avail[a].shape[-1] for a in agents)
            mask = jnp.stack([jnp.pad(avail[a].astype(bool),
                                      ((0, 0), (0, width - avail[a].shape[-1])))
                              for a in agents], axis=1)
            acts = random_legal_actions(k_act, mask)
            actions = {a: acts[:, i] for i, a in enumerate(agents)}
            step_keys = jax.lax.with_sharding_constraint(jax.random.split(k_step, num_envs),
                                                         placement)
            new_obs, states, reward, done, _ = jax.vmap(step_autoreset)(
                step_keys, states, actions, start_states, start_obs)
            obs = new_obs if with_obs else obs
            # Per-env sums, as ours: no exchange between devices every step.
            total = total + sum(r for r in reward.values()) + done["__all__"]
            return (key, states, obs, total), None

        carry, _ = jax.lax.scan(body, (key, states, obs, jnp.zeros(num_envs)), None,
                                length=steps)
        return carry

    return jax.jit(rollout)


class SmaxSimulator:
    """SMAX behind the interface `tabx_bench.suite.run_compare` expects."""

    name = "SMAX"

    def __init__(self, devices: int = 0):
        self.devices = devices  # local devices the envs are split over (0: all that divide)

    def version(self) -> str:
        return f"jaxmarl {getattr(jaxmarl, '__version__', '0.2.0')}"

    def throughput(self, team_size: int, num_envs: int, steps: int, repeats: int,
                   with_obs: bool) -> BenchResult:
        env = smax_env(mixed_types(team_size), mixed_types(team_size, 3))
        fn = make_smax_rollout(env, num_envs, steps, with_obs, self.devices)
        load_avg = load_average()
        compile_s, run_s = time_compiled(fn, lambda key: (key,), repeats)
        return BenchResult(team_size, 0, num_envs, with_obs, steps, compile_s, run_s,
                           num_envs * steps / run_s, "smax:random/random", load_avg,
                           len(env_devices(num_envs, self.devices)))

    def reconfig(self, scenarios: int, num_envs: int, steps: int, seed: int, with_obs: bool,
                 measure: int | None = None, log: Callable[[str], None] | None = None):
        measure = scenarios if measure is None else min(measure, scenarios)
        rng = np.random.default_rng(seed)
        comps = []
        for _ in range(measure):
            n_a, n_e = (int(x) for x in rng.integers(3, 11, size=2))
            comps.append(([int(t) for t in rng.integers(0, SMAX_UNIT_TYPES, n_a)],
                          [int(t) for t in rng.integers(0, SMAX_UNIT_TYPES, n_e)]))
        progress = Progress(measure)
        load_avg = load_average()
        with CompileCounter() as cc:
            t0 = time.perf_counter()
            first_s, after_first = 0.0, 0
            for i, (allies, enemies) in enumerate(comps):
                t_i = time.perf_counter()
                env = smax_env(allies, enemies)  # a new scenario: a new env, a new compile
                fn = make_smax_rollout(env, num_envs, steps, with_obs, self.devices)
                jax.block_until_ready(fn(jax.random.key(seed + i)))
                if i == 0:
                    first_s, after_first = time.perf_counter() - t0, cc.compiles
                if log is not None:
                    log(f"  SMAX scenario {i + 1:>3} {len(allies)}v{len(enemies)} "
                        f"{time.perf_counter() - t_i:7.2f} s   {progress.step()}")
            measured_s = time.perf_counter() - t0
        total_s = measured_s * scenarios / measure
        return ReconfigResult(
            "smax", scenarios, num_envs, steps, total_s, first_s, cc.seconds, cc.compiles,
            cc.compiles - after_first, scenarios * num_envs * steps / total_s, measure,
            measure < scenarios, 0.0, load_avg)

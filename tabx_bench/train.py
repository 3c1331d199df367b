"""`tabx bench train`: end-to-end training throughput of MAPPO and IPPO (by default) and of the
Q-learners IQL, VDN and QMIX (`--algorithms iql,vdn,qmix`).

Protocol (docs/benchmarks.md, "Training throughput"): the paper's defaults (128 envs x 512
steps per update, 4 epochs of 4 minibatches, hidden 128; for the Q-learners their table:
hidden 512, 8 gradient steps of 32 trajectories per update, a buffer of 5000 trajectories of
`num_steps` steps, which at 128 x 512 takes some GB of device memory) on a scenario (default
crossfire)
against an opponent (default the medium heuristic). The first update is timed from the call to
its result, compilation included; then `--updates` more updates are timed one by one
(`block_until_ready`), and the steady-state throughput is env steps per update / median seconds
per update. A fresh learner is built for each algorithm (no compiled function is reused; a
persistent compilation cache, if the user configured one, is switched off for the run), and the
level batch is a jit argument, as in training. `--reference-like` trains with the reference's
structure instead (see `reference_like`), to compare on the same machine at the same moment.
`--matmul-dtype` sets `learner.matmul_dtype` (default: the config default, bfloat16).
`--learners 1,2` runs the protocol once per learner-group size (tabx_bench.learner_group: N > 1
in N processes of this machine), each with its reduction time per update. """

from __future__ import annotations

import argparse
import dataclasses
import statistics
import time
from dataclasses import dataclass
from typing import Any

import jax
import jax.numpy as jnp

from ued.config import MATMUL_DTYPES


@dataclass
class TrainBenchResult:
    algorithm: str
    variant: str  # "ours" or "reference-like"
    scenario: str
    opponent: str
    num_envs: int
    num_steps: int
    first_update_s: float
    update_s: float  # median of the timed updates
    steps_per_s: float
    updates: int
    devices: int = 1  # the envs were split over this many devices (data parallel)
    matmul_dtype: str = "float32"  # the networks' matmul inputs (learner.matmul_dtype)
    learners: int = 1  # processes of the learner group (tabx_bench.learner_group)
    reduce_s: float = 0.0  # cross-device reduction seconds per update (estimated beside it)
    param_bytes: int = 0  # bytes of the parameters: what one gradient reduction sums


def reference_like(learner: Any) -> Any:
    """Give `learner` the reference's training structure, for comparison: each network as a
    plain per-step scan differentiated by autodiff (no rematerialisation, no unrolling) and,
    for MAPPO, the critic run once per agent on a copy of the world state (JaxMARL's
    `mappo_rnn.py`). Same maths, other speed; the fused GRU matmuls, the rollout and the
    simulator stay ours."""
    from ued.learners import networks as nw

    def plain(p, x, starts, h0):
        def body(h, inputs):
            x_t, start_t = inputs
            return nw.step(p, x_t, jnp.where(start_t[:, None], 0.0, h), learner.matmul_dtype)

        return jax.lax.scan(body, h0, (x, starts))[1]

    hidden = learner.ppo.hidden_dim

    def evaluate_sequence(params, x, world, starts):
        steps, envs, agents = x.shape[:3]
        flat = x.reshape(steps, envs * agents, x.shape[-1])
        agent_starts = jnp.repeat(starts, agents, axis=1)
        h0 = jnp.zeros((envs * agents, hidden), jnp.float32)
        if not learner.centralised:
            out = plain(params["net"], flat, agent_starts, h0).reshape(steps, envs, agents, -1)
            return out[..., :-1], out[..., -1]
        logits = plain(params["actor"], flat, agent_starts, h0)
        per_agent_world = jnp.repeat(world, agents, axis=1)
        values = plain(params["critic"], per_agent_world, agent_starts, h0)
        return (logits.reshape(steps, envs, agents, -1),
                values.reshape(steps, envs, agents).mean(-1))

    learner.evaluate_sequence = evaluate_sequence
    return learner


def run_train_bench(algorithm: str, scenario: str = "crossfire",
                    opponent: str = "heuristic:medium", num_envs: int = 128,
                    num_steps: int = 512, updates: int = 3,
                    variant: str = "ours", matmul_dtype: str | None = None,
                    learners: int = 1) -> TrainBenchResult:
    """The protocol of the module doc in this process; `learners` > 1: this process is one
    member of a learner group that runs it together (tabx_bench.learner_group)."""
    # A cold compile, always: JAX decides once per process, at its first compilation, whether
    # to use a persistent cache, so switch it off before anything here compiles (and check
    # below that the update really compiled).
    cache = jax.config.jax_enable_compilation_cache
    jax.config.update("jax_enable_compilation_cache", False)
    try:
        result = _run_train_bench(algorithm, scenario, opponent, num_envs, num_steps,
                                  updates, variant, matmul_dtype)
        return dataclasses.replace(result, learners=learners)
    finally:
        jax.config.update("jax_enable_compilation_cache", cache)


def _run_train_bench(algorithm: str, scenario: str, opponent: str, num_envs: int,
                     num_steps: int, updates: int, variant: str, matmul_dtype: str | None
                     ) -> TrainBenchResult:
    from tabx.compile_counter import CompileCounter
    from tabx.params import repeat_level
    from tabx.scenarios import config_for, load_named
    from ued.config import Q_LEARNER_SETTINGS, LearnerConfig, QLearningConfig
    from ued.learners import make_learner
    from ued.registry import learner_class

    level_scenario = load_named(scenario)
    env_config = config_for([level_scenario])
    levels = jax.tree.map(jnp.array, repeat_level(level_scenario.to_level(env_config), num_envs))
    ppo = LearnerConfig(num_envs=num_envs, num_steps=num_steps)
    q = None
    if learner_class(algorithm).settings_type is QLearningConfig:
        # The paper's Q-learning settings, learning from the first update on (every timed
        # update samples and takes its gradient steps once the buffer holds a batch).
        ppo = dataclasses.replace(ppo, **Q_LEARNER_SETTINGS)
        q = QLearningConfig(learning_starts=0,
                            buffer_size=max(QLearningConfig.buffer_size, num_envs))
    if matmul_dtype is not None:
        ppo = dataclasses.replace(ppo, matmul_dtype=matmul_dtype)
    learner = make_learner(algorithm, env_config, ppo, "ally", opponent, cached=False,
                           settings=q)
    if variant == "reference-like":
        reference_like(learner)
    key = jax.random.key(0)
    state = learner.init(key)
    key, k = jax.random.split(key)
    with CompileCounter() as compiled:  # the update's compilation alone
        t0 = time.perf_counter()
        state, metrics, _ = learner.update(state, levels, k)
        jax.block_until_ready((state, metrics))
        first = time.perf_counter() - t0
    if compiled.cache_hits or not compiled.compiles:
        raise RuntimeError("the first update was not compiled (loaded from a persistent "
                           "compilation cache set up earlier in this process): its time "
                           "would not be a cold start; run `tabx bench train` in a fresh "
                           "process")
    times = []
    for _ in range(updates):
        key, k = jax.random.split(key)
        t0 = time.perf_counter()
        state, metrics, _ = learner.update(state, levels, k)
        jax.block_until_ready((state, metrics))
        times.append(time.perf_counter() - t0)
    median = statistics.median(times) if times else float("nan")
    from tabx_bench.learner_group import param_bytes, per_update_reduction_s, reduction_s

    reduce_s = (per_update_reduction_s(ppo, *reduction_s(learner, state.params, num_envs))
                if learner_class(algorithm).devices else 0.0)
    return TrainBenchResult(algorithm, variant, scenario, opponent, num_envs, num_steps, first,
                            median, num_envs * num_steps / median, updates,
                            len(learner.learner_devices(num_envs)), ppo.matmul_dtype,
                            reduce_s=reduce_s, param_bytes=param_bytes(state.params))


def bench_train(args: argparse.Namespace) -> int:
    from tabx.errors import UserError
    from tabx_bench.simulator import machine_summary, write_results
    from ued.registry import learner_class

    variant = "reference-like" if args.reference_like else "ours"
    if args.reference_like and any(not learner_class(a).ppo_settings for a in args.algorithms):
        raise UserError("--reference-like restructures the PPO learners' training: give "
                        "--algorithms among mappo, ippo")
    print(f"# tabx bench train on {machine_summary()}; {args.scenario} vs {args.opponent}, "
          f"{args.num_envs} envs x {args.num_steps} steps per update"
          f"{'; reference-like training structure' if args.reference_like else ''}",
          flush=True)
    print(f"{'algorithm':>9} {'first update s':>14} {'update s':>9} {'steps/s':>10} "
          f"{'devices':>7} {'matmuls':>8} {'learners':>8} {'reduce ms':>9}", flush=True)
    results = []
    for algorithm in args.algorithms:
        for learners in args.learners:
            options = dict(algorithm=algorithm, scenario=args.scenario,
                           opponent=args.opponent, num_envs=args.num_envs,
                           num_steps=args.num_steps, updates=args.updates, variant=variant,
                           matmul_dtype=args.matmul_dtype)
            if learners == 1:
                r = run_train_bench(**options)
            else:
                from tabx_bench.learner_group import run_group

                r = TrainBenchResult(**run_group(learners, options, args.share_cores))
            results.append(r)
            print(f"{algorithm:>9} {r.first_update_s:>14.1f} {r.update_s:>9.2f} "
                  f"{r.steps_per_s:>10,.0f} {r.devices:>7} {r.matmul_dtype:>8} "
                  f"{r.learners:>8} {r.reduce_s * 1e3:>9.1f}", flush=True)
    if args.json:
        write_results(args.json, results)
    return 0


def _algorithms(text: str) -> list[str]:
    from ued.registry import LEARNERS

    names = [t for t in text.split(",") if t]
    unknown = [n for n in names if n not in LEARNERS]
    if not names or unknown:
        raise argparse.ArgumentTypeError(
            f"expected a comma-separated list of {', '.join(LEARNERS)}, got {text!r}")
    return names


def _positive(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected an integer >= 1, got {text!r}")
    return value


def add_train_bench(which: argparse._SubParsersAction) -> None:
    """Add `train` to the `tabx bench` sub-commands (`which` = bench.add_subparsers(...))."""
    from tabx_bench.arguments import int_list

    p = which.add_parser("train", help="learners' training throughput (env steps/s)")
    p.add_argument("--algorithms", type=_algorithms, default=["mappo", "ippo"],
                   help="comma-separated learners: mappo, ippo, iql, vdn, qmix "
                        "(default mappo,ippo)")
    p.add_argument("--scenario", default="crossfire", help="scenario (default crossfire)")
    p.add_argument("--opponent", default="heuristic:medium",
                   help="the other team (default heuristic:medium)")
    p.add_argument("--num-envs", type=_positive, default=128, help="envs (default 128)")
    p.add_argument("--num-steps", type=_positive, default=512,
                   help="rollout steps per update (default 512)")
    p.add_argument("--updates", type=_positive, default=3,
                   help="timed updates after the first (median; default 3)")
    p.add_argument("--reference-like", action="store_true",
                   help="train with the reference's structure instead (plain autodiff scans, "
                        "MAPPO critic per agent), for comparison")
    p.add_argument("--matmul-dtype", choices=MATMUL_DTYPES, default=None,
                   help="the networks' matmul inputs (learner.matmul_dtype; default: the "
                        "config default, bfloat16)")
    p.add_argument("--learners", type=int_list(1), default=[1],
                   help="comma-separated learner-group sizes: 1 runs here, N > 1 in N "
                        "processes of this machine sharing its cores (default 1)")
    p.add_argument("--share-cores", action=argparse.BooleanOptionalAction, default=True,
                   help="pin each member of a group to its share of the machine's cores, as "
                        "ray.learner_share_cores does (default; --no-share-cores: members "
                        "share every core)")
    p.add_argument("--json", help="also write results as JSON lines to this file")
    p.set_defaults(func=bench_train)


__all__ = ["TrainBenchResult", "add_train_bench", "run_train_bench"]

"""Before/after speed of the simulator across commits, timed in ONE process: each checkout
compiles its `tabx bench env` rollout in a child process and hands over the compiled program
(`jax.experimental.serialize_executable`) with its input arrays; this process then calls the
programs in turn, round after round. A slow spell of a shared machine, and the process-to-process
spread of one program (up to 20 % on the 2-core VM), then hit every commit alike.

    git worktree add --detach /work/wt-old <commit>
    python tools/ab_inprocess.py --tree old=/work/wt-old --tree new=. --rounds 20 \
        --team-sizes 3,5,10 --enemy heuristic:medium [--json FILE]

Same rollout and protocol as `tabx bench env` (random legal actions or the given controllers,
6 zones, 1024 envs, 128 steps, observations carried), compiled by each checkout's own code and
compile options, its envs placed as that checkout's benchmark places them (split over the
devices where it does, `tabx.devices`). The order of the trees rotates from round to round.
Prints per tree and team size the median and best env steps/s over the rounds and the ratio of
medians to the first tree.
"""

from __future__ import annotations

import argparse
import json
import os
import pickle
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from ab_bench import commit_of, parse_tree  # tools/, beside this script

from tabx import xla_flags

xla_flags.apply()  # first: the `tabx` command's XLA flags (one CPU device per core)

try:  # a checkout's program may call the native kernels: their targets must exist here too
    from tabx.native_lib import native_available
except ImportError:  # a checkout from before the native kernels
    pass
else:
    native_available()

# Run by the child with its checkout first on PYTHONPATH: build, compile and serialise.
_CHILD = r"""
import pickle, sys
try:  # the `tabx` command's XLA flags, before JAX starts
    from tabx import xla_flags
    xla_flags.apply()
except ImportError:  # a checkout whose `import tabx` applies them
    import tabx
import jax, jax.numpy as jnp, numpy as np
from jax.experimental import serialize_executable
try:
    from tabx_bench.simulator import bench_level, make_rollout
except ImportError:  # a checkout with the benchmark inside the simulator package
    from tabx.bench import bench_level, make_rollout
from tabx.controllers import Controller, with_tiers
from tabx.env import TabxEnv
from tabx.params import repeat_level
try:
    from tabx.jit_options import simulator_compiler_options
except ImportError:
    def simulator_compiler_options():
        return None
team, zones, envs, steps, ally, enemy, out = sys.argv[1:]
controllers = (Controller.parse(ally), Controller.parse(enemy))
config, level = bench_level(int(team), int(zones))
levels = repeat_level(with_tiers(level, controllers), int(envs))
leaves, treedef = jax.tree.flatten(levels)
leaves = [np.asarray(x) for x in leaves]
# The rollout is compiled below, as the body of one top-level jit with the checkout's options.
sys.modules[make_rollout.__module__].simulator_jit = lambda fn, **kwargs: fn
kwargs = {} if make_rollout.__code__.co_argcount < 4 else {"controllers": controllers}
rollout = make_rollout(TabxEnv(config), int(steps), True, **kwargs)
def flat(leaves, key_data):
    carry = rollout(jax.tree.unflatten(treedef, leaves), jax.random.wrap_key_data(key_data))
    return jax.tree.leaves(carry)[1:]  # all but the key
key_data = np.asarray(jax.random.key_data(jax.random.key(0)))
try:  # placed as this checkout's `tabx bench env` places them
    from tabx.devices import env_devices, env_sharding
    devices = len(env_devices(int(envs)))
    placed = jax.device_put(leaves, env_sharding(env_devices(int(envs))))
except ImportError:
    devices, placed = 1, leaves
compiled = jax.jit(flat, compiler_options=simulator_compiler_options()).lower(
    placed, key_data).compile()
payload = serialize_executable.serialize(compiled)
with open(out, "wb") as f:
    pickle.dump({"payload": payload, "leaves": leaves, "key_data": key_data,
                 "devices": devices}, f)
"""


def compile_in(folder: Path, team: int, args: argparse.Namespace, out: Path):
    env = dict(os.environ, PYTHONPATH=str(folder))
    subprocess.run([sys.executable, "-c", _CHILD, str(team), str(args.zones), str(args.num_envs),
                    str(args.steps), args.ally, args.enemy, str(out)],
                   env=env, cwd=folder, check=True)
    import jax
    from jax.experimental import serialize_executable

    with open(out, "rb") as f:
        data = pickle.load(f)
    program = serialize_executable.deserialize_and_load(*data["payload"])
    from tabx.devices import env_sharding

    placement = env_sharding(tuple(jax.local_devices()[:data.get("devices", 1)]))
    leaves = [jax.device_put(x, placement) for x in data["leaves"]]
    return program, leaves, data["key_data"]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tree", type=parse_tree, action="append", required=True,
                        help="NAME=PATH of a checkout; two or more, the first is the base")
    parser.add_argument("--rounds", type=int, default=20)
    parser.add_argument("--team-sizes", default="3,5,10")
    parser.add_argument("--zones", type=int, default=6)
    parser.add_argument("--num-envs", type=int, default=1024)
    parser.add_argument("--steps", type=int, default=128)
    parser.add_argument("--ally", default="random")
    parser.add_argument("--enemy", default="random")
    parser.add_argument("--json", help="write every timing as JSON lines to this file")
    args = parser.parse_args(argv)
    if len(args.tree) < 2:
        parser.error("give at least two --tree")
    import jax

    commits = {name: commit_of(folder) for name, folder in args.tree}
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for team in [int(t) for t in args.team_sizes.split(",")]:
            programs = {name: compile_in(folder, team, args, Path(tmp) / f"{name}-{team}.pkl")
                        for name, folder in args.tree}
            for program, leaves, key_data in programs.values():
                jax.block_until_ready(program(leaves, key_data))  # warm-up
            times: dict[str, list[float]] = {name: [] for name in programs}
            names = list(programs)
            for round_index in range(args.rounds):
                # Each round starts with the next tree: no tree always runs first (after the
                # pause of the previous round's bookkeeping) or always after a given other one.
                shift = round_index % len(names)
                for name in names[shift:] + names[:shift]:
                    program, leaves, key_data = programs[name]
                    start = time.perf_counter()
                    jax.block_until_ready(program(leaves, key_data))
                    seconds = time.perf_counter() - start
                    times[name].append(seconds)
                    rows.append({"tree": name, "commit": commits[name], "team_size": team,
                                 "zones": args.zones, "num_envs": args.num_envs,
                                 "steps": args.steps, "ally": args.ally, "enemy": args.enemy,
                                 "round": round_index, "run_s": seconds,
                                 "steps_per_s": args.num_envs * args.steps / seconds})
            base = statistics.median(times[args.tree[0][0]])
            for name, t in times.items():
                rate = args.num_envs * args.steps
                print(f"{team}v{team} {args.ally}/{args.enemy} {name:>10} ({commits[name]}): "
                      f"median {rate / statistics.median(t):>11,.0f}  best {rate / min(t):>11,.0f}"
                      f"  ratio {base / statistics.median(t):.3f}", flush=True)
    if args.json:
        from tabx.files import atomic_write_text

        atomic_write_text(args.json, "".join(json.dumps(r) + "\n" for r in rows))
        print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

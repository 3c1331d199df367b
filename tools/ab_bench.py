"""Before/after speed of the simulator across commits: `tabx bench env` alternated between
checkouts, round after round, so that a slow spell of a shared machine hits every commit alike.

    git worktree add --detach /work/wt-old <commit>
    python tools/ab_bench.py --tree old=/work/wt-old --tree new=. --rounds 5 \
        --json docs/bench/env_ab.jsonl -- --team-sizes 3,5,10 --zones 6 --num-envs 1024

Every round runs each tree's `tabx bench env` (the arguments after `--`) in a fresh process
with that tree first on PYTHONPATH, in turn. Each result line of `--json` is the benchmark's own
record plus `tree`, `commit` and `round`; the summary gives, per tree and configuration, the
median over rounds of the steps/s (each itself a median of the benchmark's timed calls) and the
ratio to the first tree.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

from tabx.files import atomic_write_text


def parse_tree(text: str) -> tuple[str, Path]:
    name, sep, path = text.partition("=")
    if not sep or not name or not path:
        raise argparse.ArgumentTypeError(f"expected NAME=PATH, got {text!r}")
    folder = Path(path).resolve()
    if not (folder / "tabx" / "__init__.py").is_file():
        raise argparse.ArgumentTypeError(f"{folder} is not a checkout of this project "
                                         "(no tabx/__init__.py)")
    return name, folder


def commit_of(folder: Path) -> str:
    result = subprocess.run(["git", "-C", str(folder), "rev-parse", "--short", "HEAD"],
                            capture_output=True, text=True)
    return result.stdout.strip() or "?"


def run_bench(folder: Path, bench_args: list[str], out: Path) -> list[dict]:
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(
        [str(folder), *filter(None, [os.environ.get("PYTHONPATH")])]))
    command = [sys.executable, "-m", "tabx", "bench", "env", *bench_args, "--json", str(out)]
    subprocess.run(command, env=env, cwd=folder, check=True, stdout=subprocess.DEVNULL)
    return [json.loads(line) for line in out.read_text().splitlines() if line.strip()]


def summarise(rows: list[dict], trees: list[str]) -> str:
    def key(r: dict) -> tuple:
        return (r["team_size"], r["zones"], r["num_envs"], r["controllers"], r["with_obs"])

    configs = sorted({key(r) for r in rows})
    lines = [f"{'configuration':<34}" + "".join(f"{t:>14}" for t in trees)
             + "".join(f"{t + '/' + trees[0]:>14}" for t in trees[1:])]
    for config in configs:
        medians = [statistics.median(r["steps_per_s"] for r in rows
                                     if key(r) == config and r["tree"] == t) for t in trees]
        team, zones, envs, controllers, obs = config
        label = f"{team}v{team} z{zones} {envs} {controllers}{'' if obs else ' no-obs'}"
        lines.append(f"{label:<34}" + "".join(f"{m:>14,.0f}" for m in medians)
                     + "".join(f"{m / medians[0]:>14.3f}" for m in medians[1:]))
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    bench_args: list[str] = []
    if "--" in argv:
        cut = argv.index("--")
        argv, bench_args = argv[:cut], argv[cut + 1:]
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tree", type=parse_tree, action="append", required=True,
                        help="NAME=PATH of a checkout; give two or more, the first is the base")
    parser.add_argument("--rounds", type=int, default=5, help="rounds (default 5)")
    parser.add_argument("--json", help="write every result as JSON lines to this file")
    args = parser.parse_args(argv)
    if len(args.tree) < 2:
        parser.error("give at least two --tree")
    if args.rounds < 1:
        parser.error("--rounds must be at least 1")
    commits = {name: commit_of(folder) for name, folder in args.tree}
    rows: list[dict] = []
    with tempfile.TemporaryDirectory() as tmp:
        for round_index in range(args.rounds):
            for name, folder in args.tree:
                out = Path(tmp) / f"{name}-{round_index}.jsonl"
                for row in run_bench(folder, bench_args, out):
                    rows.append({**row, "tree": name, "commit": commits[name],
                                 "round": round_index})
                done = [r for r in rows if r["tree"] == name and r["round"] == round_index]
                print(f"round {round_index + 1}/{args.rounds} {name} ({commits[name]}): "
                      + ", ".join(f"{r['team_size']}v{r['team_size']} {r['steps_per_s']:,.0f}"
                                  for r in done), flush=True)
    if args.json:
        atomic_write_text(args.json, "".join(json.dumps(r) + "\n" for r in rows))
        print(f"wrote {args.json}")
    print(summarise(rows, [name for name, _ in args.tree]))
    return 0


if __name__ == "__main__":
    sys.exit(main())

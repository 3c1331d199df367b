"""Plot float32 against bfloat16 matmul inputs in learning (docs/learners.md, "Matmul precision").

    python tools/plot_matmul_dtype.py docs/bench/matmul_dtype_learning_2026-11-22.jsonl \
        docs/bench/matmul_dtype_crossfire_2026-11-22.jsonl --out docs/img/matmul_dtype.png

The first file holds runs on the learning test's battle (one JSON line per algorithm, dtype and
seed, with the per-update `win_rate`); the second, runs on crossfire against the medium
heuristic (one line per algorithm and dtype, with each update's `metrics`). Left: the battle's
win rate, mean over seeds with the seeds' range shaded; middle and right: crossfire's episode
length and policy entropy per update.
"""

from __future__ import annotations

import argparse
import io
import json
from collections import defaultdict
from pathlib import Path

import numpy as np

from tabx.files import atomic_write_bytes

COLOURS = {("mappo", "float32"): "tab:blue", ("mappo", "bfloat16"): "tab:cyan",
           ("ippo", "float32"): "tab:red", ("ippo", "bfloat16"): "tab:orange"}


def _lines(path: Path) -> list[dict]:
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("battle", type=Path, help="JSON lines of the battle runs")
    parser.add_argument("crossfire", type=Path, help="JSON lines of the crossfire runs")
    parser.add_argument("--out", type=Path, required=True, help="PNG to write")
    args = parser.parse_args()

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(15, 4.2))
    runs = defaultdict(list)
    for row in _lines(args.battle):
        runs[row["algorithm"], row["dtype"]].append(row["win_rate"])
    for (algorithm, dtype), curves in sorted(runs.items()):
        curves = np.asarray(curves)
        x = np.arange(1, curves.shape[1] + 1)
        colour = COLOURS.get((algorithm, dtype))
        axes[0].plot(x, curves.mean(0), color=colour,
                     label=f"{algorithm} {dtype} ({len(curves)} seeds)")
        axes[0].fill_between(x, curves.min(0), curves.max(0), color=colour, alpha=0.15)
    axes[0].set(title="2 archers v random farmer: win rate", xlabel="update",
                ylabel="win rate (mean, range over seeds)")
    axes[0].legend(fontsize=8)
    for row in _lines(args.crossfire):
        key = row["algorithm"], row["dtype"]
        metrics = row["metrics"]
        x = np.arange(1, len(metrics) + 1)
        label = f"{key[0]} {key[1]}"
        axes[1].plot(x, [m["episode/length"] for m in metrics], color=COLOURS.get(key),
                     label=label)
        axes[2].plot(x, [m["loss/entropy"] for m in metrics], color=COLOURS.get(key),
                     label=label)
    axes[1].set(title="crossfire v heuristic:medium: episode length", xlabel="update",
                ylabel="mean episode length (steps)")
    axes[2].set(title="crossfire v heuristic:medium: policy entropy", xlabel="update",
                ylabel="entropy (nats)")
    for ax in axes[1:]:
        ax.legend(fontsize=8)
    fig.tight_layout()
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=90)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_bytes(args.out, buffer.getvalue())
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

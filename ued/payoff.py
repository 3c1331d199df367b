"""`tabx eval payoff`: policy-vs-policy payoff tables, as the paper's "Policy vs. Policy" appendix.

    tabx eval payoff runs/mappo_a runs/ippo_b runs/qmix_c --tiers heuristic:medium,random \\
        --scenario crossfire --episodes 64 --out results/payoff_crossfire
    tabx eval payoff runs/mappo_* --suite units-2F1M2Avs2S1K --out results/payoff_units

Every *side* (each run folder given, then each scripted controller of `--tiers`) that can
play the allies plays them against every side that can play the enemies, on every scenario
(`--scenario`, or the distinct scenarios of an evaluation suite, `--suite`; the suite's
opponents are not used). A policy plays the team it was trained for and, through the team swap
(`ued.evaluate.seat`), the other team when that team has as many unit slots as the policy has
agents: on a scenario with equal teams one run per algorithm fills both axes; on one with
unequal teams (pingpong is 4 v 1) the rows are the runs trained on the allies and the columns
those trained on the enemies (`env.team: enemy`), as the paper trains a policy per side.
Scripted sides play both teams. Cell (i, j) of a scenario's matrix is the win rate of the
allies (row side i) against the enemies (column side j) over `episodes` episodes, with its
95 % Wilson interval; a time-out goes to the higher health ratio and a tie to the enemies, as
everywhere in TABX. The table also reports the mean over scenarios.

The cells run through `ued.evaluate.play`, whose compiled program depends only on which
learners (network kinds and sizes) sit on each side: a table of runs of one config compiles
once, whatever the number of runs, tiers and scenarios. Each cell draws its own seed
(`seed` + cell index), so the cells are independent samples.

Output: the table printed, a JSON file (`OUT.json`) and a heatmap (`OUT.png`: one panel per
scenario, and the mean when there are several).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from tabx.params import EnvConfig
from ued.config import ConfigError

DEFAULT_EPISODES = 64


@dataclass
class PayoffTable:
    """Ally win rates of every (ally side, enemy side) pairing per scenario."""

    allies: list[str]  # row labels: a run folder's name or a controller
    enemies: list[str]  # column labels
    scenarios: list[str]
    episodes: int
    wins: np.ndarray  # (S, A, E) int: ally wins of row side i against column side j

    @property
    def win_rate(self) -> np.ndarray:
        """(S, A, E) ally win rates."""
        return self.wins / self.episodes

    def interval(self) -> tuple[np.ndarray, np.ndarray]:
        """(low, high) of the 95 % Wilson interval of every cell, each (S, N, N)."""
        from ued.evaluate import wilson

        bounds = np.array([wilson(int(w), self.episodes)[1:] for w in self.wins.ravel()])
        return (bounds[:, 0].reshape(self.wins.shape), bounds[:, 1].reshape(self.wins.shape))

    def mean(self) -> np.ndarray:
        """(A, E) win rates averaged over the scenarios."""
        return self.win_rate.mean(axis=0)

    def to_json(self) -> dict:
        low, high = self.interval()
        return {
            "allies": self.allies, "enemies": self.enemies, "episodes": self.episodes,
            "layout": "win_rate[i][j]: the ally win rate of row side i (allies) against "
                      "column side j (enemies)",
            "scenarios": {name: {"win_rate": self.win_rate[s].tolist(),
                                 "low": low[s].tolist(), "high": high[s].tolist()}
                          for s, name in enumerate(self.scenarios)},
            "mean": {"win_rate": self.mean().tolist(),
                     "row_mean": self.mean().mean(axis=1).tolist()},
        }

    def format(self) -> str:
        width = max(8, *(len(s) for s in self.allies + self.enemies)) + 2
        blocks = []
        panels = [(name, self.win_rate[s]) for s, name in enumerate(self.scenarios)]
        if len(self.scenarios) > 1:
            panels.append(("mean over scenarios", self.mean()))
        for name, matrix in panels:
            lines = [f"{name}: ally win rate ({self.episodes} episodes per cell)",
                     "ally \\ enemy".ljust(width) + "".join(s.rjust(width) for s in self.enemies)]
            for i, side in enumerate(self.allies):
                lines.append(side.ljust(width) + "".join(f"{v:.3f}".rjust(width)
                                                         for v in matrix[i]))
            blocks.append("\n".join(lines))
        return "\n\n".join(blocks)


def side_labels(texts: list[str]) -> list[str]:
    """Short unique labels: a run folder's name (`RUN/seed-<s>` for a seed of a multi-seed
    run), a controller as written; repeats get #2, #3."""
    from ued.run_folder import split_seed_dir

    labels, seen = [], {}
    for text in texts:
        base = Path(text).name if Path(text).is_dir() else text
        run, seed = split_seed_dir(text)
        if seed is not None:
            base = f"{run.name}/{base}"
        seen[base] = seen.get(base, 0) + 1
        labels.append(base if seen[base] == 1 else f"{base}#{seen[base]}")
    return labels


def payoff_table(run_dirs: list[str], tiers: list[str], scenarios: list[str],
                 episodes: int = DEFAULT_EPISODES, seed: int = 0, greedy: bool = False,
                 max_steps: int = 512, checkpoint: int | None = None) -> PayoffTable:
    """Play every (ally side, enemy side) pairing of the runs and tiers on every scenario.
    ConfigError for a run folder or controller that cannot be read, policies trained on
    different EnvConfigs, or a scenario that does not fit them."""
    from tabx.controllers import Controller
    from tabx.scenarios import ScenarioError, config_for, load_named
    from ued.evaluate import play
    from ued.run_folder import load_policy

    if episodes < 1:
        raise ConfigError(f"episodes must be >= 1, got {episodes}")
    if not run_dirs and not tiers:
        raise ConfigError("a payoff table needs at least one side: run folders and/or tiers")
    if not scenarios:
        raise ConfigError("a payoff table needs a scenario")
    sides: list = []
    for text in run_dirs:
        if not Path(text).is_dir():
            raise ConfigError(f"{text}: not a run folder")
        sides.append(load_policy(text, checkpoint))
    for text in tiers:
        try:
            sides.append(Controller.parse_scripted(text, "a tier of the table"))
        except ValueError as err:
            raise ConfigError(f"--tiers: {err}") from None
    policies = [s for s in sides if not isinstance(s, Controller)]
    try:
        loaded = [load_named(name) for name in scenarios]
    except ScenarioError as err:
        raise ConfigError(str(err)) from None
    env_config = (policies[0].learner.env_config if policies
                  else config_for(loaded, max_steps=max_steps))
    rows, columns = payoff_axes(sides, env_config)
    labels = side_labels([*run_dirs, *tiers])
    wins = np.zeros((len(loaded), len(rows), len(columns)), np.int64)
    for s, scenario in enumerate(loaded):
        try:
            level = scenario.to_level(env_config)
        except ScenarioError as err:
            raise ConfigError(f"{err} (the policies' EnvConfig: {env_config})") from None
        for i, row in enumerate(rows):
            for j, column in enumerate(columns):
                cell_seed = seed + (s * len(rows) + i) * len(columns) + j
                result = play(env_config, level, sides[row], sides[column], episodes,
                              seed=cell_seed, greedy=greedy)
                wins[s, i, j] = int(result.won[:, 0].sum())
    return PayoffTable([labels[i] for i in rows], [labels[j] for j in columns],
                       [sc.name for sc in loaded], episodes, wins)


def payoff_axes(sides: list, env_config: EnvConfig) -> tuple[list[int], list[int]]:
    """(indices of the sides that can play the allies, of those that can play the enemies):
    scripted sides play both; a policy its own team, and the other one if the slot counts
    allow (`ued.evaluate.seat`). ConfigError for a policy of another EnvConfig, or when a team
    has no side."""
    from tabx.controllers import Controller
    from ued.evaluate import TEAM_NAMES, seat, team_slots

    axes: tuple[list[int], list[int]] = ([], [])
    for index, side in enumerate(sides):
        for team in range(2):
            if isinstance(side, Controller):
                axes[team].append(index)
                continue
            first, end = team_slots(env_config, team)
            if team == side.team or end - first == side.learner.num_agents:
                seat(side, team, env_config)  # raises for another EnvConfig
                axes[team].append(index)
    for team in range(2):
        if not axes[team]:
            raise ConfigError(f"no side can play the {TEAM_NAMES[team]} team: give a run "
                              f"trained on it (env.team: {TEAM_NAMES[team]}) or a tier")
    return axes


def plot_payoff(table: PayoffTable, out: str | Path) -> Path:
    """Heatmaps of the table (one panel per scenario, then the mean), written atomically."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ued.plot import save_figure

    panels = [(name, table.win_rate[s]) for s, name in enumerate(table.scenarios)]
    if len(table.scenarios) > 1:
        panels.append(("mean", table.mean()))
    n_rows, n_cols = len(table.allies), len(table.enemies)
    cols = min(len(panels), 3)
    rows = math.ceil(len(panels) / cols)
    width, height = 1.2 + 0.7 * n_cols, 1.2 + 0.7 * n_rows
    fig, axes = plt.subplots(rows, cols, figsize=(width * cols + 1.0, height * rows),
                             squeeze=False)
    image = None
    for ax, (name, matrix) in zip(axes.ravel(), panels, strict=False):
        image = ax.imshow(matrix, vmin=0.0, vmax=1.0, cmap="RdBu")
        ax.set_title(name, fontsize=9)
        ax.set_xticks(range(n_cols), table.enemies, rotation=45, ha="right", fontsize=7)
        ax.set_yticks(range(n_rows), table.allies, fontsize=7)
        ax.set_xlabel("enemy", fontsize=8)
        ax.set_ylabel("ally", fontsize=8)
        for i in range(n_rows):
            for j in range(n_cols):
                value = matrix[i, j]
                ax.text(j, i, f"{value:.2f}", ha="center", va="center", fontsize=7,
                        color="white" if abs(value - 0.5) > 0.3 else "black")
    for ax in axes.ravel()[len(panels):]:
        ax.axis("off")
    fig.colorbar(image, ax=axes.ravel().tolist(), shrink=0.8, label="ally win rate")
    return save_figure(fig, out, bbox_inches="tight")


__all__ = ["PayoffTable", "payoff_table", "plot_payoff",
           "side_labels"]

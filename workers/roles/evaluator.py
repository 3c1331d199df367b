"""Zero-shot evaluation of a learner's policy on an evaluation suite (`ued.suites`).

    suite = load_suite("units-2F1M2Avs2S1K")
    evaluator = Evaluator(learner, suite)               # checks every entry fits the policy
    result = evaluator.evaluate(train_state.params, jax.random.key(0))
    evaluator.log(writer, step, result)                 # eval/<suite>/<label>/win_rate, ...
    print(format_table(result)); atomic_write_json(path, to_json(result))

Every entry is played for `episodes` episodes (one env each, from the entry's level, for the
learner's `max_steps`, by the episode player `tabx.episodes.play`; a finished episode is
frozen). All entries of a suite run in ONE jitted call: their levels are stacked entry by entry
(the opponent's tier written into each level, as `with_tiers`), and the opponent's kind
(heuristic, random, idle) is an int per env, so the call is compiled once per (learner, kinds
in the suite, episode total) and `evaluate` with new parameters during training never
recompiles.

The policy samples from its masked action distribution (`greedy=True`: the argmax) with its
recurrent state carried over the episode. Per entry: the policy team's win rate with a 95 %
Wilson interval (exactly one team wins an episode: a time-out goes to the higher health ratio,
ties to the enemy), the mean undiscounted team return and the mean episode length with 95 %
normal intervals; and over the suite the mean of the entries' win rates.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from tabx.controllers import SCRIPTED_KINDS, Controller, KindPerEnv, with_tiers
from tabx.episodes import SUITE_KEYS
from tabx.episodes import play as play_episodes
from tabx.params import EnvParams, stack_levels
from tabx.profiles import DEFAULT_PROFILE, with_profile
from ued.errors import ConfigError
from ued.evaluate import TEAM_NAMES, learner_policy, mean_ci, wilson
from ued.learners.ppo import PPOLearner
from ued.suites import EvalSuite
from ued.tensorboard import SummaryWriter

OPPONENT_KINDS = SCRIPTED_KINDS  # the int code of each env's opponent


@dataclass(frozen=True)
class EntryResult:
    """The result of one suite entry (rates and means over its episodes)."""

    label: str
    scenario: str
    opponent: str
    episodes: int
    wins: int
    win_rate: float
    win_low: float  # 95 % Wilson interval
    win_high: float
    mean_return: float
    return_ci: float  # half width of the 95 % normal interval
    mean_length: float
    length_ci: float


@dataclass(frozen=True)
class SuiteResult:
    suite: str
    description: str
    team: str
    episodes: int  # per entry
    greedy: bool
    entries: tuple[EntryResult, ...]

    @property
    def mean_win_rate(self) -> float:
        """The mean of the entries' win rates."""
        return float(np.mean([e.win_rate for e in self.entries]))

    def entry(self, label: str) -> EntryResult:
        for e in self.entries:
            if e.label == label:
                return e
        raise KeyError(label)


@functools.lru_cache(maxsize=16)
def compiled_runner(learner: PPOLearner, used: tuple[str, ...], greedy: bool):
    """The jitted `run(params, levels, kinds, key) -> (won (E,), returns (E,), lengths (E,))`
    of a learner: E envs (any number; a new E compiles anew), one level and one opponent kind
    per env, `max_steps` steps (`tabx.episodes.play`). Cached, so suites of one learner share
    compilations."""
    env, config, team = learner.env, learner.env_config, learner.team
    controllers = [Controller("external"), Controller("external")]
    controllers[1 - team] = KindPerEnv(used)
    policies = [None, None]
    policies[team] = learner_policy(learner, (learner.slots.start, learner.slots.stop), greedy)

    def run(params, levels, kinds, key):
        out = play_episodes(env, levels, key, config.max_steps, tuple(controllers),
                            tuple(policies), (params, params), keys=SUITE_KEYS, kinds=kinds)
        return out.states.won[:, team], out.returns[:, team], out.length

    return learner.jit(run)


class Evaluator:
    """Evaluates a learner's policy parameters on every entry of a suite (zero-shot).

    Built once per (learner, suite): the entries' scenarios are padded into the learner's
    EnvConfig (a scenario that does not fit raises ConfigError naming the entry and the slot
    counts) and stacked; `evaluate(params, key)` is then one compiled call."""

    def __init__(self, learner: PPOLearner, suite: EvalSuite, episodes: int | None = None,
                 greedy: bool = False, profile: str = DEFAULT_PROFILE):
        from tabx.scenarios import ScenarioError, load_named

        episodes = suite.episodes if episodes is None else episodes
        if isinstance(episodes, bool) or not isinstance(episodes, int) or episodes < 1:
            raise ConfigError(f"episodes: must be an integer >= 1, got {episodes!r}")
        where = suite.source or f"suite {suite.name}"
        if TEAM_NAMES[learner.team] != suite.team:
            raise ConfigError(f"{where}: team: the suite evaluates the {suite.team} team, the "
                              f"policy plays the {TEAM_NAMES[learner.team]} team")
        self.learner, self.suite, self.episodes, self.greedy = learner, suite, episodes, greedy
        config = learner.env_config
        levels, kinds = [], []
        for i, entry in enumerate(suite.entries):
            scenario = load_named(entry.scenario)
            counts = (len(scenario.allies), len(scenario.enemies), len(scenario.zones))
            limits = (config.max_allies, config.max_enemies, config.max_zones)
            if any(n > m for n, m in zip(counts, limits, strict=True)):
                raise ConfigError(
                    f"{where}: entry {i} ({entry.label}): the scenario has {counts[0]} allies, "
                    f"{counts[1]} enemies and {counts[2]} zones; the policy's EnvConfig has "
                    f"max_allies={limits[0]}, max_enemies={limits[1]}, max_zones={limits[2]}")
            try:
                level = scenario.to_level(config)
            except ScenarioError as err:
                raise ConfigError(f"{where}: entry {i} ({entry.label}): {err}") from None
            opponent = Controller.parse(entry.opponent)
            controllers = [Controller("external"), Controller("external")]
            controllers[1 - learner.team] = opponent
            levels.append(with_profile(with_tiers(level, controllers), profile))
            kinds.append(OPPONENT_KINDS.index(opponent.kind))
        #  Entry-major: envs [i * episodes, (i + 1) * episodes) play entry i.
        self.levels: EnvParams = jax.tree.map(
            lambda x: jnp.repeat(jnp.asarray(x), episodes, axis=0), stack_levels(levels))
        self.kinds = jnp.repeat(jnp.asarray(kinds, jnp.int32), episodes)
        used = tuple(k for k in OPPONENT_KINDS if OPPONENT_KINDS.index(k) in kinds)
        self._run = compiled_runner(learner, used, greedy)

    @property
    def num_envs(self) -> int:
        return len(self.suite.entries) * self.episodes

    def evaluate(self, params: Any, key: jax.Array | int = 0) -> SuiteResult:
        """Play every entry with `params` (the learner's policy parameters)."""
        if isinstance(key, int):
            key = jax.random.key(key)
        elif not jax.dtypes.issubdtype(key.dtype, jax.dtypes.prng_key):
            key = jax.random.wrap_key_data(key)  # a raw uint32 PRNGKey
        won, returns, lengths = jax.device_get(self._run(params, self.levels, self.kinds, key))
        shape = (len(self.suite.entries), self.episodes)
        won, returns = np.asarray(won).reshape(shape), np.asarray(returns).reshape(shape)
        lengths = np.asarray(lengths).reshape(shape)
        entries = []
        for i, entry in enumerate(self.suite.entries):
            wins = int(won[i].sum())
            rate, low, high = wilson(wins, self.episodes)
            ret, ret_ci = mean_ci(returns[i])
            length, length_ci = mean_ci(lengths[i].astype(np.float64))
            entries.append(EntryResult(entry.label, entry.scenario, entry.opponent,
                                       self.episodes, wins, rate, low, high, ret, ret_ci,
                                       length, length_ci))
        return SuiteResult(self.suite.name, self.suite.description, self.suite.team,
                           self.episodes, self.greedy, tuple(entries))

    def log(self, writer: SummaryWriter, step: int, result: SuiteResult) -> None:
        log(writer, step, result)


def scalars(result: SuiteResult) -> dict[str, float]:
    """The TensorBoard scalars of a result: eval/<suite>/<label>/{win_rate, win_rate_low,
    win_rate_high, return, length} and eval/<suite>/mean_win_rate."""
    prefix = f"eval/{result.suite}"
    out: dict[str, float] = {}
    for e in result.entries:
        tag = f"{prefix}/{e.label}"
        out.update({f"{tag}/win_rate": e.win_rate, f"{tag}/win_rate_low": e.win_low,
                    f"{tag}/win_rate_high": e.win_high, f"{tag}/return": e.mean_return,
                    f"{tag}/length": e.mean_length})
    out[f"{prefix}/mean_win_rate"] = result.mean_win_rate
    return out


def log(writer: SummaryWriter, step: int, result: SuiteResult) -> None:
    """Write `scalars(result)` at `step` (one event)."""
    writer.scalars(scalars(result), step=step)


def _num(x: float) -> float | None:
    return float(x) if math.isfinite(x) else None


def to_json(result: SuiteResult) -> dict[str, Any]:
    """A JSON-ready dict of the result (non-finite numbers become null)."""
    return {
        "suite": result.suite, "description": result.description, "team": result.team,
        "episodes": result.episodes, "greedy": result.greedy,
        "mean_win_rate": _num(result.mean_win_rate),
        "entries": [{"label": e.label, "scenario": e.scenario, "opponent": e.opponent,
                     "episodes": e.episodes, "wins": e.wins, "win_rate": _num(e.win_rate),
                     "win_rate_ci95": [_num(e.win_low), _num(e.win_high)],
                     "mean_return": _num(e.mean_return), "return_ci95": _num(e.return_ci),
                     "mean_length": _num(e.mean_length), "length_ci95": _num(e.length_ci)}
                    for e in result.entries],
    }


def _pm(mean: float, half: float, fmt: str) -> str:
    text = format(mean, fmt)
    return text + (f" ± {format(half, fmt.lstrip('+'))}" if math.isfinite(half) else "")


def format_table(result: SuiteResult) -> str:
    """One row per entry: scenario, opponent, win rate [95 % CI], return, episode length."""
    rows = [(e.scenario, e.opponent, f"{e.win_rate:.3f} [{e.win_low:.3f}, {e.win_high:.3f}]",
             _pm(e.mean_return, e.return_ci, "+.3f"), _pm(e.mean_length, e.length_ci, ".1f"))
            for e in result.entries]
    head = ("scenario", "opponent", "win rate [95% CI]", "return", "length")
    widths = [max(len(r[i]) for r in (head, *rows)) for i in range(len(head))]

    def line(cells):
        return "  " + "  ".join(c.ljust(w) for c, w in zip(cells, widths, strict=True)).rstrip()

    title = f"suite {result.suite}" + (f": {result.description}" if result.description else "")
    lines = [title,
             f"  {result.episodes} episodes per entry, {result.team} team, "
             f"{'greedy' if result.greedy else 'sampled'} policy",
             line(head), *(line(r) for r in rows),
             f"  mean win rate over {len(rows)} entries: {result.mean_win_rate:.3f}  "
             f"(95 % intervals: Wilson for rates, normal for means)"]
    return "\n".join(lines)


__all__ = ["EntryResult", "Evaluator", "OPPONENT_KINDS", "SuiteResult", "compiled_runner",
           "format_table", "log", "scalars", "to_json"]

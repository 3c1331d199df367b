"""`tabx analyse value-error`: how far a learner's value V(s) is from the policy's true value.

The paper's appendix "Value Error Estimation" (and the reference's `VALUE_EVAL_NUM_ENVS`;
docs/differences.md), used to compare centralised (MAPPO) with independent (IPPO) value
learning per scenario:

1. play the policy (sampling, as in training) in `states` envs for `horizon` steps, episodes
   restarting as in a training rollout, and keep one uniformly drawn time step per env: its
   env state, the policy's recurrent state and the value V(s) the learner gave it;
2. from each kept state, play `rollouts` independent continuations with the policy (its
   recurrent state restored, fresh randomness for each) until the episode ends, and take
   V*(s) = the mean discounted team return (gamma: the learner's);
3. report mean |V(s) - V*(s)| over the states with a 95 % normal interval over states, with
   the Monte-Carlo standard error of the V* estimates beside it (the floor of the measurable
   error at that many rollouts).

The paper's protocol is 128 states x 128 rollouts of 512-step trajectories (the defaults).
V(s) is the team value the learner trains: MAPPO's centralised value, IPPO's mean value over
the team's living agents (as in UED scores), MAPPO+RND's extrinsic value. Learners without a
value head (the Q-learners: IQL, VDN, QMIX) are refused before anything is loaded.
Continuations stop at the episode's end (at most the episode limit); the reward after the end
is zero.

    tabx analyse value-error runs/mappo_clover-* runs/ippo_clover-* --json ve.json --plot ve.png
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from tabx.episodes import LOOP_KEYS, Policy, sample
from tabx.episodes import play as play_episodes
from tabx.params import EnvParams, repeat_level
from ued.config import ConfigError
from ued.learners.ppo import PPOLearner, masked_logits

DEFAULT_STATES = 128
DEFAULT_ROLLOUTS = 128
DEFAULT_HORIZON = 512


@dataclass
class ValueErrorEstimate:
    """Per kept state: the learner's value, the Monte-Carlo value and its standard error."""

    scenario: str
    values: np.ndarray  # (S,) V(s)
    mc_values: np.ndarray  # (S,) V*(s)
    mc_stderr: np.ndarray  # (S,) standard error of each V*(s)
    rollouts: int

    @property
    def abs_errors(self) -> np.ndarray:
        return np.abs(self.values - self.mc_values)

    def summary(self) -> dict[str, float]:
        from ued.evaluate import mean_ci

        mean, half = mean_ci(self.abs_errors)
        return {"mean_abs_error": mean, "ci95": half, "states": int(self.values.size),
                "rollouts": self.rollouts, "mean_value": float(self.values.mean()),
                "mean_mc_value": float(self.mc_values.mean()),
                "mean_mc_stderr": float(self.mc_stderr.mean())}


def value_error(learner: PPOLearner, params: Any, level: EnvParams, key: jax.Array,
                states: int = DEFAULT_STATES, rollouts: int = DEFAULT_ROLLOUTS,
                horizon: int = DEFAULT_HORIZON, scenario: str = "") -> ValueErrorEstimate:
    """The value error of `learner` with `params` on one level (EnvParams without a batch
    axis): see the module doc. Compiled once per (learner, states, rollouts, horizon)."""
    for name, value in (("states", states), ("rollouts", rollouts), ("horizon", horizon)):
        if value < 1:
            raise ConfigError(f"{name} must be >= 1, got {value}")
    levels = jax.tree.map(jnp.asarray, repeat_level(level, states))
    program = _program(learner, states, rollouts, horizon)
    values, mc_mean, mc_stderr = jax.device_get(program(params, levels, key))
    as64 = lambda x: np.asarray(x, np.float64)
    return ValueErrorEstimate(scenario, as64(values), as64(mc_mean), as64(mc_stderr), rollouts)


@functools.lru_cache(maxsize=8)
def _program(learner: PPOLearner, states: int, rollouts: int, horizon: int) -> Any:
    env, team = learner.env, learner.team
    gamma = learner.ppo.gamma
    max_steps = learner.env_config.max_steps
    slots = learner.slots

    def network(params, obs, mask, env_states, levels, hidden):
        """(hidden, masked logits, value per agent) of every env's policy step."""
        world = learner._world(env_states, levels)
        hidden, logits, value = learner.act_step(params, learner.agent_inputs(obs[:, slots]),
                                                 world, hidden)
        return hidden, masked_logits(logits, mask[:, slots]), value

    def act(params, env_states, levels, hidden, keys):
        """One policy step of every env: (hidden, value, env actions, states after the
        opponent's controller)."""
        obs = jax.vmap(env.observe)(env_states, levels)
        mask = jax.vmap(env.action_mask)(env_states, levels)
        hidden, logits, value = network(params, obs, mask, env_states, levels, hidden)
        k_act, k_other = jnp.unstack(jax.vmap(jax.random.split)(keys), axis=1)
        action = jax.vmap(jax.random.categorical)(k_act, logits)
        actions, env_states = learner._join_actions(k_other, env_states, levels,
                                                    action.astype(jnp.int32))
        alive = env_states.alive[:, slots]
        return hidden, learner.team_value(value, alive), actions, env_states

    def policy_act(params, key, obs, mask, env_states, levels, hidden):
        hidden, logits, _ = network(params, obs, mask, env_states, levels, hidden)
        return sample(key, logits), hidden

    policies = [None, None]
    policies[team] = Policy(policy_act, learner.initial_hidden, (slots.start, slots.stop))

    def reset_where(done, tree):
        return jax.tree.map(
            lambda h: jnp.where(done.reshape(done.shape + (1,) * (h.ndim - 1)), 0.0, h), tree)

    def collect(params, levels, key):
        """Step 1: the kept (state, hidden, value) of each env (a training-style rollout:
        episodes restart, so any of the `horizon` steps can be kept)."""
        k_pick, k_steps = jax.random.split(key)
        pick = jax.random.randint(k_pick, (states,), 0, horizon)
        start = jax.vmap(env.initial_state)(levels)
        hidden = learner.initial_hidden(states)
        keep = (start, hidden, jnp.zeros(states, jnp.float32))

        def body(carry, inputs):
            env_states, hidden, keep = carry
            t, keys = inputs
            now = pick == t
            new_hidden, value, actions, stepped = act(params, env_states, levels, hidden, keys)
            chosen = (env_states, hidden, value)
            keep = jax.tree.map(
                lambda k, c: jnp.where(now.reshape(now.shape + (1,) * (c.ndim - 1)), c, k),
                keep, chosen)
            _, next_states, _, done, _ = jax.vmap(env.step_autoreset)(
                keys, stepped, actions, levels, start)
            return (next_states, reset_where(done, new_hidden), keep), None

        keys = jax.random.split(k_steps, horizon * states).reshape(horizon, states)
        (_, _, keep), _ = jax.lax.scan(body, (start, hidden, keep),
                                       (jnp.arange(horizon), keys))
        return keep

    def continuations(params, levels, kept_states, kept_hidden, key):
        """Step 2: `rollouts` continuations of each kept state until its episode ends (the
        episode player, `tabx.episodes.play`); (S, R) discounted returns."""
        spread = lambda x: jnp.repeat(x, rollouts, axis=0)
        hidden = [None, None]
        hidden[team] = jax.tree.map(spread, kept_hidden)
        out = play_episodes(env, jax.tree.map(spread, levels), key, max_steps,
                            learner.controllers, tuple(policies), (params, params),
                            keys=LOOP_KEYS, start=jax.tree.map(spread, kept_states),
                            hidden=tuple(hidden), until_done=True, discount=gamma)
        return out.returns[:, team].reshape(states, rollouts)

    @learner.jit
    def run(params, levels, key):
        k_collect, k_mc = jax.random.split(key)
        kept_states, kept_hidden, values = collect(params, levels, k_collect)
        returns = continuations(params, levels, kept_states, kept_hidden, k_mc)
        mc_mean = returns.mean(axis=1)
        stderr = (returns.std(axis=1, ddof=1) / jnp.sqrt(rollouts) if rollouts > 1
                  else jnp.full(states, jnp.nan))
        return values, mc_mean, stderr

    return run


# --- the command -----------------------------------------------------------------------------


def analyse_runs(run_dirs: list[str], scenarios: list[str] | None, states: int,
                 rollouts: int, horizon: int, seed: int, checkpoint: int | None = None
                 ) -> list[dict]:
    """One record per (run, scenario): run, algorithm, update, scenario and `summary()`."""
    from tabx.scenarios import ScenarioError, load_named
    from ued.registry import learner_class, learners_where
    from ued.run_folder import load_policy, read_run_config, split_seed_dir

    for run_dir in run_dirs:  # before any run is loaded or compiled
        algorithm = read_run_config(split_seed_dir(run_dir)[0]).algorithm
        if not learner_class(algorithm).value_head:
            raise ConfigError(
                f"{run_dir}: a {algorithm} run has no value head: the value error compares a "
                f"learner's V(s) with Monte-Carlo returns, and a Q-learner's greedy Q is in "
                f"other units (scaled rewards; VDN and QMIX mix it into the team's value); "
                f"analyse runs of {', '.join(learners_where(lambda c: c.value_head))}")
    records = []
    for run_dir in run_dirs:
        policy = load_policy(run_dir, checkpoint)
        names = scenarios or list(policy.config.env.scenario)
        for index, name in enumerate(names):
            try:
                level = load_named(name).to_level(policy.learner.env_config)
            except ScenarioError as err:
                raise ConfigError(f"{run_dir}: {err}") from None
            level = policy.learner.prepare_levels(level)
            result = value_error(policy.learner, policy.params, level,
                                 jax.random.fold_in(jax.random.key(seed), index),
                                 states, rollouts, horizon, scenario=name)
            records.append({"run": str(policy.run_dir), "algorithm": policy.config.algorithm,
                            "update": policy.update, "scenario": Path(name).stem,
                            **result.summary()})
    return records


def group_records(records: list[dict], by: str = "algorithm") -> list[dict]:
    """Bars of the plot: per (group, scenario), the mean of the runs' mean |V - V*| and its
    error bar. `by="algorithm"` pools the runs of an algorithm (seeds), the error bar then
    the standard error over runs (the paper's figures: mean and standard error over seeds),
    or a run's own 95 % interval when it is the only one; `by="run"`: one bar per run."""
    key = (lambda r: r["algorithm"]) if by == "algorithm" else (
        lambda r: f"{Path(r['run']).name} ({r['algorithm']})")
    groups: dict[tuple[str, str], list[dict]] = {}
    for record in records:
        groups.setdefault((key(record), record["scenario"]), []).append(record)
    bars = []
    for (label, scenario), members in groups.items():
        errors = np.array([m["mean_abs_error"] for m in members])
        spread = (float(errors.std(ddof=1) / np.sqrt(errors.size)) if errors.size > 1
                  else float(members[0]["ci95"]))
        bars.append({"label": label, "scenario": scenario, "runs": len(members),
                     "mean_abs_error": float(errors.mean()), "error_bar": spread})
    return bars


def plot_value_errors(records: list[dict], out: str | Path, by: str = "algorithm") -> Path:
    """Grouped bars: per scenario, one bar per algorithm (or run, `by`); see
    `group_records`."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ued.plot import save_figure

    bars = group_records(records, by)
    scenarios = list(dict.fromkeys(b["scenario"] for b in bars))
    labels = list(dict.fromkeys(b["label"] for b in bars))
    width = 0.8 / len(labels)
    fig, ax = plt.subplots(figsize=(max(4.0, 1.4 * len(scenarios) * max(1, len(labels) / 2)),
                                    3.6))
    for k, label in enumerate(labels):
        mine = {b["scenario"]: b for b in bars if b["label"] == label}
        xs = [s - 0.4 + (k + 0.5) * width for s, sc in enumerate(scenarios) if sc in mine]
        shown = [mine[sc] for sc in scenarios if sc in mine]
        ax.bar(xs, [b["mean_abs_error"] for b in shown], width,
               yerr=[b["error_bar"] for b in shown], capsize=3, label=label)
    ax.set_xticks(range(len(scenarios)), scenarios)
    ax.set_ylabel("mean |V - V*|")
    bar = ("standard error over runs, or 95 % interval over states for one run"
           if by == "algorithm" else "95 % interval over states")
    ax.set_title(f"value estimation error ({bar})", fontsize=8)
    ax.legend(fontsize=7)
    return save_figure(fig, out, bbox_inches="tight")


__all__ = ["ValueErrorEstimate", "analyse_runs",
           "group_records", "plot_value_errors", "value_error"]

"""Value-error analysis (`ued.value_error`, `tabx analyse value-error`).

The estimator is checked against a policy whose value is the true value: on the tiny duel
with both teams idle, nothing is ever damaged and every episode times out in a tie, which the
enemies win, so the allies' only reward is `lose_reward` on the episode's last step and
V(s_t) = lose_reward * gamma^(max_steps - 1 - t) exactly. The test learner always idles and
outputs that value, counting t in its critic's recurrent state (reset at episode ends like any
hidden state): the kept values must match the Monte-Carlo ones, which also checks that the
kept recurrent state is the one the value was computed from.
"""

from __future__ import annotations

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from test_learners_helpers import ENV_CONFIG, duel_level, tiny_config
from test_train_cli import run_cli

from tabx import constants as C
from ued.checkpoint import Checkpoints
from ued.config import LearnerConfig
from ued.experiment import learner_for
from ued.learners.mappo import MAPPO
from ued.run_folder import CHECKPOINT_DIR, CONFIG_FILE
from ued.value_error import value_error


class IdleWithTrueValue(MAPPO):
    """Always IDLE; value: the exact discounted return of the idle duel (module doc)."""

    def act_step(self, params, x, world, hidden):
        h_actor, h_critic = hidden
        steps_done = h_critic[:, 0]
        logits = jnp.full(x.shape[:-1] + (C.NUM_ACTIONS,), -30.0).at[..., C.IDLE].set(0.0)
        remaining = self.env_config.max_steps - 1 - steps_done
        value = self.env_config.lose_reward * self.ppo.gamma ** remaining
        return (h_actor, h_critic.at[:, 0].add(1.0)), logits, value


def test_a_policy_valued_at_its_true_value_has_no_value_error():
    learner = IdleWithTrueValue(ENV_CONFIG, LearnerConfig(num_envs=4, hidden_dim=16, gamma=0.9),
                                "ally", "idle")
    params = learner.init(jax.random.key(0)).params
    level = learner.prepare_levels(duel_level())
    result = value_error(learner, params, level, jax.random.key(1), states=24, rollouts=4,
                         horizon=20)
    # The states are spread over the episode: their values differ (the check is not 0 == 0).
    assert np.ptp(result.mc_values) > 0.3
    # gamma**k as a power and as k products in float32: at most 20 roundings of values <= 1.
    np.testing.assert_allclose(result.values, result.mc_values, atol=1e-5)
    summary = result.summary()
    assert summary["mean_abs_error"] < 1e-5 and summary["states"] == 24
    assert summary["mean_mc_stderr"] == 0.0  # deterministic continuations


def test_value_error_command_json_plot_and_errors(capsys, tmp_path):
    config = tiny_config()
    run = tmp_path / "mappo_run"
    run.mkdir()
    (run / CONFIG_FILE).write_text(config.to_yaml())
    with Checkpoints(run / CHECKPOINT_DIR) as ck:
        ck.save(0, learner_for(config).init(jax.random.key(0)), jax.random.key(0))
    out_json, out_png = tmp_path / "ve.json", tmp_path / "ve.png"
    # 8 x 4 from 16-step rollouts: the program the training test below compiles too.
    code, text, err = run_cli(capsys, "analyse", "value-error", str(run), "--states", "8",
                              "--rollouts", "4", "--horizon", "16", "--json", str(out_json),
                              "--plot", str(out_png))
    assert code == 0, err
    assert "mappo_run (mappo)" in text and "duel2a1f" in text
    data = json.loads(out_json.read_text())
    (record,) = data["results"]
    assert record["algorithm"] == "mappo" and record["states"] == 8 and record["rollouts"] == 4
    assert record["mean_abs_error"] >= 0 and np.isfinite(record["ci95"])
    assert record["mean_mc_stderr"] >= 0 and -1.0 <= record["mean_mc_value"] <= 1.0
    assert out_png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    for argv, words in ((["--states", "0"], "--states must be >= 1"),
                        ([], "not a run folder")):
        target = str(run) if argv else str(tmp_path / "nothing")
        code, _, err = run_cli(capsys, "analyse", "value-error", target, *argv)
        assert code == 2 and words in err and len(err.strip().splitlines()) == 1


def test_value_error_is_logged_during_training(tmp_path):
    from ued.config import ConfigError, config_from_dict
    from ued.tensorboard import read_scalars
    from workers.train import train

    config = tiny_config(**{"run.value_error_every": 2, "run.value_error_states": 8,
                            "run.value_error_rollouts": 4})
    run = train(config, run_dir=tmp_path / "run", progress=False)
    scalars = read_scalars(run / "events")
    steps = [s for s, _ in scalars["value_error/duel2a1f/mean_abs_error"]]
    assert steps == [2 * config.learner.steps_per_update, 4 * config.learner.steps_per_update]
    assert all(v >= 0 for _, v in scalars["value_error/duel2a1f/mean_abs_error"])
    with pytest.raises(ConfigError, match="run.value_error_every: .*plain MARL runs"):
        config_from_dict({"run": {"value_error_every": 5}, "ued": {"method": "dr"}})
    with pytest.raises(ConfigError, match="run.value_error_states: must be >= 1"):
        config_from_dict({"run": {"value_error_states": 0}})


def test_the_plot_pools_runs_of_an_algorithm_as_mean_and_standard_error():
    from ued.value_error import group_records

    record = lambda run, alg, scenario, error, ci: {
        "run": run, "algorithm": alg, "scenario": scenario, "mean_abs_error": error,
        "ci95": ci}
    records = [record("r/m0", "mappo", "clover", 0.1, 0.01),
               record("r/m1", "mappo", "clover", 0.3, 0.02),
               record("r/i0", "ippo", "clover", 0.5, 0.03)]
    bars = {b["label"]: b for b in group_records(records)}
    assert bars["mappo"]["mean_abs_error"] == pytest.approx(0.2)
    assert bars["mappo"]["error_bar"] == pytest.approx(np.std([0.1, 0.3], ddof=1) / np.sqrt(2))
    assert bars["mappo"]["runs"] == 2
    assert bars["ippo"]["error_bar"] == 0.03  # one run: its interval over states
    per_run = group_records(records, by="run")
    assert [b["label"] for b in per_run] == ["m0 (mappo)", "m1 (mappo)", "i0 (ippo)"]


def test_value_error_refuses_learners_without_a_value_head(capsys, tmp_path):
    """IQL, VDN and QMIX runs: one line before anything is loaded (their greedy Q is in
    scaled reward units, and VDN's and QMIX's team value is the mixer's, not a V(s))."""
    from ued.config import load_config

    for algorithm in ("iql", "vdn", "qmix"):
        run = tmp_path / f"{algorithm}_run"
        run.mkdir()
        config = load_config("configs/marl/iql_crossfire.yaml", [f"algorithm={algorithm}"])
        (run / CONFIG_FILE).write_text(config.to_yaml())
        code, out, err = run_cli(capsys, "analyse", "value-error", str(run))
        lines = err.strip().splitlines()
        assert code == 2 and len(lines) == 1, err
        assert f"a {algorithm} run has no value head" in lines[0] and "mappo" in lines[0]
        assert sorted(p.name for p in run.iterdir()) == [CONFIG_FILE]

"""MAPPO+RND (`ued.learners.rnd`): the intrinsic reward, its GAE, the predictor's training,
`tabx train` with `algorithm: mappo_rnd`, bit-exact resume and the config checks.

Training tests use the tiny duel of tests/ued/test_learners_helpers.py with `algorithm: mappo_rnd`
(one compiled update for the module)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from test_learners_helpers import duel_level, tiny_config, tiny_levels

from tabx.params import repeat_level
from ued.config import ConfigError, LearnerConfig, config_from_dict
from ued.experiment import learner_for
from ued.learners.ppo import Transition, gae
from ued.learners.rnd import MAPPORND, prediction_error

RND = {"algorithm": "mappo_rnd"}


def test_rnd_defaults_are_the_papers():
    ppo = LearnerConfig()
    assert (ppo.rnd_hidden_dim, ppo.rnd_output_dim, ppo.rnd_layers, ppo.rnd_lr,
            ppo.rnd_gae_coef, ppo.rnd_reward_coef, ppo.rnd_loss_coef,
            ppo.rnd_update_epochs) == (128, 256, 3, 3e-4, 0.01, 0.5, 0.01, 1)


@pytest.mark.parametrize("data, key, words", [
    ({"learner": {"rnd_reward_coef": 1.0}}, "learner.rnd_reward_coef",
     "RND settings go with algorithm mappo_rnd, not mappo"),
    ({"algorithm": "ippo", "learner": {"rnd_layers": 2}}, "learner.rnd_layers",
     "not ippo"),
    ({**RND, "learner": {"rnd_lr": 0}}, "learner.rnd_lr", r"must be in \(0, 1\]"),
    ({**RND, "learner": {"rnd_output_dim": 0}}, "learner.rnd_output_dim", "must be >= 1"),
    ({**RND, "learner": {"rnd_gae_coef": -1}}, "learner.rnd_gae_coef", "must be >= 0"),
    ({"algorithm": "mappo_rdn"}, "algorithm", "mappo_rnd"),
])
def test_rnd_config_errors_name_the_key(data, key, words):
    with pytest.raises(ConfigError, match=rf"cfg.yaml: {key.replace('.', '[.]')}: .*{words}"):
        config_from_dict(data, source="cfg.yaml")


def test_bundled_rnd_and_entropy_sweep_configs():
    from pathlib import Path

    from ued.config import load_config

    folder = Path(__file__).resolve().parents[2] / "configs" / "marl"
    for scenario in ("pingpong", "encirclement"):
        rnd = load_config(folder / f"mappo_rnd_{scenario}.yaml")
        assert rnd.algorithm == "mappo_rnd" and rnd.learner.ent_coef == 0.001
        assert rnd.learner.total_timesteps == 30_000_000
        sweep = sorted(load_config(path).learner.ent_coef for path in
                       (folder / "exploration").glob(f"mappo_{scenario}_ent*.yaml"))
        assert sweep == [0.001, 0.01, 0.05]


def _fake_rollout(learner: MAPPORND, steps: int = 6, envs: int = 2):
    """A Transition (T, E) and its bootstrap with random world states, values and rewards;
    env 0 ends an episode at step 2."""
    keys = jax.random.split(jax.random.key(4), 4)
    world = jax.random.normal(keys[0], (steps + 1, envs, learner.state_dim))
    value = jax.random.normal(keys[1], (steps + 1, envs, 2))
    done = jnp.zeros((steps, envs), bool).at[2, 0].set(True)
    reward = jax.random.normal(keys[2], (steps, envs))
    fill = jnp.zeros((steps, envs))
    traj = Transition(obs=fill, world=world[:-1], mask=fill, alive=fill, action=fill,
                      logp=fill, value=value[:-1], reward=reward, done=done, won=done)
    last = jax.tree.map(lambda x: x[-1], Transition(
        obs=fill, world=world[1:], mask=fill, alive=fill, action=fill, logp=fill,
        value=value[1:], reward=reward, done=done, won=done))
    return traj, last, world


def test_intrinsic_reward_and_the_two_advantages():
    learner = learner_for(tiny_config(**RND))
    params = learner.init(jax.random.key(0)).params
    traj, last, world = _fake_rollout(learner)
    values, adv, targets, extras = learner.returns(params, traj, last)
    ppo = learner.ppo
    # r_i of step t is the prediction error on the state after it; zero where the step ended
    # the episode (that state belongs to the next episode).
    expected = ppo.rnd_reward_coef * prediction_error(params["rnd"], world[1:])
    reward_int = np.asarray(extras["reward_int"])
    assert reward_int[2, 0] == 0.0
    keep = ~np.asarray(traj.done)
    np.testing.assert_allclose(reward_int[keep], np.asarray(expected)[keep], rtol=1e-6)
    assert np.all(reward_int[keep] > 0)
    np.testing.assert_array_equal(extras["next_world"], world[1:])
    # Extrinsic GAE stops at the episode end, intrinsic GAE runs through it.
    adv_e, target_e = gae(traj.reward, traj.value[..., 0], traj.done, last.value[..., 0],
                          ppo.gamma, ppo.gae_lambda)
    adv_i, target_i = gae(extras["reward_int"], traj.value[..., 1], jnp.zeros_like(traj.done),
                          last.value[..., 1], ppo.gamma, ppo.gae_lambda)
    np.testing.assert_allclose(adv, adv_e + ppo.rnd_gae_coef * adv_i, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(targets, np.stack([target_e, target_i], -1), rtol=1e-5,
                               atol=1e-6)
    np.testing.assert_array_equal(values, traj.value[..., 0])


def test_intrinsic_reward_falls_on_states_seen_repeatedly():
    """Update after update on the same level: the predictor learns its states, so their
    intrinsic reward falls, while states of a level never played stay novel. The target
    network never changes."""
    config = tiny_config(**RND)
    learner = learner_for(config)
    state = learner.init(jax.random.key(0))
    target0 = jax.tree.map(np.asarray, state.params["rnd"]["target"])
    levels = tiny_levels()
    # States of the training level and of an unseen one (other positions and health).
    seen = jax.vmap(learner.env.world_state)(
        jax.vmap(learner.env.initial_state)(learner.prepare_levels(levels)),
        learner.prepare_levels(levels))[:1]
    other = jax.tree.map(jnp.asarray, repeat_level(
        duel_level(ally_x=14.0, farmer_health=150.0), 1))
    unseen = jax.vmap(learner.env.world_state)(
        jax.vmap(learner.env.initial_state)(learner.prepare_levels(other)),
        learner.prepare_levels(other))
    error = lambda params, w: float(prediction_error(params["rnd"], w)[0])
    seen_0, unseen_0 = error(state.params, seen), error(state.params, unseen)
    rewards = []
    key = jax.random.key(1)
    # 20 updates: the last five's intrinsic reward is 0.38 of the first two's, the seen
    # states' error 0.33 of its start against 0.37 for the unseen ones (0.47 at 15).
    for _ in range(20):
        key, k = jax.random.split(key)
        state, metrics, _ = learner.update(state, levels, k)
        rewards.append(float(metrics["rnd/intrinsic_reward"]))
    assert np.mean(rewards[-5:]) < 0.5 * np.mean(rewards[:2]), rewards
    seen_n, unseen_n = error(state.params, seen), error(state.params, unseen)
    assert seen_n < 0.5 * seen_0
    assert seen_n / seen_0 < unseen_n / unseen_0  # the unseen level's states stay newer
    for x, y in zip(jax.tree.leaves(target0), jax.tree.leaves(state.params["rnd"]["target"]),
                    strict=True):
        np.testing.assert_array_equal(x, y)


def test_rnd_trains_from_the_command_line_and_resumes_bit_for_bit(capsys, tmp_path):
    import shutil

    from test_train_cli import run_cli

    from ued.checkpoint import Checkpoints
    from ued.run_folder import CHECKPOINT_DIR
    from ued.tensorboard import read_scalars

    config = tiny_config(**RND, **{"run.checkpoint_every": 2})  # 4 updates
    path = tmp_path / "rnd.yaml"
    path.write_text(config.to_yaml())
    full, part = tmp_path / "full", tmp_path / "part"
    assert run_cli(capsys, "train", str(path), "--run-dir", str(full), "--quiet")[0] == 0
    assert run_cli(capsys, "train", str(path), "--run-dir", str(part), "--quiet",
                   "--max-updates", "3")[0] == 0
    shutil.rmtree(part / CHECKPOINT_DIR / "3")  # resume from the middle, as after a crash
    assert run_cli(capsys, "train", "--resume", str(part), "--quiet")[0] == 0
    learner = learner_for(config)
    template = learner.init(jax.random.key(0))
    with Checkpoints(full / CHECKPOINT_DIR) as a, Checkpoints(part / CHECKPOINT_DIR) as b:
        state_a, key_a, n_a = a.restore(template)
        state_b, key_b, n_b = b.restore(template)
    assert n_a == n_b == 4
    assert set(state_a.opt_state) == {"ppo", "rnd"}
    for x, y in zip(jax.tree.leaves(state_a), jax.tree.leaves(state_b), strict=True):
        assert np.array_equal(np.asarray(x), np.asarray(y))
    assert np.array_equal(jax.random.key_data(key_a), jax.random.key_data(key_b))
    scalars = read_scalars(full / "events")
    for tag in ("rnd/intrinsic_reward", "rnd/loss", "loss/value_int"):
        assert len(scalars[tag]) == 4 and all(np.isfinite(v) for _, v in scalars[tag])
    # The trained policy plays in `tabx eval`.
    code, out, err = run_cli(capsys, "eval", str(full), "--episodes", "4")
    assert code == 0 and "(mappo_rnd, update 4)" in out, err

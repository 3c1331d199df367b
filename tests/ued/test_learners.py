"""MAPPO / IPPO learners: the loss of a learner's minibatch, the GRU trunk, the jitted update,
configs, TensorBoard events, checkpoints and bit-exact resume (GAE and the loss terms alone:
tests/ued/test_ppo_losses.py).

The update tests share one tiny learner (2 archers v 1 farmer, 4 envs x 16 steps, hidden 16),
so the update compiles once for the whole module; `test_learners_helpers.tiny_config` is also
used by tests/tabx_ued/test_train_cli.py, whose runs then reuse the same compiled update.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st
from test_learners_helpers import (
    BFLOAT16_STEP,
    ENV_CONFIG,
    duel_level,
    restore_both_and_compare,
    rounding_bound,
    tiny_config,
    tiny_learner,
    tiny_levels,
)

from tabx.params import EnvConfig, repeat_level, stack_levels
from ued.config import ConfigError, LearnerConfig, apply_overrides, config_from_dict, load_config
from ued.learners import make_learner
from ued.learners import networks as nw
from ued.learners.ippo import IPPO
from ued.learners.ppo import policy_terms, team_mean

# --- the loss of a learner ------------------------------------------------------------------


def test_team_mean_and_ippo_dead_agent_values():
    values = jnp.array([[1.0, 3.0, 100.0]])
    alive = jnp.array([[True, True, False]])
    assert float(team_mean(values, alive)[0]) == pytest.approx(2.0)
    filled, last = IPPO.value_terms(None, values, values, alive, alive)
    np.testing.assert_allclose(filled, [[1.0, 3.0, 2.0]])


def test_the_loss_ignores_dead_and_padded_agents():
    learner = tiny_learner()
    params = learner.init(jax.random.key(0)).params
    rng = np.random.default_rng(2)
    t, e, a = 6, 2, learner.num_agents
    batch = {
        "obs": jnp.asarray(rng.normal(size=(t, e, a, learner.env_config.obs_size)), jnp.float32),
        "world": jnp.asarray(rng.normal(size=(t, e, learner.state_dim)), jnp.float32),
        "mask": jnp.ones((t, e, a, 8), bool),
        "alive": jnp.asarray(np.tile([True, False], (t, e, 1))),  # agent 1 dead / padded
        "action": jnp.asarray(rng.integers(0, 8, size=(t, e, a)), jnp.int32),
        "logp": jnp.full((t, e, a), -2.0, jnp.float32),
        "value": jnp.zeros((t, e), jnp.float32),
        "adv": jnp.asarray(rng.normal(size=(t, e)), jnp.float32),
        "targets": jnp.asarray(rng.normal(size=(t, e)), jnp.float32),
        "starts": jnp.zeros((t, e), bool).at[0].set(True),
    }
    loss = jax.jit(jax.value_and_grad(learner._loss, has_aux=True))
    (total, aux), grads = loss(params, batch)
    # Change everything about the invalid agent except its observation (it is an input of the
    # shared network only through its own rows): actions, old log-probabilities, masks.
    other = dict(batch)
    other["action"] = batch["action"].at[:, :, 1].set(3)
    other["logp"] = batch["logp"].at[:, :, 1].set(-0.01)
    other["mask"] = batch["mask"].at[:, :, 1, 3:].set(False)
    (total2, aux2), grads2 = loss(params, other)
    assert float(total) == pytest.approx(float(total2), rel=1e-6)
    for g1, g2 in zip(jax.tree.leaves(grads), jax.tree.leaves(grads2), strict=True):
        np.testing.assert_allclose(g1, g2, rtol=1e-5, atol=1e-7)
    assert np.isfinite(float(total)) and float(aux["loss/entropy"]) > 0


# --- the recurrent trunk ---------------------------------------------------------------------


def _reference_sequence(p, x, starts, h0):
    """Reference: the trunk step by step in a plain scan (no rematerialisation, no unrolling)."""
    def step(h, inputs):
        xx, s = inputs
        h = jnp.where(s[:, None], 0.0, h)
        e = jax.nn.relu(nw.layer_norm(p["ln_embed"], xx @ p["embed"]["w"] + p["embed"]["b"]))
        gi = e @ p["gru"]["wi"] + p["gru"]["bi"]
        h = nw._gates(gi, h @ p["gru"]["wh"] + p["gru"]["bh"], h)[0]
        y = jax.nn.relu(nw.layer_norm(p["ln_hidden"], h @ p["hidden"]["w"]
                                      + p["hidden"]["b"]))
        return h, y @ p["out"]["w"] + p["out"]["b"]

    return jax.lax.scan(step, h0, (x, starts))[1]


def test_trunk_sequence_and_its_gradients_match_a_plain_scan(monkeypatch):
    monkeypatch.setattr(nw, "UNROLL_MIN_SIZE", 0)  # the unrolled scan of full-size training
    p = nw.trunk_init(jax.random.key(0), 10, 16, (0.01,) * 8 + (1.0,))
    p = jax.tree.map(lambda x: x + 0.1 * jax.random.normal(jax.random.key(9), x.shape), p)
    x = jax.random.normal(jax.random.key(1), (7, 5, 10))
    starts = jax.random.uniform(jax.random.key(2), (7, 5)) < 0.3
    h0 = jax.random.normal(jax.random.key(3), (5, 16))

    def loss(fn):
        return jax.jit(jax.value_and_grad(lambda p, h: jnp.sin(fn(p, x, starts, h)).sum(),
                                          (0, 1)))

    (value, ours), (value_ref, ref) = loss(nw.sequence)(p, h0), loss(_reference_sequence)(p, h0)
    assert float(value) == pytest.approx(float(value_ref), rel=1e-5)
    for a, b in zip(jax.tree.leaves(ours), jax.tree.leaves(ref), strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-5)


def _rounded(a: jax.Array) -> np.ndarray:
    return np.asarray(a.astype(jnp.bfloat16).astype(jnp.float32), np.float64)


@pytest.mark.parametrize("transposed", [True, False])
def test_bfloat16_products_round_their_inputs_and_accumulate_in_float32(transposed):
    """learner.matmul_dtype=bfloat16: the forward product and the input gradient take
    bfloat16-rounded operands and sum in float32; the weight gradient is the float32 one."""
    x = jax.random.normal(jax.random.key(0), (5, 16))
    w = jax.random.normal(jax.random.key(1), (16, 8))
    g = jax.random.normal(jax.random.key(2), (5, 8))
    w_t = w.T.astype(jnp.bfloat16) if transposed else None
    y, vjp = jax.vjp(lambda x, w: nw.linear(x, w, w_t, jnp.bfloat16), x, w)
    dx, dw = vjp(g)
    assert y.dtype == dx.dtype == dw.dtype == jnp.float32
    np.testing.assert_allclose(y, _rounded(x) @ _rounded(w), rtol=1e-5, atol=1e-5)
    assert np.abs(np.asarray(y) - np.asarray(x, np.float64) @ np.asarray(w)).max() > 1e-3
    np.testing.assert_allclose(dx, _rounded(g) @ _rounded(w).T, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(dw, np.asarray(x, np.float64).T @ np.asarray(g), rtol=1e-5,
                               atol=1e-5)


def test_float32_products_are_exact_with_or_without_transposes():
    x = jax.random.normal(jax.random.key(0), (5, 16))
    w = jax.random.normal(jax.random.key(1), (16, 8))
    plain = jax.jacrev(lambda x, w: x @ w, (0, 1))(x, w)
    ours = jax.jacrev(lambda x, w: nw.linear(x, w, w.T), (0, 1))(x, w)
    np.testing.assert_allclose(nw.linear(x, w, w.T), x @ w, rtol=1e-6, atol=1e-6)
    for a, b in zip(plain, ours, strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-6, atol=1e-6)


def test_bfloat16_training_sequences_replay_the_bfloat16_steps_and_track_float32():
    """The training pass (`sequence`) computes what the rollout's `step` computed with the
    same matmul dtype (PPO's first ratios are 1), and bfloat16 stays close to float32."""
    p = nw.trunk_init(jax.random.key(0), 10, 16, (0.01,) * 8 + (1.0,))
    x = jax.random.normal(jax.random.key(1), (12, 5, 10))
    starts = jnp.zeros((12, 5), bool)
    h0 = jnp.zeros((5, 16))

    def stepped(dtype):
        return jax.lax.scan(lambda h, x_t: nw.step(p, x_t, h, dtype), h0, x)[1]

    low = jax.jit(nw.sequence, static_argnums=4)(p, x, starts, h0, jnp.bfloat16)
    np.testing.assert_allclose(low, jax.jit(stepped, static_argnums=0)(jnp.bfloat16),
                               rtol=1e-5, atol=1e-6)
    full = jax.jit(nw.sequence)(p, x, starts, h0)
    assert not np.allclose(low, full, rtol=1e-6, atol=1e-7)
    np.testing.assert_allclose(low, full, rtol=0.05, atol=0.02)


@pytest.mark.parametrize("dtype", ["bfloat16", "float32"])
def test_the_update_program_multiplies_in_the_configured_matmul_dtype(dtype):
    ppo = LearnerConfig(num_envs=4, num_steps=8, hidden_dim=16, num_minibatches=2,
                    matmul_dtype=dtype)
    learner = make_learner("ippo", ENV_CONFIG, ppo, "ally", "random", cached=False)
    state = learner.init(jax.random.key(0))
    text = learner._update_jit.lower(state, tiny_levels(), jax.random.key(1)).as_text()
    assert ("bf16" in text) == (dtype == "bfloat16")


@settings(max_examples=25, deadline=None)
@given(shift=st.floats(-100.0, 100.0), spread=st.floats(1e-2, 1e2), seed=st.integers(0, 2**16))
def test_layer_norm_matches_float64_and_flax(shift, spread, seed):
    """Our LayerNorm (statistics as matrix-vector products) against LayerNorm in float64, and
    its gradient against flax's LayerNorm (two-pass variance, epsilon 1e-6), over offsets and
    scales of the input. Inputs whose offset dwarfs their spread (more than 100x) are left out:
    there float32 itself cannot resolve the centred values."""
    import flax.linen as fnn

    assume(abs(shift) <= 100 * spread)
    x = shift + spread * jax.random.normal(jax.random.key(seed), (6, 128))
    p = {"scale": 1.0 + 0.1 * jax.random.normal(jax.random.key(seed + 1), (128,)),
         "bias": 0.1 * jax.random.normal(jax.random.key(seed + 2), (128,))}
    x64 = np.asarray(x, np.float64)
    centred = x64 - x64.mean(-1, keepdims=True)
    want = (centred / np.sqrt((centred**2).mean(-1, keepdims=True) + nw.LN_EPS)
            * np.asarray(p["scale"], np.float64) + np.asarray(p["bias"], np.float64))
    np.testing.assert_allclose(nw.layer_norm(p, x), want, atol=1e-4)
    ln = fnn.LayerNorm(epsilon=nw.LN_EPS, use_fast_variance=False)
    g_ours = jax.grad(lambda q: jnp.sin(nw.layer_norm(q, x)).sum())(p)
    g_flax = jax.grad(lambda q: jnp.sin(ln.apply({"params": q}, x)).sum())(p)
    for a, b in zip(jax.tree.leaves(g_ours), jax.tree.leaves(g_flax), strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-3, atol=1e-3)


def test_hidden_state_resets_at_episode_starts():
    p = nw.trunk_init(jax.random.key(0), 6, 8, (1.0,))
    x = jax.random.normal(jax.random.key(1), (9, 2, 6))
    starts = jnp.zeros((9, 2), bool).at[4, 0].set(True)
    h0 = jax.random.normal(jax.random.key(2), (2, 8))
    sequence = jax.jit(nw.sequence)
    out = sequence(p, x, starts, h0)
    # From step 4 on, env 0 behaves as a fresh sequence started there from zeros.
    fresh = sequence(p, x[4:, :1], jnp.zeros((5, 1), bool), jnp.zeros((1, 8)))
    np.testing.assert_allclose(out[4:, :1], fresh, atol=1e-6)
    # Env 1 never resets: its outputs depend on h0 all along.
    no_h0 = sequence(p, x, starts, jnp.zeros((2, 8)))
    assert not np.allclose(out[8, 1], no_h0[8, 1])


def test_rollout_resets_the_policy_hidden_state_when_an_episode_ends():
    learner = tiny_learner()
    params = learner.init(jax.random.key(0)).params
    levels = learner.prepare_levels(tiny_levels())
    rollout = jax.jit(learner.rollout)
    traj, records, _ = rollout(params, levels, jax.random.key(3))
    done = np.asarray(traj.done)
    assert done.any(), "the tiny config's episodes (8 steps) must end within the rollout"
    # Replaying the actor over the rollout with resets at episode starts reproduces the
    # rollout's action log-probabilities exactly where the policy was sampled.
    starts = jnp.concatenate([jnp.ones((1, done.shape[1]), bool), traj.done[:-1]], 0)
    logits, _ = learner.evaluate_sequence(params, learner.agent_inputs(traj.obs), traj.world,
                                          starts)
    logp, _ = policy_terms(logits, traj.mask, traj.action)
    np.testing.assert_allclose(logp, traj.logp, atol=1e-4)


# --- the jitted update -----------------------------------------------------------------------


def test_update_returns_metrics_and_rollout_stats_per_env():
    learner = tiny_learner()
    state = learner.init(jax.random.key(0))
    state, metrics, stats = learner.update(state, tiny_levels(), jax.random.key(1))
    ppo = learner.ppo
    for field in ("values", "advantages", "dones", "rewards", "wins"):
        assert getattr(stats, field).shape == (ppo.num_steps, ppo.num_envs)
    assert int(state.update) == 1
    for key in ("loss/policy", "loss/value", "loss/entropy", "episode/win_rate",
                "episode/return", "episode/length", "episode/first_kill_rate", "grad_norm"):
        assert key in metrics
    assert np.isfinite(float(metrics["loss/total"]))
    assert float(metrics["episode/count"]) == float(np.sum(stats.dones))
    # Wins only at episode ends.
    assert not np.any(np.asarray(stats.wins) & ~np.asarray(stats.dones))
    from ued.scores import positive_value_loss

    pvl = positive_value_loss(stats.advantages, stats.dones)
    assert pvl.shape == (ppo.num_envs,)


def test_new_levels_never_recompile_and_the_update_stays_on_device():
    learner = tiny_learner()
    state = learner.init(jax.random.key(0))
    levels = tiny_levels()
    assert len(learner.learner_devices(learner.ppo.num_envs)) == 2  # the data-parallel path
    state, _, _ = learner.update(state, levels, jax.random.key(1))
    size = learner._update_jit._cache_size()
    # Other levels of the same EnvConfig: other positions, health, opponent tier.
    other = stack_levels([duel_level(ally_x=-10.0 - i, farmer_health=30.0 + 10 * i)
                          for i in range(learner.ppo.num_envs)])
    other = jax.tree.map(jnp.asarray, other)
    key = jax.random.key(2)
    with jax.transfer_guard("disallow"):
        state, metrics, _ = learner.update(state, other, key)
    jax.block_until_ready(metrics)
    assert learner._update_jit._cache_size() == size
    # Results come back on the caller's device, ready for the next update or a checkpoint.
    assert {d for leaf in jax.tree.leaves((state, metrics)) for d in leaf.devices()} == {
        jax.devices()[0]}


@pytest.mark.parametrize("algorithm", ["mappo", pytest.param("ippo", marks=pytest.mark.slow)])
def test_an_update_split_over_two_devices_equals_the_one_device_update(algorithm):
    """Data parallel: each env draws from its own keys, so both play the same rollout
    (episodes equal exactly); with one minibatch (the same rows either way) the summed shard
    gradients give the parameters of the one-device update within `rounding_bound`: the
    shards' float32 sums add in another order (its docstring derives the bound)."""
    results = []
    for devices in (1, 2):
        ppo = LearnerConfig(num_envs=4, num_steps=16, hidden_dim=16, num_minibatches=1,
                        update_epochs=2, num_devices=devices)
        learner = make_learner(algorithm, ENV_CONFIG, ppo, "ally", "random", cached=False)
        assert len(learner.learner_devices(4)) == devices
        state = learner.init(jax.random.key(0))
        start = jax.device_get(state.params)
        state, metrics, stats = learner.update(state, tiny_levels(), jax.random.key(1))
        results.append((jax.device_get(state.params), jax.device_get(metrics),
                        jax.device_get(stats)))
    (params_1, metrics_1, stats_1), (params_2, metrics_2, stats_2) = results
    bound = rounding_bound(ppo)
    moved = max(float(np.max(np.abs(a - b))) for a, b in zip(
        jax.tree.leaves(params_1), jax.tree.leaves(start), strict=True))
    assert moved > 100 * bound  # the update moved the parameters far more than the bound
    for a, b in zip(jax.tree.leaves(params_1), jax.tree.leaves(params_2), strict=True):
        np.testing.assert_allclose(a, b, rtol=0, atol=bound)
    assert float(metrics_1["episode/count"]) > 0
    for name in ("dones", "rewards", "wins"):  # the same rollout, exactly
        np.testing.assert_array_equal(getattr(stats_1, name), getattr(stats_2, name))
    for name in ("episode/count", "episode/win_rate"):  # counted from those: exact
        assert metrics_1[name] == metrics_2[name], name
    # Losses, norms and values are means over 128 rows of products that may each round one
    # bfloat16 step (2**-8) apart: relative to their size, and to the mean of absolute terms
    # where they nearly cancel.
    for name in ("loss/total", "loss/value", "loss/entropy", "grad_norm", "value/mean"):
        np.testing.assert_allclose(metrics_1[name], metrics_2[name], rtol=BFLOAT16_STEP,
                                   atol=BFLOAT16_STEP * 1e-2, err_msg=name)
    assert_values_close(stats_1.values, stats_2.values)


def assert_values_close(a, b) -> None:
    """Values of the same states from two programs that sum in another order: a last float32
    bit may round a bfloat16 input one step (2**-8) apart, moving a value by up to that share
    of the largest values' size."""
    np.testing.assert_allclose(a, b, rtol=0, atol=BFLOAT16_STEP * float(np.max(np.abs(a))))


def test_scoring_split_over_two_devices_equals_one_device_scoring():
    """`score` plays each env from its own keys: same episodes, values to rounding
    (`assert_values_close`)."""
    results = []
    for devices in (1, 2):
        ppo = LearnerConfig(num_envs=4, num_steps=16, hidden_dim=16, num_minibatches=2,
                        num_devices=devices)
        learner = make_learner("ippo", ENV_CONFIG, ppo, "ally", "random", cached=False)
        params = learner.init(jax.random.key(0)).params
        levels = jax.tree.map(jnp.asarray, repeat_level(duel_level(), 6))  # 6: not 4
        assert len(learner.learner_devices(6, minibatches=1, strict=False)) == devices
        metrics, stats = learner.score(params, levels, jax.random.key(4), 12)
        assert stats.dones.shape == (12, 6)
        assert {d for leaf in jax.tree.leaves((metrics, stats)) for d in leaf.devices()} == {
            jax.devices()[0]}
        results.append(jax.device_get((metrics, stats)))
    (metrics_1, stats_1), (metrics_2, stats_2) = results
    assert metrics_1["episode/count"] == metrics_2["episode/count"] > 0
    for name in ("dones", "rewards", "wins"):
        np.testing.assert_array_equal(getattr(stats_1, name), getattr(stats_2, name))
    for name in ("values", "advantages"):  # the episodes' rewards are equal; values round
        assert_values_close(getattr(stats_1, name), getattr(stats_2, name))


def test_devices_are_chosen_to_split_the_envs_evenly():
    def devices(**ppo):
        learner = make_learner("ippo", ENV_CONFIG, LearnerConfig(**ppo), "ally", "random",
                               cached=False)
        return len(learner.learner_devices(ppo["num_envs"]))

    assert devices(num_envs=8, num_minibatches=2) == 2
    assert devices(num_envs=6, num_minibatches=2) == 1  # 3 envs per minibatch: no even split
    assert devices(num_envs=8, num_minibatches=2, num_devices=1) == 1
    with pytest.raises(ValueError, match="learner.num_devices: 3 devices asked for"):
        devices(num_envs=12, num_minibatches=2, num_devices=3)
    # Scoring takes any batch: as many devices as divide it, at most the configured number.
    learner = make_learner("ippo", ENV_CONFIG, LearnerConfig(num_envs=8, num_minibatches=2,
                                                         num_devices=1), "ally", "random")
    assert len(learner.learner_devices(6, minibatches=1, strict=False)) == 1
    learner = make_learner("ippo", ENV_CONFIG, LearnerConfig(num_envs=8, num_minibatches=2),
                           "ally", "random")
    assert len(learner.learner_devices(6, minibatches=1, strict=False)) == 2
    assert len(learner.learner_devices(5, minibatches=1, strict=False)) == 1


def test_learner_plays_the_enemy_team():
    config = tiny_config(**{"env.team": "enemy"})
    learner = make_learner(config.algorithm, EnvConfig(max_allies=2, max_enemies=1,
                                                       max_zones=0, max_steps=8),
                           config.learner, "enemy", "random")
    assert learner.slots == slice(2, 3) and learner.num_agents == 1
    params = learner.init(jax.random.key(0)).params
    traj, _, _ = jax.jit(learner.rollout)(params, learner.prepare_levels(tiny_levels()),
                                             jax.random.key(0))
    assert traj.obs.shape[2] == 1


# --- configs ---------------------------------------------------------------------------------


def test_config_defaults_are_the_papers():
    ppo = LearnerConfig()
    assert (ppo.lr, ppo.hidden_dim, ppo.gamma, ppo.gae_lambda, ppo.clip_eps, ppo.ent_coef,
            ppo.vf_coef, ppo.update_epochs, ppo.num_envs) == (
        4e-3, 128, 0.99, 0.95, 0.05, 0.01, 0.5, 4, 128)


@pytest.mark.parametrize("data, key", [
    ({"learner": {"lrr": 0.1}}, "learner.lrr"),
    ({"algoritm": "mappo"}, "algoritm"),
    ({"learner": {"gamma": 1.5}}, "learner.gamma"),
    ({"learner": {"num_envs": "many"}}, "learner.num_envs"),
    ({"learner": {"num_envs": 10, "num_minibatches": 4}}, "learner.num_minibatches"),
    ({"learner": {"num_devices": -1}}, "learner.num_devices"),
    ({"learner": {"matmul_dtype": "float16"}}, "learner.matmul_dtype"),
    ({"learner": {"num_envs": 8, "num_minibatches": 2, "num_devices": 3}},
     "learner.num_devices"),
    ({"env": {"team": "blue"}}, "env.team"),
    ({"env": {"opponent": "heuristic:godlike"}}, "env.opponent"),
    ({"algorithm": "dqn"}, "algorithm"),
    ({"run": {"checkpoint_every": 0}}, "run.checkpoint_every"),
    ({"learner": {"anneal_lr": "yes"}}, "learner.anneal_lr"),
    ({"env": ["crossfire"]}, "env"),
])
def test_config_errors_name_the_key(data, key):
    with pytest.raises(ConfigError, match=rf"cfg.yaml: .*{key.replace('.', '[.]')}"):
        config_from_dict(data, source="cfg.yaml")


def test_config_file_overrides_and_yaml_numbers(tmp_path):
    path = tmp_path / "c.yaml"
    path.write_text("algorithm: ippo\nlearner:\n  total_timesteps: 5e7\n  lr: 1e-3\n"
                    "env:\n  scenario: [crossfire, vsrangers]\n")
    config = load_config(path, ["learner.num_envs=64", "ent_coef=0.02", "env.team=enemy"])
    assert config.algorithm == "ippo"
    assert config.learner.total_timesteps == 50_000_000 and config.learner.lr == 1e-3
    assert config.learner.num_envs == 64 and config.learner.ent_coef == 0.02
    assert config.env.scenario == ("crossfire", "vsrangers") and config.env.team == "enemy"
    assert load_config(path).to_dict()["env"]["scenario"] == ["crossfire", "vsrangers"]
    with pytest.raises(ConfigError, match="unknown key 'lrate'"):
        apply_overrides({}, ["lrate=1"])
    # A mistyped override is the override's mistake, and the hint is the whole key.
    with pytest.raises(ConfigError, match="override 'learner.lrr=1': unknown key 'learner.lrr'; "
                                          "did you mean 'learner.lr'"):
        load_config(path, ["learner.lrr=1"])
    with pytest.raises(ConfigError, match="KEY=VALUE"):
        apply_overrides({}, ["=3"])
    with pytest.raises(ConfigError, match="cannot read"):
        load_config(tmp_path / "missing.yaml")


def test_every_bundled_config_loads():
    from pathlib import Path

    folder = Path(__file__).resolve().parents[2] / "configs" / "marl"
    files = sorted(folder.glob("*.yaml"))
    assert len(files) >= 16
    for path in files:
        config = load_config(path)
        assert path.stem == f"{config.algorithm}_{config.env.scenario[0]}"
        assert config.env.opponent == "heuristic:medium"


# --- TensorBoard -----------------------------------------------------------------------------


def test_tensorboard_events_are_readable(tmp_path):
    from tensorboard.backend.event_processing import event_accumulator

    from ued.tensorboard import SummaryWriter, read_scalars

    with SummaryWriter(tmp_path) as writer:
        writer.scalars({"episode/win_rate": 0.25, "loss/value": 1.5, "skip": float("nan")}, 10)
        writer.scalar("episode/win_rate", 0.5, 20)
    scalars = read_scalars(tmp_path)
    assert scalars["episode/win_rate"] == [(10, 0.25), (20, 0.5)]
    assert "skip" not in scalars
    acc = event_accumulator.EventAccumulator(str(tmp_path))
    acc.Reload()
    assert [(e.step, e.value) for e in acc.Scalars("loss/value")] == [(10, 1.5)]


# --- checkpoints and resume ------------------------------------------------------------------


def test_resume_continues_bit_for_bit(tmp_path):
    from ued.checkpoint import Checkpoints
    from ued.experiment import learner_for
    from ued.run_folder import CHECKPOINT_DIR
    from workers.train import train

    config = tiny_config(**{"run.checkpoint_every": 2})  # 4 updates; checkpoints at 2, 4
    full = train(config, run_dir=tmp_path / "full", progress=False)
    part = train(config, run_dir=tmp_path / "part", progress=False, max_updates=3)  # "killed"
    with Checkpoints(part / CHECKPOINT_DIR) as ck:
        assert ck.latest() == 3  # the last update of a call always saves
    # Forget update 3 to resume from a checkpoint in the middle, as after a crash.
    import shutil

    shutil.rmtree(part / CHECKPOINT_DIR / "3")
    learner = learner_for(config)
    compiled = learner._update_jit._cache_size()
    train(run_dir=part, resume=True, progress=False)
    assert learner._update_jit._cache_size() == compiled  # the resumed run reuses the compilation
    _, update = restore_both_and_compare(full, part, learner.init(jax.random.key(0)))
    assert update == 4
    # The resumed run logged the updates it redid and the rest.
    from ued.tensorboard import read_scalars

    steps = [s for s, _ in read_scalars(part / "events")["loss/total"]]
    assert steps[-1] == 4 * config.learner.steps_per_update


def test_levels_repeat_the_scenarios_in_turn():
    from ued.experiment import training_levels

    config = tiny_config(**{"learner.num_envs": 4})
    _, levels = training_levels(config)
    assert levels.reward_mode.shape == (4,)
    one = repeat_level(duel_level(), 4)
    np.testing.assert_allclose(levels.units.position, one.units.position)

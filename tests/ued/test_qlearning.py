"""The Q-learners (IQL, VDN, QMIX): mixers, configs, a tiny run of each that resumes bit for bit
and plays in `tabx eval`, and (with -m slow) that each learns to win a small battle."""

from __future__ import annotations

import shutil

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from test_learners_helpers import (
    ENV_CONFIG,
    TINY,
    duel_level,
    learning_duel,
    restore_both_and_compare,
    scenario_file,
)

from tabx.params import repeat_level
from ued.config import (
    Q_LEARNER_SETTINGS,
    ConfigError,
    LearnerConfig,
    QLearningConfig,
    apply_overrides,
    config_from_dict,
)
from ued.learners import make_learner, mixers
from ued.learners.qlearning import GREEDY_LOGIT_SCALE, epsilon_schedule, masked_argmax

Q_ALGORITHMS = ("iql", "vdn", "qmix")


def tiny_q_config(algorithm: str, tmp_dir: str = "runs", overrides: dict | None = None):
    """4 envs x 16 steps (episodes of 8 steps), 4 updates, a buffer of 2 trajectories per env."""
    data = {"algorithm": algorithm, "seed": 3,
            "env": {**TINY["env"], "scenario": scenario_file()},
            "learner": {"num_envs": 4, "num_steps": 16, "total_timesteps": 256,
                        "hidden_dim": 16, "update_epochs": 2, "lr": 1e-3},
            "qlearning": {"buffer_size": 8, "batch_size": 4, "learning_starts": 0,
                          "target_update_interval": 2},
            "run": {**TINY["run"], "dir": tmp_dir}}
    items = [f"{k}={v}" for k, v in (overrides or {}).items()]
    return config_from_dict(apply_overrides(data, items), source="tiny q config")


# --- mixers ----------------------------------------------------------------------------------


@settings(max_examples=20, deadline=None)
@given(agents=st.integers(1, 6), seed=st.integers(0, 2**31 - 1))
def test_vdn_is_the_sum_of_the_agent_values(agents, seed):
    learner = make_learner("vdn", ENV_CONFIG, LearnerConfig(num_envs=4, num_steps=8, hidden_dim=8),
                           settings=QLearningConfig(buffer_size=8, batch_size=4))
    q = jax.random.normal(jax.random.key(seed), (5, 3, agents)) * 10
    np.testing.assert_allclose(learner.mix(None, q, None), q.sum(-1),
                               rtol=1e-6)


@settings(max_examples=20, deadline=None)
@given(agents=st.sampled_from([1, 3, 6]), state_dim=st.sampled_from([1, 12]),
       seed=st.integers(0, 2**31 - 1), init_scale=st.sampled_from([0.001, 1.0, 10.0]))
def test_qmix_mixing_weights_are_non_negative_and_q_tot_is_monotonic(agents, state_dim, seed,
                                                                      init_scale):
    k_init, k_state, k_q, k_noise = jax.random.split(jax.random.key(seed), 4)
    params = mixers.qmix_init(k_init, agents, state_dim, 8, 16, init_scale)
    # Parameters anywhere, not only where the initialisation puts them.
    leaves, tree = jax.tree.flatten(params)
    noise = jax.random.split(k_noise, len(leaves))
    params = jax.tree.unflatten(tree, [x + jax.random.normal(k, x.shape)
                                       for x, k in zip(leaves, noise, strict=True)])
    state = jax.random.normal(k_state, (7, state_dim)) * 5
    q = jax.random.normal(k_q, (7, agents)) * 5
    w1, _, w2, _ = mixers.qmix_weights(params, state, agents)
    assert w1.shape == (7, agents, 8) and w2.shape == (7, 8)
    assert bool(jnp.all(w1 >= 0)) and bool(jnp.all(w2 >= 0))
    grads = jax.vmap(jax.grad(lambda q, s: mixers.qmix(params, q, s)))(q, state)
    assert bool(jnp.all(grads >= 0))


def test_masked_argmax_and_the_greedy_logits_pick_only_legal_actions():
    q = jnp.array([[5.0, 1.0, 3.0, -2.0]])
    mask = jnp.array([[False, True, True, False]])
    assert int(masked_argmax(q, mask)[0]) == 2
    logits = jnp.where(mask, q * GREEDY_LOGIT_SCALE, -1e10)
    draws = jax.vmap(lambda k: jax.random.categorical(k, logits[0]))(
        jax.random.split(jax.random.key(0), 200))
    assert bool(jnp.all(draws == 2))


def test_epsilon_falls_linearly_then_stays():
    eps = epsilon_schedule(QLearningConfig(eps_start=1.0, eps_finish=0.05, eps_decay=0.1), 100)
    assert float(eps(0)) == pytest.approx(1.0)
    assert float(eps(5)) == pytest.approx(0.525)
    assert float(eps(10)) == pytest.approx(0.05)
    assert float(eps(99)) == pytest.approx(0.05)


@pytest.mark.parametrize("algorithm", ["iql", pytest.param("vdn", marks=pytest.mark.slow),
                                       "qmix"])
def test_td_loss_equals_a_step_by_step_double_q_computation(algorithm):
    """The batched loss against plain loops over steps, trajectories and agents: double-Q
    targets over legal actions, no bootstrap past an episode's end (or, for IQL, an agent's
    death), dead agents at 0 in the mixer, the last step only where it ended an episode."""
    from ued.learners.qlearning import Trajectory, qnet_sequence

    learner = make_learner(algorithm, ENV_CONFIG,
                           LearnerConfig(num_envs=4, num_steps=6, hidden_dim=8, gamma=0.9,
                                     matmul_dtype="float32"),
                           settings=QLearningConfig(buffer_size=8, batch_size=4,
                                                    reward_scale=2.0))
    keys = jax.random.split(jax.random.key(7), 9)
    params, target = learner.init_params(keys[0]), learner.init_params(keys[1])
    T, B, A = 6, 3, learner.num_agents
    mask = jax.random.bernoulli(keys[2], 0.6, (T, B, A, 8)).at[..., 0].set(True)
    action = jax.vmap(jax.random.categorical)(
        jax.random.split(keys[3], T * B * A),
        jnp.where(mask, 0.0, -1e10).reshape(-1, 8)).reshape(T, B, A).astype(jnp.int32)
    done = jnp.array([[0, 0, 1, 0, 0, 1], [0, 1, 0, 0, 0, 0], [0, 0, 0, 0, 1, 0]], bool).T
    batch = Trajectory(
        obs=jax.random.normal(keys[4], (T, B, A, ENV_CONFIG.obs_size)),
        world=(jax.random.normal(keys[5], (T, B, ENV_CONFIG.state_size))
               if algorithm == "qmix" else None),
        mask=mask, alive=jax.random.bernoulli(keys[6], 0.7, (T, B, A)), action=action,
        reward=jax.random.normal(keys[7], (T, B)), done=done)
    loss, _ = jax.jit(learner._loss)(params, target, batch)

    starts = np.concatenate([np.ones((1, B), bool), np.asarray(done[:-1])], 0)
    x = learner.agent_inputs(batch.obs).reshape(T, B * A, -1)
    q_of = lambda p: np.asarray(qnet_sequence(p["agent"], x, jnp.repeat(starts, A, 1))
                                ).reshape(T, B, A, 8)
    q, qt = q_of(params), q_of(target)
    mask, alive, action = np.asarray(mask), np.asarray(batch.alive), np.asarray(action)
    reward, done = np.asarray(batch.reward) * 2.0, np.asarray(done)

    qmix = jax.jit(mixers.qmix)

    def mixed(p, values, t, b):
        if algorithm == "vdn":
            return float(np.sum(values))
        return float(qmix(p["mixer"], jnp.asarray(values, jnp.float32), batch.world[t, b]))

    errors = []
    for t in range(T):
        for b in range(B):
            if t == T - 1 and not done[t, b]:
                continue  # no next observation to bootstrap from
            nxt = []
            for a in range(A):
                if t + 1 < T:
                    best = int(np.argmax(np.where(mask[t + 1, b, a], q[t + 1, b, a], -np.inf)))
                    nxt.append(qt[t + 1, b, a, best])
                else:
                    nxt.append(0.0)
            if algorithm == "iql":
                for a in range(A):
                    if alive[t, b, a]:
                        boot = (not done[t, b]) and t + 1 < T and alive[t + 1, b, a]
                        y = reward[t, b] + 0.9 * nxt[a] * boot
                        errors.append(q[t, b, a, action[t, b, a]] - y)
            else:
                taken = [q[t, b, a, action[t, b, a]] * alive[t, b, a] for a in range(A)]
                boot = 0.0
                if not done[t, b]:
                    boot = mixed(target, np.array(nxt) * alive[t + 1, b], t + 1, b)
                y = reward[t, b] + 0.9 * boot
                errors.append(mixed(params, np.array(taken), t, b) - y)
    assert float(loss) == pytest.approx(float(np.mean(np.square(errors))), rel=1e-4)


def test_a_mixing_q_learner_fits_what_its_class_mixes():
    """Which targets the loss takes is the class's: a VDN subclass whose `mix` doubles the sum
    doubles both Q_tot and, with no reward, its target, so the squared TD error is exactly 4
    times VDN's."""
    from ued.learners.qlearning import VDN, Trajectory

    class DoubleVDN(VDN):
        def mix(self, params, q, world):
            return 2.0 * super().mix(params, q, world)

    ppo = LearnerConfig(num_envs=4, num_steps=6, hidden_dim=8, matmul_dtype="float32")
    q = QLearningConfig(buffer_size=8, batch_size=4)
    vdn, double = VDN(ENV_CONFIG, ppo, q=q), DoubleVDN(ENV_CONFIG, ppo, q=q)
    keys = jax.random.split(jax.random.key(3), 4)
    params = vdn.init_params(keys[0])
    T, B, A = 6, 3, vdn.num_agents
    batch = Trajectory(
        obs=jax.random.normal(keys[1], (T, B, A, ENV_CONFIG.obs_size)), world=None,
        mask=jnp.ones((T, B, A, 8), bool), alive=jax.random.bernoulli(keys[2], 0.7, (T, B, A)),
        action=jax.random.randint(keys[3], (T, B, A), 0, 8), reward=jnp.zeros((T, B)),
        done=jnp.zeros((T, B), bool).at[2, 0].set(True))
    loss, _ = vdn._loss(params, params, batch)
    loss_double, _ = double._loss(params, params, batch)
    assert float(loss) > 0 and float(loss_double) == 4 * float(loss)


# --- configs ---------------------------------------------------------------------------------


@pytest.mark.parametrize("overrides, message", [
    ({"algorithm": "dqn"},
     "algorithm: must be one of mappo, ippo, mappo_rnd, iql, vdn, qmix or a learner class "
     "given as module:Class, got 'dqn'"),
    ({"qlearning.mixer_hidden_dim": 32}, "qlearning.mixer_hidden_dim: a setting of QMIX's "
                                         "mixing network; iql has none"),
    ({"learner.ent_coef": 0.1}, "learner.ent_coef: a PPO setting; iql does not use it"),
    ({"learner.num_minibatches": 2}, "learner.num_minibatches: a PPO setting"),
    ({"qlearning.batch_size": 16}, "qlearning.buffer_size: must hold at least one batch "
                                   "(batch_size 16 trajectories"),
    ({"qlearning.buffer_size": 2}, "qlearning.buffer_size: must hold at least one trajectory "
                                   "per env (learner.num_envs 4), got 2"),
    ({"qlearning.eps_finish": 1.5}, "qlearning.eps_finish: must be in [0, 1], got 1.5"),
    ({"learner.num_devices": 2}, "learner.num_devices: iql runs on one device"),
    ({"ued.method": "dr"}, "ued.method: the UED curricula train MAPPO or IPPO"),
])
def test_bad_q_configs_name_the_key(overrides, message):
    with pytest.raises(ConfigError) as err:
        tiny_q_config("iql", overrides=overrides)
    assert message in str(err.value)
    assert str(err.value).startswith("tiny q config: ")


@pytest.mark.parametrize("algorithm", ["mappo", "ippo"])
def test_q_settings_on_a_ppo_learner_are_an_error(algorithm):
    from test_learners_helpers import tiny_config

    with pytest.raises(ConfigError, match=(
            f"qlearning.mixer_embed_dim: a setting of the Q-learners \\(iql, vdn, qmix\\); "
            f"{algorithm} does not use it")):
        tiny_config(algorithm=algorithm, **{"qlearning.mixer_embed_dim": 32})
    with pytest.raises(ConfigError, match="qlearning.buffer_size: a setting of the Q-learners"):
        tiny_config(algorithm=algorithm, **{"qlearning.buffer_size": 100})


def test_every_q_config_file_loads_with_the_paper_settings():
    from pathlib import Path

    from ued.config import load_config

    files = sorted(Path("configs/marl").glob("*.yaml"))
    q_files = [f for f in files if f.name.split("_")[0] in Q_ALGORITHMS]
    assert {f.name.split("_")[0] for f in q_files} == set(Q_ALGORITHMS)
    for path in q_files:
        config = load_config(path)
        for name, value in Q_LEARNER_SETTINGS.items():
            assert getattr(config.learner, name) == value, (path, name)
        assert config.learner.num_envs == 128 and config.learner.num_steps == 512
        assert config.qlearning == QLearningConfig()  # the defaults are the paper's


def test_make_learner_refuses_q_settings_for_ppo():
    with pytest.raises(ValueError, match="mappo has no settings section of its own"):
        make_learner("mappo", ENV_CONFIG, settings=QLearningConfig())
    with pytest.raises(ValueError, match="algorithm: must be one of .*, got 'dqn'"):
        make_learner("dqn", ENV_CONFIG)


# --- a tiny run of each learner: resume, no recompilation, evaluation ------------------------


# IQL in the default run; VDN and QMIX (the same loop with a mixer) with `-m slow`.
@pytest.mark.parametrize("algorithm", [a if a == "iql" else pytest.param(a, marks=pytest.mark.slow)
                                       for a in Q_ALGORITHMS])
def test_tiny_run_resumes_bit_for_bit_and_plays_in_eval(algorithm, tmp_path, capsys):
    """Each learner's smoke test: a run of 4 updates equals one stopped after 3, resumed
    from the checkpoint of update 2; one compiled update throughout."""
    from tabx_ued.cli import main
    from ued.experiment import learner_for
    from ued.run_folder import CHECKPOINT_DIR, load_policy
    from ued.tensorboard import read_scalars
    from workers.train import train

    config = tiny_q_config(algorithm, str(tmp_path), {"run.checkpoint_every": 2})
    full = train(config, run_dir=tmp_path / "full", progress=False)
    part = train(config, run_dir=tmp_path / "part", progress=False, max_updates=3)
    shutil.rmtree(part / CHECKPOINT_DIR / "3")  # resume from update 2, as after a crash
    learner = learner_for(config)
    compiled = learner._update_jit._cache_size()
    train(run_dir=part, resume=True, progress=False)
    assert learner._update_jit._cache_size() == compiled == 1
    template = learner.init(jax.random.key(0))
    state_a, update = restore_both_and_compare(full, part, template)
    assert update == 4
    # The buffer holds 2 trajectories per env, and the learner learned.
    assert int(state_a.buffer.current_index) == 0 and bool(state_a.buffer.is_full)
    assert not np.array_equal(np.asarray(state_a.params["agent"]["out"]["w"]),
                              np.asarray(template.params["agent"]["out"]["w"]))
    scalars = read_scalars(part / "events")
    assert [s for s, _ in scalars["loss/td"]][-1] == 4 * config.learner.steps_per_update
    assert all(np.isfinite(v) for _, v in scalars["loss/td"])
    assert scalars["buffer/trajectories"][-1][1] == 8.0

    # A policy loads its parameters alone (not the buffer), the same ones.
    policy = load_policy(full)
    assert policy.update == 4
    for x, y in zip(jax.tree.leaves(policy.params), jax.tree.leaves(state_a.params),
                    strict=True):
        assert np.array_equal(np.asarray(x), np.asarray(y))
    # Other levels of the same EnvConfig run through the same compiled update.
    moved = jax.tree.map(jnp.asarray, repeat_level(duel_level(ally_x=-6.0), 4))
    state, metrics, _ = learner.update(state_a, moved, jax.random.key(9))
    assert learner._update_jit._cache_size() == 1 and np.isfinite(float(metrics["loss/td"]))

    if algorithm != "qmix":  # the evaluation path is the same for every Q-learner
        return
    code = main(["eval", str(full), "--episodes", "4", "--greedy"])
    out, err = capsys.readouterr()
    assert code == 0, err
    assert f"ally  {full} ({algorithm}, update 4)" in out and "win rate" in out


# --- learning (slow) -------------------------------------------------------------------------


@pytest.mark.slow
@pytest.mark.parametrize("algorithm", Q_ALGORITHMS)
def test_learns_two_archers_against_a_farmer(algorithm):
    """The duel of tests/ued/test_learners_learning.py: a random policy (the first updates, at
    epsilon 1) seldom wins; after 40 updates of 32 envs x 64 steps the greedy policy mostly
    does."""
    config, level = learning_duel()
    num_envs, num_steps, updates = 32, 64, 40
    levels = jax.tree.map(jnp.asarray, repeat_level(level, num_envs))
    ppo = LearnerConfig(num_envs=num_envs, num_steps=num_steps, hidden_dim=64, lr=3e-3,
                    anneal_lr=False, max_grad_norm=10.0, adam_eps=1e-8, update_epochs=16,
                    total_timesteps=num_envs * num_steps * updates)
    q = QLearningConfig(buffer_size=num_envs * 8, batch_size=32, learning_starts=0,
                        target_update_interval=4, eps_decay=0.3)
    learner = make_learner(algorithm, config, ppo, team="ally", opponent="random", settings=q)
    state = learner.init(jax.random.key(0))
    key = jax.random.key(1)
    win_rates = []
    for _ in range(updates):
        key, k = jax.random.split(key)
        state, metrics, _ = learner.update(state, levels, k)
        win_rates.append(float(metrics["episode/win_rate"]))
    greedy, _ = learner.score(state.params, levels, jax.random.key(5))
    random_policy = sum(win_rates[:3]) / 3  # epsilon near 1
    assert random_policy < 0.3, win_rates
    assert float(greedy["episode/win_rate"]) > 0.6, (float(greedy["episode/win_rate"]),
                                                     win_rates)

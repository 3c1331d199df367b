"""Auto-reset wrapper, JaxMARL adapter, and the rollout / bench command lines."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from tabx import constants as C
from tabx.env import TabxEnv, random_legal_actions
from tabx.marl import TabxMarlEnv
from tabx.params import EnvConfig, levels_equal, make_level
from tabx.wrappers import AutoResetEnv
from tabx_ued.cli import main

CONFIG = EnvConfig(max_allies=2, max_enemies=2, max_zones=1, max_steps=6)


def duel(ally_x: float = -3.0, health: float = 60.0):
    return make_level(CONFIG, [dict(unit="farmer", position=(ally_x, 0.0), health=health)],
                      [dict(unit="farmer", position=(3.0, 0.0), heading=np.pi)])


def test_autoreset_restarts_the_same_level_after_truncation():
    env = AutoResetEnv(TabxEnv(CONFIG))
    level = duel()
    obs0, state = env.reset(jax.random.key(0), level)
    step = jax.jit(env.step)
    moves = jnp.array([C.UP, C.IDLE, C.DOWN, C.IDLE], jnp.int32)
    dones = []
    for _ in range(CONFIG.max_steps):
        obs, state, reward, done, _ = step(jax.random.key(1), state, moves)
        dones.append(bool(done))
    assert dones == [False] * (CONFIG.max_steps - 1) + [True]
    # Truncation at max_steps: ties go to the enemy, and the state restarts at the beginning.
    assert reward.tolist() == pytest.approx([-1.0, 1.0])
    assert int(state.env_state.step) == 0
    np.testing.assert_allclose(obs, obs0)


def test_autoreset_switches_to_the_next_level_only_at_episode_end():
    env = AutoResetEnv(TabxEnv(CONFIG))
    first, second = duel(-3.0), duel(-5.0, health=30.0)
    _, state = env.reset(jax.random.key(0), first)
    step = jax.jit(env.step)
    idle = jnp.full((4,), C.IDLE, jnp.int32)
    for t in range(CONFIG.max_steps):
        _, state, _, done, _ = step(jax.random.key(t), state, idle, second)
        expected = second if t == CONFIG.max_steps - 1 else first
        assert levels_equal(state.level, expected)
    assert bool(done)
    assert float(state.env_state.health[0]) == 30.0


def test_marl_adapter_has_jaxmarl_semantics():
    env = TabxMarlEnv(CONFIG, level=duel(), opponent="random")
    assert env.agents == ["ally_0", "ally_1"] and env.num_agents == 2
    assert env.action_space("ally_0").n == C.NUM_ACTIONS
    assert env.observation_space("ally_1").shape == (CONFIG.obs_size,)
    obs, state = env.reset(jax.random.key(0))
    assert set(obs) == {"ally_0", "ally_1", "world_state"}
    assert obs["world_state"].shape == (CONFIG.state_size,)
    avail = env.get_avail_actions(state)
    assert avail["ally_0"].shape == (C.NUM_ACTIONS,)
    assert not bool(avail["ally_1"][C.UP])  # a padded slot may only idle
    actions = {a: jnp.int32(C.IDLE) for a in env.agents}
    obs, state, rewards, dones, infos = jax.jit(env.step)(jax.random.key(1), state, actions)
    assert set(dones) == {"ally_0", "ally_1", "__all__"}
    assert set(rewards) == {"ally_0", "ally_1"}
    assert "returned_win" in infos


def test_marl_adapter_runs_a_vmapped_jaxmarl_style_rollout_with_sampled_levels():
    def sampler(key):
        x = jax.random.uniform(key, (), minval=-20.0, maxval=-2.0)
        level = duel()
        return level.replace(units=level.units.replace(
            position=level.units.position.at[0, 0].set(x)))

    env = TabxMarlEnv(CONFIG, level_sampler=sampler, team="both")
    assert env.num_agents == 4
    num_envs = 8

    def rollout(key):
        obs, state = jax.vmap(env.reset)(jax.random.split(key, num_envs))

        def body(carry, key):
            obs, state = carry
            avail = jax.vmap(env.get_avail_actions)(state)
            keys = jax.random.split(key, env.num_agents + 1)
            actions = {a: random_legal_actions(keys[i], avail[a])
                       for i, a in enumerate(env.agents)}
            obs, state, rewards, dones, _ = jax.vmap(env.step)(
                jax.random.split(keys[-1], num_envs), state, actions)
            return (obs, state), (rewards["ally_0"], dones["__all__"])

        _, (rewards, dones) = jax.lax.scan(body, (obs, state), jax.random.split(key, 20))
        return rewards, dones

    rewards, dones = jax.jit(rollout)(jax.random.key(0))
    assert rewards.shape == (20, num_envs)
    assert bool(jnp.all(jnp.isfinite(rewards)))
    # max_steps = 6: every env finishes at least three episodes in 20 steps.
    assert bool(jnp.all(dones.sum(0) >= 3))


def test_marl_adapter_rejects_bad_arguments():
    with pytest.raises(ValueError, match="exactly one"):
        TabxMarlEnv(CONFIG)
    with pytest.raises(ValueError, match="unknown controller"):
        TabxMarlEnv(CONFIG, level=duel(), opponent="smart")
    with pytest.raises(ValueError, match="unknown learner team"):
        TabxMarlEnv(CONFIG, level=duel(), team="neutral")
    with pytest.raises(ValueError, match="opponent must be"):
        TabxMarlEnv(CONFIG, level=duel(), opponent="external")


def test_flipped_adapter_puts_the_learner_on_the_enemy_team():
    """team='enemy': the agents are the enemy slots, their rewards the enemy team's, and the
    ally team follows the heuristic at the named tier (written into the level)."""
    env = TabxMarlEnv(CONFIG, level=duel(-2.0), team="enemy", opponent="heuristic:expert")
    assert env.agents == ["enemy_0", "enemy_1"]
    np.testing.assert_allclose(env.level.heuristic.epsilon[C.ALLY], 0.01)
    obs, state = env.reset(jax.random.key(0))
    full = env.env.observe(state)
    np.testing.assert_array_equal(obs["enemy_0"], full[CONFIG.max_allies])
    step = jax.jit(env.step)
    total = 0.0
    for t in range(CONFIG.max_steps - 1):  # before the terminal reward
        actions = {a: jnp.int32(C.IDLE) for a in env.agents}
        obs, state, rewards, dones, infos = step(jax.random.key(t), state, actions)
        total += float(rewards["enemy_0"])
    # The idle enemy gets hit by the scripted ally: its team reward is negative.
    assert total < 0.0


def test_rollout_cli_prints_the_outcome(capsys):
    assert main(["rollout", "ambush", "--steps", "40", "--seed", "2"]) == 0
    out = capsys.readouterr().out
    assert "scenario ambush: 2 allies v 1 enemies" in out
    assert "outcome: still running after 40 steps" in out


def test_rollout_cli_reports_unknown_scenarios_and_bad_steps(capsys):
    assert main(["rollout", "nosuchscenario"]) == 2
    assert "unknown scenario" in capsys.readouterr().err
    assert main(["rollout", "ambush", "--steps", "0"]) == 2
    assert "--steps must be >= 1" in capsys.readouterr().err


def test_bench_env_cli_runs_a_tiny_configuration(capsys, tmp_path):
    out_file = tmp_path / "bench.jsonl"
    assert main(["bench", "env", "--team-sizes", "2", "--zones", "0", "--num-envs", "2",
                 "--steps", "4", "--repeats", "1", "--json", str(out_file)]) == 0
    assert "2v2" in capsys.readouterr().out
    assert '"steps_per_s"' in out_file.read_text()


def test_bench_env_cli_rejects_bad_lists():
    with pytest.raises(SystemExit):
        main(["bench", "env", "--num-envs", "a,b"])

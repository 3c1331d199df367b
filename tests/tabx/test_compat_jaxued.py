"""`tabx.compat.jaxued`: our levels behind jaxued's `UnderspecifiedEnv` interface, driven by a
DR / PLR loop with the structure of jaxued's examples (written here: a replay decision, new
levels or replayed ones through `lax.cond`, rollouts under `AutoReplayWrapper`, scores back
into a buffer), all in one compiled program that new levels never recompile."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import struct

from tabx.compat.jaxued import (
    AutoReplayState,
    AutoReplayWrapper,
    MultiAgentDiscrete,
    TabxUEDParams,
    TabxUnderspecifiedEnv,
    UnderspecifiedEnv,
)
from tabx.compile_counter import CompileCounter
from tabx.params import EnvConfig, stack_levels
from tabx.random_levels import random_levels
from tabx.scenarios import ScenarioError, load_levels, load_named

CONFIG = EnvConfig(max_allies=4, max_enemies=4, max_zones=2, max_steps=24)
POOL_SIZE, NUM_ENVS, NUM_STEPS, CAPACITY = 12, 4, 24, 8


@pytest.fixture(scope="module")
def pool():
    """Random levels (1-4 units a side, up to 2 zones); every other one randomises its start."""
    levels = stack_levels(random_levels(POOL_SIZE, seed=3, config=CONFIG, min_units=1,
                                        max_units=4, max_zones=2))
    noise = jnp.where(jnp.arange(POOL_SIZE) % 2 == 1, 3.0, 0.0).astype(jnp.float32)
    return levels.replace(start_noise=noise)


@pytest.fixture(scope="module")
def env():
    return AutoReplayWrapper(TabxUnderspecifiedEnv(CONFIG, opponent="heuristic:novice"))


def take(levels, idx):
    return jax.tree.map(lambda x: x[idx], levels)


def test_the_interface_and_auto_replay(env, pool):
    params = env.default_params
    assert params == TabxUEDParams(max_steps_in_episode=CONFIG.max_steps,
                                   num_agents=CONFIG.max_allies)
    space = env.action_space(params)
    assert isinstance(space, MultiAgentDiscrete) and space.n == 8
    assert space.shape == (CONFIG.max_allies,) == (env.num_agents,)
    assert space.sample(jax.random.key(0)).shape == space.shape
    reset = jax.jit(env.reset_to_level)
    level = take(pool, 1)  # randomised start
    obs, state = reset(jax.random.key(0), level, params)
    assert obs.shape == (CONFIG.max_allies, CONFIG.obs_size)
    _, other = reset(jax.random.key(1), level, params)
    active = np.asarray(level.units.active)
    start = np.asarray(state.env_state.env_state.position)
    assert not np.array_equal(start[active], np.asarray(other.env_state.env_state.position)[active])
    fixed = take(pool, 0)
    a, b = (reset(jax.random.key(s), fixed, params)[1] for s in (0, 1))
    assert np.array_equal(a.env_state.env_state.position, b.env_state.env_state.position)

    step = jax.jit(env.step)
    key, ends = jax.random.key(2), 0
    for _ in range(CONFIG.max_steps + 1):  # every episode ends by the step limit
        key, k = jax.random.split(key)
        idle = jnp.full((env.num_agents,), 7, jnp.int32)
        obs, state, reward, done, info = step(k, state, idle, params)
        assert reward.shape == () and info["legal_actions"].shape == (env.num_agents, 8)
        if bool(done):
            ends += 1
            # Replayed: the same level, from step 0 again.
            assert int(state.env_state.env_state.step) == 0
            assert jax.tree.all(jax.tree.map(jnp.array_equal, state.level, level))
    assert ends >= 1


@struct.dataclass
class Buffer:
    """A minimal PLR level buffer, in jax arrays (the shape of jaxued's LevelSampler)."""

    levels: object
    scores: jax.Array
    filled: jax.Array
    replays: jax.Array


def make_loop(env, pool):
    params = env.default_params

    def rollout_scores(key, levels):
        """Mean learner return per level under a random legal policy (a stand-in for the
        learner: harder levels score higher, as regret estimates do)."""
        k_reset, k_run = jax.random.split(key)
        _, state = jax.vmap(env.reset_to_level, (0, 0, None))(
            jax.random.split(k_reset, NUM_ENVS), levels, params)

        def body(state, key):
            k_act, k_step = jax.random.split(key)
            legal = jax.vmap(env.legal_actions)(state.env_state)
            action = jax.random.categorical(k_act, jnp.where(legal, 0.0, -1e9))
            _, state, reward, done, _ = jax.vmap(env.step, (0, 0, 0, None))(
                jax.random.split(k_step, NUM_ENVS), state, action, params)
            return state, (reward, done)

        _, (reward, done) = jax.lax.scan(body, state, jax.random.split(k_run, NUM_STEPS))
        episodes = jnp.maximum(done.sum(0), 1)
        return -reward.sum(0) / episodes

    def on_new(key, buffer):
        idx = jax.random.randint(key, (NUM_ENVS,), 0, POOL_SIZE)  # DR: fresh levels
        return take(pool, idx), jnp.full((NUM_ENVS,), -1)

    def on_replay(key, buffer):
        weights = jnp.where(buffer.filled, jax.nn.softmax(buffer.scores), 0.0)
        idx = jax.random.choice(key, CAPACITY, (NUM_ENVS,), p=weights / weights.sum())
        return take(buffer.levels, idx), idx

    def train_step(buffer, key):
        k_decide, k_levels, k_roll = jax.random.split(key, 3)
        replay = (jax.random.uniform(k_decide) < 0.5) & (buffer.filled.sum() >= NUM_ENVS)
        levels, ids = jax.lax.cond(replay, on_replay, on_new, k_levels, buffer)
        scores = rollout_scores(k_roll, levels)

        def rescore(buffer):
            return buffer.replace(scores=buffer.scores.at[ids].set(scores),
                                  replays=buffer.replays + 1)

        def insert(buffer):  # new levels take the lowest-scored (or empty) slots
            order = jnp.argsort(jnp.where(buffer.filled, buffer.scores, -jnp.inf))[:NUM_ENVS]
            stored = jax.tree.map(lambda b, n: b.at[order].set(n), buffer.levels, levels)
            return buffer.replace(levels=stored, scores=buffer.scores.at[order].set(scores),
                                  filled=buffer.filled.at[order].set(True))

        return jax.lax.cond(replay, rescore, insert, buffer), replay

    def run(key, iterations):
        buffer = Buffer(levels=take(pool, jnp.zeros(CAPACITY, jnp.int32)),
                        scores=jnp.zeros(CAPACITY), filled=jnp.zeros(CAPACITY, bool),
                        replays=jnp.zeros((), jnp.int32))
        return jax.lax.scan(train_step, buffer, jax.random.split(key, iterations))

    return jax.jit(run, static_argnums=1)


def test_a_jaxued_style_dr_plr_loop_runs_on_our_levels_without_recompiling(env, pool):
    run = make_loop(env, pool)
    buffer, replayed = run(jax.random.key(0), 8)
    assert bool(buffer.filled.all()) and np.isfinite(np.asarray(buffer.scores)).all()
    assert 0 < int(replayed.sum()) == int(buffer.replays) < 8
    with CompileCounter() as counter:  # other keys: other levels, the same program
        other, _ = run(jax.random.key(1), 8)
    assert counter.compiles == 0, counter.traced
    assert not np.array_equal(np.asarray(other.levels.units.position),
                              np.asarray(buffer.levels.units.position))


class JaxuedStyleAutoReplay(UnderspecifiedEnv):
    """A stand-in with the forwarding of jaxued's own `AutoReplayWrapper`: `default_params`
    and `action_space` reach the inner env, no other attribute does (no `__getattr__`)."""

    def __init__(self, env):
        self._env = env

    @property
    def default_params(self):
        return self._env.default_params

    def reset_env_to_level(self, rng, level, params):
        obs, env_state = self._env.reset_to_level(rng, level, params)
        return obs, AutoReplayState(env_state=env_state, level=level)

    def step_env(self, rng, state, action, params):
        obs, env_state, reward, done, info = self._env.step(rng, state.env_state, action,
                                                            params)
        return obs, state.replace(env_state=env_state), reward, done, info

    def action_space(self, params):
        return self._env.action_space(params)


def test_num_agents_and_the_step_limit_reach_a_loop_through_jaxueds_wrapper(pool):
    env = JaxuedStyleAutoReplay(TabxUnderspecifiedEnv(CONFIG, team="enemy"))
    assert not hasattr(env, "num_agents")
    params = env.default_params
    assert params.num_agents == env.action_space(params).num_agents == CONFIG.max_enemies
    # Static: sizes a scan inside jit, as jaxued's evaluation does.
    lengths = jax.jit(lambda p: jnp.arange(p.max_steps_in_episode))(params)
    assert lengths.shape == (CONFIG.max_steps,)


def test_a_misshaped_action_or_foreign_params_fail_when_traced(pool):
    inner = TabxUnderspecifiedEnv(CONFIG)
    params = inner.default_params
    _, state = jax.eval_shape(inner.reset_to_level, jax.random.key(0), take(pool, 0), params)
    for bad in (jnp.int32(7), jnp.full((2, CONFIG.max_allies), 7, jnp.int32)):
        with pytest.raises(ValueError, match="one per learner agent"):
            jax.eval_shape(inner.step, jax.random.key(1), state, bad, params)
    other = params.replace(max_steps_in_episode=CONFIG.max_steps + 1)
    with pytest.raises(ValueError, match="default_params"):
        jax.eval_shape(inner.reset_to_level, jax.random.key(0), take(pool, 0), other)


def test_load_levels_batches_named_scenarios_in_one_config():
    config, levels = load_levels(["crossfire", "2F1M2Avs2S1K", "ambush"], max_steps=32)
    assert levels.reward_mode.shape == (3,) and config.max_steps == 32
    alone = load_named("crossfire")
    assert config.max_allies >= len(alone.allies) and config.max_enemies >= len(alone.enemies)
    first = jax.tree.map(lambda x: x[0], levels)
    assert jax.tree.all(jax.tree.map(jnp.array_equal, first, alone.to_level(config)))
    with pytest.raises(ScenarioError):
        load_levels("crossfire")

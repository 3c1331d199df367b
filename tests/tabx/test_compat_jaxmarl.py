"""`tabx.compat.jaxmarl`: our battle as a JaxMARL `MultiAgentEnv`, driven by JaxMARL's own
wrappers (`SMAXLogWrapper`, `CTRolloutManager`) for a few hundred steps, by a world-state
wrapper shaped like the one of JaxMARL's MAPPO SMAX baseline, and by one update of IPPO and
MAPPO loops with the structure of JaxMARL's SMAX baselines (written here). Runs where jaxmarl
is installed (the `peers` extra); `pytest -m peers` runs all of them, the slow loops too."""

from __future__ import annotations

import copy
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest
import yaml

jaxmarl = pytest.importorskip("jaxmarl")
pytestmark = pytest.mark.peers

from flax import linen as nn  # noqa: E402
from jaxmarl.environments.multi_agent_env import MultiAgentEnv  # noqa: E402
from jaxmarl.environments.spaces import Box, Discrete  # noqa: E402
from jaxmarl.wrappers.baselines import (  # noqa: E402
    CTRolloutManager,
    JaxMARLWrapper,
    SMAXLogWrapper,
)

from tabx.compat.jaxmarl import TabxJaxMARLEnv, make_env  # noqa: E402
from tabx.controllers import Controller  # noqa: E402
from tabx.params import level_config  # noqa: E402
from tabx.scenarios import load_named  # noqa: E402

NUM_ENVS = 4


@pytest.fixture(scope="module")
def env():
    level = load_named("crossfire").to_level()
    config = level_config(level, max_steps=64)  # short episodes: several end in a test
    return TabxJaxMARLEnv(config, level, opponent="heuristic:novice")


def random_legal_actions(key, avail):
    """A uniformly random legal action per agent: avail {agent: (envs, A)} -> {agent: (envs,)}."""
    keys = jax.random.split(key, len(avail))
    return {a: jax.random.categorical(k, jnp.where(m, 0.0, -1e9)).astype(jnp.int32)
            for k, (a, m) in zip(keys, sorted(avail.items()), strict=True)}


def test_it_is_a_jaxmarl_env_with_smax_attributes(env):
    assert isinstance(env, MultiAgentEnv)
    assert all(isinstance(env.observation_space(a), Box) for a in env.agents)
    assert all(isinstance(env.action_space(a), Discrete) for a in env.agents)
    assert env.agents == ["ally_0", "ally_1", "ally_2"] and env.num_agents == env.num_allies
    assert (env.num_allies, env.num_enemies) == (3, 3) and "smax" in env.name.lower()
    obs, state = jax.jit(env.reset)(jax.random.key(0))
    assert obs["world_state"].shape == (env.state_size,)
    assert all(obs[a].shape == env.observation_space(a).shape for a in env.agents)
    assert env.get_world_state(state).shape == (env.state_size,)
    assert set(env.get_avail_actions(state)) == set(env.agents)


def test_smax_log_wrapper_runs_hundreds_of_steps_with_per_agent_infos(env):
    wrapped = SMAXLogWrapper(env)  # replace_info=False: our infos are per agent already
    obs, states = jax.vmap(wrapped.reset)(jax.random.split(jax.random.key(0), NUM_ENVS))

    def body(carry, key):
        states = carry
        k_act, k_step = jax.random.split(key)
        avail = jax.vmap(env.get_avail_actions)(states.env_state)
        actions = random_legal_actions(k_act, avail)
        obs, states, reward, done, info = jax.vmap(wrapped.step)(
            jax.random.split(k_step, NUM_ENVS), states, actions)
        return states, (done["__all__"], info)

    _, (done, info) = jax.jit(lambda s, k: jax.lax.scan(body, s, jax.random.split(k, 200)))(
        states, jax.random.key(1))
    # The baselines reshape every info leaf to (steps, envs, agents).
    assert all(v.shape == (200, NUM_ENVS, env.num_agents) for v in info.values())
    ended = np.asarray(info["returned_episode"][..., 0])
    assert np.array_equal(ended, np.asarray(done)) and ended.sum() >= NUM_ENVS
    lengths = np.asarray(info["returned_episode_lengths"][..., 0])[ended]
    assert np.all((lengths >= 1) & (lengths <= 64))
    # The wrapper's win count (team reward >= 1 on the last step) never exceeds ours.
    won_wrapper = np.asarray(info["returned_won_episode"][..., 0])[ended]
    won_ours = np.asarray(info["won"][..., 0])[ended]
    assert np.all(won_wrapper <= won_ours)


def test_ct_rollout_manager_uses_world_state_and_legal_actions(env):
    manager = CTRolloutManager(env, batch_size=NUM_ENVS)
    assert manager.obs_size == env.obs_size + env.num_agents  # padded obs + one-hot agent id
    obs, states = manager.batch_reset(jax.random.key(0))
    assert obs["__all__"].shape == (NUM_ENVS, env.state_size)
    step = jax.jit(manager.batch_step)
    key = jax.random.key(1)
    ends = 0
    for _ in range(100):
        key, k_act, k_step = jax.random.split(key, 3)
        avail = manager.get_valid_actions(states)
        actions = random_legal_actions(k_act, avail)
        obs, states, reward, done, _ = step(k_step, states, actions)
        ends += int(np.asarray(done["__all__"]).sum())
        assert np.array_equal(reward["__all__"], reward[env.agents[0]])
    world = jax.vmap(env.get_world_state)(states)
    assert np.array_equal(obs["__all__"], world) and ends >= 1
    assert obs[env.agents[0]].shape == (NUM_ENVS, manager.obs_size)


class WorldStateWrapper(JaxMARLWrapper):
    """The shape of the world-state wrapper of JaxMARL's MAPPO SMAX baseline: the global state
    repeated per agent, with the agent's one-hot id."""

    def reset(self, key):
        obs, state = self._env.reset(key)
        obs["world_state"] = self.world_state(obs)
        return obs, state

    def step(self, key, state, action):
        obs, state, reward, done, info = self._env.step(key, state, action)
        obs["world_state"] = self.world_state(obs)
        return obs, state, reward, done, info

    def world_state(self, obs):
        repeated = obs["world_state"][None].repeat(self._env.num_allies, axis=0)
        return jnp.concatenate([repeated, jnp.eye(self._env.num_allies)], axis=1)

    def world_state_size(self):
        return self._env.state_size + self._env.num_allies


# --- one update of IPPO and MAPPO, structured like JaxMARL's SMAX baselines -----------------

def batchify(x: dict, agents: list[str], num_actors: int) -> jax.Array:
    return jnp.stack([x[a] for a in agents]).reshape((num_actors, -1))


def unbatchify(x: jax.Array, agents: list[str], num_envs: int) -> dict:
    x = x.reshape((len(agents), num_envs, -1))
    return {a: x[i] for i, a in enumerate(agents)}


class Head(nn.Module):
    out: int

    @nn.compact
    def __call__(self, x):
        x = nn.tanh(nn.Dense(64)(x))
        return nn.Dense(self.out)(nn.tanh(nn.Dense(64)(x)))


class Transition(NamedTuple):
    done: jax.Array
    action: jax.Array
    value: jax.Array
    reward: jax.Array
    log_prob: jax.Array
    obs: jax.Array
    critic_in: jax.Array
    avail: jax.Array


def one_update(base_env: TabxJaxMARLEnv, centralised: bool, num_steps: int = 16):
    """Collect `num_steps` x NUM_ENVS steps and take one PPO step: (loss, whether every
    parameter moved, the log wrapper's infos)."""
    env = SMAXLogWrapper(WorldStateWrapper(base_env) if centralised else base_env)
    agents, num_actors = base_env.agents, base_env.num_agents * NUM_ENVS
    n_actions = base_env.action_space(agents[0]).n
    obs_dim = base_env.observation_space(agents[0]).shape[0]
    critic_dim = env.world_state_size() if centralised else obs_dim
    actor, critic = Head(n_actions), Head(1)
    key = jax.random.key(0)
    k_a, k_c, k_reset, k_run = jax.random.split(key, 4)
    params = {"actor": actor.init(k_a, jnp.zeros(obs_dim)),
              "critic": critic.init(k_c, jnp.zeros(critic_dim))}
    tx = optax.chain(optax.clip_by_global_norm(0.5), optax.adam(3e-4))
    opt_state = tx.init(params)
    obs, states = jax.vmap(env.reset)(jax.random.split(k_reset, NUM_ENVS))

    def policy(params, obs_batch, avail):
        logits = actor.apply(params["actor"], obs_batch)
        return jnp.where(avail, logits, -1e10)

    def critic_input(obs):
        if centralised:  # (envs, agents, ws) -> (actors, ws), agent-major like batchify
            return obs["world_state"].swapaxes(0, 1).reshape((num_actors, -1))
        return batchify(obs, agents, num_actors)

    def env_step(carry, key):
        states, obs = carry
        k_act, k_step = jax.random.split(key)
        avail = jax.vmap(base_env.get_avail_actions)(env_state_of(states))
        avail = batchify(avail, agents, num_actors).astype(bool)
        obs_batch = batchify(obs, agents, num_actors)
        logits = policy(params, obs_batch, avail)
        action = jax.random.categorical(k_act, logits)
        log_prob = jnp.take_along_axis(jax.nn.log_softmax(logits), action[:, None], 1)[:, 0]
        value = critic.apply(params["critic"], critic_input(obs))[:, 0]
        env_act = {a: v.squeeze(-1) for a, v in unbatchify(action, agents, NUM_ENVS).items()}
        new_obs, states, reward, done, info = jax.vmap(env.step)(
            jax.random.split(k_step, NUM_ENVS), states, env_act)
        info = jax.tree.map(lambda x: x.reshape((num_actors,)), info)
        transition = Transition(batchify(done, agents, num_actors).squeeze(-1), action, value,
                                batchify(reward, agents, num_actors).squeeze(-1), log_prob,
                                obs_batch, critic_input(obs), avail)
        return (states, new_obs), (transition, info)

    def env_state_of(states):  # through the log (and world-state) wrappers to ours
        return states.env_state

    (states, last_obs), (traj, info) = jax.lax.scan(env_step, (states, obs),
                                                    jax.random.split(k_run, num_steps))
    last_value = critic.apply(params["critic"], critic_input(last_obs))[:, 0]

    def gae(carry, t):
        advantage, next_value = carry
        delta = t.reward + 0.99 * next_value * (1 - t.done) - t.value
        advantage = delta + 0.99 * 0.95 * (1 - t.done) * advantage
        return (advantage, t.value), advantage

    _, advantages = jax.lax.scan(gae, (jnp.zeros_like(last_value), last_value), traj,
                                 reverse=True)
    targets = advantages + traj.value

    def loss_fn(params):
        logits = policy(params, traj.obs, traj.avail)
        log_prob = jnp.take_along_axis(jax.nn.log_softmax(logits), traj.action[..., None],
                                       -1)[..., 0]
        ratio = jnp.exp(log_prob - traj.log_prob)
        norm = (advantages - advantages.mean()) / (advantages.std() + 1e-8)
        actor_loss = -jnp.minimum(ratio * norm, jnp.clip(ratio, 0.8, 1.2) * norm).mean()
        value = critic.apply(params["critic"], traj.critic_in)[..., 0]
        return actor_loss + 0.5 * jnp.square(value - targets).mean()

    loss, grads = jax.value_and_grad(loss_fn)(params)
    updates, _ = tx.update(grads, opt_state, params)
    new_params = optax.apply_updates(params, updates)
    moved = jax.tree.leaves(jax.tree.map(lambda a, b: jnp.any(a != b), params, new_params))
    return loss, jnp.all(jnp.stack(moved)), info


@pytest.mark.slow
@pytest.mark.parametrize("centralised", [False, True], ids=["ippo", "mappo"])
def test_one_update_of_a_jaxmarl_style_ppo_loop(env, centralised):
    loss, moved, info = jax.jit(lambda: one_update(env, centralised))()
    assert np.isfinite(float(loss)) and bool(moved)
    assert info["returned_episode_returns"].shape == (16, env.num_agents * NUM_ENVS)


def apply_overrides(config: dict, overrides: list[str]) -> dict:
    """Hydra's command-line overrides on a baseline config dict, as far as the env line needs
    them: `KEY=VALUE` and dotted `ENV_KWARGS.key=VALUE`, values read as YAML primitives."""
    out = copy.deepcopy(config)
    for item in overrides:
        dotted, value = item.split("=", 1)
        *parents, leaf = dotted.lstrip("+").split(".")
        node = out
        for key in parents:
            node = node.setdefault(key, {})
        node[leaf] = value if ":" in value else yaml.safe_load(value)
    return out


# The env part of JaxMARL's baselines/IPPO/config/ippo_rnn_smax.yaml, as it ships.
BASELINE_CONFIG = {"ENV_NAME": "HeuristicEnemySMAX", "MAP_NAME": "2s3z",
                   "ENV_KWARGS": {"see_enemy_actions": True, "walls_cause_death": True,
                                  "attack_mode": "closest"}}


def test_make_env_takes_map_name_and_env_kwargs_from_hydra_style_overrides():
    config = apply_overrides(BASELINE_CONFIG, [
        "ENV_NAME=TABX-SMAX", "MAP_NAME=crossfire", "+ENV_KWARGS.opponent=heuristic:expert",
        "+ENV_KWARGS.max_steps=64", "+ENV_KWARGS.start_noise=2.0"])
    with pytest.warns(UserWarning, match="attack_mode"):  # SMAX's keys: ignored, said so
        env = make_env(config["MAP_NAME"], **config["ENV_KWARGS"])  # the baselines' env line
    assert isinstance(env, TabxJaxMARLEnv) and env.map_name == "crossfire"
    assert env.config.max_steps == 64 and (env.num_allies, env.num_enemies) == (3, 3)
    assert float(env.marl.level.start_noise) == 2.0
    assert env.marl.controllers[1] == Controller.parse("heuristic:expert")
    with pytest.raises(TypeError, match="unknown keyword arguments.*max_step"):
        make_env("crossfire", max_step=64)

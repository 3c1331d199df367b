"""Recurrent Q-learning for TABX teams: IQL, VDN and QMIX, one core (`QLearner`, IQL's
per-agent targets) and its mixing subclasses (`MixingQLearner`: VDN's sum, QMIX's network).

The learners share the PPO learners' interface (ued.learners.ppo: `init`, the jitted
`update(train_state, levels, key)`, `policy_step` for evaluation) and their rollout: each
update resets every env into its level and plays `num_steps` steps (a finished episode restarts
in the same level), here acting epsilon-greedily. Then, in the same jitted program:

1. the rollout goes into a replay buffer of trajectories (flashbax's trajectory buffer, on the
   device): one item per env, its whole `num_steps` steps, `buffer_size // num_envs` items kept
   per env, the oldest overwritten;
2. once the buffer holds a batch and `learning_starts` env steps have been played,
   `update_epochs` gradient steps each sample `batch_size` trajectories uniformly, unroll the
   online and the target Q-networks over them from zero hidden states (reset at every episode
   start inside a trajectory), and minimise the squared TD error of double-Q targets;
3. every `target_update_interval` updates the target network moves to the online one
   (a copy with tau 1).

The Q-network (the reference's `RNNQNetwork`; docs/differences.md) is shared by the agents of
the team, with a one-hot agent id appended to the observation as for PPO:

    x -> Dense(H) -> LayerNorm -> ReLU -> GRU(H) -> Dense(8)     (H = learner.hidden_dim)

Targets, with r the team reward times `reward_scale` and gamma the discount:

- IQL (no mixer): each agent learns Q_i(o_i, a_i) of the team reward;
  y_i = r + gamma Q_i^target(o_i', argmax_{a valid} Q_i(o_i', a)), without the bootstrap when
  the episode ended or the agent's unit died (its last step). Only the steps where the agent's
  unit is alive enter the loss.
- VDN / QMIX: Q_tot = mixer(Q_1(a_1), ..., Q_A(a_A); s) with s the world state (QMIX);
  y = r + gamma Q_tot^target(argmax_a Q_i(o_i', a) per agent; s'), without the bootstrap at the
  end of an episode. Agents whose unit is dead (or padded) enter the mixer with Q = 0.

Invalid actions are masked out of every argmax and out of exploration. The last step of a
sampled trajectory has no next observation in it: it enters the loss only where it ended an
episode (its target needs no bootstrap), so episodes that run to the rollout's end (the time
limit, with num_steps = max_steps) still teach their final reward.

Evaluation (`tabx eval`, the evaluation suites) plays the greedy policy: `policy_step` returns
the Q-values scaled by `GREEDY_LOGIT_SCALE` as logits, so that sampling them picks the
greedy action (ties split evenly), as taking their argmax does.
"""

from __future__ import annotations

from typing import Any

import flashbax as fbx
import jax
import jax.numpy as jnp
import optax
from flax import struct

from tabx import constants as C
from tabx.controllers import Controller
from tabx.params import EnvConfig, EnvParams
from ued.config import LearnerConfig, QLearningConfig
from ued.learners import mixers
from ued.learners import networks as nw
from ued.learners.ppo import (
    MASKED_LOGIT,
    PPOLearner,
    RolloutStats,
    episode_metrics,
    gae,
    local_devices,
    team_mean,
)

# Scale of the Q-values returned as logits by `policy_step`: Q-values a thousandth apart
# differ by 1e4 in logit, so a categorical sample is the argmax.
GREEDY_LOGIT_SCALE = 1e7


@struct.dataclass
class QTrainState:
    """What a Q-learning update changes. `params` is what a policy needs (the agent network,
    and QMIX's mixer), `update` the number of updates done, as in the PPO `TrainState`."""

    params: Any
    target_params: Any
    opt_state: Any
    buffer: Any  # flashbax TrajectoryBufferState of `Trajectory` items
    update: jax.Array  # int32 scalar


@struct.dataclass
class Trajectory:
    """One env's rollout as stored in the replay buffer (leading axis: time)."""

    obs: jax.Array  # (T, A, obs_size) without the agent id
    world: jax.Array | None  # (T, state_size) for QMIX, None otherwise (nothing stored)
    mask: jax.Array  # (T, A, 8) legal actions
    alive: jax.Array  # (T, A)
    action: jax.Array  # (T, A) int32
    reward: jax.Array  # (T,) team reward
    done: jax.Array  # (T,) the step ended the episode


# --- the Q-network ---------------------------------------------------------------------------


def qnet_init(key: jax.Array, n_in: int, hidden: int) -> dict:
    """Dense(H, orthogonal 1) -> LayerNorm -> ReLU -> GRU(H) -> Dense(8, orthogonal 1)."""
    k_embed, k_gru, k_out = jax.random.split(key, 3)
    return {"embed": nw.dense_init(k_embed, n_in, hidden, 1.0),
            "ln_embed": nw.layer_norm_init(hidden),
            "gru": nw.gru_init(k_gru, hidden, hidden),
            "out": nw.dense_init(k_out, hidden, C.NUM_ACTIONS, 1.0)}


def qnet_step(p: dict, x: jax.Array, h: jax.Array, dtype: jnp.dtype = jnp.float32
              ) -> tuple[jax.Array, jax.Array]:
    """One step: (new hidden (..., H), Q-values (..., 8))."""
    h = nw.gru_cell(p["gru"], nw.encode(p, x, dtype), h, dtype)
    return h, nw.dense(p["out"], h, dtype)


def qnet_sequence(p: dict, x: jax.Array, starts: jax.Array, dtype: jnp.dtype = jnp.float32
                  ) -> jax.Array:
    """Q-values (T, B, 8) over inputs (T, B, n_in) from zero hidden states, reset to zeros
    where `starts` (T, B). The embedding and the GRU's input projection do not depend on the
    hidden state: they run over all steps at once, and only the recurrence is scanned."""
    gi = nw.encode(p, x, dtype)
    h0 = jnp.zeros((x.shape[1], p["gru"]["wh"].shape[0]), jnp.float32)

    def body(h, inputs):
        gi_t, start_t = inputs
        h = nw.gru_cell(p["gru"], gi_t, jnp.where(start_t[:, None], 0.0, h), dtype)
        return h, h

    _, hs = jax.lax.scan(body, h0, (gi, starts))
    return nw.dense(p["out"], hs, dtype)


def _shift_in_zero(x: jax.Array) -> jax.Array:
    """x (T-1, ...) of steps 1..T-1, as (T, ...) aligned with steps 0..T-1 (zeros last)."""
    return jnp.concatenate([x, jnp.zeros((1, *x.shape[1:]), x.dtype)], axis=0)


def masked_argmax(q: jax.Array, mask: jax.Array) -> jax.Array:
    """The best legal action (int32) over the last axis."""
    return jnp.argmax(jnp.where(mask, q, MASKED_LOGIT), -1).astype(jnp.int32)


def pick(q: jax.Array, action: jax.Array) -> jax.Array:
    """q[..., action] over the last axis."""
    return jnp.take_along_axis(q, action[..., None], -1)[..., 0]


def epsilon_schedule(q: QLearningConfig, num_updates: int) -> optax.Schedule:
    """Update count -> epsilon: linear from eps_start to eps_finish over the first
    `eps_decay` of the run's updates, then eps_finish."""
    return optax.linear_schedule(q.eps_start, q.eps_finish,
                                 max(1, int(q.eps_decay * num_updates)))


# --- the learner -----------------------------------------------------------------------------


class QLearner(PPOLearner):
    """Static description of a recurrent Q-learner for one EnvConfig (see the module doc):
    each agent learns its own Q-values of the team reward (IQL); `MixingQLearner` mixes them
    into the team's. Runs on one device: the replay buffer lives there, and the whole update
    (rollout, insert, sampling, gradient steps, target update) is one jitted program; other
    levels of the same EnvConfig never recompile it."""

    name = "qlearning"
    family = "Q-learners"
    settings_section = "qlearning"
    settings_type = QLearningConfig
    ppo_settings = False
    value_head = False
    seeds = False
    curricula = False
    devices = False

    @classmethod
    def validate_settings(cls, settings: QLearningConfig, learner: LearnerConfig) -> None:
        settings.validate(learner.num_envs)

    def __init__(self, env_config: EnvConfig, ppo: LearnerConfig | None = None,
                 team: str | int = "ally", opponent: str | Controller = "heuristic:medium",
                 q: QLearningConfig | None = None):
        self.q = q if q is not None else QLearningConfig()
        ppo = ppo if ppo is not None else LearnerConfig()
        self.q.validate(ppo.num_envs)  # the buffer's sizes (a ConfigError naming the field)
        self.epsilon = epsilon_schedule(self.q, ppo.num_updates)
        self.per_env = self.q.buffer_size // ppo.num_envs
        self.buffer = fbx.make_trajectory_buffer(
            max_length_time_axis=max(1, self.per_env),
            min_length_time_axis=max(1, -(-self.q.batch_size // ppo.num_envs)),
            sample_batch_size=self.q.batch_size, add_batch_size=ppo.num_envs,
            sample_sequence_length=1, period=1)
        super().__init__(env_config, ppo, team, opponent)

    # --- networks ----------------------------------------------------------------------------

    def init_params(self, key: jax.Array) -> dict[str, Any]:
        k_agent, k_mixer = jax.random.split(key)
        return {"agent": qnet_init(k_agent, self.obs_dim, self.ppo.hidden_dim),
                **self.mixer_params(k_mixer)}

    def mixer_params(self, key: jax.Array) -> dict[str, Any]:
        """The parameters of a mixing network, beside the agent network's (none here)."""
        return {}

    def initial_hidden(self, num_envs: int) -> jax.Array:
        return jnp.zeros((num_envs, self.num_agents, self.ppo.hidden_dim), jnp.float32)

    def q_values(self, params: Any, x: jax.Array, hidden: jax.Array
                 ) -> tuple[jax.Array, jax.Array]:
        """One step of the agent network: (new hidden, Q-values (E, A, 8))."""
        return qnet_step(params["agent"], x, hidden, self.matmul_dtype)

    def policy_step(self, params, x, hidden):
        """The greedy policy as logits (see the module doc)."""
        hidden, q = self.q_values(params, x, hidden)
        return hidden, q * GREEDY_LOGIT_SCALE

    def act_step(self, params, x, world, hidden):
        hidden, q = self.q_values(params, x, hidden)
        return hidden, q, jnp.max(q, -1)

    def act(self, params, keys, x, world, mask, hidden):
        """Epsilon-greedy over the legal actions; `params` is (network params, epsilon).
        The value is the greedy Q-value of each agent."""
        params, eps = params
        hidden, q = self.q_values(params, x, hidden)
        greedy = masked_argmax(q, mask)

        def explore(key, mask):
            k_which, k_random = jax.random.split(key)
            random = jax.random.categorical(k_random, jnp.where(mask, 0.0, MASKED_LOGIT))
            return jax.random.uniform(k_which, mask.shape[:-1]) < eps, random

        explored, random = jax.vmap(explore)(keys, mask)
        action = jnp.where(explored, random, greedy).astype(jnp.int32)
        return hidden, action, jnp.zeros(action.shape, jnp.float32), pick(q, greedy)

    # --- optimiser and state -----------------------------------------------------------------

    def _make_optimizer(self) -> optax.GradientTransformation:
        """RAdam with gradient clipping (the reference's); with `anneal_lr`, the learning
        rate decays linearly to 0 over the run's gradient steps."""
        ppo = self.ppo
        total = ppo.update_epochs * ppo.num_updates

        def schedule(count: jax.Array) -> jax.Array:
            return ppo.lr * jnp.maximum(1.0 - count / total, 0.0)

        lr = schedule if ppo.anneal_lr else ppo.lr
        return optax.chain(optax.clip_by_global_norm(ppo.max_grad_norm),
                           optax.radam(lr, eps=ppo.adam_eps))

    def _init(self, key: jax.Array) -> QTrainState:
        params = self.init_params(key)
        T, A = self.ppo.num_steps, self.num_agents
        item = Trajectory(
            obs=jnp.zeros((T, A, self.env_config.obs_size), jnp.float32),
            world=jnp.zeros((T, self.state_dim), jnp.float32) if self.centralised else None,
            mask=jnp.zeros((T, A, C.NUM_ACTIONS), bool), alive=jnp.zeros((T, A), bool),
            action=jnp.zeros((T, A), jnp.int32), reward=jnp.zeros(T, jnp.float32),
            done=jnp.zeros(T, bool))
        # flashbax starts its index as a weakly typed int; the updated one is strongly typed,
        # and the update would compile twice (once per argument type).
        buffer = self.buffer.init(item)
        buffer = buffer.replace(current_index=jnp.zeros((), jnp.int32))
        return QTrainState(params=params, target_params=params,
                           opt_state=self.optimizer.init(params), buffer=buffer,
                           update=jnp.zeros((), jnp.int32))

    def learner_devices(self, num_envs: int, minibatches: int | None = None,
                        strict: bool = True) -> tuple[jax.Device, ...]:
        """One device: the replay buffer lives there."""
        return (local_devices()[0],)

    def buffer_size(self, state: QTrainState) -> jax.Array:
        """Trajectories in the buffer now."""
        per_env = jnp.where(state.buffer.is_full, self.per_env, state.buffer.current_index)
        return per_env * self.ppo.num_envs

    # --- the update --------------------------------------------------------------------------

    def update(self, train_state: QTrainState, levels: EnvParams, key: jax.Array
               ) -> tuple[QTrainState, dict[str, jax.Array], RolloutStats]:
        """One update on `levels` (a batch of `num_envs` levels): (train state, metrics,
        rollout stats). The train state is donated: do not reuse one passed in."""
        num_envs = levels.reward_mode.shape[0]
        if num_envs != self.ppo.num_envs:
            raise ValueError(f"{num_envs} levels for a learner of {self.ppo.num_envs} envs "
                             "(the replay buffer takes one trajectory per env)")
        return self._update_jit(train_state, levels, key)

    def _update(self, train_state: QTrainState, levels: EnvParams, key: jax.Array
                ) -> tuple[QTrainState, dict[str, jax.Array], RolloutStats]:
        ppo, q = self.ppo, self.q
        levels = self.prepare_levels(levels)
        num_envs = levels.reward_mode.shape[0]
        k_rollout, k_train = jax.random.split(key)
        eps = self.epsilon(train_state.update)
        traj, records, last = self.rollout_with_keys(
            (train_state.params, eps), levels,
            self.rollout_keys(k_rollout, ppo.num_steps, num_envs))
        world = traj.world if self.centralised else None
        item = Trajectory(obs=traj.obs, world=world, mask=traj.mask, alive=traj.alive,
                          action=traj.action, reward=traj.reward, done=traj.done)
        # (T, E, ...) -> (E, 1, T, ...): each env adds one item, its whole trajectory.
        buffer = self.buffer.add(train_state.buffer,
                                 jax.tree.map(lambda x: jnp.swapaxes(x, 0, 1)[:, None], item))
        env_steps = (train_state.update + 1) * ppo.steps_per_update
        learn = self.buffer.can_sample(buffer) & (env_steps > q.learning_starts)

        def train(params, opt_state, target_params):
            def step(carry, k):
                params, opt_state = carry
                batch = self.buffer.sample(buffer, k).experience
                batch = jax.tree.map(lambda x: jnp.swapaxes(x[:, 0], 0, 1), batch)  # (T, B)
                (_, aux), grads = jax.value_and_grad(self._loss, has_aux=True)(
                    params, target_params, batch)
                aux["grad_norm"] = optax.tree.norm(grads)
                updates, opt_state = self.optimizer.update(grads, opt_state, params)
                return (optax.apply_updates(params, updates), opt_state), aux

            (params, opt_state), aux = jax.lax.scan(
                step, (params, opt_state), jax.random.split(k_train, ppo.update_epochs))
            return params, opt_state, jax.tree.map(jnp.mean, aux)

        def wait(params, opt_state, target_params):
            zero = jnp.zeros((), jnp.float32)
            return params, opt_state, {"loss/td": zero, "q/taken": zero, "q/target": zero,
                                       "grad_norm": zero}

        params, opt_state, aux = jax.lax.cond(learn, train, wait, train_state.params,
                                              train_state.opt_state, train_state.target_params)
        update = train_state.update + 1
        target_params = jax.lax.cond(
            update % q.target_update_interval == 0,
            lambda: optax.incremental_update(params, train_state.target_params, q.tau),
            lambda: train_state.target_params)
        new_state = QTrainState(params=params, target_params=target_params,
                                opt_state=opt_state, buffer=buffer, update=update)
        stats = self._q_stats(traj, last.value, last.alive)
        metrics = {**aux, **episode_metrics(records)}
        metrics["value/mean"] = jnp.mean(stats.values)
        metrics["explore/epsilon"] = eps
        metrics["buffer/trajectories"] = self.buffer_size(new_state).astype(jnp.float32)
        metrics["buffer/learning"] = learn.astype(jnp.float32)
        return new_state, metrics, stats

    def _q_stats(self, traj: Any, last_value: jax.Array, last_alive: jax.Array
                 ) -> RolloutStats:
        """Per env and step: the team's greedy value (the mean over living agents of their
        greedy Q-values, in reward units) and its one-step TD error as the advantage."""
        scale = 1.0 / self.q.reward_scale
        values = team_mean(traj.value, traj.alive) * scale
        last = team_mean(last_value, last_alive) * scale
        adv, _ = gae(traj.reward, values, traj.done, last, self.ppo.gamma, 0.0)
        return RolloutStats(values=values, advantages=adv, dones=traj.done,
                            rewards=traj.reward, wins=traj.won)

    def _loss(self, params: Any, target_params: Any, batch: Trajectory
              ) -> tuple[jax.Array, dict[str, jax.Array]]:
        """Mean squared TD error of a batch of trajectories (time-major, (T, B, ...))."""
        scale = self.q.reward_scale
        steps, size, agents = batch.action.shape
        starts = jnp.concatenate([jnp.ones((1, size), bool), batch.done[:-1]], axis=0)
        x = self.agent_inputs(batch.obs).reshape(steps, size * agents, -1)
        agent_starts = jnp.repeat(starts, agents, axis=1)

        def q_of(p):
            q = qnet_sequence(p["agent"], x, agent_starts, self.matmul_dtype)
            return q.reshape(steps, size, agents, -1)

        q = q_of(params)
        q_target = jax.lax.stop_gradient(q_of(target_params))
        # Double Q: the online network picks the next action, the target network values it.
        # The step after the last has no observation here: its value is 0, and the last step
        # enters the loss only where it ended an episode (no bootstrap needed).
        next_action = masked_argmax(jax.lax.stop_gradient(q[1:]), batch.mask[1:])
        next_q = _shift_in_zero(pick(q_target[1:], next_action))  # (T, B, A)
        next_alive = _shift_in_zero(batch.alive[1:])
        taken = pick(q, batch.action)
        reward = batch.reward * scale
        cont = 1.0 - batch.done.astype(jnp.float32)
        in_loss = jnp.ones((steps, size), bool).at[-1].set(batch.done[-1])
        taken, target, valid = self.td_terms(params, target_params, batch, taken, next_q,
                                             next_alive, reward, cont, in_loss)
        td = taken - jax.lax.stop_gradient(target)
        count = jnp.maximum(jnp.sum(valid), 1)
        mean = lambda v: jnp.sum(jnp.where(valid, v, 0.0)) / count
        loss = mean(jnp.square(td))
        return loss, {"loss/td": loss, "q/taken": mean(taken), "q/target": mean(target)}

    def td_terms(self, params: Any, target_params: Any, batch: Trajectory, taken: jax.Array,
                 next_q: jax.Array, next_alive: jax.Array, reward: jax.Array,
                 cont: jax.Array, in_loss: jax.Array
                 ) -> tuple[jax.Array, jax.Array, jax.Array]:
        """(the Q-values the loss fits, their targets, which entries enter the loss) from the
        agents' Q of the taken actions and their double-Q next values (T, B, A), the scaled
        reward, 1 - done and the steps in the loss (T, B). Here each agent's own: no bootstrap
        past its unit's death, only the steps where it is alive (IQL)."""
        gamma = self.ppo.gamma
        target = reward[..., None] + gamma * cont[..., None] * next_alive * next_q
        return taken, target, batch.alive & in_loss[..., None]

    # --- scoring -----------------------------------------------------------------------------

    def _score_envs(self, params: Any, levels: EnvParams, keys: jax.Array
                    ) -> tuple[dict[str, jax.Array], RolloutStats]:
        """The greedy policy's rollout (epsilon 0)."""
        traj, records, last = self.rollout_with_keys(
            (params, jnp.zeros((), jnp.float32)), levels, keys)
        return records, self._q_stats(traj, last.value, last.alive)


class IQL(QLearner):
    """Independent Q-learning: each agent's own Q-values, no mixer."""

    name = "iql"


class MixingQLearner(QLearner):
    """A Q-learner of the team's Q_tot, mixed from the agents' Q-values (`mix`): the TD error
    of Q_tot against the team's target, dead agents entering the mixer with Q = 0."""

    def mix(self, params: Any, q: jax.Array, world: jax.Array | None) -> jax.Array:
        """Q_tot (...) of agent values q (..., A) (zero for dead agents) and world states
        (..., S) (None unless `centralised`)."""
        raise NotImplementedError

    def td_terms(self, params, target_params, batch, taken, next_q, next_alive, reward, cont,
                 in_loss):
        gamma = self.ppo.gamma
        zero_dead = lambda v, a: jnp.where(a, v, 0.0)
        taken = self.mix(params, zero_dead(taken, batch.alive), batch.world)
        next_world = None if batch.world is None else _shift_in_zero(batch.world[1:])
        next_q = self.mix(target_params, zero_dead(next_q, next_alive), next_world)
        return taken, reward + gamma * cont * next_q, in_loss


class VDN(MixingQLearner):
    """Value decomposition: Q_tot is the sum of the agents' Q-values."""

    name = "vdn"

    def mix(self, params, q, world):
        return mixers.vdn(q)


class QMIX(MixingQLearner):
    """QMIX: a monotonic mixing network conditioned on the world state (which the rollout
    records for centralised learners only)."""

    name = "qmix"
    centralised = True
    own_settings = ("qlearning.mixer_embed_dim", "qlearning.mixer_hidden_dim",
                    "qlearning.mixer_init_scale")
    refusal = "a setting of QMIX's mixing network; {algorithm} has none"

    def mixer_params(self, key):
        q = self.q
        return {"mixer": mixers.qmix_init(key, self.num_agents, self.state_dim,
                                          q.mixer_embed_dim, q.mixer_hidden_dim,
                                          q.mixer_init_scale)}

    def mix(self, params, q, world):
        return mixers.qmix(params["mixer"], q, world)


__all__ = ["GREEDY_LOGIT_SCALE", "IQL", "QMIX", "MixingQLearner", "QLearner",
           "QTrainState", "Trajectory", "VDN", "epsilon_schedule",
           "masked_argmax", "qnet_init", "qnet_sequence", "qnet_step"]

"""MAPPO+RND: MAPPO with a random-network-distillation exploration bonus on the world state.

The paper's exploration baseline (section "Exploration", appendix "Exploration", table "RND
Hyperparameters"; the reference's `mappo_rnn_rnd.py`, docs/differences.md):

- a fixed, randomly initialised *target* network g and a trained *predictor* f, both MLPs of
  `rnd_layers` x Dense(`rnd_hidden_dim`) + ReLU and a Dense(`rnd_output_dim`) output, read the
  world state s' after each step; the intrinsic reward of the step is
  r_i = `rnd_reward_coef` * mean((f(s') - g(s'))^2), zero on the step that ends an episode
  (s' is then the next episode's first state);
- two critic towers on the world state, each MAPPO's recurrent critic: V_e for the team
  reward and V_i for r_i. The extrinsic GAE stops at episode ends; the intrinsic one does not
  (the reference's `RND_IS_EPISODIC = False`: novelty is a property of the run, not of an
  episode). The policy's advantage is A_e + `rnd_gae_coef` * A_i; both value heads are
  trained (clipped, as MAPPO's) with `vf_coef` on their sum;
- after the PPO epochs, the predictor is trained for `rnd_update_epochs` epochs of the same
  env minibatches on `rnd_loss_coef` * mean((f(s') - g(s'))^2), with its own Adam
  (`rnd_lr`); the PPO optimiser leaves both RND networks alone (`frozen_groups`), the target
  is never trained.

The rollout computes r_i with the predictor of the rollout (before this update trains it), so
a state seen repeatedly earns less and less. Differences from the reference: each critic tower
carries its own hidden state, reset at episode boundaries (the reference feeds the intrinsic
GRU the extrinsic GRU's output state and carries one hidden state); see docs/learners_algorithms.md.

`RolloutStats` (what UED scores read) carry the extrinsic value and the combined advantage.
"""

from __future__ import annotations

import math
from typing import Any

import jax
import jax.numpy as jnp
import optax

from tabx import constants as C
from ued.learners import networks as nw
from ued.learners.mappo import MAPPO
from ued.learners.ppo import PPOLearner, Transition, gae, masked_mean, valid_count, value_loss


def mlp_init(key: jax.Array, n_in: int, hidden: int, layers: int, n_out: int) -> dict:
    """`layers` Dense(hidden) layers (orthogonal sqrt 2) and a Dense(n_out) output
    (orthogonal 1)."""
    keys = jax.random.split(key, layers + 1)
    sizes = [n_in] + [hidden] * layers
    return {"hidden": [nw.dense_init(k, a, b, math.sqrt(2.0))
                       for k, a, b in zip(keys[:-1], sizes[:-1], sizes[1:], strict=True)],
            "out": nw.dense_init(keys[-1], hidden, n_out, 1.0)}


def mlp(p: dict, x: jax.Array) -> jax.Array:
    for layer in p["hidden"]:
        x = jax.nn.relu(nw.dense(layer, x))
    return nw.dense(p["out"], x)


def prediction_error(rnd: dict, world: jax.Array) -> jax.Array:
    """mean((f(s) - g(s))^2) over the output features, per state (the leading axes of
    `world`); `rnd` holds the `predictor` f and the `target` g."""
    target = jax.lax.stop_gradient(mlp(rnd["target"], world))
    return jnp.mean(jnp.square(mlp(rnd["predictor"], world) - target), axis=-1)


class MAPPORND(MAPPO):
    """Recurrent MAPPO with RND (the paper's settings: `LearnerConfig.rnd_*`, ent_coef 0.001 in
    the configs)."""

    name = "mappo_rnd"
    frozen_groups = ("rnd",)
    own_settings = tuple(f"learner.rnd_{name}" for name in (
        "reward_coef", "gae_coef", "loss_coef", "lr", "update_epochs", "hidden_dim",
        "output_dim", "layers"))
    refusal = "RND settings go with algorithm mappo_rnd, not {algorithm}"

    def __init__(self, *args: Any, **kwargs: Any):
        super().__init__(*args, **kwargs)
        self.rnd_optimizer = optax.adam(self.ppo.rnd_lr, eps=self.ppo.adam_eps)

    # --- networks ----------------------------------------------------------------------------

    def init_params(self, key: jax.Array) -> dict[str, Any]:
        k_actor, k_ext, k_int, k_pred, k_target = jax.random.split(key, 5)
        ppo, hidden = self.ppo, self.ppo.hidden_dim
        rnd = lambda k: mlp_init(k, self.state_dim, ppo.rnd_hidden_dim, ppo.rnd_layers,
                                 ppo.rnd_output_dim)
        return {"actor": nw.trunk_init(k_actor, self.obs_dim, hidden, (0.01,) * C.NUM_ACTIONS),
                "critic": nw.trunk_init(k_ext, self.state_dim, hidden, (1.0,)),
                "critic_int": nw.trunk_init(k_int, self.state_dim, hidden, (1.0,)),
                "rnd": {"predictor": rnd(k_pred), "target": rnd(k_target)}}

    def label_params(self, params: Any) -> Any:
        group = {"actor": "actor", "critic": "critic", "critic_int": "critic", "rnd": "rnd"}
        return {name: jax.tree.map(lambda _, g=group[name]: g, sub)
                for name, sub in params.items()}

    def initial_hidden(self, num_envs: int) -> tuple[jax.Array, jax.Array, jax.Array]:
        hidden = self.ppo.hidden_dim
        critic = jnp.zeros((num_envs, hidden), jnp.float32)
        return (jnp.zeros((num_envs, self.num_agents, hidden), jnp.float32), critic, critic)

    def act_step(self, params, x, world, hidden):
        """Values (E, 2): extrinsic and intrinsic."""
        h_actor, h_ext, h_int = hidden
        h_actor, logits = nw.step(params["actor"], x, h_actor, self.matmul_dtype)
        h_ext, v_ext = nw.step(params["critic"], world, h_ext, self.matmul_dtype)
        h_int, v_int = nw.step(params["critic_int"], world, h_int, self.matmul_dtype)
        return (h_actor, h_ext, h_int), logits, jnp.concatenate([v_ext, v_int], -1)

    def policy_step(self, params, x, hidden):
        h_actor, h_ext, h_int = hidden
        h_actor, logits = nw.step(params["actor"], x, h_actor, self.matmul_dtype)
        return (h_actor, h_ext, h_int), logits

    def evaluate_sequence(self, params, x, world, starts):
        steps, envs, agents = x.shape[:3]
        flat = x.reshape(steps, envs * agents, x.shape[-1])
        hidden = self.ppo.hidden_dim
        critic_h0 = jnp.zeros((envs, hidden), jnp.float32)
        logits, v_ext, v_int = nw.sequences(
            (params["actor"], params["critic"], params["critic_int"]), (flat, world, world),
            (jnp.repeat(starts, agents, axis=1), starts, starts),
            (jnp.zeros((envs * agents, hidden), jnp.float32), critic_h0, critic_h0),
            self.matmul_dtype)
        return logits.reshape(steps, envs, agents, -1), jnp.concatenate([v_ext, v_int], -1)

    def team_value(self, value: jax.Array, alive: jax.Array) -> jax.Array:
        """The extrinsic value (the team reward's)."""
        return value[..., 0]

    # --- training ----------------------------------------------------------------------------

    def _init(self, key: jax.Array):
        state = PPOLearner._init(self, key)
        rnd_state = self.rnd_optimizer.init(state.params["rnd"]["predictor"])
        return state.replace(opt_state={"ppo": state.opt_state, "rnd": rnd_state})

    def intrinsic_rewards(self, params: Any, traj: Transition, last: Transition
                          ) -> tuple[jax.Array, jax.Array]:
        """(intrinsic reward (T, E), the world state after each step (T, E, S))."""
        next_world = jnp.concatenate([traj.world[1:], last.world[None]], axis=0)
        reward = self.ppo.rnd_reward_coef * prediction_error(params["rnd"], next_world)
        return jnp.where(traj.done, 0.0, reward), next_world

    def returns(self, params, traj, last):
        ppo = self.ppo
        reward_int, next_world = self.intrinsic_rewards(params, traj, last)
        adv_ext, target_ext = gae(traj.reward, traj.value[..., 0], traj.done,
                                  last.value[..., 0], ppo.gamma, ppo.gae_lambda)
        adv_int, target_int = gae(reward_int, traj.value[..., 1], jnp.zeros_like(traj.done),
                                  last.value[..., 1], ppo.gamma, ppo.gae_lambda)
        adv = adv_ext + ppo.rnd_gae_coef * adv_int
        targets = jnp.stack([target_ext, target_int], axis=-1)
        return (traj.value[..., 0], adv, targets,
                {"next_world": next_world, "reward_int": reward_int})

    def critic_loss(self, values, batch, valid, count, axis_name):
        ppo = self.ppo
        every = jnp.ones(values.shape[:-1], bool)  # one value per env and step
        n = valid_count(every, axis_name)
        head = lambda i: value_loss(values[..., i], batch["value"][..., i],
                                    batch["targets"][..., i], every, ppo.clip_eps,
                                    ppo.clip_value, n)
        v_ext, v_int = head(0), head(1)
        return v_ext + v_int, {"loss/value": v_ext, "loss/value_int": v_int}

    def optimise(self, params, opt_state, batch, key, axis_name=None):
        ppo = self.ppo
        k_ppo, k_rnd = jax.random.split(key)
        # The PPO minibatches need not carry the RND-only entries.
        ppo_batch = {k: v for k, v in batch.items() if k not in ("next_world", "reward_int")}
        params, ppo_state, aux = super().optimise(params, opt_state["ppo"], ppo_batch, k_ppo,
                                                  axis_name)
        target = params["rnd"]["target"]

        def rnd_loss(predictor, mb):
            error = prediction_error({"predictor": predictor, "target": target},
                                     mb["next_world"])
            every = jnp.ones(error.shape, bool)
            loss = ppo.rnd_loss_coef * masked_mean(error, every, valid_count(every, axis_name))
            return loss, {"rnd/loss": loss}

        rnd_batch = {"next_world": batch["next_world"], "starts": batch["starts"]}
        predictor, rnd_state, rnd_aux = self.minibatch_epochs(
            rnd_loss, self.rnd_optimizer, params["rnd"]["predictor"], opt_state["rnd"],
            rnd_batch, k_rnd, ppo.rnd_update_epochs, axis_name)
        params = {**params, "rnd": {"predictor": predictor, "target": target}}
        reward = batch["reward_int"]
        every = jnp.ones(reward.shape, bool)
        mean_reward = masked_mean(reward, every, valid_count(every, axis_name))
        if axis_name is not None:
            mean_reward = jax.lax.psum(mean_reward, axis_name)
        aux = {**aux, "rnd/loss": rnd_aux["rnd/loss"], "rnd/grad_norm": rnd_aux["grad_norm"],
               "rnd/intrinsic_reward": mean_reward}
        return params, {"ppo": ppo_state, "rnd": rnd_state}, aux


__all__ = ["MAPPORND", "mlp", "mlp_init", "prediction_error"]

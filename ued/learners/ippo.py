"""IPPO: one shared recurrent actor-critic per agent, on the agent's own observation.

As the reference's `ActorCriticRNN`, the policy logits and the value are two heads of one
trunk (one recurrent pass per agent gives both). Each agent has its own value V(o_i) of the
team reward. Dead and padded agents are out of every loss term; for GAE, an agent's value
after its unit died (it no longer acts, but the team's reward goes on) is the mean value of its
living teammates, so the advantage of its last steps still sees how the episode ends.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp

from tabx import constants as C
from ued.learners import networks as nw
from ued.learners.ppo import PPOLearner, team_mean


class IPPO(PPOLearner):
    """Recurrent IPPO with a shared actor-critic (paper's defaults in `LearnerConfig`)."""

    name = "ippo"
    centralised = False

    def init_params(self, key: jax.Array) -> dict[str, Any]:
        return {"net": nw.trunk_init(key, self.obs_dim, self.ppo.hidden_dim,
                                     (0.01,) * C.NUM_ACTIONS + (1.0,))}

    def initial_hidden(self, num_envs: int) -> jax.Array:
        return jnp.zeros((num_envs, self.num_agents, self.ppo.hidden_dim), jnp.float32)

    def act_step(self, params, x, world, hidden):
        hidden, out = nw.step(params["net"], x, hidden, self.matmul_dtype)
        return hidden, out[..., :C.NUM_ACTIONS], out[..., C.NUM_ACTIONS]

    def policy_step(self, params, x, hidden):
        hidden, out = nw.step(params["net"], x, hidden, self.matmul_dtype)
        return hidden, out[..., :C.NUM_ACTIONS]

    def evaluate_sequence(self, params, x, world, starts):
        steps, envs, agents = x.shape[:3]
        flat = x.reshape(steps, envs * agents, x.shape[-1])
        h0 = jnp.zeros((envs * agents, self.ppo.hidden_dim), jnp.float32)
        out = nw.sequence(params["net"], flat, jnp.repeat(starts, agents, axis=1), h0,
                          self.matmul_dtype)
        out = out.reshape(steps, envs, agents, -1)
        return out[..., :C.NUM_ACTIONS], out[..., C.NUM_ACTIONS]

    def value_terms(self, values, last_value, alive, last_alive):
        """A dead agent's value is its living teammates' mean value (see the module doc)."""
        fill = lambda v, a: jnp.where(a, v, team_mean(v, a)[..., None])
        return fill(values, alive), fill(last_value, last_alive)


__all__ = ["IPPO"]

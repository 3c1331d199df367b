"""MAPPO: a shared recurrent actor on each agent's observation and a centralised recurrent
critic on the world state.

The critic runs once per env on `TabxEnv.world_state` and outputs one value per env: the team's
value V(s). The reference evaluates its critic once per agent on a copy of the same world
state (no agent id in it), so its per-agent values are the same function of the same input and
differ only through its death-only hidden resets; one pass per env gives that value at a third
of the cost here (3 agents), and every agent of the env uses it as its baseline (the team
shares one reward). The actor and the critic have separate gradient clipping and Adam states,
as the reference's two train states.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp

from tabx import constants as C
from ued.learners import networks as nw
from ued.learners.ppo import PPOLearner


class MAPPO(PPOLearner):
    """Recurrent MAPPO (paper's defaults in `LearnerConfig`)."""

    name = "mappo"
    centralised = True
    param_groups = ("actor", "critic")

    def init_params(self, key: jax.Array) -> dict[str, Any]:
        k_actor, k_critic = jax.random.split(key)
        hidden = self.ppo.hidden_dim
        return {"actor": nw.trunk_init(k_actor, self.obs_dim, hidden, (0.01,) * C.NUM_ACTIONS),
                "critic": nw.trunk_init(k_critic, self.state_dim, hidden, (1.0,))}

    def label_params(self, params: Any) -> Any:
        return {name: jax.tree.map(lambda _, name=name: name, sub)
                for name, sub in params.items()}

    def initial_hidden(self, num_envs: int) -> tuple[jax.Array, jax.Array]:
        hidden = self.ppo.hidden_dim
        return (jnp.zeros((num_envs, self.num_agents, hidden), jnp.float32),
                jnp.zeros((num_envs, hidden), jnp.float32))

    def act_step(self, params, x, world, hidden):
        h_actor, h_critic = hidden
        h_actor, logits = nw.step(params["actor"], x, h_actor, self.matmul_dtype)
        h_critic, value = nw.step(params["critic"], world, h_critic, self.matmul_dtype)
        return (h_actor, h_critic), logits, value[..., 0]

    def policy_step(self, params, x, hidden):
        h_actor, h_critic = hidden
        h_actor, logits = nw.step(params["actor"], x, h_actor, self.matmul_dtype)
        return (h_actor, h_critic), logits

    def evaluate_sequence(self, params, x, world, starts):
        steps, envs, agents = x.shape[:3]
        flat = x.reshape(steps, envs * agents, x.shape[-1])
        agent_starts = jnp.repeat(starts, agents, axis=1)
        hidden = self.ppo.hidden_dim
        logits, values = nw.sequences(
            (params["actor"], params["critic"]), (flat, world), (agent_starts, starts),
            (jnp.zeros((envs * agents, hidden), jnp.float32),
             jnp.zeros((envs, hidden), jnp.float32)), self.matmul_dtype)
        return logits.reshape(steps, envs, agents, -1), values[..., 0]


__all__ = ["MAPPO"]

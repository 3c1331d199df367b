"""Value mixers of the Q-learners: how agent Q-values make the team's Q_tot.

- VDN: Q_tot = sum over agents of Q_i.
- QMIX: a two-layer mixing network whose weights come from hypernetworks on the world state
  (as the reference's; docs/differences.md): with E the embedding width and H the
  hypernetworks' hidden width,

      W1 = |Dense(A E)(relu(Dense(H)(s)))|      b1 = Dense(E)(s)
      W2 = |Dense(E)(relu(Dense(H)(s)))|        b2 = Dense(1)(relu(Dense(E)(s)))
      Q_tot = elu(q W1 + b1) W2 + b2

  The absolute values keep every mixing weight non-negative, so dQ_tot/dQ_i >= 0 (QMIX's
  monotonicity: each agent's greedy action is the team's). Every layer is orthogonally
  initialised with the small scale `init_scale` (0.001 in the reference) and zero biases.

Both are pure functions over parameter dicts (as ued.learners.networks), batched over any
leading axes.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from ued.learners import networks as nw


def vdn(q: jax.Array) -> jax.Array:
    """(..., A) agent values -> (...) their sum."""
    return jnp.sum(q, -1)


def qmix_init(key: jax.Array, num_agents: int, state_dim: int, embed_dim: int,
              hidden_dim: int, init_scale: float) -> dict:
    """Parameters of the QMIX mixing network's hypernetworks."""
    keys = jax.random.split(key, 7)

    def hyper(k1: jax.Array, k2: jax.Array, hidden: int, out: int) -> dict:
        return {"hidden": nw.dense_init(k1, state_dim, hidden, init_scale),
                "out": nw.dense_init(k2, hidden, out, init_scale)}

    return {"w1": hyper(keys[0], keys[1], hidden_dim, num_agents * embed_dim),
            "b1": nw.dense_init(keys[2], state_dim, embed_dim, init_scale),
            "w2": hyper(keys[3], keys[4], hidden_dim, embed_dim),
            "b2": hyper(keys[5], keys[6], embed_dim, 1)}


def _hyper(p: dict, state: jax.Array) -> jax.Array:
    return nw.dense(p["out"], jax.nn.relu(nw.dense(p["hidden"], state)))


def qmix_weights(p: dict, state: jax.Array, num_agents: int
                 ) -> tuple[jax.Array, jax.Array, jax.Array, jax.Array]:
    """(W1 (..., A, E), b1 (..., E), W2 (..., E), b2 (...)) for world states (..., S)."""
    w1 = jnp.abs(_hyper(p["w1"], state))
    w1 = w1.reshape(*w1.shape[:-1], num_agents, w1.shape[-1] // num_agents)
    b1 = nw.dense(p["b1"], state)
    w2 = jnp.abs(_hyper(p["w2"], state))
    b2 = _hyper(p["b2"], state)[..., 0]
    return w1, b1, w2, b2


def qmix(p: dict, q: jax.Array, state: jax.Array) -> jax.Array:
    """(..., A) agent values and (..., S) world states -> (...) Q_tot."""
    w1, b1, w2, b2 = qmix_weights(p, state, q.shape[-1])
    hidden = jax.nn.elu(jnp.einsum("...a,...ae->...e", q, w1) + b1)
    return jnp.sum(hidden * w2, -1) + b2


__all__ = ["qmix", "qmix_init", "qmix_weights", "vdn"]

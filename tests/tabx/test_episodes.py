"""The episode player (`tabx.episodes.play`) on the tiny duel of the learner tests (2 archers v
1 farmer, 8 steps), scripted teams only, in one compiled program: an episode's numbers do not
depend on the batch it is played in (per-env keys), the per-step record ends in the final
state, and the loop that stops when every episode has ended returns what the scan does."""

from __future__ import annotations

import jax
import numpy as np
import pytest
from test_learners_helpers import ENV_CONFIG, duel_level

from tabx.controllers import Controller, with_tiers
from tabx.env import TabxEnv
from tabx.episodes import EPISODE_KEYS, LOOP_KEYS, Policy, play
from tabx.jit_options import simulator_jit
from tabx.params import repeat_level

CONTROLLERS = (Controller("random"), Controller("heuristic", "expert"))


def test_batches_records_and_the_early_stopping_loop_agree():
    env = TabxEnv(ENV_CONFIG)
    levels = jax.tree.map(jax.numpy.asarray,
                          repeat_level(with_tiers(duel_level(), CONTROLLERS), 3))
    steps = ENV_CONFIG.max_steps

    @simulator_jit
    def run(keys):
        record = lambda states, info, levels: states.hp_ratio  # noqa: E731
        batch = play(env, levels, keys, steps, CONTROLLERS, keys=EPISODE_KEYS, record=record)
        alone = play(env, jax.tree.map(lambda x: x[1:2], levels), keys[1:2], steps,
                     CONTROLLERS, keys=EPISODE_KEYS)
        looped = play(env, levels, keys[0], steps + 5, CONTROLLERS, keys=LOOP_KEYS,
                      start=batch.start, until_done=True)
        return batch, alone, looped

    batch, alone, looped = jax.device_get(run(jax.random.split(jax.random.key(0), 3)))
    for name in ("returns", "length"):
        np.testing.assert_array_equal(getattr(batch, name)[1:2], getattr(alone, name))
    np.testing.assert_array_equal(batch.states.position[1:2], alone.states.position)
    assert batch.record.shape == (steps, 3, 2)
    np.testing.assert_array_equal(batch.record[-1], batch.states.hp_ratio)
    # Every episode times out at the limit: both loops play exactly `max_steps` steps.
    assert (batch.length == steps).all() and (looped.length == steps).all()
    assert looped.states.done.all() and (looped.states.step == steps).all()


def test_a_policy_team_must_be_external():
    policy = Policy(lambda *args: None, lambda n: None, (0, 2))
    env = TabxEnv(ENV_CONFIG)
    with pytest.raises(ValueError, match="must be external"):
        play(env, repeat_level(duel_level(), 1), jax.random.key(0)[None], 2, CONTROLLERS,
             (policy, None), keys=EPISODE_KEYS)

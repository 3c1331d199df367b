"""Play a batch of episodes: one loop over steps of a vmap over levels, each team driven by a
scripted controller or a policy, returning what every caller of an episode needs.

    out = play(env, levels, key, steps, controllers, keys=EPISODE_KEYS)
    out.returns, out.length, out.states.won       # (E, 2), (E,), (E, 2)

Each step: the policies (teams whose controller is `external`) act on the observations and
action masks of their unit slots, with their recurrent state carried from step to step; the
scripted controllers (`tabx.controllers`) act for the other teams in one call (the heuristic's
memory is part of the state); every env steps. Nothing auto-resets: a finished episode is
frozen (stepping it changes nothing and pays nothing), so a scan can simply run a fixed number
of steps. `until_done=True` instead loops until every episode has ended (a `lax.while_loop`,
so short battles stop early); per-step outputs (`record`) need the scan.

Per episode the result holds the final state (`won`, `hp_ratio`, `step`), the summed reward
of each team (discounted by `discount` if given), the number of steps played before the
episode ended, and optionally a per-step record (`record(states, info, levels)`, e.g. frames
to render) and a per-step accumulator (`track`, e.g. the step of the first death).

The function is traceable, not compiled: each caller compiles the program it belongs to with
its own options (`tabx.jit_options`: `simulator_jit` without networks, `learner_jit` with).
The levels, parameters and keys are data, so a new level never recompiles.

Policies come from the layers above (this package trains no network): a `Policy` is a
traceable `act` with its recurrent state and unit slots. How the randomness of the controllers
and policies is drawn from the key is a `KeyChain`; the chains below are the ones the callers'
results were defined with, kept so that a seed gives the same episodes as it always has.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from tabx import constants as C
from tabx.controllers import Controller, KindPerEnv, controlled_actions, scripted_actions_by_kind
from tabx.env import TabxEnv
from tabx.params import EnvParams
from tabx.state import EnvState

# act(params, key, obs (E, N, obs_size), mask (E, N, num_actions), states, levels, hidden)
#   -> (actions (E, end - first) int32 of the team's slots, new hidden); traceable. `key` is
# one key for the batch or one per env (E,), as the key chain draws them (`sample` takes both).
PolicyAct = Callable[..., tuple[jax.Array, Any]]


@dataclass(frozen=True)
class Policy:
    """A team played by a network. `act` and `initial_hidden` decide what the compiled program
    computes: give the same objects for the same network and seat so that programs are reused;
    the network's parameters are data, passed to `play` beside it."""

    act: PolicyAct
    initial_hidden: Callable[[int], Any]  # num_envs -> its recurrent state at an episode start
    slots: tuple[int, int]  # (first, end) unit slots it drives


def sample(key: jax.Array, logits: jax.Array) -> jax.Array:
    """int32 actions drawn from `logits` (E, ..., A): with one key for the whole batch, or one
    key per env (E,)."""
    if key.ndim == 0:
        return jax.random.categorical(key, logits).astype(jnp.int32)
    return jax.vmap(jax.random.categorical)(key, logits).astype(jnp.int32)


# --- key chains -------------------------------------------------------------------------------


class KeyChain:
    """How a batch of episodes draws its randomness from `play`'s key: the reset keys, one key
    per step (`steps` for a scan, `next` for a loop that may stop early), and from a step's key
    the keys of the policies and the scripted controllers' key per env (`draw`)."""

    def reset(self, key: jax.Array, num_envs: int) -> jax.Array:
        raise NotImplementedError(f"{type(self).__name__} starts from given states")

    def steps(self, key: jax.Array, num_envs: int, steps: int) -> jax.Array:
        raise NotImplementedError(f"{type(self).__name__} draws its step keys as it goes")

    def next(self, key: jax.Array, num_envs: int) -> tuple[jax.Array, jax.Array]:
        raise NotImplementedError(f"{type(self).__name__} draws its step keys up front")

    def draw(self, step_key: jax.Array, num_envs: int, policy_teams: tuple[int, ...]
             ) -> tuple[dict[int, jax.Array], jax.Array]:
        raise NotImplementedError


class _BatchKeys(KeyChain):
    """One key per step for the whole batch, split into `parts`: each team's policy takes part
    `policy_parts[team]`, and part `controller_part` is split into the controllers' keys, one
    per env. With `split_start` the key is first split into a reset key and a steps key;
    otherwise both are drawn from the key itself."""

    def __init__(self, parts: int, policy_parts: tuple[int, int], controller_part: int,
                 split_start: bool):
        self.parts, self.policy_parts = parts, policy_parts
        self.controller_part, self.split_start = controller_part, split_start

    def reset(self, key, num_envs):
        return jax.random.split(jax.random.split(key)[0] if self.split_start else key, num_envs)

    def steps(self, key, num_envs, steps):
        return jax.random.split(jax.random.split(key)[1] if self.split_start else key, steps)

    def draw(self, step_key, num_envs, policy_teams):
        parts = jax.random.split(step_key, self.parts)
        policy = {team: parts[self.policy_parts[team]] for team in policy_teams}
        return policy, jax.random.split(parts[self.controller_part], num_envs)


class _PerEnvKeys(KeyChain):
    """`play`'s key is one key per env (E,), each env's episode drawn from its own: it resets
    with it, splits it into one key per step, and the step's key drives its controllers
    (`split_controller_key`: the first half of its split) and, folded in with 1 + team, each
    policy. An episode's numbers do not depend on the batch it is played in."""

    def __init__(self, split_controller_key: bool):
        self.split_controller_key = split_controller_key

    def reset(self, key, num_envs):
        return key

    def steps(self, key, num_envs, steps):
        return jnp.swapaxes(jax.vmap(lambda k: jax.random.split(k, steps))(key), 0, 1)

    def draw(self, step_key, num_envs, policy_teams):
        policy = {team: jax.vmap(jax.random.fold_in, (0, None))(step_key, 1 + team)
                  for team in policy_teams}
        controller = (jax.vmap(jax.random.split)(step_key)[:, 0] if self.split_controller_key
                      else step_key)
        return policy, controller


class _LoopKeys(KeyChain):
    """One key carried through the loop: each step splits off a key and splits that into one
    per env; an env's key drives its controllers, or, when a policy plays, is split into the
    policy's key and the controllers'."""

    def next(self, key, num_envs):
        key, sub = jax.random.split(key)
        return key, jax.random.split(sub, num_envs)

    def draw(self, step_key, num_envs, policy_teams):
        if not policy_teams:
            return {}, step_key
        halves = jax.vmap(jax.random.split)(step_key)
        return {team: halves[:, 0] for team in policy_teams}, halves[:, 1]


# `tabx eval` (ued.evaluate.play): one key per step, split in four (ally policy, enemy policy,
# controllers, a fourth unused); the resets draw from the key itself.
EVAL_KEYS = _BatchKeys(parts=4, policy_parts=(0, 1), controller_part=2, split_start=False)
# Evaluation suites (workers.roles.evaluator): reset and steps from the two halves of the
# key; a step's key split in three (the policy, whichever team it plays; the controllers).
SUITE_KEYS = _BatchKeys(parts=3, policy_parts=(0, 0), controller_part=1, split_start=True)
# `tabx rollout`: one key per episode.
EPISODE_KEYS = _PerEnvKeys(split_controller_key=False)
# The editor's preview: one key per episode; the controllers take half of each step's key.
PREVIEW_KEYS = _PerEnvKeys(split_controller_key=True)
# Loops until every episode has ended (tournaments, value-error continuations).
LOOP_KEYS = _LoopKeys()


# --- the player -------------------------------------------------------------------------------


class Episodes(NamedTuple):
    """What `play` returns: per episode (leading axis E) unless said otherwise."""

    states: EnvState  # the final states (won, hp_ratio, step, ...)
    returns: jax.Array  # (E, 2) float32: each team's summed (or discounted) reward
    length: jax.Array  # (E,) int32: steps played before the episode ended (all if it did not)
    hidden: tuple  # per team: the policy's final recurrent state, or None
    record: Any = None  # `record`'s outputs with a leading time axis (T, ...), or None
    tracked: Any = None  # `track`'s final accumulator, or None
    start: EnvState | None = None  # the states the episodes started from


def play(env: TabxEnv, levels: EnvParams, key: jax.Array, steps: int,
         controllers: tuple[Controller | KindPerEnv, Controller | KindPerEnv],
         policies: tuple[Policy | None, Policy | None] = (None, None),
         params: tuple[Any, Any] = (None, None), *, keys: KeyChain,
         kinds: jax.Array | None = None, start: EnvState | None = None,
         hidden: tuple[Any, Any] | None = None, until_done: bool = False,
         discount: float | None = None,
         record: Callable[[EnvState, dict, EnvParams], Any] | None = None,
         track: tuple[Any, Callable[[Any, EnvState, EnvParams], Any]] | None = None
         ) -> Episodes:
    """Play one episode per level of `levels` (a batch, leading axis E) for `steps` steps (at
    most `steps` with `until_done`); traceable.

    `controllers`: per team a `Controller` (`external` where `policies` gives the team's
    `Policy`, whose parameters are `params`), or one team's `KindPerEnv` with the kind of each
    env in `kinds` (E,) (the other team then a policy). `keys`: how the randomness is drawn
    from `key` (module doc). `start`: the states to start from (default: reset every env with
    the chain's reset keys); `hidden`: the policies' recurrent states at the start (default
    their `initial_hidden`). `discount`: sum discount**t * reward. `record(states, info,
    levels)`: a per-step output (the scan only). `track`: (initial value, update(value,
    states, levels)), folded over the steps.
    """
    num_envs = jax.tree.leaves(levels)[0].shape[0]
    num_units = env.config.num_units
    playing = tuple(team for team in range(C.NUM_TEAMS) if policies[team] is not None)
    for team in playing:
        if not (isinstance(controllers[team], Controller)
                and controllers[team].kind == "external"):
            raise ValueError(f"team {team} is played by a policy: its controller must be "
                             f"external, got {controllers[team]}")
    per_env = [team for team, c in enumerate(controllers) if isinstance(c, KindPerEnv)]
    if per_env and (kinds is None or len(per_env) != 1 or not playing):
        raise ValueError("a team whose controller kind is per env needs `kinds` and a policy "
                         "on the other team")
    if record is not None and until_done:
        raise ValueError("a per-step record needs the scan: drop until_done")
    if start is None:
        _, start = jax.vmap(env.reset)(keys.reset(key, num_envs), levels)
    if hidden is None:
        hidden = tuple(None if p is None else p.initial_hidden(num_envs) for p in policies)
    # The policies' slots, for the per-env controllers' merge.
    policy_slots = np.zeros(num_units, bool)
    for team in playing:
        policy_slots[slice(*policies[team].slots)] = True

    def scripted(ctrl_keys, states, external):
        if per_env:
            actions, states = jax.vmap(
                lambda k, s, lv, kind: scripted_actions_by_kind(k, s, lv, kind,
                                                                controllers[per_env[0]].used))(
                ctrl_keys, states, levels, kinds)
            return jnp.where(policy_slots[None, :], external, actions), states
        return jax.vmap(lambda k, s, lv, e: controlled_actions(k, s, lv, e, controllers))(
            ctrl_keys, states, levels, external)

    def step(states, hidden, returns, length, weight, tracked, step_key):
        policy_keys, ctrl_keys = keys.draw(step_key, num_envs, playing)
        external = None
        if playing:
            obs = jax.vmap(env.observe)(states, levels)
            mask = jax.vmap(env.action_mask)(states, levels)
            external = jnp.zeros((num_envs, num_units), jnp.int32)
            hidden = list(hidden)
            for team in playing:
                acts, hidden[team] = policies[team].act(params[team], policy_keys[team], obs,
                                                        mask, states, levels, hidden[team])
                external = external.at[:, slice(*policies[team].slots)].set(acts)
            hidden = tuple(hidden)
        actions, acting = scripted(ctrl_keys, states, external)
        was_done = states.done
        # The step draws nothing (its key is unused): the controllers' keys stand in.
        _, states, reward, _, info = jax.vmap(env.step)(ctrl_keys, acting, actions, levels)
        if discount is None:
            returns = returns + reward
        else:
            returns = returns + jnp.where(was_done[:, None], 0.0, weight[:, None] * reward)
            weight = weight * discount
        length = length + (~was_done).astype(jnp.int32)
        if track is not None:
            tracked = track[1](tracked, states, levels)
        out = record(states, info, levels) if record is not None else None
        return (states, hidden, returns, length, weight, tracked), out

    init = (start, hidden, jnp.zeros((num_envs, C.NUM_TEAMS), jnp.float32),
            jnp.zeros(num_envs, jnp.int32), jnp.ones(num_envs, jnp.float32),
            None if track is None else track[0])
    if until_done:
        def cond(carry):
            return jnp.any(~carry[0][0].done) & (carry[2] < steps)

        def body(carry):
            inner, key, t = carry
            key, step_key = keys.next(key, num_envs)
            inner, _ = step(*inner, step_key)
            return inner, key, t + 1

        final, _, _ = jax.lax.while_loop(cond, body, (init, key, jnp.zeros((), jnp.int32)))
        trace = None
    else:
        final, trace = jax.lax.scan(lambda carry, k: step(*carry, k), init,
                                    keys.steps(key, num_envs, steps))
    states, hidden, returns, length, _, tracked = final
    return Episodes(states, returns, length, hidden, trace, tracked, start)


__all__ = ["EPISODE_KEYS", "EVAL_KEYS", "LOOP_KEYS", "PREVIEW_KEYS", "SUITE_KEYS", "Episodes",
           "KeyChain", "Policy", "PolicyAct", "play", "sample"]

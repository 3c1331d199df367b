"""Who drives each team: external actions (a learner), the scripted heuristic, random, or idle.

A `Controller` per team is static (it decides what the compiled step computes); the heuristic's
skill is data in the level (`EnvParams.heuristic`), so switching tier never recompiles. A tier
named in a controller (`heuristic:expert`) is written into the level by `with_tiers`; a bare
`heuristic` plays the level's own parameters (what UED varies).

    controllers = (Controller.parse("external"), Controller.parse("heuristic:medium"))
    level = with_tiers(level, controllers)
    actions, state = controlled_actions(key, state, level, learner_actions, controllers)
    obs, state, reward, done, info = env.step(key, state, actions, level)

`controlled_actions` returns the state with the heuristic's memory updated: step that state.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import jax
import jax.numpy as jnp

from tabx import constants as C
from tabx.heuristic import heuristic_actions_from_bits
from tabx.observe import action_mask, pick_legal
from tabx.params import HEURISTIC_TIERS, EnvParams
from tabx.rng import random_words, to_unit_float
from tabx.state import EnvState

CONTROLLER_KINDS = ("external", "heuristic", "random", "idle")
# The scripted kinds, numbered: a team whose kind is data per env (`KindPerEnv`) gives each env
# its kind as an index into this tuple.
SCRIPTED_KINDS = ("heuristic", "random", "idle")


@dataclass(frozen=True)
class Controller:
    """How one team chooses its actions. `tier` (heuristic only) overrides the level's
    heuristic parameters for this team; None keeps the level's own."""

    kind: str = "external"
    tier: str | None = None

    def __post_init__(self) -> None:
        if self.kind not in CONTROLLER_KINDS:
            raise ValueError(f"unknown controller {self.kind!r}; expected one of "
                             f"{', '.join(CONTROLLER_KINDS)} (heuristic as heuristic:TIER)")
        if self.tier is not None:
            if self.kind != "heuristic":
                raise ValueError(f"a tier only goes with the heuristic controller, got "
                                 f"{self.kind}:{self.tier}")
            if self.tier not in HEURISTIC_TIERS:
                raise ValueError(f"unknown heuristic tier {self.tier!r}; expected one of "
                                 f"{', '.join(HEURISTIC_TIERS)}")

    @classmethod
    def parse(cls, text: str) -> Controller:
        """'external', 'heuristic', 'heuristic:TIER', 'random' or 'idle'."""
        if not isinstance(text, str) or not text:
            raise ValueError(f"expected a controller such as heuristic:medium, got {text!r}")
        kind, _, tier = text.partition(":")
        return cls(kind, tier or None)

    @classmethod
    def parse_scripted(cls, text: str, role: str = "a team controller") -> Controller:
        """`parse`, refusing 'external' (a learner's actions): for the places where no learner
        plays (rollouts, benchmarks, opponents). `role` names the slot in the message."""
        controller = cls.parse(text)
        if controller.kind == "external":
            raise ValueError(f"'external' is not {role}: it stands for a learner's actions and "
                             "no learner plays here; use heuristic[:TIER], random or idle")
        return controller

    def __str__(self) -> str:
        return self.kind if self.tier is None else f"{self.kind}:{self.tier}"


@dataclass(frozen=True)
class KindPerEnv:
    """A scripted team whose kind is data, one `SCRIPTED_KINDS` index per env (an evaluation
    suite plays many opponents in one batch). Only the kinds in `used` are computed."""

    used: tuple[str, ...]


def with_tiers(params: EnvParams, controllers: Sequence[Controller]) -> EnvParams:
    """The level(s) with the heuristic parameters of each team whose controller names a tier.
    Works on one level or a batch (heuristic leaves of shape (..., 2))."""
    h = params.heuristic
    for team, controller in enumerate(controllers):
        if controller.tier is None:
            continue
        preset = HEURISTIC_TIERS[controller.tier]
        h = h.replace(**{name: getattr(h, name).at[..., team].set(preset[name])
                         for name in h.__dataclass_fields__})
    return params.replace(heuristic=h)


def controlled_actions(key: jax.Array, state: EnvState, params: EnvParams,
                       external: jax.Array | None, controllers: Sequence[Controller]
                       ) -> tuple[jax.Array, EnvState]:
    """(actions (N,) for every unit slot, state with the heuristic's memory) of one env.

    `external` (N,) int gives the actions of the teams controlled externally (its other
    entries are ignored); it may be None when no team is external. Only the controllers in use
    are computed (the kinds are static).
    """
    n = params.units.team.shape[0]
    return controlled_actions_from_words(random_words(key, (2, n)), state, params, external,
                                         controllers)


def controller_words(key: jax.Array, num_envs: int, num_units: int) -> jax.Array:
    """uint32 (num_envs, 2, num_units): the random words of `controlled_actions_from_words` for
    a whole batch of envs from one key. Drawing them per env (a key per env, as
    `controlled_actions` under vmap does) runs threefry for every env, a rolled loop of small
    kernels on a CPU; this draws one threefry word for the batch (`tabx.rng`)."""
    return random_words(key, (num_envs, 2, num_units))


def controlled_actions_from_words(words: jax.Array, state: EnvState, params: EnvParams,
                                  external: jax.Array | None, controllers: Sequence[Controller]
                                  ) -> tuple[jax.Array, EnvState]:
    """`controlled_actions` with its randomness given: uint32 words (2, N), row 0 for the
    scripted policy and row 1 for the random one (`controller_words` draws a batch's)."""
    kinds = [c.kind for c in controllers]
    if len(kinds) != C.NUM_TEAMS:
        raise ValueError(f"expected one controller per team ({C.NUM_TEAMS}), got {len(kinds)}")
    if "external" in kinds and external is None:
        raise ValueError("a team is controlled externally but no actions were given")
    team = params.units.team
    n = team.shape[0]
    by_kind: dict[str, jax.Array] = {"idle": jnp.full((n,), C.IDLE, jnp.int32)}
    if external is not None:
        by_kind["external"] = jnp.asarray(external, jnp.int32)
    if "heuristic" in kinds:
        by_kind["heuristic"], state = heuristic_actions_from_bits(words[0], state, params)
    if "random" in kinds:
        by_kind["random"] = pick_legal(to_unit_float(words[1]), action_mask(state, params))
    if kinds[0] == kinds[1]:
        return by_kind[kinds[0]], state
    return jnp.where(team == C.ALLY, by_kind[kinds[0]], by_kind[kinds[1]]), state


def scripted_actions_by_kind(key: jax.Array, state: EnvState, params: EnvParams, kind: jax.Array,
                             used: Sequence[str]) -> tuple[jax.Array, EnvState]:
    """(actions (N,) for every unit slot, state with the heuristic's memory where it plays) of
    one env whose scripted kind is `kind` (a `SCRIPTED_KINDS` index), with the randomness of
    `controlled_actions`. Only the kinds in `used` are computed."""
    n = params.units.team.shape[0]
    bits = random_words(key, (2, n))
    actions = jnp.full((n,), C.IDLE, jnp.int32)
    if "heuristic" in used:
        heuristic, after = heuristic_actions_from_bits(bits[0], state, params)
        is_heuristic = kind == SCRIPTED_KINDS.index("heuristic")
        actions = jnp.where(is_heuristic, heuristic, actions)
        state = jax.tree.map(lambda a, b: jnp.where(is_heuristic, a, b), after, state)
    if "random" in used:
        random = pick_legal(to_unit_float(bits[1]), action_mask(state, params))
        actions = jnp.where(kind == SCRIPTED_KINDS.index("random"), random, actions)
    return actions.astype(jnp.int32), state


__all__ = ["CONTROLLER_KINDS", "SCRIPTED_KINDS", "Controller", "KindPerEnv", "controlled_actions",
           "controlled_actions_from_words", "controller_words", "scripted_actions_by_kind",
           "with_tiers"]

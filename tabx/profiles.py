"""Behaviour profiles: the reference implementation's choices, restorable per level.

Where the reference implementation made a defensible choice that we made differently (the
scripted opponent's random draw, its kiting rule, search direction, memory, when it attacks, a
corpse's last drift, ...), the level says which behaviour to play: `EnvParams.profile` holds
one bit per choice, set bit = the reference's behaviour. Fixes of the reference's defects (NaN
padding, late termination, resurrection, ...) hold in every profile. Being level data, a
profile never recompiles the step, and a batch may mix profiles; each choice costs the step a
select.

Two named profiles:

- `tabx-ued` (the default): every choice ours (bits 0), the paper's team health formula;
- `reference`: every choice the reference's, and the reference code's team health formula
  (sum of health over sum of max health, `EnvParams.reward_mode`), to reproduce the paper's
  published numbers.

docs/differences.md lists every difference, and which profile restores which.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from tabx import constants as C
from tabx.params import EnvParams

# One bit per reference choice (set = the reference's behaviour). The names are what
# docs/differences.md calls them.
EPSILON_MOVES = 1 << 0  # the epsilon override draws among the 6 moves and turns only
KITE_MOVE_POINT = 1 << 1  # kiting measures the distance to the target's move point
SEARCH_RIGHT = 1 << 2  # the search always turns right
TURN_PREDICTION = 1 << 3  # turn-to-engage predicts with the observation's sight angle
TURN_IN_PLACE = 1 << 4  # turn-to-engage also when no whole turn step faces the target
MEMORY_REACH = 1 << 5  # memory forgotten within sqrt(2) dt, after the arrival step's move
BUSH_BOX = 1 << 6  # a ranger is "in the bush" inside the nearest bush's bounding box
ASSASSIN_CURRENT_SPEED = 1 << 7  # the assassin role reads the current (swamp-slowed) speed
CORPSE_DRIFT = 1 << 8  # a unit that dies keeps the velocity of its last move one more step
CORPSE_VISION = 1 << 9  # a dead teammate inside a bush still shares what it sees there
OBSERVED_COOLDOWN = 1 << 10  # the scripted unit attacks a step after its attack is ready

CHOICES: dict[str, int] = {
    "epsilon-moves": EPSILON_MOVES,
    "kite-move-point": KITE_MOVE_POINT,
    "search-right": SEARCH_RIGHT,
    "turn-prediction": TURN_PREDICTION,
    "turn-in-place": TURN_IN_PLACE,
    "memory-reach": MEMORY_REACH,
    "bush-box": BUSH_BOX,
    "assassin-current-speed": ASSASSIN_CURRENT_SPEED,
    "corpse-drift": CORPSE_DRIFT,
    "corpse-vision": CORPSE_VISION,
    "observed-cooldown": OBSERVED_COOLDOWN,
}
ALL_CHOICES = sum(CHOICES.values())

# name -> (profile bits, reward mode)
PROFILES: dict[str, tuple[int, int]] = {
    "tabx-ued": (0, C.REWARD_MEAN_OF_RATIOS),
    "reference": (ALL_CHOICES, C.REWARD_RATIO_OF_SUMS),
}
DEFAULT_PROFILE = "tabx-ued"
PROFILE_NAMES = tuple(PROFILES)


def check_profile(name: str) -> str:
    """`name` if it is a profile, else ValueError listing the profiles."""
    if name not in PROFILES:
        raise ValueError(f"unknown profile {name!r}; expected one of {', '.join(PROFILES)}")
    return name


def with_profile(levels: EnvParams, name: str) -> EnvParams:
    """The level(s) (one, or a batch) playing profile `name`: its bits and reward mode."""
    bits, reward_mode = PROFILES[check_profile(name)]
    shape = jnp.shape(levels.profile)
    return levels.replace(profile=jnp.full(shape, bits, jnp.int32),
                          reward_mode=jnp.full(shape, reward_mode, jnp.int32))


def profile_name(level: EnvParams) -> str:
    """The profile one level plays, or `custom (bits B, reward mode M)` for another mix."""
    bits, mode = int(np.asarray(level.profile)), int(np.asarray(level.reward_mode))
    for name, value in PROFILES.items():
        if value == (bits, mode):
            return name
    mode_name = C.REWARD_MODE_NAMES[mode] if 0 <= mode < len(C.REWARD_MODE_NAMES) else mode
    return f"custom (bits {bits:#x}, reward mode {mode_name})"


def reference_choice(params: EnvParams, choice: int) -> jax.Array:
    """bool scalar: the level plays the reference's behaviour for `choice` (one bit)."""
    return (params.profile & choice) != 0


__all__ = ["ALL_CHOICES", "ASSASSIN_CURRENT_SPEED", "BUSH_BOX", "CHOICES", "CORPSE_DRIFT",
           "CORPSE_VISION", "DEFAULT_PROFILE", "EPSILON_MOVES", "KITE_MOVE_POINT",
           "MEMORY_REACH", "OBSERVED_COOLDOWN", "PROFILES", "PROFILE_NAMES", "SEARCH_RIGHT",
           "TURN_IN_PLACE", "TURN_PREDICTION", "check_profile", "profile_name",
           "reference_choice", "with_profile"]

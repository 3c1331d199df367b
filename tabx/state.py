"""`EnvState`: the dynamic part of one battle (the level, `EnvParams`, stays outside).

Besides positions, health and the like, the state keeps the geometry computed at the end of the
previous step (visibility, which units each unit can hit, its nearest target), and the
memory of the scripted opponent (last seen target position, search direction). Observations and
the attack resolution of the next step read exactly this, so an agent's attack hits what its
observation said it could hit. The heading is also kept as a unit vector, rotated by the turn
actions, so the step evaluates no sine or cosine per unit (slow on CPU).
"""

from __future__ import annotations

import jax
from flax import struct


@struct.dataclass
class EnvState:
    position: jax.Array  # (N, 2) float32
    velocity: jax.Array  # (N, 2) float32, set by the last action; applied at the next step
    heading: jax.Array  # (N,) float32 radians in [0, 2 pi)
    facing: jax.Array  # (N, 2) float32 (cos, sin) of heading, rotated along with it
    half_sight: jax.Array  # (N, 2) float32 (cos, sin) of half the sight angle (fixed per episode)
    health: jax.Array  # (N,) float32 in [0, max_health]
    alive: jax.Array  # (N,) bool; False for padding, and forever once dead
    # (N,) float32 seconds since the last attack, as the next action sees it, capped at the
    # cooldown (one dt later under the reference's observed-cooldown choice: tabx.env.cooldown_cap)
    cooldown: jax.Array
    speed: jax.Array  # (N,) float32 current speed (swamps slow it), used by the next move
    visible: jax.Array  # (N, N) bool: visible[v, t] = v sees t (field of view + bush rules)
    attackable: jax.Array  # (N, N) bool: attackable[a, t] = a's attack would reach t now
    target: jax.Array  # (N,) int32 nearest attackable unit (valid where has_target)
    has_target: jax.Array  # (N,) bool
    hp_ratio: jax.Array  # (2,) float32 team health ratio (per the level's reward mode)
    step: jax.Array  # () int32 steps taken in this episode
    done: jax.Array  # () bool: the episode has ended (stepping further changes nothing)
    won: jax.Array  # (2,) bool: which team won (set when done)
    # Memory of the heuristic policy (tabx.heuristic), per unit slot; cleared at reset. It is
    # part of the state so that a scripted unit remembers across steps inside jit/scan.
    memory_position: jax.Array  # (N, 2) float32 where the unit last saw its chosen target
    memory_valid: jax.Array  # (N,) bool: memory_position is set and not yet reached
    search_turn: jax.Array  # (N,) int32 TURN_LEFT or TURN_RIGHT: current search direction

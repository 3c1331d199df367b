"""The role-appropriate scripted policy (paper section 4.2 and appendix A.7), for every unit slot.

One pure, jittable function computes an action for every unit of both teams from what each
unit can see: the living units in its (team-shared, bush-filtered) field of view, their
positions, headings, radii, health and max health, which of them it can hit now, its own state,
the zones, and its memory. Nothing hidden is read. Every rule is an (N, N) or (N, Z) array
operation: there is no loop or branch per unit.

Roles come from unit stats and the team's `HeuristicParams` (data in the level, so changing
tier never recompiles): assassin = speed >= assassin_speed, ranger = attack range >=
ranger_attack_range, healer = negative damage. Roles overlap.

Pipeline per unit:
1. candidates: healers the visible injured allies (else all visible allies); the others the
   visible enemies; assassins keep those of lowest max health (nearest on ties);
2. a move point per candidate: behind it (assassins), on it (healers), in front of it (others);
   the target is the candidate with the nearest move point;
3. priority, highest first: ATTACK (a candidate is attackable and the cooldown is ready);
   TURN toward the target if turning would make it attackable; ranger KITE (retreat from a
   candidate closer than attack range x threshold); MOVE to the target's move point; PURSUE the
   remembered last position of the target (face it, then move); rangers SEEK the nearest bush;
   SEARCH by rotating (a direction that reverses at random: the paper's stochastic search);
4. epsilon override: with probability epsilon, a uniformly random legal action.

Differences from the reference code (docs/differences.md): the turn prediction uses the real
sight angle and target radius, and a turn is only chosen when a whole turn step faces the
target better; the search rotation is stochastic (paper) not always right; kiting measures the
distance to the threatening unit itself; the epsilon draw and the random action use independent
randomness and the random action is any legal one; memory is forgotten when the spot is reached
within one move, or a corpse lies there; "in a bush" is the bush's ellipse; the assassin role
reads the unit's base speed; a unit attacks on the first step its attack is ready (the
reference's reads its cooldown from its observation, a step old). The level's profile
(`tabx.profiles`) restores the reference's choice for each of these, one select each.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp

from tabx import constants as C
from tabx import profiles
from tabx.geometry import atan2, in_ellipses, pairwise_offsets, sincos
from tabx.observe import action_mask, cooldown_ready, pick_legal
from tabx.params import EnvParams
from tabx.rng import random_words
from tabx.selection import index_one_hot, materialise, pick_row, row_argmin
from tabx.state import EnvState

# Probability per step that a searching unit reverses its rotation. One full turn takes
# 2 pi / (turn_rate dt) = 24 steps at the default dt, so a reversal comes about once a sweep.
SEARCH_REVERSE_PROB = 0.05
# Max-health tolerance of the assassin's "lowest max health" (the reference's 0.01).
ASSASSIN_HP_TOLERANCE = 0.01


def _toward(v: jax.Array) -> jax.Array:
    """(N,) world-frame move along the dominant axis of v (N, 2), toward its sign."""
    horizontal = jnp.abs(v[:, 0]) >= jnp.abs(v[:, 1])
    x_move = jnp.where(v[:, 0] > 0, C.RIGHT, C.LEFT)
    y_move = jnp.where(v[:, 1] > 0, C.UP, C.DOWN)
    return jnp.where(horizontal, x_move, y_move).astype(jnp.int32)


def _in_frame(v: jax.Array, facing: jax.Array) -> tuple[jax.Array, jax.Array]:
    """(x, y) of world vectors v (N, 2) in each unit's frame (+x = its facing (N, 2))."""
    fx, fy = facing[:, 0], facing[:, 1]
    return fx * v[:, 0] + fy * v[:, 1], -fy * v[:, 0] + fx * v[:, 1]


def _turn_toward(angle: jax.Array) -> jax.Array:
    return jnp.where(angle > 0, C.TURN_LEFT, C.TURN_RIGHT).astype(jnp.int32)


def unit_roles(params: EnvParams, speed: jax.Array | None = None
               ) -> tuple[jax.Array, jax.Array, jax.Array]:
    """(assassin, ranger, healer) bool (N,) from unit stats and each team's thresholds; the
    assassin test reads `speed` (default: the base speed)."""
    u, h = params.units, params.heuristic
    speed = u.speed if speed is None else speed
    assassin = speed >= _per_team(h.assassin_speed, u.team)
    ranger = u.attack_range >= _per_team(h.ranger_attack_range, u.team)
    return assassin, ranger, u.heals.astype(bool)


def _per_team(value: jax.Array, team: jax.Array) -> jax.Array:
    """value[team] for a (2,) per-team parameter, as a select (a gather is slow under vmap)."""
    return jnp.where(team == C.ALLY, value[C.ALLY], value[C.ENEMY])


def heuristic_actions(key: jax.Array, state: EnvState, params: EnvParams
                      ) -> tuple[jax.Array, EnvState]:
    """(actions (N,), state with updated memory) of the scripted policy for every unit slot.

    Single environment; vmap over envs. Dead and padded slots IDLE. Apply the returned state's
    memory by stepping *that* state (its other fields are unchanged).
    """
    bits = random_words(key, state.alive.shape)
    return heuristic_actions_from_bits(bits, state, params)


def heuristic_actions_from_bits(bits: jax.Array, state: EnvState, params: EnvParams
                                ) -> tuple[jax.Array, EnvState]:
    """`heuristic_actions` with its randomness given: one uint32 (N,) word per unit slot
    (callers that draw for several controllers at once save random-number calls)."""
    u, h, z = params.units, params.heuristic, params.zones
    n = u.team.shape[0]
    team = u.team
    position = state.position
    reference = functools.partial(profiles.reference_choice, params)
    # The reference reads the observed, swamp-slowed speed: an assassin in a swamp loses its role.
    assassin, ranger, healer = unit_roles(
        params, jnp.where(reference(profiles.ASSASSIN_CURRENT_SPEED), state.speed, u.speed))
    epsilon = _per_team(h.epsilon, team)
    threshold = jnp.where(healer, _per_team(h.healer_aggressive_threshold, team),
                          _per_team(h.aggressive_threshold, team))
    step_angle = params.physics.turn_rate * params.physics.dt

    # 1. Candidates: what the unit sees, alive, not itself.
    rel = pairwise_offsets(position)  # rel[i, j] = p_j - p_i
    same_team = team[:, None] == team[None, :]
    seen = state.visible & state.alive[None, :] & ~jnp.eye(n, dtype=bool)
    allies_seen = seen & same_team
    injured = allies_seen & (state.health < u.max_health - 1e-6)[None, :]
    healer_set = jnp.where(jnp.any(injured, -1, keepdims=True), injured, allies_seen)
    candidates = jnp.where(healer[:, None], healer_set, seen & ~same_team)
    has_target = jnp.any(candidates, -1)
    lowest_hp = jnp.min(jnp.where(candidates, u.max_health[None, :], jnp.inf), -1)
    weakest = u.max_health[None, :] <= lowest_hp[:, None] + ASSASSIN_HP_TOLERANCE
    choosable = jnp.where((assassin & ~healer)[:, None], candidates & weakest, candidates)

    # 2. Move points and the target: behind (assassins), on (healers), in front (others).
    side = jnp.where(assassin, -1.0, jnp.where(healer, 0.0, 1.0))
    reach = (u.radius[None, :] + u.radius[:, None]) * side[:, None]  # (N, N)
    move_point = rel + state.facing[None, :, :] * reach[..., None]
    chosen_index, _, _ = row_argmin(jnp.sum(move_point**2, -1), choosable)
    chosen = index_one_hot(chosen_index, n)  # (N, N)
    # Everything read at the chosen target in one row selection (one reduction, not four).
    picked = pick_row(jnp.concatenate(
        [move_point, rel, jnp.broadcast_to(u.radius[None, :, None], (n, n, 1)),
         state.attackable[..., None].astype(jnp.float32)], -1), chosen)  # (N, 6)
    target_move, target_rel = picked[:, 0:2], picked[:, 2:4]
    target_radius, target_attackable = picked[:, 4], picked[:, 5] > 0.5

    # 3a. Attack: a candidate is attackable now and the cooldown is ready. The reference's unit
    # reads its cooldown from its observation, a step old: it attacks one step after the attack
    # is ready (a king, cooldown 2.5 s at dt 0.5, every 6 steps instead of 5).
    late = jnp.where(reference(profiles.OBSERVED_COOLDOWN), params.physics.dt, 0.0)
    ready = cooldown_ready(state.cooldown - late, u.cooldown)
    attack = jnp.any(candidates & state.attackable, -1) & ready

    # 3b. Turn to engage: would the turns that face the target bring it into the hurtbox?
    # Angles relative to the heading come from the target's coordinates in the unit's frame
    # (the state's facing vector), with polynomial atan2/sin/cos (tabx.geometry): XLA:CPU's
    # own are scalar code, and were most of this policy's time.
    target_x, target_y = _in_frame(target_rel, state.facing)
    angle = atan2(target_y, target_x)  # the target's bearing from the heading
    turns = jnp.rint(angle / step_angle)
    sin_k, cos_k = sincos(turns * step_angle)
    local_x = cos_k * target_x + sin_k * target_y  # in the frame after those turns
    local_y = -sin_k * target_x + cos_k * target_y
    # The reference predicts with the sight angle as the observation stores it (angle / 2 pi)
    # and its own radius for the target's (a tenth of it squared for melee units).
    reference_turn = reference(profiles.TURN_PREDICTION)
    sight_sin, sight_cos = sincos(u.sight_angle / (4.0 * jnp.pi))
    half_cos = jnp.where(reference_turn, sight_cos, state.half_sight[:, 0])
    half_sin = jnp.where(reference_turn, sight_sin, state.half_sight[:, 1])
    reach2 = jnp.where(reference_turn, jnp.where(ranger, 1.0, 0.1) * u.radius**2,
                       target_radius**2)
    x0 = u.radius * half_cos
    gap_x = jnp.maximum(jnp.maximum(x0 - local_x, local_x - (x0 + u.attack_range)), 0.0)
    gap_y = jnp.maximum(jnp.abs(local_y) - u.radius * half_sin, 0.0)
    would_hit = gap_x**2 + gap_y**2 < reach2
    # No whole turn step faces the target better: the heading stays (the reference turns).
    turning = (turns != 0) | reference(profiles.TURN_IN_PLACE)
    rotate = has_target & ~target_attackable & would_hit & turning

    # 3c. Kite: a ranger retreats from the nearest candidate inside range x threshold. The
    # reference measures the distance to each candidate's move point and steps back along the
    # axis of the move toward its target's. (Selecting the offsets, not the distances, keeps
    # XLA from computing the move points' distances in a kernel of their own.)
    reference_kite = reference(profiles.KITE_MOVE_POINT)
    threat_rel = jnp.where(reference_kite, move_point, rel)
    dist2 = jnp.sum(threat_rel * threat_rel, -1)
    threat_index, _, threatened = row_argmin(dist2, candidates)
    threat = index_one_hot(threat_index, n)
    threat_at = pick_row(jnp.concatenate([dist2[..., None], rel], -1), threat)  # (N, 3)
    kite = ranger & threatened & (threat_at[:, 0] < (u.attack_range * threshold) ** 2)
    kite_move = _toward(-jnp.where(reference_kite, target_move, threat_at[:, 1:]))

    # 3d-e. Pursue the remembered spot: face it, then move to it. The memory is forgotten once
    # the unit is within one move of the spot on both axes, or a visible corpse lies on it. The
    # reference's radius is sqrt(2) dt whatever the speed, and it still pursues on the step it
    # reaches the spot (a corpse there stops the pursuit at once in both).
    reference_memory = reference(profiles.MEMORY_REACH)
    memory_rel = state.memory_position - position
    step_len = jnp.where(reference_memory, 1.0, u.speed) * params.physics.dt
    reached = jnp.sum(memory_rel**2, -1) < 2.0 * step_len**2
    corpse = state.visible & (u.active.astype(bool) & ~state.alive)[None, :]
    to_spot = position[None, :, :] - state.memory_position[:, None, :]  # (N, N, 2)
    on_spot = jnp.sum(to_spot**2, -1) <= jnp.square(u.radius)[None, :]
    corpse_on_spot = jnp.any(corpse & on_spot, -1)
    forget = reached | corpse_on_spot
    keep_memory = state.memory_valid & ~forget
    pursuing = jnp.where(reference_memory, state.memory_valid & ~corpse_on_spot, keep_memory)
    memory_angle = atan2(*_in_frame(memory_rel, state.facing)[::-1])
    pursue = jnp.where(jnp.abs(memory_angle) <= step_angle, _toward(memory_rel),
                       _turn_toward(memory_angle))

    # 3f. Rangers seek the nearest bush they are not in (a config without zone slots has none).
    if z.zone_type.shape[-1] > 0:
        bush = z.zone_type == C.ZONE_BUSH
        bush_rel = z.centre[None, :, :] - position[:, None, :]  # (N, Z, 2)
        bush_index, _, _ = row_argmin(jnp.sum(bush_rel**2, -1),
                                      jnp.broadcast_to(bush[None, :], (n, bush.shape[0])))
        # The choice computed once (`materialise`): XLA would otherwise re-derive the row
        # minimum inside every element of the selection below.
        bush_index = materialise(bush_index.astype(jnp.float32)[:, None])[:, 0]
        nearest_bush = index_one_hot(bush_index.astype(jnp.int32), bush.shape[0])
        nearest = pick_row(jnp.concatenate(
            [bush_rel, jnp.broadcast_to(z.semi_axes[None], bush_rel.shape)], -1), nearest_bush)
        in_bush = jnp.where(
            reference(profiles.BUSH_BOX),  # the reference: the nearest bush's bounding box
            jnp.all(jnp.abs(nearest[:, :2]) < nearest[:, 2:], -1),
            jnp.any(in_ellipses(position, z.centre, z.semi_axes, z.zone_type) & bush[None, :],
                    -1))
        seek_bush = ranger & jnp.any(bush) & ~in_bush
        bush_move = _toward(nearest[:, :2])
    else:
        seek_bush, bush_move = jnp.zeros(n, bool), jnp.zeros(n, jnp.int32)

    # Randomness: one 32-bit draw per unit split into the epsilon draw (12 bits), the random
    # action (10 bits) and the search reversal (10 bits): a third of the threefry work.
    draw_epsilon = (bits >> 20).astype(jnp.float32) / 4096.0
    draw_action = ((bits >> 10) & 0x3FF).astype(jnp.float32) / 1024.0
    draw_reverse = (bits & 0x3FF).astype(jnp.float32) / 1024.0
    reverse = (draw_reverse < SEARCH_REVERSE_PROB) & ~reference(profiles.SEARCH_RIGHT)
    search_turn = jnp.where(reverse, C.TURN_LEFT + C.TURN_RIGHT - state.search_turn,
                            state.search_turn).astype(jnp.int32)

    action = search_turn
    action = jnp.where(seek_bush, bush_move, action)
    action = jnp.where(pursuing, pursue, action)
    action = jnp.where(has_target, _toward(target_move), action)
    action = jnp.where(has_target & kite, kite_move, action)
    action = jnp.where(rotate, _turn_toward(angle), action)
    action = jnp.where(attack, C.ATTACK, action)

    # 4. Epsilon override with a uniform legal action (the reference: one of the 6 moves and
    # turns, never ATTACK or IDLE); the dead and padding idle.
    mask = action_mask(state, params)
    move_or_turn = jnp.minimum(jnp.floor(draw_action * 6.0), 5.0).astype(jnp.int32)
    move_or_turn = move_or_turn + (move_or_turn >= C.ATTACK)  # 0-3 moves, 5-6 turns
    random_action = jnp.where(reference(profiles.EPSILON_MOVES), move_or_turn,
                              pick_legal(draw_action, mask))
    action = jnp.where(draw_epsilon < epsilon, random_action, action)
    action = jnp.where(state.alive, action, C.IDLE).astype(jnp.int32)

    # Memory: the chosen target's position while it is seen (the reference forgets a reached
    # spot even then, and remembers the new one from the next sighting).
    memory_valid = jnp.where(reference_memory, (has_target | state.memory_valid) & ~forget,
                             has_target | keep_memory)
    memory_position = jnp.where(has_target[:, None], position + target_rel,
                                state.memory_position)
    memory_valid = memory_valid & state.alive
    new_state = state.replace(memory_position=memory_position, memory_valid=memory_valid,
                              search_turn=search_turn)
    return action, new_state


__all__ = ["heuristic_actions", "heuristic_actions_from_bits", "unit_roles",
           "SEARCH_REVERSE_PROB"]

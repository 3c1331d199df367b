"""`TabxEnv`: the TABX battle as pure functions over (EnvState, EnvParams), array API.

One step, in order (the reference's, with the differences listed in docs/differences.md;
the level's profile (`tabx.profiles`) restores the reference's choices):
1. motion: Euler with the velocity set by the previous action, wall damage and clipping,
   one simultaneous collision pass, clipping again;
2. actions of every unit slot: moves set the next velocity, turns rotate now, ATTACK hits the
   nearest attackable unit chosen at the end of the previous step (what the observation showed);
3. zones: lava damage, swamp speed for the next move;
4. all health changes summed and clamped at once; units at 0 health die (for good);
5. geometry for the next step: field of view, bush rules, hurtboxes, nearest targets;
6. team health ratios, reward, termination on the step the last unit of a team dies,
   truncation at `max_steps`.

Only `EnvConfig` is static: every level with the same config runs through the same compiled
step. A finished episode is frozen: stepping it again changes nothing and pays nothing.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from tabx import constants as C
from tabx.combat import attackable_pairs, nearest_targets, resolve_attacks
from tabx.geometry import facing, field_of_view, in_ellipses, pairwise_offsets, view_trig
from tabx.observe import action_mask, cooldown_ready, observe, pick_legal, world_state
from tabx.params import EnvConfig, EnvParams
from tabx.physics import integrate, resolve_collisions, wall_contact
from tabx.profiles import CORPSE_DRIFT, CORPSE_VISION, OBSERVED_COOLDOWN, reference_choice
from tabx.reward import dense_reward, team_hp_ratio, winner_mask
from tabx.rng import random_words, to_unit_float
from tabx.selection import materialise
from tabx.starts import randomise_start
from tabx.state import EnvState
from tabx.zones import apply_bush_hiding, bush_hidden, lava_damage, swamp_speed

# A host array, made a device constant where a step is traced: an import starts no JAX backend
# (XLA_FLAGS must still be settable after `import tabx`).
_ACTION_TABLE = np.asarray(C.ACTION_TABLE, np.float32)

Info = dict[str, jax.Array]


class TabxEnv:
    """The battle simulator for one static `EnvConfig`; vmap its methods over envs."""

    def __init__(self, config: EnvConfig):
        self.config = config

    # --- public API --------------------------------------------------------------------------

    @property
    def num_units(self) -> int:
        return self.config.num_units

    @property
    def num_actions(self) -> int:
        return C.NUM_ACTIONS

    def reset(self, key: jax.Array, params: EnvParams) -> tuple[jax.Array, EnvState]:
        """(obs (N, obs_size), state) at the start of the level. The key draws the start
        positions where the level randomises them (`start_noise`, `shuffle_positions`;
        `tabx.starts`); otherwise the start is the level's own, whatever the key."""
        state = self.start_state(key, params)
        return self.observe(state, params), state

    def start_state(self, key: jax.Array, params: EnvParams) -> EnvState:
        """The start state of a level, with its randomised starts drawn from `key`."""
        return self.initial_state(randomise_start(key, params))

    def step(self, key: jax.Array, state: EnvState, actions: jax.Array, params: EnvParams
             ) -> tuple[jax.Array, EnvState, jax.Array, jax.Array, Info]:
        """One step for every unit slot. actions: int (N,). Returns (obs, state, reward (2,)
        per team, done, info). Stepping a finished episode returns it unchanged, reward 0."""
        del key
        advanced, interacted, inside, reward, info = self._advance(state, actions, params)
        new_state = self._refresh_geometry(advanced, params, interacted, inside)
        frozen = state.done
        new_state = jax.tree.map(lambda old, new: jnp.where(frozen, old, new), state, new_state)
        reward = jnp.where(frozen, 0.0, reward)
        info = jax.tree.map(lambda x: jnp.where(frozen, jnp.zeros_like(x), x), info)
        return self.observe(new_state, params), new_state, reward, new_state.done, info

    def step_autoreset(self, key: jax.Array, state: EnvState, actions: jax.Array,
                       params: EnvParams, reset_state: EnvState,
                       reset_params: EnvParams | None = None
                       ) -> tuple[jax.Array, EnvState, jax.Array, jax.Array, Info]:
        """Step; where the episode ends, continue from `reset_state` (the start state of
        `reset_params`, default the same level, from `initial_state`). Reward, done and info
        belong to the step that ended; obs and state are the reset ones (JaxMARL semantics).
        Passing the start state in, rather than recomputing it, makes the reset a select."""
        del key
        advanced, interacted, inside, reward, info = self._advance(state, actions, params)
        stepped = self._refresh_geometry(advanced, params, interacted, inside)
        done = advanced.done
        new_state = jax.tree.map(lambda s, r: jnp.where(done, r, s), stepped, reset_state)
        obs_params = params if reset_params is None else jax.tree.map(
            lambda p, r: jnp.where(done, r, p), params, reset_params)
        return self.observe(new_state, obs_params), new_state, reward, done, info

    def initial_state(self, params: EnvParams) -> EnvState:
        fields, inside = self._initial_fields(params)
        return self._refresh_geometry(fields, params, jnp.zeros_like(fields.visible), inside)

    def observe(self, state: EnvState, params: EnvParams) -> jax.Array:
        return observe(self.config, state, params)

    def world_state(self, state: EnvState, params: EnvParams) -> jax.Array:
        return world_state(self.config, state, params)

    def action_mask(self, state: EnvState, params: EnvParams) -> jax.Array:
        return action_mask(state, params)

    # --- internals ---------------------------------------------------------------------------

    def _initial_fields(self, params: EnvParams) -> tuple[EnvState, jax.Array]:
        """Start-of-episode state with empty geometry, and zone membership."""
        u, z, ph = params.units, params.zones, params.physics
        n = self.config.num_units
        active = u.active.astype(bool)
        health = jnp.where(active, jnp.clip(u.health, 0.0, u.max_health), 0.0)
        alive = active & (health > 0)
        position = wall_contact(u.position, u.radius, ph.arena_size)[0]
        inside = in_ellipses(position, z.centre, z.semi_axes, z.zone_type)
        heading = jnp.mod(u.heading, 2 * jnp.pi)
        facing_vec, half_sight = facing(heading, u.sight_angle)
        state = EnvState(
            position=position,
            velocity=jnp.zeros((n, 2), jnp.float32),
            heading=heading,
            facing=facing_vec,
            half_sight=half_sight,
            health=health,
            alive=alive,
            # Seconds since the last attack as the first action sees it (the reference starts
            # at 0 and adds dt before acting): an archer (cooldown 8, dt 0.5) shoots at step 16.
            cooldown=jnp.clip(jnp.broadcast_to(ph.dt, (n,)), 0.0, cooldown_cap(params)),
            speed=swamp_speed(inside, z.zone_type, z.effect, u.speed),
            visible=jnp.zeros((n, n), bool),
            attackable=jnp.zeros((n, n), bool),
            target=jnp.zeros(n, jnp.int32),
            has_target=jnp.zeros(n, bool),
            hp_ratio=team_hp_ratio(health, u.max_health, u.team, active, params.reward_mode),
            step=jnp.zeros((), jnp.int32),
            done=jnp.zeros((), bool),
            won=jnp.zeros(C.NUM_TEAMS, bool),
            memory_position=jnp.zeros((n, 2), jnp.float32),
            memory_valid=jnp.zeros(n, bool),
            search_turn=jnp.full((n,), C.TURN_RIGHT, jnp.int32),
        )
        return state, inside

    def _advance(self, state: EnvState, actions: jax.Array, params: EnvParams
                 ) -> tuple[EnvState, jax.Array, jax.Array, jax.Array, Info]:
        """Dynamics of one step, up to but excluding the next step's geometry."""
        u, z, ph = params.units, params.zones, params.physics
        dt = ph.dt
        able = state.alive

        # 1. Motion: last action's velocity, wall, collisions (corpses collide, padding not).
        position = integrate(state.position, state.velocity, dt)
        position, touching = wall_contact(position, u.radius, ph.arena_size)
        wall_loss = jnp.where(touching & able, ph.boundary_damage_rate * u.max_health * dt, 0.0)
        position, _ = resolve_collisions(position, state.velocity, u.radius, u.mass,
                                         u.active.astype(bool), ph.restitution, ph.slop,
                                         ph.percent)
        position = wall_contact(position, u.radius, ph.arena_size)[0]

        # 2. Actions. Materialised: XLA would otherwise fuse a policy's whole per-unit
        # computation (the scripted policy, say) into every (N, N) consumer downstream.
        action = materialise_actions(actions)
        attacking = (action == C.ATTACK) & cooldown_ready(state.cooldown, u.cooldown) & able
        attack_loss, hit, interacted = resolve_attacks(attacking, state.has_target,
                                                       state.target, u.damage)
        table = jnp.asarray(_ACTION_TABLE)[action]
        velocity = table[:, :2] * jnp.where(able, state.speed, 0.0)[:, None]
        turn = table[:, 2] * able  # -1 right, +1 left, 0 none
        step_angle = ph.turn_rate * dt
        heading = jnp.mod(state.heading + turn * step_angle, 2 * jnp.pi)
        # Rotate the facing vector by the same angle (one cos/sin per env, not per unit), and
        # renormalise so that rounding never accumulates over an episode.
        cos_t = jnp.where(turn != 0, jnp.cos(step_angle), 1.0)
        sin_t = turn * jnp.sin(step_angle)
        fx, fy = state.facing[:, 0], state.facing[:, 1]
        rotated = jnp.stack([fx * cos_t - fy * sin_t, fy * cos_t + fx * sin_t], -1)
        facing_vec = rotated * jax.lax.rsqrt(jnp.sum(rotated * rotated, -1, keepdims=True))
        # A whiffed attack still spends the cooldown (reference behaviour).
        cooldown = jnp.clip(jnp.where(attacking, 0.0, state.cooldown) + dt, 0.0,
                            cooldown_cap(params))

        # 3. Zones at the new positions.
        inside = in_ellipses(position, z.centre, z.semi_axes, z.zone_type)
        lava_loss = jnp.where(able, lava_damage(inside, z.zone_type, z.effect, dt), 0.0)
        speed = swamp_speed(inside, z.zone_type, z.effect, u.speed)

        # 4. Health: every change of the step at once; the dead stay dead.
        health = jnp.clip(state.health - wall_loss - attack_loss - lava_loss, 0.0, u.max_health)
        health = jnp.where(able, health, state.health)
        alive = able & (health > 0)
        # A unit that dies this step does not drift on with the move it chose; the reference's
        # corpse moves once more (profile choice CORPSE_DRIFT).
        drifts = alive | (able & reference_choice(params, CORPSE_DRIFT))
        velocity = jnp.where(drifts[:, None], velocity, 0.0)

        # 6. Outcome.
        active = u.active.astype(bool)
        hp_ratio = team_hp_ratio(health, u.max_health, u.team, active, params.reward_mode)
        reward = dense_reward(hp_ratio, state.hp_ratio)
        members = u.team[None, :] == jnp.arange(C.NUM_TEAMS)[:, None]  # (2, N)
        eliminated = jnp.any(~jnp.any(members & alive[None, :], axis=-1))
        step = state.step + 1
        truncated = step >= self.config.max_steps
        done = eliminated | truncated
        won = winner_mask(hp_ratio) & done
        terminal = jnp.where(won, self.config.win_reward, self.config.lose_reward)
        reward = reward + jnp.where(done, terminal, 0.0)

        advanced = state.replace(
            position=position, velocity=velocity, heading=heading, facing=facing_vec,
            health=health, alive=alive,
            cooldown=cooldown, speed=speed, hp_ratio=hp_ratio, step=step, done=done, won=won)
        info = {
            "attacking": attacking,
            "hit": hit,
            "damage_dealt": jnp.where(hit, u.damage, 0.0),
            "won": won,
            "terminated": eliminated,
            "truncated": truncated & ~eliminated,
            "dead_units": jnp.sum(members & (active & ~alive)[None, :], -1),
        }
        return advanced, interacted, inside, reward, info

    def _refresh_geometry(self, state: EnvState, params: EnvParams, interacted: jax.Array,
                          inside: jax.Array) -> EnvState:
        """Visibility, hurtbox reach and nearest targets for the state's positions."""
        u, z = params.units, params.zones
        n = self.config.num_units
        active = u.active.astype(bool)
        # Per-unit inputs computed once (positions after collisions, health after damage), not
        # inside each element of the (N, N) tests; the view trigonometry with them.
        unit = materialise(jnp.concatenate(
            [state.position, state.alive[:, None].astype(jnp.float32),
             view_trig(state.facing, state.half_sight)], -1))
        rel = pairwise_offsets(unit[:, :2])
        alive = unit[:, 2] > 0.5
        trig = unit[:, 3:]
        fov = field_of_view(rel, trig, u.radius) & active[None, :]
        attackable = attackable_pairs(rel, trig, u.radius, u.attack_range, u.team,
                                      u.heals.astype(bool), alive)
        # Who shares what it sees in a bush: the living; in the reference also the dead
        # (profile choice CORPSE_VISION).
        sharing = jnp.where(reference_choice(params, CORPSE_VISION), active, state.alive)
        hidden = bush_hidden(inside, z.zone_type, u.team, sharing, interacted)  # (2, N)
        # The pairwise tests and the bush rule computed once, packed as small integers in one
        # (N + 2, N) matrix: XLA would otherwise re-derive them inside each of visible,
        # attackable, target and has_target (and the auto-reset select of each).
        code = materialise(jnp.concatenate(
            [fov.astype(jnp.float32) + 2.0 * attackable, hidden.astype(jnp.float32)], 0))
        attackable = code[:n] >= 1.5
        fov = (code[:n] == 1.0) | (code[:n] == 3.0)
        visible = apply_bush_hiding(fov, u.team, code[n:] > 0.5)
        target, has_target = nearest_targets(rel, attackable)
        return state.replace(visible=visible, attackable=attackable, target=target,
                             has_target=has_target)


def cooldown_cap(params: EnvParams) -> jax.Array:
    """(N,) the most `EnvState.cooldown` holds: the attack cooldown, or one dt more where the
    level plays the reference's OBSERVED_COOLDOWN. The reference caps its clock at the cooldown
    before adding the step's dt, and its scripted units read the value a step old, so they must
    tell "ready since the last step" from "ready now" (tabx.heuristic). Readiness and the
    observation read the clock capped at the cooldown either way."""
    u = params.units
    return u.cooldown + jnp.where(reference_choice(params, OBSERVED_COOLDOWN),
                                  params.physics.dt, 0.0)


def materialise_actions(actions: jax.Array) -> jax.Array:
    """Actions clipped to the valid range, computed once. XLA on CPU drops optimization
    barriers before fusing, and fuses a policy's whole per-unit computation (the scripted
    policy's, say) into every element of whatever consumes it: into each (N, N) geometry element
    (N times the work) or each slot of a one-hot (8 times). A matrix product is never fused with
    its operands, so multiplying by the identity makes XLA compute the actions once (exact for
    these small integers)."""
    ids = jnp.clip(actions.astype(jnp.int32), 0, C.NUM_ACTIONS - 1).astype(jnp.float32)
    identity = jnp.eye(ids.shape[-1], dtype=jnp.float32)
    product = jnp.matmul(ids, identity, precision=jax.lax.Precision.HIGHEST)
    return jnp.rint(product).astype(jnp.int32)


def random_legal_actions(key: jax.Array, mask: jax.Array) -> jax.Array:
    """Uniform random legal action per unit slot from a (..., 8) bool mask. One threefry word
    per call, spread over the unit slots by a hash (tabx.rng): threefry runs as a rolled loop
    of small kernels on CPU, a large part of a random-action step."""
    return pick_legal(to_unit_float(random_words(key, mask.shape[:-1])), mask)

"""UED level generation and ACCEL mutation: `LevelSpace` (the `levels:` config section),
`LevelGenerator` (jitted `sample` and `mutate`) and `validate_level`.

A generated level is a base scenario level (`EnvParams`, padded to one `EnvConfig`) with its
*free parameters* resampled:

- `health`, `speed`, `damage` (`unit_spec` = all three): per real unit, independently; padded
  slots are never touched; healers stay healers (negative damage, `heals` kept) and damage
  dealers stay damage dealers; max health is resampled and the initial health keeps the base's
  initial fraction of it.
- `zone`: every zone slot in use (the base's count, or a count drawn from `zone_count`): type
  from `zone_types`, centre anywhere in the arena (at least `zone_margin` inside each wall; the
  ellipse itself may cross a wall), both semi-axes from `zone_semi_axes`, effect in the type's
  range (lava HP/s, swamp slow fraction, bush 0).
- `heuristic`: epsilon and aggressive threshold of both teams.
- `physics`: restitution, boundary damage rate and turn rate.

ACCEL mutation applies `num_edits` edits per level, each drawn uniformly from the edits that
apply: parameter perturbation (independent uniform noise on every free continuous parameter,
`noise` x the parameter's range, clipped to the range), semi-axis swap of one zone, re-typing of
one zone (effect rescaled into the new type's range). Everything is a pure JAX function of
(key, level): one compile per batch size, no recompilation on later calls. See docs/levels.md.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from dataclasses import asdict, dataclass
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from tabx import constants as C
from tabx.params import EnvConfig, EnvParams
from tabx.rng import fmix32, random_words, to_unit_float
from tabx.scenarios.format import (
    HEURISTIC_RANGES,
    MAX_ZONES,
    PHYSICS_RANGES,
    SEMI_AXIS_RANGE,
    UNIT_STAT_RANGES,
    ZONE_EFFECT_RANGES,
    ZONE_TYPES,
    Range,
    ScenarioError,
    level_to_scenario,
)
from ued.errors import ConfigError
from ued.errors import check as _check

UNIT_SPEC_PARAMS = ("health", "speed", "damage")
FREE_PARAMS = (*UNIT_SPEC_PARAMS, "zone", "heuristic", "physics")
FREE_NAMES = (*FREE_PARAMS, "unit_spec")  # unit_spec = health + speed + damage
PHYSICS_FREE = ("restitution", "boundary_damage_rate", "turn_rate")
HEURISTIC_FREE = ("epsilon", "aggressive_threshold")
EDITS = ("perturb", "swap_axes", "retype")

# Physical bounds of each range field of LevelSpace (the scenario validator's ranges).
RANGE_BOUNDS: dict[str, Range] = {
    "health": UNIT_STAT_RANGES["max_health"],
    "speed": UNIT_STAT_RANGES["speed"],
    "damage": Range(0.0, UNIT_STAT_RANGES["damage"].hi),
    "heal": Range(0.0, -UNIT_STAT_RANGES["damage"].lo),
    "zone_semi_axes": SEMI_AXIS_RANGE,
    "lava_effect": ZONE_EFFECT_RANGES["lava"],
    "swamp_effect": Range(0.0, 1.0, hi_open=True),  # 1 would freeze units in the swamp
    "epsilon": HEURISTIC_RANGES["epsilon"],
    "aggressive_threshold": HEURISTIC_RANGES["aggressive_threshold"],
    **{name: PHYSICS_RANGES[name] for name in PHYSICS_FREE},
}


@dataclass(frozen=True)
class LevelSpace:
    """The `levels:` section of a UED config: which free parameters vary and their ranges.

    Every range is a `(min, max)` pair, sampled uniformly. See docs/levels.md.
    """

    free: tuple[str, ...] = ("zone",)  # health, speed, damage, unit_spec (= the three), zone,
    #                                    heuristic, physics
    health: tuple[float, ...] = (25.0, 685.0)  # max health (initial health keeps its fraction)
    speed: tuple[float, ...] = (0.5, 1.4)  # world units per second
    damage: tuple[float, ...] = (10.0, 80.0)  # per hit, damage dealers (positive)
    heal: tuple[float, ...] = (3.0, 10.0)  # per hit, healers (magnitude; stored as -heal)
    zone_types: tuple[str, ...] = ("lava", "bush", "swamp")
    zone_count: tuple[int, ...] | None = None  # None: the base's count; (lo, hi): uniform
    zone_semi_axes: tuple[float, ...] = (2.0, 10.0)  # both semi-axes
    zone_margin: float = 0.0  # zone centres at least this far inside each wall
    lava_effect: tuple[float, ...] = (2.0, 20.0)  # health lost per second
    swamp_effect: tuple[float, ...] = (0.1, 0.8)  # slow fraction: speed x (1 - effect)
    epsilon: tuple[float, ...] = (0.0, 1.0)  # heuristic random-action probability, both teams
    aggressive_threshold: tuple[float, ...] = (0.0, 1.0)  # heuristic ranger kiting, both teams
    restitution: tuple[float, ...] = (0.5, 1.0)
    boundary_damage_rate: tuple[float, ...] = (0.05, 0.2)  # fraction of max health per second
    turn_rate: tuple[float, ...] = (math.pi / 12, math.pi / 3)  # radians per second
    num_edits: int = 3  # ACCEL edits per mutation
    noise: float = 0.1  # perturbation noise as a fraction of each parameter's range

    @property
    def free_params(self) -> frozenset[str]:
        """The free parameters with `unit_spec` expanded to health, speed and damage."""
        out: set[str] = set()
        for name in self.free:
            out.update(UNIT_SPEC_PARAMS if name == "unit_spec" else (name,))
        return frozenset(out)

    def validate(self, prefix: str = "levels") -> LevelSpace:
        """Check every field; raises ConfigError naming `prefix.field`."""
        _check_names(self.free, FREE_NAMES, f"{prefix}.free", "free parameter")
        for name, bounds in RANGE_BOUNDS.items():
            _check_range(getattr(self, name), bounds, f"{prefix}.{name}")
        key = f"{prefix}.zone_types"
        _check_names(self.zone_types, ZONE_TYPES, key, "zone type")
        _check(len(set(self.zone_types)) == len(self.zone_types), key,
               f"lists a zone type twice: {list(self.zone_types)}")
        key = f"{prefix}.zone_count"
        if self.zone_count is not None:
            count = self.zone_count
            _check(isinstance(count, tuple | list) and len(count) == 2
                   and all(isinstance(c, int | np.integer) and not isinstance(c, bool)
                           for c in count), key,
                   f"expected null (the base level's count) or [min, max] integers, got {count!r}")
            _check(0 <= count[0] <= count[1] <= MAX_ZONES, key,
                   f"expected 0 <= min <= max <= {MAX_ZONES}, got {list(count)}")
        _check(_is_number(self.zone_margin) and 0.0 <= self.zone_margin <= 1000.0,
               f"{prefix}.zone_margin", f"must be a number in [0, 1000], got {self.zone_margin!r}")
        _check(isinstance(self.num_edits, int | np.integer) and not isinstance(self.num_edits, bool)
               and 0 <= self.num_edits <= 1000, f"{prefix}.num_edits",
               f"must be an integer in [0, 1000], got {self.num_edits!r}")
        _check(_is_number(self.noise) and 0.0 <= self.noise <= 1.0, f"{prefix}.noise",
               f"must be a number in [0, 1] (a fraction of each range), got {self.noise!r}")
        return self

    def to_dict(self) -> dict[str, Any]:
        """Plain lists and numbers (YAML-safe: PyYAML's safe dumper cannot write tuples)."""
        return {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(self).items()}


def _is_number(x: Any) -> bool:
    return (isinstance(x, int | float | np.integer | np.floating) and not isinstance(x, bool)
            and math.isfinite(float(x)))


def _check_names(values: Any, allowed: tuple[str, ...], key: str, what: str) -> None:
    """`values` is a non-empty list of names out of `allowed` (ConfigError naming `key`)."""
    choices = ", ".join(allowed)
    _check(isinstance(values, tuple | list) and len(values) > 0, key,
           f"needs at least one {what} out of {choices}")
    for name in values:
        _check(isinstance(name, str) and name in allowed, key,
               f"unknown {what} {name!r}; expected some of {choices}")


def _check_range(value: Any, bounds: Range, key: str) -> None:
    _check(isinstance(value, tuple | list) and len(value) == 2 and all(_is_number(v)
                                                                        for v in value), key,
           f"expected a [min, max] pair of numbers, got {value!r}")
    lo, hi = float(value[0]), float(value[1])
    _check(lo <= hi, key, f"min {lo:g} exceeds max {hi:g}")
    _check(bounds.contains(lo) and bounds.contains(hi), key,
           f"expected both ends in {bounds}, got [{lo:g}, {hi:g}]")


def _f32_range(lo: float, hi: float, bounds: Range) -> tuple[float, float]:
    """[lo, hi] in float32 (nearest), moved one float32 step inwards where rounding would
    leave the validator's physical bounds (e.g. a turn rate of exactly 2 pi), positive
    subnormals raised to the smallest normal float32."""
    lo32, hi32 = np.float32(lo), np.float32(hi)
    # XLA on CPU flushes float32 subnormals to zero: lift positive ones to the smallest normal.
    tiny = np.finfo(np.float32).tiny
    lo32 = tiny if 0 < lo32 < tiny else lo32
    hi32 = tiny if 0 < hi32 < tiny else hi32
    if not bounds.contains(float(lo32)):
        lo32 = np.nextafter(lo32, np.float32(np.inf))
    if not bounds.contains(float(hi32)):
        hi32 = np.nextafter(hi32, np.float32(-np.inf))
    return float(lo32), float(max(lo32, hi32))


def _tree_where(cond: jax.Array, a: Any, b: Any) -> Any:
    return jax.tree.map(lambda x, y: jnp.where(cond, x, y), a, b)


class LevelGenerator:
    """Fresh levels (`sample`) and ACCEL mutations (`mutate`) in a `LevelSpace`, from a batch
    of base levels padded to `env_config`. Both are jitted: one compile per batch size, shared
    by every generator of the same (EnvConfig, LevelSpace) and number of base levels."""

    def __init__(self, env_config: EnvConfig, base_levels: EnvParams, space: LevelSpace):
        space = dataclasses.replace(space, **{  # lists (from code) as tuples: hashable
            f.name: tuple(getattr(space, f.name)) for f in dataclasses.fields(space)
            if isinstance(getattr(space, f.name), list)}).validate()
        self.env_config, self.space = env_config, space
        base = jax.tree.map(jnp.asarray, base_levels)
        if base.reward_mode.ndim == 0:  # one level: a batch of one
            base = jax.tree.map(lambda x: x[None], base)
        if base.reward_mode.ndim != 1 or base.reward_mode.shape[0] < 1:
            raise ValueError("base_levels must be a stacked batch of levels (leading axis >= 1)")
        n, z = base.units.active.shape[-1], base.zones.zone_type.shape[-1]
        if (n, z) != (env_config.num_units, env_config.max_zones):
            raise ValueError(f"base_levels have {n} unit slots and {z} zone slots, but the "
                             f"EnvConfig has {env_config.num_units} and {env_config.max_zones}: "
                             "pad the base scenarios with Scenario.to_level(env_config)")
        if space.zone_count is not None and "zone" in space.free_params:
            _check(space.zone_count[1] <= env_config.max_zones, "levels.zone_count",
                   f"max {space.zone_count[1]} exceeds the env's max_zones "
                   f"({env_config.max_zones})")
        self.base_levels = base
        self.num_base = int(base.reward_mode.shape[0])
        self._kernel = _kernel(env_config, space)
        self._sample_jit = self._kernel.sample_jit
        self._mutate_jit = self._kernel.mutate_jit

    def sample(self, key: jax.Array, n: int) -> EnvParams:
        """`n` fresh levels (leading axis n), each from a uniformly chosen base level with every
        free parameter resampled uniformly in its range."""
        if isinstance(n, bool) or not isinstance(n, int | np.integer) or n <= 0:
            raise ValueError(f"sample needs a number of levels n >= 1, got {n!r}")
        return self._sample_jit(key, self.base_levels, int(n))

    def mutate(self, key: jax.Array, levels: EnvParams) -> EnvParams:
        """ACCEL: `space.num_edits` random edits per level of a batch (or of one level)."""
        if jnp.ndim(levels.reward_mode) == 0:
            return self._kernel.mutate_single_jit(key, levels)
        return self._mutate_jit(key, levels)

    def sample_one(self, key: jax.Array, base: EnvParams) -> EnvParams:
        """The pure (unjitted) resampling of one level: for use inside other jitted code."""
        return self._kernel.resample(key, base)

    def mutate_one(self, key: jax.Array, level: EnvParams) -> EnvParams:
        """The pure (unjitted) mutation of one level: for use inside other jitted code."""
        return self._kernel.mutate(key, level)


@functools.lru_cache(maxsize=32)
def _kernel(env_config: EnvConfig, space: LevelSpace) -> _Kernel:
    return _Kernel(env_config, space)


class _Kernel:
    """The pure part of a generator (no base levels): every function of (key, level)."""

    def __init__(self, env_config: EnvConfig, space: LevelSpace):
        self.env_config, self.space = env_config, space
        self.free = space.free_params
        r = self._ranges = space_ranges(space)
        self._zone_codes = np.array([C.ZONE_TYPE_BY_NAME[t] for t in space.zone_types], np.int32)
        # Effect range per zone type code (none, lava, bush, swamp); bush and none: [0, 0].
        self._effect_lo = np.array([0.0, r["lava_effect"][0], 0.0, r["swamp_effect"][0]],
                                   np.float32)
        self._effect_hi = np.array([0.0, r["lava_effect"][1], 0.0, r["swamp_effect"][1]],
                                   np.float32)
        self.sample_jit = jax.jit(self._sample_batch, static_argnums=2)
        self.mutate_jit = jax.jit(self._mutate_batch)
        self.mutate_single_jit = jax.jit(self.mutate)

    # --- sampling ----------------------------------------------------------------------------

    def _sample_batch(self, key: jax.Array, base: EnvParams, n: int) -> EnvParams:
        seeds = random_words(key, (n + 1,))
        idx = _pick_index(_Stream(seeds[0]).uniform((n,)), base.reward_mode.shape[0])
        picked = jax.tree.map(lambda x: x[idx], base)
        return jax.vmap(lambda s, lv: self._resample(_Stream(s), lv))(seeds[1:], picked)

    def resample(self, key: jax.Array, level: EnvParams) -> EnvParams:
        """One level with every free parameter resampled (a pure function of key and level)."""
        return self._resample(_Stream.from_key(key), level)

    def _uniform(self, rng: _Stream, shape: tuple[int, ...], name: str) -> jax.Array:
        lo, hi = self._ranges[name]
        return jnp.clip(lo + rng.uniform(shape) * (hi - lo), lo, hi)

    def _resample(self, rng: _Stream, level: EnvParams) -> EnvParams:
        free = self.free
        if free & set(UNIT_SPEC_PARAMS):
            level = level.replace(units=self._resample_units(rng, level.units))
        if "zone" in free and self.env_config.max_zones > 0:
            level = level.replace(zones=self._resample_zones(rng, level))
        if "heuristic" in free:
            h = level.heuristic
            level = level.replace(heuristic=h.replace(**{
                name: self._uniform(rng, getattr(h, name).shape, name) for name in HEURISTIC_FREE}))
        if "physics" in free:
            level = level.replace(physics=level.physics.replace(**{
                name: self._uniform(rng, (), name) for name in PHYSICS_FREE}))
        return level

    def _resample_units(self, rng: _Stream, u: Any) -> Any:
        n = u.active.shape
        out = {}
        if "health" in self.free:
            out.update(self._set_max_health(u, self._uniform(rng, n, "health")))
        if "speed" in self.free:
            out["speed"] = jnp.where(u.active, self._uniform(rng, n, "speed"), u.speed)
        if "damage" in self.free:
            new = jnp.where(u.heals, -self._uniform(rng, n, "heal"),
                            self._uniform(rng, n, "damage"))
            out["damage"] = jnp.where(u.active, new, u.damage)
        return u.replace(**out)

    @staticmethod
    def _set_max_health(u: Any, new_max: jax.Array) -> dict[str, jax.Array]:
        """New max health for active units; the initial health keeps its fraction of it."""
        ratio = jnp.clip(u.health / u.max_health, 0.0, 1.0)
        health = jnp.minimum(ratio * new_max, new_max)
        return dict(max_health=jnp.where(u.active, new_max, u.max_health),
                    health=jnp.where(u.active, health, u.health))

    def _centre_bound(self, level: EnvParams) -> jax.Array:
        """(2,) largest |x|, |y| of a zone centre: half the arena less the margin (>= 0)."""
        half = level.physics.arena_size.astype(jnp.float32) / 2.0
        return jnp.maximum(half - jnp.float32(self.space.zone_margin), 0.0)

    def _effect(self, zone_type: jax.Array, fraction: jax.Array) -> jax.Array:
        lo, hi = jnp.asarray(self._effect_lo)[zone_type], jnp.asarray(self._effect_hi)[zone_type]
        return jnp.clip(lo + fraction * (hi - lo), lo, hi)

    def _resample_zones(self, rng: _Stream, level: EnvParams) -> Any:
        z = level.zones
        num = z.zone_type.shape[0]
        count = self.space.zone_count
        if count is None:
            used = z.zone_type != C.ZONE_NONE
        else:
            k = count[0] + _pick_index(rng.uniform(), count[1] - count[0] + 1)
            used = jnp.arange(num) < k
        codes = jnp.asarray(self._zone_codes)
        zone_type = codes[_pick_index(rng.uniform((num,)), codes.shape[0])]
        bound = self._centre_bound(level)
        centre = jnp.clip((2.0 * rng.uniform((num, 2)) - 1.0) * bound, -bound, bound)
        semi = self._uniform(rng, (num, 2), "zone_semi_axes")
        effect = self._effect(zone_type, rng.uniform((num,)))
        if count is None:  # unused slots stay as they are (padding)
            empty = (z.zone_type, z.centre, z.semi_axes, z.effect)
        else:  # unused slots become padding (the empty_zones values)
            empty = (jnp.zeros_like(z.zone_type), jnp.zeros_like(z.centre),
                     jnp.ones_like(z.semi_axes), jnp.zeros_like(z.effect))
        return z.replace(zone_type=jnp.where(used, zone_type, empty[0]),
                         centre=jnp.where(used[:, None], centre, empty[1]),
                         semi_axes=jnp.where(used[:, None], semi, empty[2]),
                         effect=jnp.where(used, effect, empty[3]))

    # --- mutation ----------------------------------------------------------------------------

    def _mutate_batch(self, key: jax.Array, levels: EnvParams) -> EnvParams:
        seeds = random_words(key, (levels.reward_mode.shape[0],))
        return jax.vmap(self._mutate)(seeds, levels)

    def mutate(self, key: jax.Array, level: EnvParams) -> EnvParams:
        """`num_edits` edits of one level (a pure function of key and level)."""
        return self._mutate(jax.random.bits(key, (), jnp.uint32), level)

    def _mutate(self, seed: jax.Array, level: EnvParams) -> EnvParams:
        if self.space.num_edits == 0:
            return level

        def body(lv: EnvParams, edit: jax.Array) -> tuple[EnvParams, None]:
            return self._edit(_Stream(_derive(seed, edit)), lv), None

        level, _ = jax.lax.scan(body, level, jnp.arange(self.space.num_edits, dtype=jnp.uint32))
        return level

    def _retype_candidates(self, z: Any) -> jax.Array:
        """(Z, T) allowed new types per zone: a zone in use, a type of the space, not its own."""
        codes = jnp.asarray(self._zone_codes)
        return (z.zone_type != C.ZONE_NONE)[:, None] & (codes[None, :] != z.zone_type[:, None])

    def _edit(self, rng: _Stream, level: EnvParams) -> EnvParams:
        """One edit, drawn uniformly from the edits that apply to this level (none: no-op)."""
        free = self.free
        zones = "zone" in free and self.env_config.max_zones > 0
        z = level.zones
        used = z.zone_type != C.ZONE_NONE
        can_perturb = jnp.asarray(bool(free - {"zone"}))
        if free & set(UNIT_SPEC_PARAMS):
            can_perturb = can_perturb & (jnp.any(level.units.active)
                                         | jnp.asarray(bool(free & {"heuristic", "physics"})))
        if zones:
            can_perturb = can_perturb | jnp.any(used)
        u_kind = rng.uniform()
        candidates = [self._perturb(rng, level)]
        ok = [can_perturb]
        if zones:
            swappable = used & (z.semi_axes[:, 0] != z.semi_axes[:, 1])
            candidates.append(self._swap(rng, level, swappable))
            ok.append(jnp.any(swappable))
            retypable = self._retype_candidates(z)
            candidates.append(self._retype(rng, level, retypable))
            ok.append(jnp.any(retypable))
        ok_arr = jnp.stack(ok)
        kind = jnp.where(jnp.any(ok_arr), _pick_true(u_kind, ok_arr), -1)
        out = level
        for i, cand in enumerate(candidates):
            out = _tree_where(kind == i, cand, out)
        return out

    def _noise(self, rng: _Stream, shape: tuple[int, ...], width: Any) -> jax.Array:
        return (2.0 * rng.uniform(shape) - 1.0) * (self.space.noise * width)

    def _perturbed(self, rng: _Stream, x: jax.Array, name: str) -> jax.Array:
        lo, hi = self._ranges[name]
        return jnp.clip(x + self._noise(rng, x.shape, hi - lo), lo, hi)

    def _perturb(self, rng: _Stream, level: EnvParams) -> EnvParams:
        """Independent uniform noise on every free continuous parameter, clipped to range."""
        free = self.free
        u = level.units
        out = {}
        if "health" in free:
            out.update(self._set_max_health(u, self._perturbed(rng, u.max_health, "health")))
        if "speed" in free:
            out["speed"] = jnp.where(u.active, self._perturbed(rng, u.speed, "speed"), u.speed)
        if "damage" in free:
            new = jnp.where(u.heals, -self._perturbed(rng, -u.damage, "heal"),
                            self._perturbed(rng, u.damage, "damage"))
            out["damage"] = jnp.where(u.active, new, u.damage)
        if out:
            level = level.replace(units=u.replace(**out))
        if "zone" in free and self.env_config.max_zones > 0:
            z = level.zones
            used = z.zone_type != C.ZONE_NONE
            bound = self._centre_bound(level)
            centre = jnp.clip(z.centre + self._noise(rng, z.centre.shape, 2.0 * bound),
                              -bound, bound)
            semi = self._perturbed(rng, z.semi_axes, "zone_semi_axes")
            lo = jnp.asarray(self._effect_lo)[z.zone_type]
            hi = jnp.asarray(self._effect_hi)[z.zone_type]
            effect = jnp.clip(z.effect + self._noise(rng, z.effect.shape, hi - lo), lo, hi)
            has_effect = used & ((z.zone_type == C.ZONE_LAVA) | (z.zone_type == C.ZONE_SWAMP))
            level = level.replace(zones=z.replace(
                centre=jnp.where(used[:, None], centre, z.centre),
                semi_axes=jnp.where(used[:, None], semi, z.semi_axes),
                effect=jnp.where(has_effect, effect, z.effect)))
        if "heuristic" in free:
            h = level.heuristic
            level = level.replace(heuristic=h.replace(**{
                name: self._perturbed(rng, getattr(h, name), name) for name in HEURISTIC_FREE}))
        if "physics" in free:
            ph = level.physics
            level = level.replace(physics=ph.replace(**{
                name: self._perturbed(rng, getattr(ph, name), name) for name in PHYSICS_FREE}))
        return level

    def _swap(self, rng: _Stream, level: EnvParams, swappable: jax.Array) -> EnvParams:
        """Swap the two semi-axes of one zone (a 90-degree turn of the ellipse)."""
        z = level.zones
        j = _pick_true(rng.uniform(), swappable)
        pick = (jnp.arange(swappable.shape[0]) == j) & swappable
        return level.replace(zones=z.replace(
            semi_axes=jnp.where(pick[:, None], z.semi_axes[:, ::-1], z.semi_axes)))

    def _retype(self, rng: _Stream, level: EnvParams, allowed: jax.Array) -> EnvParams:
        """Give one zone another type of the space; its effect keeps its position within the
        old type's range, mapped into the new type's (a uniform draw when coming from bush)."""
        z = level.zones
        retypable = jnp.any(allowed, -1)
        j = _pick_true(rng.uniform(), retypable)
        pick = (jnp.arange(allowed.shape[0]) == j) & retypable
        new_type = jnp.asarray(self._zone_codes)[_pick_true(rng.uniform(), allowed[j])]
        old_type = z.zone_type[j]
        lo = jnp.asarray(self._effect_lo)[old_type]
        hi = jnp.asarray(self._effect_hi)[old_type]
        span = hi - lo
        fraction = jnp.where(span > 0, (z.effect[j] - lo) / jnp.where(span > 0, span, 1.0), 0.5)
        ranged = (old_type == C.ZONE_LAVA) | (old_type == C.ZONE_SWAMP)
        fraction = jnp.where(ranged, jnp.clip(fraction, 0.0, 1.0), rng.uniform())
        effect = self._effect(new_type, fraction)
        return level.replace(zones=z.replace(
            zone_type=jnp.where(pick, new_type, z.zone_type),
            effect=jnp.where(pick, effect, z.effect)))


# --- randomness ----------------------------------------------------------------------------------
# One threefry word per level (or per edit), spread by tabx.rng's counter hash: XLA compiles a
# threefry call per jax.random draw, which made these functions several times slower to compile.

_GOLDEN = 0x9E3779B9


class _Stream:
    """Uniform float32 draws from one uint32 seed: word i = fmix32(seed + i * golden ratio),
    as in tabx.rng. A trace-time counter gives every draw fresh words."""

    def __init__(self, seed: jax.Array):
        self.seed, self.used = seed, 0

    @classmethod
    def from_key(cls, key: jax.Array) -> _Stream:
        return cls(jax.random.bits(key, (), jnp.uint32))

    def uniform(self, shape: tuple[int, ...] = ()) -> jax.Array:
        """Floats in [0, 1) (24 random bits each)."""
        count = math.prod(shape)
        counter = jnp.arange(self.used, self.used + count, dtype=jnp.uint32).reshape(shape)
        self.used += count
        return to_unit_float(fmix32(self.seed + counter * jnp.uint32(_GOLDEN)))


def _derive(seed: jax.Array, i: jax.Array) -> jax.Array:
    """An independent-looking seed for sub-stream i of `seed`."""
    return fmix32(seed ^ fmix32(i * jnp.uint32(0x85EBCA77) + jnp.uint32(0x68E31DA4)))


def _pick_index(u: jax.Array, n: int) -> jax.Array:
    """A uniform integer in [0, n) from u in [0, 1)."""
    return jnp.minimum(jnp.floor(u * n).astype(jnp.int32), n - 1)


def _pick_true(u: jax.Array, mask: jax.Array) -> jax.Array:
    """A uniformly chosen index where `mask` (1-D) is True (0 if none), from u in [0, 1)."""
    count = jnp.sum(mask.astype(jnp.int32))
    k = jnp.minimum(jnp.floor(u * count).astype(jnp.int32), jnp.maximum(count - 1, 0))
    return jnp.argmax(jnp.cumsum(mask.astype(jnp.int32)) > k)


def validate_level(level: EnvParams, env_config: EnvConfig | None = None) -> None:
    """Run the scenario-file validator on a level (or on each level of a batch): round trip
    through `level_to_scenario(level).validate()`. Raises ScenarioError (a ValueError)."""
    active = np.asarray(level.units.active)
    if env_config is not None:
        n, z = active.shape[-1], np.shape(level.zones.zone_type)[-1]
        if (n, z) != (env_config.num_units, env_config.max_zones):
            raise ScenarioError(f"the level has {n} unit slots and {z} zone slots; the EnvConfig "
                                f"has {env_config.num_units} and {env_config.max_zones}")
    if active.ndim == 2:
        for i in range(active.shape[0]):
            try:
                validate_level(jax.tree.map(lambda x, i=i: np.asarray(x)[i], level))
            except ScenarioError as err:
                raise ScenarioError(err.message, err.path, f"level {i} of the batch") from None
        return
    level_to_scenario(level, name="generated").validate()


def space_ranges(space: LevelSpace) -> dict[str, tuple[float, float]]:
    """The float32 (min, max) of every range field of a space: what the generator samples
    and clips to (the config's values rounded to float32)."""
    return {name: _f32_range(*getattr(space, name), RANGE_BOUNDS[name]) for name in RANGE_BOUNDS}


__all__ = ["EDITS", "FREE_NAMES", "FREE_PARAMS", "PHYSICS_FREE", "RANGE_BOUNDS",
           "ConfigError", "LevelGenerator", "LevelSpace", "space_ranges",
           "validate_level"]

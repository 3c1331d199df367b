"""UED level generation and ACCEL mutation (ued/levels.py): ranges, roles, padding, which
parameters change, edit counts and noise scale, scenario validity, compile counts and config
errors. Generators are built once per space (module cache) and keep one batch size, so the
file compiles each sample / mutate only once."""

from __future__ import annotations

import dataclasses
import math
import os

import jax
import numpy as np
import pytest
from hypothesis import HealthCheck, Phase, example, given, settings
from hypothesis import strategies as st

from tabx import constants as C
from tabx.compile_counter import CompileCounter
from tabx.params import EnvConfig, index_level, stack_levels
from tabx.scenarios import ScenarioError, load_named
from ued.errors import ConfigError
from ued.levels import FREE_NAMES, LevelGenerator, LevelSpace, space_ranges, validate_level

CONFIG = EnvConfig(max_allies=7, max_enemies=7, max_zones=7, max_steps=64)
# Healers on both teams (1H each side), padded unit and zone slots in both.
BASE_NAMES = ("1F1M3A1Hvs2F1S1K1A1H_2L2B2S", "2F1M2Avs2S1K_2L")
BASES = [load_named(name).to_level(CONFIG) for name in BASE_NAMES]
BASE = stack_levels(BASES)
N = 16
ALL = ("unit_spec", "zone", "heuristic", "physics")
# One zone space for several tests: varying count, a margin, two types, pure swap / retype
# edits (noise 0 makes the perturbation a no-op).
ZONE_SPACE = dict(free=("zone",), num_edits=1, noise=0.0, zone_count=(0, 7), zone_margin=20.0,
                  zone_types=("lava", "swamp"))
FAST = settings(max_examples=int(os.environ.get("TABX_HYPOTHESIS_EXAMPLES", "8")), deadline=None,
                suppress_health_check=[HealthCheck.too_slow,
                                       HealthCheck.function_scoped_fixture])

# Leaves each free parameter may change.
CHANGES = {
    "health": {".units.health", ".units.max_health"},
    "speed": {".units.speed"},
    "damage": {".units.damage"},
    "zone": {".zones.zone_type", ".zones.centre", ".zones.semi_axes", ".zones.effect"},
    "heuristic": {".heuristic.epsilon", ".heuristic.aggressive_threshold"},
    "physics": {".physics.restitution", ".physics.boundary_damage_rate", ".physics.turn_rate"},
}

_GENERATORS: dict[LevelSpace, LevelGenerator] = {}


def generator(**fields) -> LevelGenerator:
    space = LevelSpace(**fields)
    if space not in _GENERATORS:
        _GENERATORS[space] = LevelGenerator(CONFIG, BASE, space)
    return _GENERATORS[space]


def key(i: int) -> jax.Array:
    return jax.random.PRNGKey(i)


def leaves(level) -> dict[str, np.ndarray]:
    flat, _ = jax.tree_util.tree_flatten_with_path(level)
    return {jax.tree_util.keystr(path): np.asarray(x) for path, x in flat}


def changed(a, b) -> set[str]:
    la, lb = leaves(a), leaves(b)
    return {k for k in la if not np.array_equal(la[k], lb[k])}


def levels_of(batch) -> list:
    """The levels of a batch, as numpy (eager jnp indexing would compile per shape)."""
    batch = jax.tree.map(np.asarray, batch)
    return [jax.tree.map(lambda x, i=i: x[i], batch) for i in range(batch.reward_mode.shape[0])]


def base_of(level):
    """The base level a generated level came from (unit layout identifies it)."""
    for b in BASES:
        if (np.array_equal(np.asarray(level.units.unit_type), np.asarray(b.units.unit_type))
                and np.array_equal(np.asarray(level.units.active), np.asarray(b.units.active))):
            return b
    raise AssertionError("no base level matches")


def in_range(x, rng, tol=0.0) -> bool:
    x = np.asarray(x)
    return bool(np.all(x >= rng[0] - tol) and np.all(x <= rng[1] + tol))


def check_level(level, space: LevelSpace, base=None) -> None:
    """Every invariant of a generated or mutated level of `space`."""
    base = base_of(level) if base is None else base
    r = space_ranges(space)
    free = space.free_params
    u, bu = leaves(level.units), leaves(base.units)
    act = bu[".active"]
    for name in (".team", ".unit_type", ".position", ".heading", ".attack_range", ".cooldown",
                 ".radius", ".mass", ".sight_angle", ".heals", ".active"):
        np.testing.assert_array_equal(u[name], bu[name], err_msg=name)
    for name in u:  # padded slots untouched
        np.testing.assert_array_equal(u[name][~act], bu[name][~act], err_msg=f"padded {name}")
    heals = bu[".heals"]
    if "health" in free:
        assert in_range(u[".max_health"][act], r["health"])
        assert np.all(u[".health"][act] > 0) and np.all(u[".health"] <= u[".max_health"])
        # The base starts at full health, so the generated levels do too.
        np.testing.assert_array_equal(u[".health"][act], u[".max_health"][act])
    if "speed" in free:
        assert in_range(u[".speed"][act], r["speed"])
    if "damage" in free:
        dealers, healers = act & ~heals, act & heals
        assert dealers.any()
        assert in_range(u[".damage"][dealers], r["damage"]) and np.all(u[".damage"][dealers] >= 0)
        assert in_range(-u[".damage"][healers], r["heal"]) and np.all(u[".damage"][healers] <= 0)
    z, bz = leaves(level.zones), leaves(base.zones)
    used = z[".zone_type"] != C.ZONE_NONE
    if "zone" in free:
        codes = [C.ZONE_TYPE_BY_NAME[t] for t in space.zone_types]
        assert np.isin(z[".zone_type"][used], codes).all()
        if space.zone_count is None:
            np.testing.assert_array_equal(used, bz[".zone_type"] != C.ZONE_NONE)
        else:
            k = int(used.sum())
            assert space.zone_count[0] <= k <= space.zone_count[1]
            assert used[:k].all() and not used[k:].any()
        bound = np.maximum(np.asarray(level.physics.arena_size) / 2 - space.zone_margin, 0.0)
        assert np.all(np.abs(z[".centre"][used]) <= bound)
        assert in_range(z[".semi_axes"][used], r["zone_semi_axes"])
        ztype, effect = z[".zone_type"], z[".effect"]
        assert in_range(effect[used & (ztype == C.ZONE_LAVA)], r["lava_effect"])
        assert in_range(effect[used & (ztype == C.ZONE_SWAMP)], r["swamp_effect"])
        assert np.all(effect[used & (ztype == C.ZONE_BUSH)] == 0.0)
        if space.zone_count is None:
            for name in z:  # padded zone slots untouched
                np.testing.assert_array_equal(z[name][~used], bz[name][~used])
    for name in ("epsilon", "aggressive_threshold"):
        if "heuristic" in free:
            assert in_range(getattr(level.heuristic, name), r[name])
    for name in ("restitution", "boundary_damage_rate", "turn_rate"):
        if "physics" in free:
            assert in_range(getattr(level.physics, name), r[name])
    for name in ("dt", "slop", "percent", "arena_size"):
        np.testing.assert_array_equal(getattr(level.physics, name), getattr(base.physics, name))
    allowed = set().union(*(CHANGES[f] for f in free))
    assert changed(level, base) <= allowed
    validate_level(level, CONFIG)


# --- sampling ------------------------------------------------------------------------------------


def test_sample_respects_ranges_roles_and_padding():
    gen = generator(free=ALL)
    batch = gen.sample(key(0), N)
    assert batch.reward_mode.shape == (N,)
    assert batch.units.health.shape == (N, CONFIG.num_units)
    levels = levels_of(batch)
    for level in levels:
        check_level(level, gen.space)
    validate_level(batch, CONFIG)  # the batch form too
    # Both bases are used, levels differ, all three zone types and both teams' params vary.
    assert {id(base_of(lv)) for lv in levels} == {id(b) for b in BASES}
    heals = np.asarray(batch.units.heals) & np.asarray(batch.units.active)
    assert heals[:, :CONFIG.max_allies].any() and heals[:, CONFIG.max_allies:].any()
    assert np.all(np.asarray(batch.units.damage)[heals] < 0)  # healers keep healing
    assert len({float(lv.units.speed[0]) for lv in levels}) == N
    speed = np.asarray(batch.units.speed)[np.asarray(batch.units.active)]
    lo, hi = gen.space.speed
    assert speed.min() < lo + 0.1 * (hi - lo) and speed.max() > hi - 0.1 * (hi - lo)
    types = np.asarray(batch.zones.zone_type)
    assert {C.ZONE_LAVA, C.ZONE_BUSH, C.ZONE_SWAMP} <= set(types.ravel().tolist())
    eps = np.asarray(batch.heuristic.epsilon)
    assert len(set(eps[:, 0].tolist())) == N and len(set(eps[:, 1].tolist())) == N
    # Zone centres reach every quadrant (the reference's only reached the upper-right one).
    centre = np.asarray(batch.zones.centre)[types != C.ZONE_NONE]
    assert {(bool(x > 0), bool(y > 0)) for x, y in centre} == {(a, b) for a in (True, False)
                                                               for b in (True, False)}


@pytest.mark.parametrize("free", ["health", "speed", "damage", "zone", "heuristic", "physics"])
def test_only_the_chosen_free_parameters_change(free):
    gen = generator(**ZONE_SPACE) if free == "zone" else generator(free=(free,), num_edits=1)
    batch = gen.sample(key(1), N)
    mutated = gen.mutate(key(2), batch)
    for level, mut in zip(levels_of(batch), levels_of(mutated), strict=True):
        base = base_of(level)
        assert changed(level, base), "a free parameter should change"
        assert changed(level, base) <= CHANGES[free]
        assert changed(mut, level) <= CHANGES[free]
        check_level(level, gen.space, base)
        check_level(mut, gen.space, base)


def test_unit_spec_is_the_three_unit_parameters():
    space = LevelSpace(free=("unit_spec",))
    assert space.free_params == {"health", "speed", "damage"}
    assert LevelSpace(free=("unit_spec", "health", "zone")).free_params == {
        "health", "speed", "damage", "zone"}


def test_initial_health_keeps_its_fraction_of_max_health():
    hurt = BASE.replace(units=BASE.units.replace(health=BASE.units.health * 0.5))
    # Same space, config and number of bases as a generator above: shares its compilation.
    gen = LevelGenerator(CONFIG, hurt, LevelSpace(free=("health",), num_edits=1))
    batch = gen.sample(key(3), N)
    for level in levels_of(batch) + levels_of(gen.mutate(key(4), batch)):
        act = np.asarray(level.units.active)
        ratio = np.asarray(level.units.health)[act] / np.asarray(level.units.max_health)[act]
        np.testing.assert_allclose(ratio, 0.5, rtol=1e-6)
        validate_level(level, CONFIG)


def test_zone_count_varies_up_to_max_zones_with_margin():
    gen = generator(**ZONE_SPACE)
    batch = gen.sample(key(5), N)
    counts = (np.asarray(batch.zones.zone_type) != C.ZONE_NONE).sum(-1)
    assert counts.min() < counts.max() and counts.max() <= 7
    for level in levels_of(batch):
        check_level(level, gen.space)
        empty = np.asarray(level.zones.zone_type) == C.ZONE_NONE
        np.testing.assert_array_equal(np.asarray(level.zones.semi_axes)[empty], 1.0)
        np.testing.assert_array_equal(np.asarray(level.zones.effect)[empty], 0.0)
        np.testing.assert_array_equal(np.asarray(level.zones.centre)[empty], 0.0)
    for level in levels_of(gen.mutate(key(6), batch)):
        check_level(level, gen.space)


def test_sample_rejects_bad_n():
    gen = generator(free=ALL)
    for bad in (0, -3, 2.5, True, "4"):
        with pytest.raises(ValueError, match="n >= 1"):
            gen.sample(key(0), bad)


def test_generator_rejects_mismatched_base_levels_and_zone_count():
    with pytest.raises(ValueError, match="unit slots"):
        LevelGenerator(EnvConfig(max_allies=6, max_enemies=7, max_zones=7), BASE, LevelSpace())
    with pytest.raises(ConfigError, match=r"levels\.zone_count"):
        LevelGenerator(CONFIG, BASE, LevelSpace(zone_count=(1, 8)))
    # One unbatched level is a batch of one.
    assert LevelGenerator(CONFIG, BASES[0], LevelSpace()).num_base == 1


# --- mutation ------------------------------------------------------------------------------------


def test_zero_edits_leave_levels_unchanged():
    batch = generator(free=ALL).sample(key(7), N)
    assert not changed(generator(free=ALL, num_edits=0).mutate(key(8), batch), batch)


def test_one_perturbation_changes_every_free_value_within_the_noise():
    space = LevelSpace(free=("health",), num_edits=1)
    gen = generator(**dataclasses.asdict(space))
    lo, hi = space_ranges(space)["health"]
    batch = gen.sample(key(9), N)
    mutated = gen.mutate(key(10), batch)
    for level, mut in zip(levels_of(batch), levels_of(mutated), strict=True):
        act = np.asarray(level.units.active)
        before, after = np.asarray(level.units.max_health), np.asarray(mut.units.max_health)
        # Only perturbation applies: one edit moves every active unit's max health (fresh
        # samples are inside the range, so no value is stuck at a bound) and nothing else.
        assert int((before != after).sum()) == int(act.sum())
        assert np.abs(after - before).max() <= space.noise * (hi - lo) * (1 + 1e-5)
        assert changed(mut, level) == {".units.health", ".units.max_health"}
        check_level(mut, space)


def test_many_edits_stay_in_range_and_within_num_edits_times_noise():
    gen = generator(free=ALL)
    space, r = gen.space, space_ranges(gen.space)
    batch = gen.sample(key(11), N)
    mutated = gen.mutate(key(12), batch)
    bound = space.num_edits * space.noise * (1 + 1e-5)
    for level, mut in zip(levels_of(batch), levels_of(mutated), strict=True):
        check_level(mut, space)
        for name, rng in (("max_health", "health"), ("speed", "speed")):
            delta = np.abs(np.asarray(getattr(mut.units, name)) - getattr(level.units, name))
            assert delta.max() <= bound * (r[rng][1] - r[rng][0])
        for name in ("epsilon", "aggressive_threshold"):
            delta = np.abs(np.asarray(getattr(mut.heuristic, name)) - getattr(level.heuristic,
                                                                               name))
            assert delta.max() <= bound * (r[name][1] - r[name][0])
        half = np.asarray(level.physics.arena_size) / 2
        delta = np.abs(np.asarray(mut.zones.centre) - np.asarray(level.zones.centre))
        assert np.all(delta <= bound * 2 * half)
    assert changed(mutated, batch)


def test_swap_and_retype_edit_one_zone():
    gen = generator(**ZONE_SPACE)
    space, r = gen.space, space_ranges(gen.space)
    batch = gen.sample(key(13), N)
    pairs = [(lv, mut) for k in (14, 15, 16) for lv, mut in zip(
        levels_of(batch), levels_of(gen.mutate(key(k), batch)), strict=True)]
    kinds = []
    for level, mut in pairs:
        check_level(mut, space)
        a, b = leaves(level.zones), leaves(mut.zones)
        rows = {j for name in a for j in np.flatnonzero(
            np.any((a[name] != b[name]).reshape(a[name].shape[0], -1), -1))}
        assert len(rows) <= 1, "an edit touches one zone"
        np.testing.assert_array_equal(a[".centre"], b[".centre"])  # noise 0: no perturbation
        if not rows:
            kinds.append("none")
            continue
        (j,) = rows
        if a[".zone_type"][j] == b[".zone_type"][j]:
            kinds.append("swap")
            np.testing.assert_array_equal(b[".semi_axes"][j], a[".semi_axes"][j][::-1])
            assert a[".effect"][j] == b[".effect"][j]
        else:
            kinds.append("retype")
            np.testing.assert_array_equal(b[".semi_axes"][j], a[".semi_axes"][j])
            old = "lava_effect" if a[".zone_type"][j] == C.ZONE_LAVA else "swamp_effect"
            new = "lava_effect" if b[".zone_type"][j] == C.ZONE_LAVA else "swamp_effect"
            frac = (a[".effect"][j] - r[old][0]) / (r[old][1] - r[old][0])
            np.testing.assert_allclose((b[".effect"][j] - r[new][0]) / (r[new][1] - r[new][0]),
                                       frac, atol=1e-5)
    assert {"swap", "retype"} <= set(kinds)


def test_mutate_takes_one_level_too():
    gen = generator(free=("health",), num_edits=1)
    level = index_level(gen.sample(key(15), N), 3)
    mut = gen.mutate(key(16), level)
    assert np.shape(mut.reward_mode) == () and changed(mut, level)
    check_level(mut, gen.space)


@FAST
@given(seed=st.integers(0, 2**31 - 1))
def test_any_key_gives_valid_levels_and_mutations(seed):
    gen = generator(free=ALL)
    k1, k2 = jax.random.split(key(seed))
    batch = gen.sample(k1, N)
    for level in levels_of(batch) + levels_of(gen.mutate(k2, batch)):
        check_level(level, gen.space)


@st.composite
def spaces(draw) -> LevelSpace:
    def pair(lo: float, hi: float) -> tuple[float, float]:
        a, b = draw(st.floats(lo, hi)), draw(st.floats(lo, hi))
        return (min(a, b), max(a, b))

    return LevelSpace(
        free=tuple(draw(st.lists(st.sampled_from(FREE_NAMES), min_size=1, max_size=4,
                                 unique=True))),
        health=pair(1.0, 1000.0), speed=pair(0.0, 10.0), damage=pair(0.0, 200.0),
        heal=pair(0.0, 50.0),
        zone_types=tuple(draw(st.lists(st.sampled_from(("lava", "bush", "swamp")), min_size=1,
                                       max_size=3, unique=True))),
        zone_count=draw(st.none() | st.tuples(st.integers(0, 3), st.integers(3, 7))),
        zone_semi_axes=pair(0.1, 60.0), zone_margin=draw(st.floats(0.0, 80.0)),
        lava_effect=pair(0.0, 100.0), swamp_effect=pair(0.0, 0.999),
        epsilon=pair(0.0, 1.0), aggressive_threshold=pair(0.0, 1.0),
        restitution=pair(0.0, 1.0), boundary_damage_rate=pair(0.0, 10.0),
        turn_rate=pair(0.01, 2 * math.pi), num_edits=draw(st.integers(0, 4)),
        noise=draw(st.floats(0.0, 1.0)))


# Every example compiles a new space: no shrinking (each shrink step would compile too).
@settings(max_examples=int(os.environ.get("TABX_HYPOTHESIS_EXAMPLES", "5")), deadline=None,
          suppress_health_check=[HealthCheck.too_slow],
          phases=(Phase.explicit, Phase.reuse, Phase.generate))
@example(space=LevelSpace(free=("unit_spec",), health=(1.0, 1.0), speed=(1.4e-45, 5.4),
                          damage=(1.4e-45, 1.0), heal=(0.0, 0.0), num_edits=3, noise=0.67),
         seed=0)
@given(space=spaces(), seed=st.integers(0, 2**31 - 1))
def test_any_space_gives_levels_in_its_ranges(space, seed):
    space.validate()
    gen = LevelGenerator(CONFIG, BASE, space)  # a new space compiles anew (small N: cheap)
    k1, k2 = jax.random.split(key(seed))
    batch = gen.sample(k1, 4)
    for level in levels_of(batch) + levels_of(gen.mutate(k2, batch)):
        check_level(level, space)


def test_pure_functions_compose_inside_jit():
    gen = generator(free=ALL)
    keys = jax.random.split(key(17), 2)
    levels = jax.jit(jax.vmap(gen.sample_one))(keys, BASE)
    mutated = jax.jit(jax.vmap(gen.mutate_one))(keys, levels)
    for level, base in zip(levels_of(levels), BASES, strict=True):
        check_level(level, gen.space, base)
    for level, base in zip(levels_of(mutated), BASES, strict=True):
        check_level(level, gen.space, base)


# --- compilation ---------------------------------------------------------------------------------



def test_no_recompilation_on_new_keys_and_levels():
    gen = generator(free=ALL)
    keys = [key(100 + i) for i in range(8)]
    batch = gen.sample(keys[0], N)
    gen.mutate(keys[1], batch)
    sizes = gen._sample_jit._cache_size(), gen._mutate_jit._cache_size()
    with CompileCounter() as cc:
        for i in range(2, 8, 2):
            batch = gen.sample(keys[i], N)
            batch = gen.mutate(keys[i + 1], batch)
        jax.block_until_ready(batch)
    assert cc.traces == 0, f"{cc.traces} retraces: {cc.traced}"
    assert (gen._sample_jit._cache_size(), gen._mutate_jit._cache_size()) == sizes


# --- validation ----------------------------------------------------------------------------------


@pytest.mark.parametrize("fields, field", [
    (dict(free=("hp",)), "free"),
    (dict(free=()), "free"),
    (dict(health=(100.0, 50.0)), "health"),
    (dict(health=(0.0, 50.0)), "health"),
    (dict(health=(1.0, 2.0, 3.0)), "health"),
    (dict(speed=(-1.0, 1.0)), "speed"),
    (dict(speed=(0.5, math.nan)), "speed"),
    (dict(damage=(-5.0, 10.0)), "damage"),
    (dict(heal=(-1.0, 5.0)), "heal"),
    (dict(zone_types=("mud",)), "zone_types"),
    (dict(zone_types=()), "zone_types"),
    (dict(zone_types=("lava", "lava")), "zone_types"),
    (dict(zone_count=(3, 1)), "zone_count"),
    (dict(zone_count=(1,)), "zone_count"),
    (dict(zone_count=(-1, 2)), "zone_count"),
    (dict(zone_semi_axes=(0.0, 5.0)), "zone_semi_axes"),
    (dict(zone_margin=-1.0), "zone_margin"),
    (dict(lava_effect=(-2.0, 5.0)), "lava_effect"),
    (dict(swamp_effect=(0.1, 1.0)), "swamp_effect"),
    (dict(epsilon=(0.0, 1.5)), "epsilon"),
    (dict(aggressive_threshold=(-0.1, 0.5)), "aggressive_threshold"),
    (dict(restitution=(0.5, 1.2)), "restitution"),
    (dict(boundary_damage_rate=(-0.1, 0.2)), "boundary_damage_rate"),
    (dict(turn_rate=(0.0, 1.0)), "turn_rate"),
    (dict(num_edits=-1), "num_edits"),
    (dict(num_edits=1.5), "num_edits"),
    (dict(noise=2.0), "noise"),
    (dict(noise=-0.1), "noise"),
])
def test_bad_level_space_names_the_field(fields, field):
    with pytest.raises(ConfigError, match=rf"^levels\.{field}: "):
        LevelSpace(**fields).validate()
    with pytest.raises(ConfigError, match=rf"^ued\.levels\.{field}: "):
        LevelSpace(**fields).validate("ued.levels")


def test_default_space_is_valid_and_yaml_safe():
    import yaml

    space = LevelSpace().validate()
    assert space.free == ("zone",) and space.num_edits == 3 and space.noise == 0.1
    text = yaml.safe_dump(LevelSpace(zone_count=(1, 3)).to_dict())
    assert LevelSpace(**{k: tuple(v) if isinstance(v, list) else v
                         for k, v in yaml.safe_load(text).items()}) == LevelSpace(
        zone_count=(1, 3))


def test_validate_level_rejects_broken_levels():
    level = BASES[0]
    validate_level(level, CONFIG)
    outside = level.replace(zones=level.zones.replace(
        centre=level.zones.centre.at[0, 0].set(500.0)))
    with pytest.raises(ScenarioError, match=r"zones\[0\]\.centre"):
        validate_level(outside)
    hurt = level.replace(units=level.units.replace(health=level.units.health.at[0].set(1e4)))
    with pytest.raises(ScenarioError, match="exceeds max_health"):
        validate_level(hurt)
    with pytest.raises(ScenarioError, match="level 1 of the batch"):
        validate_level(stack_levels([level, outside]))
    with pytest.raises(ScenarioError, match="slots"):
        validate_level(level, EnvConfig(max_allies=7, max_enemies=7, max_zones=2))

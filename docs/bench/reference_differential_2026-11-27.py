"""Differential test against recorded reference episodes (docs/heuristics_reference.md, "The
reference code beside ours"): each recorded state is given to our scripted policy and to our step.

    python docs/bench/reference_differential_2026-11-27.py SCENARIO RECORD.npz [PROFILE]

RECORD.npz holds E episodes of T steps played by the reference implementation, both teams
scripted by its heuristic policy (a harness outside this repository writes it; nothing here
imports the reference). Arrays, unit axis in the reference's slot order (allies first):

    position (E, T, N, 2), rotation (E, T, N), velocity (E, T, N, 2), health, cooldown (its
    time since the last attack, before the step adds dt), alive, speed (E, T, N); visible,
    attackable (E, T, N, N); target (E, T, N); timestep (E, T); mem_pos (E, T, N, 2) and
    mem_valid (E, T, N) (its LastVisibleTarget); action (E, T, N) (what was played);
    det_action (E, T, N) (its decision with epsilon 0); done_before (E, T).

Prints (a) how many decisions of living units differ from ours (epsilon 0, the reference's
own geometry matrices), by (reference action, ours); (b) after one step of ours with the
recorded actions, the largest differences from the next recorded state.
"""

from __future__ import annotations

import sys
from collections import Counter

import jax
import jax.numpy as jnp
import numpy as np

from tabx.env import TabxEnv, cooldown_cap
from tabx.geometry import facing, in_ellipses
from tabx.heuristic import heuristic_actions_from_bits
from tabx.params import heuristic_params
from tabx.profiles import with_profile
from tabx.scenarios import config_for, load_named

FIELDS = ("position", "rotation", "velocity", "health", "cooldown", "alive", "speed",
          "visible", "attackable", "target", "timestep", "mem_pos", "mem_valid")


def main(name: str, path: str, profile: str = "reference") -> None:
    rec = dict(np.load(path))
    scenario = load_named(name)
    config = config_for([scenario], max_steps=512)
    level = with_profile(scenario.to_level(config), profile).replace(
        heuristic=heuristic_params("medium", "medium"))
    greedy = level.replace(heuristic=level.heuristic.replace(epsilon=jnp.zeros(2)))
    env = TabxEnv(config)
    u, dt = level.units, level.physics.dt

    def to_state(s):
        """Our state for a recorded one: our clock runs dt ahead of the reference's."""
        heading = jnp.mod(s["rotation"], 2 * jnp.pi)
        facing_vec, half = facing(heading, u.sight_angle)
        state = env.initial_state(level).replace(
            position=s["position"], velocity=s["velocity"], heading=heading, facing=facing_vec,
            half_sight=half, health=s["health"], alive=s["alive"], speed=s["speed"],
            cooldown=jnp.clip(s["cooldown"] + dt, 0.0, cooldown_cap(level)),
            memory_position=s["mem_pos"], memory_valid=s["mem_valid"],
            step=s["timestep"].astype(jnp.int32))
        z = level.zones
        inside = in_ellipses(state.position, z.centre, z.semi_axes, z.zone_type)
        return env._refresh_geometry(state, level, jnp.zeros_like(state.visible), inside)

    def one(s, actions):
        state = to_state(s)
        theirs = state.replace(visible=s["visible"], attackable=s["attackable"],
                               target=s["target"], has_target=jnp.any(s["attackable"], -1))
        decided, _ = heuristic_actions_from_bits(jnp.zeros(config.num_units, jnp.uint32),
                                                 theirs, greedy)
        _, after, _, _, _ = env.step(jax.random.key(0), state, actions, level)
        return decided, after

    e, t = rec["action"].shape[:2]
    flat = {k: rec[k].reshape(e * t, *rec[k].shape[2:]) for k in FIELDS}
    decided, after = jax.jit(jax.vmap(one))(flat, rec["action"].reshape(e * t, -1))
    decided = np.asarray(decided).reshape(e, t, -1)
    live = ~rec["done_before"]
    mask = live[..., None] & rec["alive"]
    differ = (decided != rec["det_action"]) & mask
    print(f"{name}, profile {profile}: {live.sum()} states, {mask.sum()} decisions")
    pairs = zip(rec["det_action"][differ].tolist(), decided[differ].tolist(), strict=True)
    print(f"(a) decisions that differ: {differ.sum()}", Counter(pairs))
    both = live[:, :-1] & live[:, 1:]
    for key, ref in (("position", rec["position"]), ("health", rec["health"]),
                     ("velocity", rec["velocity"]), ("alive", rec["alive"].astype(float))):
        ours = np.asarray(getattr(after, key), float).reshape(e, t, *ref.shape[2:])
        gap = np.abs(ours[:, :-1] - ref[:, 1:]).reshape(e, t - 1, -1).max(-1)
        print(f"(b) {key}: largest difference {gap[both].max():.3g}, "
              f"steps over 1e-3: {(gap[both] > 1e-3).sum()}")
    heading = np.asarray(after.heading).reshape(e, t, -1)[:, :-1]
    turn = np.abs((heading - rec["rotation"][:, 1:] + np.pi) % (2 * np.pi) - np.pi)
    print(f"(b) heading: largest difference {turn[both].max():.3g}")


if __name__ == "__main__":
    main(*sys.argv[1:])

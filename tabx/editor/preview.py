"""Editor previews: play a scenario in the real simulator and return every step as plain data.

One preview is one jitted episode of the episode player (`tabx.episodes.play`), with the
actions of each team chosen by a `Controller` (`heuristic:TIER`, `heuristic`, `random` or
`idle`). Compiled functions are cached per (EnvConfig, controller kinds). The config is padded
to buckets (unit slots and zone slots to powers of two, at least 4; steps to powers of two, at
least 64) so that adding a unit, drawing a zone or asking for a few more steps reuses the
compiled function: only the first preview of a size pays for compilation. The heuristic tier is
level data, so switching tiers never recompiles either.
"""

from __future__ import annotations

import threading
import time
from typing import Any

import numpy as np

from tabx.scenarios import Scenario, ScenarioError

MAX_PREVIEW_STEPS = 2048
MIN_STEP_BUCKET = 64
MIN_SLOT_BUCKET = 4
PREVIEW_CONTROLLERS = ("heuristic", "random", "idle")  # no learner in the editor: no external
MAX_CONTROLLER_TEXT = 64

_lock = threading.Lock()
_compiled: dict[tuple, Any] = {}


def _bucket(n: int, minimum: int) -> int:
    size = minimum
    while size < n:
        size *= 2
    return size


def preview_config(scenario: Scenario, steps: int):
    """The padded EnvConfig a preview of `scenario` for `steps` steps runs under."""
    from tabx.params import EnvConfig

    return EnvConfig(
        max_allies=_bucket(len(scenario.allies), MIN_SLOT_BUCKET),
        max_enemies=_bucket(len(scenario.enemies), MIN_SLOT_BUCKET),
        max_zones=_bucket(len(scenario.zones), MIN_SLOT_BUCKET),
        max_steps=_bucket(steps, MIN_STEP_BUCKET),
    )


def parse_controller(text: Any, path: str):
    """A Controller for the editor (external is refused); ScenarioError naming `path`."""
    from tabx.controllers import Controller

    shown = repr(text)
    shown = shown if len(shown) <= 60 else shown[:60] + "..."
    if not isinstance(text, str) or not text:
        raise ScenarioError(f"expected a controller such as heuristic:medium, got {shown}", path)
    if len(text) > MAX_CONTROLLER_TEXT:
        raise ScenarioError(f"expected heuristic[:TIER], random or idle (at most "
                            f"{MAX_CONTROLLER_TEXT} characters), got {shown}", path)
    try:
        controller = Controller.parse(text)
    except ValueError as err:
        raise ScenarioError(str(err), path) from None
    if controller.kind not in PREVIEW_CONTROLLERS:
        raise ScenarioError(f"expected heuristic[:TIER], random or idle, got {shown}", path)
    return controller


def _build(config, kinds: tuple[str, str]):
    """play(level, key) -> (first frame, frames of steps 1..max_steps, attacking), jitted."""
    import jax
    import jax.numpy as jnp

    from tabx.controllers import Controller
    from tabx.env import TabxEnv
    from tabx.episodes import PREVIEW_KEYS
    from tabx.episodes import play as play_episodes
    from tabx.jit_options import simulator_jit

    env = TabxEnv(config)
    controllers = tuple(Controller(kind) for kind in kinds)

    def frame(state, level):
        ready = jnp.clip(state.cooldown / jnp.maximum(level.units.cooldown, 1e-6), 0.0, 1.0)
        return {"position": state.position, "heading": state.heading, "health": state.health,
                "alive": state.alive, "cooldown": ready, "hp_ratio": state.hp_ratio,
                "done": state.done, "won": state.won}

    def play(level, key):
        levels = jax.tree.map(lambda x: x[None], level)  # a batch of one episode
        out = play_episodes(env, levels, key[None], config.max_steps, controllers,
                            keys=PREVIEW_KEYS,
                            record=lambda states, info, levels: (frame(states, levels),
                                                                 info["attacking"]))
        first = jax.tree.map(lambda x: x[0], frame(out.start, levels))
        frames, attacking = jax.tree.map(lambda x: x[:, 0], out.record)
        return first, frames, attacking

    return simulator_jit(play)


def run_preview(scenario: Scenario, steps: int, ally: Any = "heuristic:medium",
                enemy: Any = "heuristic:medium", seed: int = 0) -> dict[str, Any]:
    """Play `steps` steps of `scenario`; every array is per step (steps + 1 frames, the first
    is the start) and per unit in the scenario's unit order. Raises ScenarioError."""
    import jax

    from tabx.controllers import with_tiers

    if isinstance(steps, bool) or not isinstance(steps, int) or not 1 <= steps <= MAX_PREVIEW_STEPS:
        raise ScenarioError(f"expected an integer in [1, {MAX_PREVIEW_STEPS}], got {steps!r}",
                            "steps")
    if isinstance(seed, bool) or not isinstance(seed, int) or not 0 <= seed < 2**31:
        raise ScenarioError(f"expected an integer in [0, 2^31), got {seed!r}", "seed")
    controllers = (parse_controller(ally, "ally"), parse_controller(enemy, "enemy"))
    if not scenario.playable:
        raise ScenarioError("a preview needs at least one ally and one enemy", "units")
    config = preview_config(scenario, steps)
    level = with_tiers(scenario.to_level(config), controllers)
    kinds = (controllers[0].kind, controllers[1].kind)
    key = jax.random.key(seed)
    with _lock:
        cache_key = (config, kinds)
        cached = cache_key in _compiled
        t0 = time.perf_counter()
        if not cached:
            _compiled[cache_key] = _build(config, kinds).lower(level, key).compile()
        t1 = time.perf_counter()
        first, frames, attacking = jax.device_get(_compiled[cache_key](level, key))
        t2 = time.perf_counter()

    # Scenario unit order -> level slot (allies fill 0.., enemies start at max_allies).
    slots, n_ally, n_enemy = [], 0, 0
    for u in scenario.units:
        if u.team == "ally":
            slots.append(n_ally)
            n_ally += 1
        else:
            slots.append(config.max_allies + n_enemy)
            n_enemy += 1
    idx = np.asarray(slots)

    def series(name: str, decimals: int | None = 3) -> list:
        values = np.concatenate([np.asarray(first[name])[None], np.asarray(frames[name])])
        values = values[: steps + 1]
        if values.ndim >= 2 and name not in ("hp_ratio", "won"):
            values = values[:, idx]
        if decimals is not None and values.dtype.kind == "f":
            values = np.round(values.astype(np.float64), decimals)
        return values.tolist()

    done = np.concatenate([[bool(first["done"])], np.asarray(frames["done"])])[: steps + 1]
    done_at = int(np.argmax(done)) if done.any() else None
    won = np.asarray(frames["won"])[steps - 1]
    winner = how = None
    if done_at is not None:
        winner = "ally" if won[0] else "enemy"
        alive_end = np.concatenate([np.asarray(first["alive"])[None],
                                    np.asarray(frames["alive"])])[done_at][idx]
        teams = np.asarray([u.team for u in scenario.units])
        wiped = not alive_end[teams == "ally"].any() or not alive_end[teams == "enemy"].any()
        how = "elimination" if wiped else "time limit"
    return {
        "ok": True,
        "steps": steps,
        "config": {"max_allies": config.max_allies, "max_enemies": config.max_enemies,
                   "max_zones": config.max_zones, "max_steps": config.max_steps},
        "controllers": [str(c) for c in controllers],
        "seed": seed,
        "max_health": [round(u.stats()["max_health"], 3) for u in scenario.units],
        "position": series("position"),
        "heading": series("heading", 4),
        "health": series("health"),
        "alive": series("alive", None),
        "cooldown": series("cooldown"),
        "hp_ratio": series("hp_ratio", 4),
        "attacking": [[False] * len(slots)]
        + np.asarray(attacking)[:steps][:, idx].tolist(),
        "done_at": done_at,
        "winner": winner,
        "outcome": how,
        "compiled": not cached,
        "compile_s": round(t1 - t0, 3),
        "run_s": round(t2 - t1, 3),
    }

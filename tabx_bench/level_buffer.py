"""Timings of the level buffer at PLR scale: `python -m tabx_bench.level_buffer`.

A full buffer of 4000 levels with 20 leaves shaped like TABX unit / zone slots (up to (20, 2)),
batches of 128: insert_batch (fresh levels, some duplicates), sample, update_batch, and
save / load of the whole buffer. Prints the median of several repeats, in milliseconds.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from level_buffer.buffer import LevelBuffer


def toy_level(num_units: int = 20, num_zones: int = 4) -> dict[str, np.ndarray]:
    """A level pytree of 20 leaves, like EnvParams' unit and zone slots."""
    u, z = num_units, num_zones
    level: dict[str, Any] = {"units": {}, "zones": {}}
    for name in ("health", "max_health", "speed", "damage", "attack_range", "cooldown",
                 "radius", "mass", "heading", "sight_angle"):
        level["units"][name] = np.zeros(u, np.float32)
    level["units"]["position"] = np.zeros((u, 2), np.float32)
    level["units"]["unit_type"] = np.zeros(u, np.int32)
    level["units"]["team"] = np.zeros(u, np.int32)
    level["units"]["active"] = np.zeros(u, bool)
    level["units"]["heals"] = np.zeros(u, bool)
    level["zones"]["zone_type"] = np.zeros(z, np.int32)
    level["zones"]["centre"] = np.zeros((z, 2), np.float32)
    level["zones"]["semi_axes"] = np.zeros((z, 2), np.float32)
    level["zones"]["effect"] = np.zeros(z, np.float32)
    level["reward_mode"] = np.zeros((), np.int32)
    return level


def random_levels(rng: np.random.Generator, n: int, template: Any) -> Any:
    def leaf(x: np.ndarray) -> np.ndarray:
        shape = (n, *x.shape)
        if x.dtype == bool:
            return rng.random(shape) < 0.5
        if x.dtype.kind == "i":
            return rng.integers(0, 9, shape).astype(x.dtype)
        return (rng.random(shape) * 100).astype(x.dtype)

    return {k: leaf(v) if isinstance(v, np.ndarray) else {kk: leaf(vv) for kk, vv in v.items()}
            for k, v in template.items()}


def _median_ms(fn: Any, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return 1000 * float(np.median(times))


def run(capacity: int = 4000, batch: int = 128, repeats: int = 20,
        near_duplicates: bool = False, seed: int = 0) -> dict[str, float]:
    """Median milliseconds per operation on a full buffer."""
    rng = np.random.default_rng(seed)
    template = toy_level()
    buf = LevelBuffer(template, capacity=capacity, near_duplicates=near_duplicates, seed=seed)
    while buf.size < capacity:
        buf.insert_batch(random_levels(rng, 500, template), rng.random(500))

    def insert() -> None:
        levels = random_levels(rng, batch, template)
        dups = buf.get(buf.ids[rng.integers(0, buf.size, batch // 8)])  # 1/8 are duplicates
        for k, v in levels.items():
            d = dups[k]
            if isinstance(v, dict):
                for kk in v:
                    v[kk][: batch // 8] = d[kk]
            else:
                v[: batch // 8] = d
        buf.insert_batch(levels, rng.random(batch) + 0.5)

    replay = buf.sample(batch)
    out = {
        "insert_batch": _median_ms(insert, repeats),
        "sample": _median_ms(lambda: buf.sample(batch), repeats),
        "update_batch": _median_ms(lambda: buf.update_batch(replay.ids, rng.random(batch),
                                                            max_returns=rng.random(batch)),
                                   repeats),
        "weights": _median_ms(buf.weights, repeats),
    }
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "buffer.msgpack"
        out["save"] = _median_ms(lambda: buf.save(path), max(3, repeats // 4))
        out["load"] = _median_ms(lambda: LevelBuffer.load(path, template), max(3, repeats // 4))
        out["file_MiB"] = path.stat().st_size / 2**20
    return out


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--capacity", type=int, default=4000)
    parser.add_argument("--batch", type=int, default=128)
    parser.add_argument("--repeats", type=int, default=20)
    parser.add_argument("--near-duplicates", action="store_true")
    args = parser.parse_args(argv)
    result = run(args.capacity, args.batch, args.repeats, args.near_duplicates)
    print(f"capacity {args.capacity}, batch {args.batch}, near duplicates "
          f"{args.near_duplicates}")
    for name, value in result.items():
        unit = "MiB" if name == "file_MiB" else "ms"
        print(f"{name.replace('_MiB', ''):>13}: {value:8.2f} {unit}")


if __name__ == "__main__":
    main()

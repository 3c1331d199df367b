"""LevelService: the level generator, the ACCEL mutator and the scored level buffer in one place.

It hands out batches of levels (fresh, replayed, mutated, or SFL's learnable ones) and takes
their scores back. Everything it holds is host-side state that a resumed run needs, so it
saves and loads itself as files in a snapshot folder:

    buffer-<step>.msgpack       the PLR buffer (levels, scores, staleness, its random state)
    learnable-<step>.msgpack    SFL's learnable set (a buffer whose scores are p (1 - p))
    state-<step>.json           the caller's small state (the curriculum's); written last, so
                                its presence marks a complete snapshot

In local mode the driver calls it directly; the Ray version wraps the same class in an actor
(levels cross as numpy pytrees).
"""

from __future__ import annotations

import json
import os
import re
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from level_buffer import BufferConfig, InsertResult, LevelBuffer, Replay, Source
from tabx.files import atomic_write_text
from tabx.params import EnvParams
from ued.config import UEDSection
from ued.levels import LevelGenerator
from ued.run_folder import SNAPSHOT_FILES

SNAPSHOT_PATTERN = re.compile(r"^state-(\d+)\.json$")


def buffer_config(ued: UEDSection) -> BufferConfig:
    """The level buffer settings of a UED config section."""
    return BufferConfig(capacity=ued.buffer_size, replay_prob=ued.replay_prob,
                        staleness_coeff=ued.staleness_coef,
                        minimum_fill_ratio=ued.min_fill_ratio,
                        prioritization=ued.prioritization, temperature=ued.temperature,
                        topk_k=ued.topk, duplicate_check=ued.duplicate_check)


def to_host(levels: EnvParams) -> EnvParams:
    """A batch of levels as numpy arrays (what crosses process boundaries and goes into the
    buffer)."""
    return jax.tree.map(np.asarray, levels)


def to_device(levels: EnvParams) -> EnvParams:
    """A batch of levels as jax arrays with the dtypes of a fresh level, so the jitted update
    sees the same argument signature whatever the source and never recompiles."""
    return jax.tree.map(jnp.asarray, levels)


class LevelService:
    """Generator + mutator + buffer (+ SFL's learnable set)."""

    def __init__(self, generator: LevelGenerator, template_level: EnvParams, ued: UEDSection,
                 seed: int = 0, use_buffer: bool = True):
        self.generator = generator
        self.ued = ued
        self.seed = seed
        self.template = to_host(template_level)
        self.buffer = (LevelBuffer(self.template, buffer_config(ued), seed=seed)
                       if use_buffer else None)
        self.learnable: LevelBuffer | None = None

    # --- levels out --------------------------------------------------------------------------

    def fresh(self, key: jax.Array, n: int) -> EnvParams:
        """n fresh random levels from the generator."""
        return self.generator.sample(key, n)

    def replay(self, n: int) -> Replay:
        """n levels drawn from the buffer by score and staleness."""
        return self._need_buffer().sample(n)

    def get(self, ids: Any) -> EnvParams:
        """The stored levels of these ids (in order)."""
        return self._need_buffer().get(np.asarray(ids, np.int64))

    def mutate(self, key: jax.Array, levels: EnvParams) -> EnvParams:
        """ACCEL children: `levels.num_edits` edits of each level."""
        return self.generator.mutate(key, to_device(levels))

    def mutate_ids(self, key: jax.Array, parent_ids: Any) -> EnvParams:
        """ACCEL children of the stored levels `parent_ids` (read and edited in one call, so
        no insert can evict a parent in between)."""
        return self.mutate(key, self.get(parent_ids))

    def mutate_replay(self, key: jax.Array, replay: Replay) -> EnvParams:
        """ACCEL children of a replay batch's levels (as drawn: a parent evicted since then
        still has its children)."""
        return self.mutate(key, replay.levels)

    def sample_replay_decision(self) -> bool:
        """Replay (True) or new levels: the buffer's decision (the curriculum asks)."""
        return self._need_buffer().sample_replay_decision()

    def buffer_size(self) -> int | None:
        """Levels in the buffer (None without one)."""
        return None if self.buffer is None else len(self.buffer)

    def has_learnable(self) -> bool:
        """Whether SFL's learnable set holds levels."""
        return self.learnable is not None and len(self.learnable) > 0

    # --- scores in ---------------------------------------------------------------------------

    def insert(self, levels: EnvParams, scores: Any, max_returns: Any, policy_version: int,
               source: Source = Source.RANDOM, parent_ids: Any = -1) -> InsertResult:
        """Offer scored new (or mutated) levels to the buffer."""
        return self._need_buffer().insert_batch(
            to_host(levels), np.asarray(scores, np.float64), sources=source,
            parent_ids=parent_ids, policy_versions=policy_version,
            max_returns=np.asarray(max_returns, np.float64))

    def update(self, ids: Any, scores: Any, max_returns: Any, policy_version: int) -> None:
        """New scores for replayed levels."""
        self._need_buffer().update_batch(ids, np.asarray(scores, np.float64),
                                         max_returns=np.asarray(max_returns, np.float64),
                                         policy_versions=policy_version)

    # --- SFL ---------------------------------------------------------------------------------

    def set_learnable(self, levels: EnvParams, scores: Any, top_k: int) -> np.ndarray:
        """Keep the `top_k` levels of highest learnability (ties: the earlier level) as SFL's
        learnable set; returns their learnability scores, best first."""
        scores = np.asarray(scores, np.float64).reshape(-1)
        k = min(int(top_k), scores.shape[0])
        order = np.argsort(-scores, kind="stable")[:k]
        chosen = jax.tree.map(lambda x: np.asarray(x)[order], to_host(levels))
        learnable = LevelBuffer(self.template, BufferConfig(capacity=k, duplicate_check=False,
                                                            minimum_fill_ratio=0.0),
                                seed=self.seed)  # seeded: the saved set is reproducible
        # -inf (no episode ended) would be refused by the buffer: keep such levels at a score
        # below every real learnability instead, so the set always has k levels.
        kept = np.where(np.isfinite(scores[order]), scores[order], -1.0)
        learnable.insert_batch(chosen, kept, sources=Source.RANDOM)
        self.learnable = learnable
        return kept

    def sample_learnable(self, key: jax.Array, n: int) -> EnvParams:
        """n levels drawn uniformly (with replacement) from the learnable set."""
        if self.learnable is None or len(self.learnable) == 0:
            raise RuntimeError("the SFL learnable set is empty: call set_learnable first")
        ids = self.learnable.ids
        picks = np.asarray(jax.random.randint(key, (n,), 0, ids.shape[0]))
        return self.learnable.get(ids[picks])

    # --- statistics --------------------------------------------------------------------------

    def stats(self) -> dict[str, float]:
        """Buffer statistics for TensorBoard (empty without a buffer)."""
        out: dict[str, float] = {}
        buf = self.buffer
        if buf is not None:
            out["buffer/size"] = float(len(buf))
            if len(buf):
                scores = buf.scores
                finite = scores[np.isfinite(scores)]
                if finite.size:
                    out["buffer/score_mean"] = float(finite.mean())
                    out["buffer/score_max"] = float(finite.max())
                out["buffer/staleness_mean"] = float(buf.staleness().mean())
                out["buffer/depth_mean"] = float(buf.column("depth").mean())
                out["buffer/mutated_fraction"] = float(
                    (buf.column("source") == int(Source.MUTATION)).mean())
            for name, value in buf.stats.items():
                out[f"buffer/{name}"] = float(value)
        if self.learnable is not None and len(self.learnable):
            out["sfl/learnable_size"] = float(len(self.learnable))
            out["sfl/learnability_mean"] = float(self.learnable.scores.mean())
        return out

    # --- snapshots ---------------------------------------------------------------------------

    def save(self, folder: str | os.PathLike, step: int, state: dict[str, Any],
             keep: int | None = None) -> None:
        """Write the snapshot of step `step` atomically: the buffer, the SFL set and the
        caller's `state` (JSON-able); then delete all but the newest `keep` snapshots."""
        folder = Path(folder)
        folder.mkdir(parents=True, exist_ok=True)
        if self.buffer is not None:
            self.buffer.save(folder / f"buffer-{step}.msgpack")
        if self.learnable is not None:
            self.learnable.save(folder / f"learnable-{step}.msgpack")
        atomic_write_text(folder / f"state-{step}.json", json.dumps(state, indent=1))
        if keep is not None:
            for old in snapshot_steps(folder)[:-keep]:
                for name in SNAPSHOT_FILES:
                    (folder / name.format(old)).unlink(missing_ok=True)

    def load(self, folder: str | os.PathLike, step: int) -> dict[str, Any]:
        """Read the snapshot of step `step` (written by `save`); returns the caller's state."""
        folder = Path(folder)
        state_path = folder / f"state-{step}.json"
        if not state_path.is_file():
            raise FileNotFoundError(f"{state_path}: the level snapshot of step {step} is "
                                    "missing; the run folder is incomplete")
        try:
            state = json.loads(state_path.read_text())
        except (OSError, ValueError, RecursionError) as err:
            raise FileNotFoundError(f"{state_path}: unreadable ({err})") from None
        if self.buffer is not None:
            self.buffer = LevelBuffer.load(folder / f"buffer-{step}.msgpack", self.template)
        path = folder / f"learnable-{step}.msgpack"
        self.learnable = LevelBuffer.load(path, self.template) if path.is_file() else None
        return state

    def _need_buffer(self) -> LevelBuffer:
        if self.buffer is None:
            raise RuntimeError("this curriculum has no level buffer")
        return self.buffer


def snapshot_steps(folder: str | os.PathLike) -> list[int]:
    """The steps that have a complete snapshot in `folder`, oldest first."""
    folder = Path(folder)
    if not folder.is_dir():
        return []
    steps = []
    for path in folder.iterdir():
        match = SNAPSHOT_PATTERN.fullmatch(path.name)
        if match:
            steps.append(int(match.group(1)))
    return sorted(steps)


__all__ = ["LevelService", "buffer_config", "snapshot_steps", "to_device", "to_host"]

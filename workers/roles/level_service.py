"""LevelService: the level generator, the ACCEL mutator and the scored level buffer in one place.

It hands out batches of levels (fresh, replayed, mutated, or SFL's learnable ones) and takes
their scores back. Everything it holds is host-side state that a resumed run needs, so it
saves and loads itself as files in a snapshot folder:

    buffer-<step>.msgpack       the PLR buffer (levels, scores, staleness, its random state)
    learnable-<step>.msgpack    SFL's learnable set (a buffer whose scores are p (1 - p))
    sfl-window-<step>.msgpack   SFL's newest scored batches, each one's most learnable levels
                                (`add_learnable`, the Ray driver's continuous schedule)
    parents-<step>.msgpack      the levels the run's next step edits (ACCEL after a replay
                                step), in order: the buffer may have evicted some of them
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
from ued.curricula import Curriculum
from ued.levels import LevelGenerator
from ued.run_folder import SNAPSHOT_FILES

SNAPSHOT_PATTERN = re.compile(r"^state-(\d+)\.json$")


def to_host(levels: EnvParams) -> EnvParams:
    """A batch of levels as numpy arrays (what crosses process boundaries and goes into the
    buffer)."""
    return jax.tree.map(np.asarray, levels)


def to_device(levels: EnvParams) -> EnvParams:
    """A batch of levels as jax arrays with the dtypes of a fresh level, so the jitted update
    sees the same argument signature whatever the source and never recompiles."""
    return jax.tree.map(jnp.asarray, levels)


class LevelService:
    """Generator + mutator + buffer (+ SFL's learnable set). `curriculum`: the run's method,
    for what the buffer does its way (`buffer_config`: its settings, none where it keeps no
    buffer; `insert_scores`: the scores new levels enter with); None: no buffer."""

    def __init__(self, generator: LevelGenerator, template_level: EnvParams, ued: UEDSection,
                 seed: int = 0, curriculum: Curriculum | None = None):
        self.generator = generator
        self.ued = ued
        self.seed = seed
        self.template = to_host(template_level)
        self.curriculum = curriculum
        self.buffer = (LevelBuffer(self.template, curriculum.buffer_config(ued), seed=seed)
                       if curriculum is not None and curriculum.uses_buffer else None)
        self.learnable: LevelBuffer | None = None
        # The continuous schedule's window (`add_learnable`): the `sfl_top_k` most learnable
        # levels of each of the newest `sfl_num_batches` committed batches, in commit order.
        self.sfl_window: LevelBuffer | None = None

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

    def stored_levels(self, ids: Any) -> EnvParams | None:
        """The stored levels of these ids (in order), or None when the buffer no longer holds
        one of them."""
        buffer = self._need_buffer()
        ids = np.asarray(ids, np.int64).reshape(-1)
        if not np.isin(ids, buffer.ids).all():
            return None
        return buffer.get(ids)

    def mutate(self, key: jax.Array, levels: EnvParams) -> EnvParams:
        """ACCEL children: `levels.num_edits` edits of each level."""
        return self.generator.mutate(key, to_device(levels))

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
        """Offer scored new (or mutated) levels to the buffer, with the scores the curriculum
        gives them (`Curriculum.insert_scores`)."""
        buffer, levels = self._need_buffer(), to_host(levels)
        scores = self.curriculum.insert_scores(levels, np.asarray(scores, np.float64), buffer)
        return buffer.insert_batch(
            levels, np.asarray(scores, np.float64), sources=source,
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
        chosen, kept = most_learnable(levels, scores, top_k)
        self.learnable = self._level_set(chosen, kept)
        return kept

    def add_learnable(self, levels: EnvParams, scores: Any) -> np.ndarray:
        """One more batch of levels scored by learnability (the Ray driver's continuous
        schedule): the learnable set becomes the `sfl_top_k` most learnable levels of the
        newest `sfl_num_batches` batches added (ties: the earlier batch, then the earlier
        level); returns its scores, best first. Only each batch's own top `sfl_top_k` can be
        among them, so the window keeps those (`sfl_window`), a batch's at a time."""
        ued = self.ued
        n = np.asarray(scores).reshape(-1).shape[0]
        if n != ued.sfl_batch_size:  # the window counts batches of sfl_batch_size levels
            raise ValueError(f"add_learnable: {n} scores, but a batch holds "
                             f"ued.sfl_batch_size = {ued.sfl_batch_size} levels")
        k = min(ued.sfl_top_k, ued.sfl_batch_size)
        levels, scores = most_learnable(levels, scores, k)
        window = self.sfl_window
        if window is not None and len(window) and ued.sfl_num_batches > 1:
            # Slots hold the batches in commit order (each window is built afresh): keep the
            # newest sfl_num_batches - 1 batches' levels, the oldest one leaves.
            ids = window.ids[-(ued.sfl_num_batches - 1) * k:]
            levels = jax.tree.map(lambda a, b: np.concatenate([a, b]), window.get(ids), levels)
            scores = np.concatenate([window.scores[-ids.shape[0]:], scores])
        self.sfl_window = self._level_set(levels, scores, ued.sfl_num_batches * k)
        chosen, kept = most_learnable(levels, scores, ued.sfl_top_k)
        self.learnable = self._level_set(chosen, kept)
        return kept

    def _level_set(self, levels: EnvParams, scores: np.ndarray, capacity: int | None = None
                   ) -> LevelBuffer:
        """A buffer of `capacity` (default: as many as `levels`) holding `levels` in order."""
        capacity = scores.shape[0] if capacity is None else capacity
        out = LevelBuffer(self.template, BufferConfig(capacity=capacity, duplicate_check=False,
                                                      minimum_fill_ratio=0.0),
                          seed=self.seed)  # seeded: the saved set is reproducible
        out.insert_batch(levels, scores, sources=Source.RANDOM)
        return out

    def sfl_batch(self, key: jax.Array, n: int) -> EnvParams:
        """SFL's training batch on the host (`sfl_split`): fresh levels and levels drawn from
        the learnable set; all fresh while the set is empty (the continuous schedule before
        its first scored batch is committed)."""
        k_fresh, n_fresh, k_pick, n_pick = sfl_split(key, n, self.ued.sfl_fresh_fraction)
        if not self.has_learnable():
            n_fresh, n_pick = n, 0
        parts = []
        if n_fresh:
            parts.append(to_host(self.fresh(k_fresh, n_fresh)))
        if n_pick:
            parts.append(to_host(self.sample_learnable(k_pick, n_pick)))
        return jax.tree.map(lambda *xs: np.concatenate(xs), *parts)

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
             keep: int | None = None, parents: EnvParams | None = None) -> None:
        """Write the snapshot of step `step` atomically: the buffer, the SFL set, `parents`
        (the levels the next step edits, if any) and the caller's `state` (JSON-able); then
        delete all but the newest `keep` snapshots."""
        folder = Path(folder)
        folder.mkdir(parents=True, exist_ok=True)
        if parents is not None:
            count = jax.tree.leaves(parents)[0].shape[0]
            self._level_set(to_host(parents), np.zeros(count)).save(
                folder / f"parents-{step}.msgpack")
        if self.buffer is not None:
            self.buffer.save(folder / f"buffer-{step}.msgpack")
        if self.learnable is not None:
            self.learnable.save(folder / f"learnable-{step}.msgpack")
        if self.sfl_window is not None:
            self.sfl_window.save(folder / f"sfl-window-{step}.msgpack")
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
        path = folder / f"sfl-window-{step}.msgpack"
        self.sfl_window = LevelBuffer.load(path, self.template) if path.is_file() else None
        return state

    def load_parents(self, folder: str | os.PathLike, step: int) -> EnvParams | None:
        """The levels `save` kept as the next step's parents at step `step`, in order; None
        when that snapshot kept none."""
        path = Path(folder) / f"parents-{step}.msgpack"
        if not path.is_file():
            return None
        parents = LevelBuffer.load(path, self.template)
        return parents.get(parents.ids)

    def _need_buffer(self) -> LevelBuffer:
        if self.buffer is None:
            raise RuntimeError("this curriculum has no level buffer")
        return self.buffer


def most_learnable(levels: EnvParams, scores: Any, top_k: int) -> tuple[EnvParams, np.ndarray]:
    """The `top_k` levels of highest learnability (ties: the earlier level) and their scores,
    best first. -inf (no episode ended) would be refused by a buffer: such levels keep a score
    of -1, below every real learnability, so that a set always has `top_k` levels."""
    scores = np.asarray(scores, np.float64).reshape(-1)
    order = np.argsort(-scores, kind="stable")[:min(int(top_k), scores.shape[0])]
    chosen = jax.tree.map(lambda x: np.asarray(x)[order], to_host(levels))
    return chosen, np.where(np.isfinite(scores[order]), scores[order], -1.0)


def sfl_split(key: jax.Array, n: int, fresh_fraction: float
              ) -> tuple[jax.Array, int, jax.Array, int]:
    """How SFL's training batch of `n` levels is drawn with `key`: (fresh levels' key, their
    number, the learnable set's key, its number)."""
    k_fresh, k_pick = jax.random.split(key)
    n_fresh = int(round(n * fresh_fraction))
    return k_fresh, n_fresh, k_pick, n - n_fresh


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


__all__ = ["LevelService", "most_learnable", "sfl_split", "snapshot_steps",
           "to_device", "to_host"]

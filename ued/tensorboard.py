"""TensorBoard event files without TensorFlow: a thin scalar writer.

`flax.metrics.tensorboard` and `clu` import TensorFlow; this writes the same event files with
the `tensorboard` package alone (its `EventFileWriter` and the `Event` / `Summary` protos),
as scalar `simple_value` summaries, which TensorBoard's scalar dashboard reads directly.

    with SummaryWriter(run_dir / "events") as writer:
        writer.scalars({"episode/win_rate": 0.4, "loss/value": 0.01}, step=65536)
"""

from __future__ import annotations

import math
import os
import time
from collections.abc import Mapping

from tensorboard.compat.proto.event_pb2 import Event, SessionLog
from tensorboard.compat.proto.summary_pb2 import Summary
from tensorboard.summary.writer.event_file_writer import EventFileWriter


class SummaryWriter:
    """Scalar summaries into an event file in `logdir` (created if needed). `purge_step`: the
    first step this writer logs again (a resumed run redoes the steps after its checkpoint):
    TensorBoard, and `read_scalars`, drop the earlier files' points at steps >= it, so
    that no step has two points (a `SessionLog.START` event, as PyTorch's writer does)."""

    def __init__(self, logdir: str | os.PathLike, flush_secs: float = 10.0,
                 purge_step: int | None = None):
        os.makedirs(logdir, exist_ok=True)
        self.logdir = str(logdir)
        self._writer = EventFileWriter(self.logdir, flush_secs=flush_secs)
        if purge_step is not None:
            self._writer.add_event(Event(wall_time=time.time(), step=int(purge_step),
                                         session_log=SessionLog(status=SessionLog.START)))

    def scalar(self, tag: str, value: float, step: int) -> None:
        self.scalars({tag: value}, step)

    def scalars(self, values: Mapping[str, float], step: int,
                wall_time: float | None = None) -> None:
        """One event holding every finite value of `values` (NaN and inf are skipped)."""
        items = [Summary.Value(tag=tag, simple_value=float(v)) for tag, v in values.items()
                 if math.isfinite(float(v))]
        if not items:
            return
        event = Event(wall_time=time.time() if wall_time is None else wall_time,
                      step=int(step), summary=Summary(value=items))
        self._writer.add_event(event)

    def flush(self) -> None:
        self._writer.flush()

    def close(self) -> None:
        self._writer.close()

    def __enter__(self) -> SummaryWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def read_scalars(logdir: str | os.PathLike) -> dict[str, list[tuple[int, float]]]:
    """Every scalar in the event files of `logdir`: tag -> [(step, value), ...] in file order
    (for tests and scripts; TensorBoard itself reads the files directly). A writer's
    `purge_step` drops the points before it at steps >= it, as TensorBoard does."""
    from tensorboard.backend.event_processing.event_file_loader import RawEventFileLoader

    out: dict[str, list[tuple[int, float]]] = {}
    names = sorted(n for n in os.listdir(logdir) if "tfevents" in n)
    for name in names:
        for record in RawEventFileLoader(os.path.join(logdir, name)).Load():
            event = Event.FromString(record)
            if event.HasField("session_log") and event.session_log.status == SessionLog.START:
                for points in out.values():
                    points[:] = [p for p in points if p[0] < event.step]
            for value in event.summary.value:
                if value.HasField("simple_value"):
                    out.setdefault(value.tag, []).append((event.step, value.simple_value))
    return out


__all__ = ["SummaryWriter", "read_scalars"]

"""The scored, prioritised, persistent level buffer of PLR / Robust PLR / ACCEL.

    from level_buffer import LevelBuffer, Source
    buf = LevelBuffer(template_level, capacity=4000)
    buf.insert_batch(levels, scores, sources=Source.RANDOM)
    if buf.sample_replay_decision():
        replay = buf.sample(128)
        ...
        buf.update_batch(replay.ids, new_scores, max_returns=...)
    buf.save("run/buffer.msgpack"); buf = LevelBuffer.load("run/buffer.msgpack", template_level)

See docs/level_buffer.md for the semantics, the file format and the `tabx buffer` CLI.
"""

from level_buffer.buffer import DUPLICATE, INSERTED, REJECTED, InsertResult, LevelBuffer, Replay
from level_buffer.config import BufferConfig, Source
from level_buffer.fileformat import FORMAT_VERSION, BufferFileError
from level_buffer.state import SLOT_FIELDS, BufferState
from level_buffer.tree import LevelSpec

__all__ = [
    "DUPLICATE", "FORMAT_VERSION", "INSERTED", "REJECTED", "SLOT_FIELDS", "BufferConfig",
    "BufferFileError", "BufferState", "InsertResult", "LevelBuffer", "LevelSpec", "Replay",
    "Source",
]

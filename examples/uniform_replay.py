"""UniformReplay: Robust PLR whose replay levels are drawn uniformly from the level buffer,
whatever their scores or staleness. It asks what prioritised replay adds: the buffer still
keeps the highest-regret levels (insertion is by score), but a replay no longer favours them.

A UED method in one file, used by import path; from this folder:

    tabx train quickstart ued.method=uniform_replay:UniformReplay
    tabx sweep new_method_vs_baselines.yaml && tabx sweep report sweeps/new_method_vs_baselines

Every driver runs it (local, Ray's deterministic, asynchronous and continuous schedules),
with resume and sweeps, because every decision is a hook of `ued.curricula.Curriculum`
(docs/new_method.md). Here only one hook changes: the level buffer's replay distribution.
"""

from __future__ import annotations

from typing import Any

from level_buffer import BufferConfig
from ued.curricula.robust_plr import RobustPLR


class UniformReplay(RobustPLR):
    """Robust PLR (new levels scored by Explorers, replays trained on) with uniform replay."""

    name = "uniform_replay"

    def buffer_config(self, ued: Any) -> BufferConfig:
        # Every stored level alike: no rank weighting and no staleness term.
        return self.with_replay(super().buffer_config(ued), prioritization="uniform",
                                staleness_coeff=0.0)

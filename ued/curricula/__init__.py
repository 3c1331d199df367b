"""UED curricula: one method per module, each a `Curriculum` (`ued.curricula.base`: the hooks
every driver calls) deciding which kind of step comes next and what it plays.

A UED run is a sequence of steps; every step rolls the policy out on one batch of
`num_envs` levels for `num_steps` steps. What differs between methods is where the batch comes
from and whether the rollout also trains the policy:

    DR          every step: fresh random levels, gradient update                (Jakobi 1997)
    PLR         replay decision: buffer levels (gradient) or fresh levels
                (gradient too: "exploratory gradient updates")                  (Jiang 2021a)
    Robust PLR  as PLR, but fresh levels are only scored, never trained on      (Jiang 2021b)
    ACCEL       as Robust PLR, and after every replay step a step that mutates
                the replayed levels and scores the children (no gradient)       (Parker-Holder 2022)
    SFL         every step: half fresh levels, half drawn uniformly from the
                most learnable levels (p (1 - p)) of a large random batch that is
                rebuilt every `sfl_update_freq` steps; always a gradient update (Rutherford 2024)

`ued.registry` names the built-in ones; any other subclass is used by import path
(`ued.method: my_module:MyCurriculum`, docs/new_method.md).
"""

from ued.curricula.accel import ACCEL
from ued.curricula.base import Branch, Curriculum, LevelRequest, ReplayDecider
from ued.curricula.dr import DomainRandomization
from ued.curricula.plr import PLR
from ued.curricula.robust_plr import RobustPLR
from ued.curricula.sfl import SFL

__all__ = ["ACCEL", "PLR", "SFL", "Branch", "Curriculum", "DomainRandomization",
           "LevelRequest", "ReplayDecider", "RobustPLR"]

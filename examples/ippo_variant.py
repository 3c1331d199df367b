"""A learner variant in one file: IPPO whose value loss clips at a range of its own.

IPPO clips the value's change per update at `learner.clip_eps`, the policy ratio's clip (the
paper's 0.05). Here the value clips at `my_ippo.value_clip` instead, so the critic can move
further per update while the policy stays as tightly clipped. From this folder:

    tabx train quickstart algorithm=ippo_variant:MyIPPO my_ippo.value_clip=0.2

The class says what it reads and supports by its class attributes (docs/new_learner.md); what
it does not set, it inherits from IPPO (a value head, several seeds, the UED curricula, several
devices).
"""

from __future__ import annotations

from dataclasses import dataclass

from ued.errors import check
from ued.learners.ippo import IPPO
from ued.learners.ppo import value_loss


@dataclass(frozen=True)
class ValueClip:
    """The `my_ippo:` section of a config."""

    value_clip: float = 0.2  # the value's change per update clips at this, not clip_eps


class MyIPPO(IPPO):
    """IPPO with its own value-loss clip range."""

    name = "my_ippo"
    settings_section = "my_ippo"  # the config's top-level key of its settings
    settings_type = ValueClip

    def __init__(self, env_config, ppo=None, team="ally", opponent="heuristic:medium",
                 settings: ValueClip | None = None):
        self.settings = settings if settings is not None else ValueClip()
        super().__init__(env_config, ppo, team, opponent)

    @classmethod
    def validate_settings(cls, settings: ValueClip, learner) -> None:
        check(settings.value_clip > 0, "my_ippo.value_clip",
              f"must be > 0, got {settings.value_clip}")

    def critic_loss(self, values, batch, valid, count, axis_name):
        """IPPO's per-agent value loss (valid agent steps), clipped at `value_clip` (where
        `learner.clip_value` clips at all)."""
        loss = value_loss(values, batch["value"], batch["targets"], valid,
                          self.settings.value_clip, self.ppo.clip_value, count)
        return loss, {"loss/value": loss}

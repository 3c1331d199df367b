"""The registry of UED curricula and learners: what each method needs, by name, without
building it.

An entry says what its method needs: a curriculum whether it keeps a level buffer, which
level scores it computes and whether it has steps for Explorers; a learner which config
sections it reads and what it supports (a value head, several seeds in one program, the UED
curricula, several devices). Config validation, `tabx runs check` and the drivers read the
entries; only `CurriculumEntry.build` and `LearnerEntry.load` import the method's module, so
reading the registry compiles and allocates nothing.

A method is registered once, here (the built-in ones) or by its own module (`register_curriculum`,
`register_learner`; tests/example_curriculum.py is a worked example). `build`/`cls` name the
method's class as "package.module:Class" (imported when first used) or are the class itself.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any


def _resolve(ref: str | Callable[..., Any]) -> Any:
    """The object `ref` names ("package.module:attribute"), or `ref` itself."""
    if not isinstance(ref, str):
        return ref
    module, _, attribute = ref.partition(":")
    return getattr(importlib.import_module(module), attribute)


# --- curricula -----------------------------------------------------------------------------------


@dataclass(frozen=True)
class CurriculumEntry:
    """A UED method (`ued.method`): what it needs, and its class (a `ued.curricula.Curriculum`
    whose `from_config(ued_section)` builds it)."""

    name: str
    cls: str | Callable[..., Any]
    uses_buffer: bool  # keeps a level buffer (snapshotted with each checkpoint)
    # The level scores it computes (`ued.scores`): "ued.score" is the config's choice of regret
    # estimate (max_mc or pvl), by which buffer levels are ranked.
    scores: tuple[str, ...]
    explorers: bool  # has steps that only score levels, which Explorers can take
    section: str = "ued"  # the config section of its settings

    def build(self, section: Any) -> Any:
        """The curriculum, configured by `section` (the config's UEDSection)."""
        return _resolve(self.cls).from_config(section)


CURRICULA: dict[str, CurriculumEntry] = {}


def register_curriculum(entry: CurriculumEntry) -> CurriculumEntry:
    """Add (or replace) the curriculum of `entry.name`."""
    CURRICULA[entry.name] = entry
    return entry


def curriculum_entry(method: str) -> CurriculumEntry:
    """The registry entry of `method`; ValueError naming the registered ones if none."""
    try:
        return CURRICULA[method]
    except KeyError:
        raise ValueError(f"unknown UED method {method!r}; expected one of "
                         f"{', '.join(CURRICULA)}") from None


def curriculum_for(section: Any) -> Any:
    """The curriculum of a UEDSection (`section.method` looked up here)."""
    return curriculum_entry(section.method).build(section)


for _entry in (
        CurriculumEntry("dr", "ued.curricula:DomainRandomization", uses_buffer=False,
                        scores=(), explorers=False),
        CurriculumEntry("plr", "ued.curricula:PLR", uses_buffer=True, scores=("ued.score",),
                        explorers=False),
        CurriculumEntry("robust_plr", "ued.curricula:RobustPLR", uses_buffer=True,
                        scores=("ued.score",), explorers=True),
        CurriculumEntry("accel", "ued.curricula:ACCEL", uses_buffer=True,
                        scores=("ued.score",), explorers=True),
        CurriculumEntry("sfl", "ued.curricula:SFL", uses_buffer=False,
                        scores=("learnability",), explorers=True)):
    register_curriculum(_entry)


# --- learners ------------------------------------------------------------------------------------


@dataclass(frozen=True)
class LearnerEntry:
    """A learner (`algorithm`): the config it reads, what it supports, and its class (called
    as `cls(env_config, learner_section, team, opponent[, settings_section])`)."""

    name: str
    cls: str | Callable[..., Any]
    family: str  # how config errors name its kind: "PPO learners", "Q-learners"
    # Its own config section beside `learner` (an attribute of TrainConfig), passed to the
    # class as its fifth argument; None: `learner` only.
    settings: str | None = None
    ppo_settings: bool = False  # reads the `learner` fields only PPO reads (ued.config)
    # "section.field" settings only this learner reads: any other learner must leave them at
    # their defaults, or the config is refused with `refusal` (formatted with `algorithm`).
    own_settings: tuple[str, ...] = ()
    refusal: str = ""
    value_head: bool = False  # has a value head (run.value_error_every)
    seeds: bool = False  # several seeds train in one vmapped program (`seeds`)
    curricula: bool = False  # the UED curricula can train it (ued.method)
    devices: bool = False  # data parallel over several devices (learner.num_devices)

    def load(self) -> type:
        """The learner class (imports its module)."""
        return _resolve(self.cls)


LEARNERS: dict[str, LearnerEntry] = {}


def register_learner(entry: LearnerEntry) -> LearnerEntry:
    """Add (or replace) the learner of `entry.name`."""
    LEARNERS[entry.name] = entry
    return entry


def learner_entry(algorithm: str) -> LearnerEntry:
    """The registry entry of `algorithm`; ValueError naming the registered ones if none."""
    try:
        return LEARNERS[algorithm]
    except KeyError:
        raise ValueError(f"unknown algorithm {algorithm!r}; expected one of "
                         f"{', '.join(LEARNERS)}") from None


def learners_where(test: Callable[[LearnerEntry], bool]) -> tuple[str, ...]:
    """The names of the registered learners whose entry passes `test`, in registry order."""
    return tuple(name for name, entry in LEARNERS.items() if test(entry))


_RND = tuple(f"learner.rnd_{name}" for name in (
    "reward_coef", "gae_coef", "loss_coef", "lr", "update_epochs", "hidden_dim", "output_dim",
    "layers"))
_MIXER = ("qlearning.mixer_embed_dim", "qlearning.mixer_hidden_dim",
          "qlearning.mixer_init_scale")
_PPO = dict(family="PPO learners", ppo_settings=True, value_head=True, seeds=True,
            curricula=True, devices=True)
_Q = dict(family="Q-learners", settings="qlearning")

for _entry in (
        LearnerEntry("mappo", "ued.learners.mappo:MAPPO", **_PPO),
        LearnerEntry("ippo", "ued.learners.ippo:IPPO", **_PPO),
        LearnerEntry("mappo_rnd", "ued.learners.rnd:MAPPORND", **_PPO, own_settings=_RND,
                     refusal="RND settings go with algorithm mappo_rnd, not {algorithm}"),
        LearnerEntry("iql", "ued.learners.qlearning:IQL", **_Q),
        LearnerEntry("vdn", "ued.learners.qlearning:VDN", **_Q),
        LearnerEntry("qmix", "ued.learners.qlearning:QMIX", **_Q, own_settings=_MIXER,
                     refusal="a setting of QMIX's mixing network; {algorithm} has none")):
    register_learner(_entry)
del _entry


__all__ = ["CURRICULA", "LEARNERS", "CurriculumEntry", "LearnerEntry", "curriculum_entry",
           "curriculum_for", "learner_entry", "learners_where", "register_curriculum",
           "register_learner"]

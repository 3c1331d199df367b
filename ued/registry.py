"""The registry of UED curricula and learners: what each method needs, by name, without
building it.

A curriculum's entry is its name and class: the class says what it needs (a level buffer, its
branches, its scores; `ued.curricula.base`), and any other `Curriculum` subclass is used by
import path (`ued.method: my_module:MyCurriculum`, `curriculum_class`). A learner's entry says
which config sections it reads and what it supports (a value head, several seeds in one
program, the UED curricula, several devices). Config validation, `tabx runs check` and the
drivers read them; importing a class compiles and allocates nothing.

A method is registered once, here (the built-in ones) or by its own module (`register_curriculum`,
`register_learner`; tests/example_curriculum.py is a worked example). `build`/`cls` name the
method's class as "package.module:Class" (imported when first used) or are the class itself.
"""

from __future__ import annotations

import importlib
import os
import sys
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from ued.errors import ConfigError


def _resolve(ref: str | Callable[..., Any]) -> Any:
    """The object `ref` names ("package.module:attribute"), or `ref` itself."""
    if not isinstance(ref, str):
        return ref
    module, _, attribute = ref.partition(":")
    return getattr(importlib.import_module(module), attribute)


# --- curricula -----------------------------------------------------------------------------------


@dataclass(frozen=True)
class CurriculumEntry:
    """A UED method (`ued.method`) by name: its class (a `ued.curricula.Curriculum`, which
    says what it needs: a buffer, its branches, its scores), as "package.module:Class" or the
    class itself."""

    name: str
    cls: str | Callable[..., Any]

    def load(self) -> type:
        """The curriculum class (imports its module)."""
        return _resolve(self.cls)

    def build(self, section: Any) -> Any:
        """The curriculum, configured by `section` (the config's UEDSection)."""
        return self.load().from_config(section)


CURRICULA: dict[str, CurriculumEntry] = {}


def register_curriculum(entry: CurriculumEntry) -> CurriculumEntry:
    """Add (or replace) the curriculum of `entry.name`."""
    CURRICULA[entry.name] = entry
    return entry


def is_import_path(ref: str) -> bool:
    """Whether a method or algorithm name is an import path, "module:Class"."""
    module, colon, attribute = ref.partition(":")
    return bool(colon and module and attribute)


def import_path(ref: str, key: str) -> Any:
    """The object "module:Attribute" names, imported as `python -m` would from the current
    directory (which Ray's actors and Tune's trials then import from too). ConfigError
    naming `key` when it cannot be imported."""
    module, _, attribute = ref.partition(":")
    if "" not in sys.path and os.getcwd() not in sys.path:
        sys.path.insert(0, os.getcwd())
    try:
        found = importlib.import_module(module)
    except Exception as err:  # noqa: BLE001 - the user's module: any error is theirs to fix
        raise ConfigError(f"{key}: cannot import {module!r} for {ref!r} "
                          f"({type(err).__name__}: {str(err).splitlines()[0] if str(err) else ''}"
                          f"); run from its folder or put it on PYTHONPATH") from None
    try:
        return getattr(found, attribute)
    except AttributeError:
        raise ConfigError(f"{key}: module {module!r} has no {attribute!r} (for {ref!r})"
                          ) from None


def curriculum_class(method: str, key: str = "ued.method") -> type:
    """The class of `method`: a registered name or an import path "module:Class" (which must
    name a `ued.curricula.Curriculum` subclass). ValueError naming the registered ones for an
    unknown name; ConfigError naming `key` for a path that does not lead to a curriculum."""
    if is_import_path(method):
        from ued.curricula import Curriculum

        cls = import_path(method, key)
        if not (isinstance(cls, type) and issubclass(cls, Curriculum)):
            raise ConfigError(f"{key}: {method!r} is not a ued.curricula.Curriculum subclass")
        return cls
    return curriculum_entry(method).load()


def curriculum_entry(method: str) -> CurriculumEntry:
    """The registry entry of `method`; ValueError naming the registered ones if none."""
    try:
        return CURRICULA[method]
    except KeyError:
        raise ValueError(f"unknown UED method {method!r}; expected one of "
                         f"{', '.join(CURRICULA)} or an import path module:Class") from None


def curriculum_for(section: Any) -> Any:
    """The curriculum of a UEDSection (`section.method`: a name or an import path)."""
    return curriculum_class(section.method).from_config(section)


for _entry in (CurriculumEntry("dr", "ued.curricula.dr:DomainRandomization"),
               CurriculumEntry("plr", "ued.curricula.plr:PLR"),
               CurriculumEntry("robust_plr", "ued.curricula.robust_plr:RobustPLR"),
               CurriculumEntry("accel", "ued.curricula.accel:ACCEL"),
               CurriculumEntry("sfl", "ued.curricula.sfl:SFL")):
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


__all__ = ["CURRICULA", "LEARNERS", "CurriculumEntry", "LearnerEntry", "curriculum_class",
           "curriculum_entry", "curriculum_for", "import_path", "is_import_path",
           "learner_entry", "learners_where", "register_curriculum", "register_learner"]

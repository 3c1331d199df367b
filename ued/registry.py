"""The registry of UED curricula and learners: what each method needs, by name, without
building it, and the import of a method's class given by path ("module:Class").

A curriculum's entry is its name and class: the class says what it needs (a level buffer, its
branches, its scores, a settings section of its own; `ued.curricula.base`), and any other
`Curriculum` subclass is used by import path (`ued.method: my_module:MyCurriculum`,
`curriculum_class`). Importing a class compiles and allocates nothing.

A learner is its class: `LEARNERS` maps the built-in names to their classes' paths, and
`algorithm: module:Class` names any other (`learner_class`). What a learner reads and supports
(its own config section, a value head, several seeds in one program, the UED curricula,
several devices) are class attributes (ued.learners.ppo.PPOLearner), read without building it.

`import_path` imports a class given by path for any config key, and `import_env` hands the
folders it found them in to the run's other processes (Ray actors, sweep trials).
"""

from __future__ import annotations

import importlib
import os
import re
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ued.errors import ConfigError


def _resolve(ref: str | Callable[..., Any]) -> Any:
    """The object `ref` names ("package.module:attribute"), or `ref` itself."""
    if not isinstance(ref, str):
        return ref
    module, _, attribute = ref.partition(":")
    return getattr(importlib.import_module(module), attribute)


# --- classes by import path ----------------------------------------------------------------------

# Folders (os.pathsep-separated) where `import_path` also looks for a module: the Ray actors and
# the sweep's trials get the folders of the driver's by-path imports here (`import_env`).
IMPORT_PATH_ENV = "TABX_IMPORT_PATH"
_PATH = re.compile(r"[A-Za-z_]\w*(\.[A-Za-z_]\w*)*:[A-Za-z_]\w*(\.[A-Za-z_]\w*)*")
_ROOTS: dict[str, None] = {}  # the folders this process's by-path imports came from


def import_path(ref: str, key: str) -> Any:
    """The object `ref` names as "package.module:Attribute", a class defined outside the project
    included, for the config key `key`. The module is looked for on sys.path, then in the
    current folder and the folders of $TABX_IMPORT_PATH. A `ref` of another form, a module that
    is not found or fails to import, or a missing attribute is a ConfigError, one line naming
    `key`."""
    if not isinstance(ref, str) or not _PATH.fullmatch(ref):
        raise ConfigError(f"{key}: expected a class as module:Class (e.g. my_module:MyClass), "
                          f"got {ref!r}")
    module_name, _, attribute = ref.partition(":")
    for folder in [os.getcwd(), *os.environ.get(IMPORT_PATH_ENV, "").split(os.pathsep)]:
        if folder and folder not in sys.path:
            sys.path.append(folder)  # last: a file there shadows no installed module
    try:
        module = importlib.import_module(module_name)
    except ModuleNotFoundError as err:
        if err.name and (module_name + ".").startswith(err.name + "."):
            raise ConfigError(f"{key}: no module {err.name!r} (looked on sys.path and in "
                              f"{os.getcwd()}); run from its folder or put that folder on "
                              f"PYTHONPATH") from None
        raise ConfigError(f"{key}: importing {module_name} failed: {err}") from None
    except Exception as err:  # noqa: BLE001 - any error of the user's module, in one line
        text = " ".join(str(err).split())
        raise ConfigError(f"{key}: importing {module_name} failed: {type(err).__name__}: "
                          f"{text}") from None
    value: Any = module
    for part in attribute.split("."):
        if not hasattr(value, part):
            raise ConfigError(f"{key}: {module_name} ({getattr(module, '__file__', '?')}) has "
                              f"no {attribute!r}")
        value = getattr(value, part)
    _remember_root(module_name)
    return value


def _remember_root(module_name: str) -> None:
    """Note the sys.path folder the top-level package of `module_name` was found in."""
    spec = getattr(sys.modules.get(module_name.split(".")[0]), "__spec__", None)
    if spec is None:
        return
    if spec.submodule_search_locations:  # a package: its folder's parent
        root = Path(list(spec.submodule_search_locations)[0]).parent
    elif spec.origin and spec.has_location:  # a module file: its folder
        root = Path(spec.origin).parent
    else:
        return
    _ROOTS[str(root)] = None


def import_env() -> dict[str, str]:
    """The environment variable that lets another process of this run (a Ray actor, a sweep
    trial) import what this one imported by path: {IMPORT_PATH_ENV: folders}, or {} if
    nothing was."""
    folders = dict.fromkeys([*os.environ.get(IMPORT_PATH_ENV, "").split(os.pathsep), *_ROOTS])
    folders.pop("", None)
    return {IMPORT_PATH_ENV: os.pathsep.join(folders)} if folders else {}


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

    def build(self, section: Any, settings: Any = None) -> Any:
        """The curriculum, configured by `section` (the config's UEDSection) and `settings`
        (its own section: `curriculum_for`)."""
        return build_curriculum(self.load(), section, settings)


CURRICULA: dict[str, CurriculumEntry] = {}


def register_curriculum(entry: CurriculumEntry) -> CurriculumEntry:
    """Add (or replace) the curriculum of `entry.name`."""
    CURRICULA[entry.name] = entry
    return entry


def is_import_path(ref: str) -> bool:
    """Whether a method or algorithm name is an import path, "module:Class"."""
    module, colon, attribute = ref.partition(":")
    return bool(colon and module and attribute)


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


def curriculum_for(section: Any, settings: Any = None) -> Any:
    """The curriculum of a UEDSection (`section.method`: a name or an import path) and its own
    settings section, an instance of its class's `settings_type` (default: that type's
    defaults; a config's: `TrainConfig.curriculum_settings()`)."""
    return build_curriculum(curriculum_class(section.method), section, settings)


def build_curriculum(cls: type, section: Any, settings: Any = None) -> Any:
    """`cls.from_config(section, settings)`, `settings` defaulting to `cls.settings_type()`
    (None for a class without a section, which takes none: ValueError)."""
    if cls.settings_type is None and settings is not None:
        raise ValueError(f"{cls.name} has no settings section of its own: it takes no settings")
    if settings is None and cls.settings_type is not None:
        settings = cls.settings_type()
    return cls.from_config(section, settings)


for _entry in (CurriculumEntry("dr", "ued.curricula.dr:DomainRandomization"),
               CurriculumEntry("plr", "ued.curricula.plr:PLR"),
               CurriculumEntry("robust_plr", "ued.curricula.robust_plr:RobustPLR"),
               CurriculumEntry("accel", "ued.curricula.accel:ACCEL"),
               CurriculumEntry("sfl", "ued.curricula.sfl:SFL")):
    register_curriculum(_entry)


# --- learners ------------------------------------------------------------------------------------

# The built-in learners: `algorithm` name -> class. A learner's class says what it reads and
# supports (the class attributes of ued.learners.ppo.PPOLearner); `algorithm: module:Class`
# names any other learner class by its import path, registered nowhere.
LEARNERS: dict[str, str] = {
    "mappo": "ued.learners.mappo:MAPPO",
    "ippo": "ued.learners.ippo:IPPO",
    "mappo_rnd": "ued.learners.rnd:MAPPORND",
    "iql": "ued.learners.qlearning:IQL",
    "vdn": "ued.learners.qlearning:VDN",
    "qmix": "ued.learners.qlearning:QMIX",
}


# What config validation and the drivers read of a learner class (ued.learners.ppo.PPOLearner
# has them all): a class by path without them is refused when the config is read.
LEARNER_ATTRIBUTES = ("name", "family", "settings_section", "settings_type", "ppo_settings",
                      "own_settings", "refusal", "value_head", "seeds", "curricula", "devices",
                      "validate_settings", "init", "update", "score", "policy_step")


def learner_class(algorithm: str, key: str = "algorithm") -> type:
    """The learner class of `algorithm`: a built-in name (`LEARNERS`) or "module:Class" (a
    subclass of ued.learners.ppo.PPOLearner). ConfigError naming `key` when it is neither."""
    if algorithm in LEARNERS:
        return _resolve(LEARNERS[algorithm])
    if not isinstance(algorithm, str) or ":" not in algorithm:
        raise ConfigError(f"{key}: must be one of {', '.join(LEARNERS)} or a learner class "
                          f"given as module:Class, got {algorithm!r}")
    cls = import_path(algorithm, key)
    missing = [name for name in LEARNER_ATTRIBUTES if not hasattr(cls, name)]
    if not isinstance(cls, type) or missing:
        raise ConfigError(f"{key}: {algorithm} is not a learner class (a subclass of "
                          f"ued.learners.ppo.PPOLearner; it has no {', '.join(missing)})")
    return cls


def learners_where(test: Callable[[type], bool]) -> tuple[str, ...]:
    """The names of the built-in learners whose class passes `test`, in `LEARNERS` order."""
    return tuple(name for name in LEARNERS if test(learner_class(name)))


__all__ = ["CURRICULA", "IMPORT_PATH_ENV", "LEARNERS", "LEARNER_ATTRIBUTES", "CurriculumEntry",
           "build_curriculum", "curriculum_class", "curriculum_entry", "curriculum_for",
           "import_env", "import_path", "is_import_path", "learner_class", "learners_where",
           "register_curriculum"]

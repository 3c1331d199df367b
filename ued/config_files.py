"""The training configs shipped with the package, found by name.

    resolve_config("quickstart")             -> .../configs/ued/quickstart.yaml
    resolve_config("ued/accel_zone")         -> .../configs/ued/accel_zone.yaml
    resolve_config("my_runs/tiny.yaml")      -> my_runs/tiny.yaml (an existing file wins)

A config's name is its path inside the configs folder without `.yaml` (`marl/mappo_crossfire`);
a bare stem (`quickstart`) names it too when only one config has that stem. The folder is
`ued/data/configs` in an installed package (the build copies the repository's `configs/` there,
setup.py) and the repository's own `configs/` in a source checkout, so `tabx train NAME` works
from any directory, and a name that is neither a file nor a config fails with the close names.
"""

from __future__ import annotations

import difflib
from importlib import resources
from pathlib import Path

from ued.errors import ConfigError

PACKAGED_FOLDER = ("data", "configs")  # inside the `ued` package, in an installed wheel
SUFFIXES = (".yaml", ".yml")


def config_folder() -> Path | None:
    """Where the shipped configs are: the installed package's copy, else the source checkout's
    `configs/`; None when neither exists."""
    packaged = Path(str(resources.files("ued").joinpath(*PACKAGED_FOLDER)))
    if packaged.is_dir():
        return packaged
    checkout = Path(str(resources.files("ued"))).parent / "configs"
    return checkout if checkout.is_dir() else None


def bundled_configs() -> dict[str, Path]:
    """Name (`ued/quickstart`) -> file of every shipped config, sorted by name."""
    folder = config_folder()
    if folder is None:
        return {}
    files = sorted(p for p in folder.rglob("*") if p.suffix in SUFFIXES and p.is_file())
    return {p.relative_to(folder).with_suffix("").as_posix(): p for p in files}


SWEEP_FOLDER = "sweeps"  # shipped sweep files (`tabx sweep`), not training configs


def list_configs() -> list[str]:
    """The names of the shipped training configs, sorted (the sweep files under sweeps/ are
    found by name too, but they are not configs a run trains with)."""
    return [name for name in bundled_configs() if not name.startswith(f"{SWEEP_FOLDER}/")]


def resolve_config(name_or_path: str | Path) -> Path:
    """The config file that `name_or_path` means: an existing file, else a shipped config's name
    (with or without its folder and `.yaml`). Raises ConfigError naming the close names."""
    path = Path(name_or_path)
    if path.is_file():
        return path
    text = str(name_or_path).strip().replace("\\", "/")
    key = text[: -len(path.suffix)] if path.suffix in SUFFIXES else text
    configs = bundled_configs()
    if key in configs:
        return configs[key]
    by_stem = [name for name in configs if name.rsplit("/", 1)[-1] == key]
    if len(by_stem) == 1:
        return configs[by_stem[0]]
    if len(by_stem) > 1:
        raise ConfigError(f"config name {text!r} is ambiguous: use one of {', '.join(by_stem)}")
    # A folder, a device, a FIFO that is no shipped config's name: never opened (a FIFO blocks).
    if path.exists():
        kind = "a folder" if path.is_dir() else "not a regular file"
        raise ConfigError(f"{path}: cannot read the config ({kind}; give a YAML file or a "
                          "shipped config's name)")
    stems = {name.rsplit("/", 1)[-1]: name for name in configs}
    close = difflib.get_close_matches(key, list(configs), n=3, cutoff=0.6)
    close += [stems[s] for s in difflib.get_close_matches(key.rsplit("/", 1)[-1], list(stems),
                                                          n=3, cutoff=0.6)
              if stems[s] not in close]
    hint = (f"; close names: {', '.join(close[:3])}" if close
            else "; shipped configs: tabx train --list-configs")
    raise ConfigError(f"{text}: cannot read the config (no such file, and no shipped config of "
                      f"that name{hint})")


__all__ = ["bundled_configs", "config_folder", "list_configs", "resolve_config"]

"""The error type of every config, suite and run-folder problem in `ued` and `workers`.

Lives in its own module so that config sections defined next to what they configure
(`ued.levels.LevelSpace`, ...) can raise it without importing `ued.config`.
"""

from __future__ import annotations


class ConfigError(ValueError):
    """A config that cannot be used; the message names the source, the key and the problem."""


def check(cond: bool, key: str, message: str) -> None:
    """Raise `ConfigError("key: message")` unless `cond`."""
    if not cond:
        raise ConfigError(f"{key}: {message}")

"""The error type of every config, suite and run-folder problem in `ued` and `workers`.

Lives in its own module so that config sections defined next to what they configure
(`ued.levels.LevelSpace`, ...) can raise it without importing `ued.config`.
"""

from __future__ import annotations

from tabx.errors import UserError


class ConfigError(UserError, ValueError):
    """A config that cannot be used; the message names the source, the key and the problem.
    A `UserError`: the command line prints it as one line."""


def gist(err: BaseException) -> str:
    """An error in one short line: its type and the first line of its message, without
    TensorStore's object dump (for messages that quote a library's error)."""
    text = str(err).strip()
    for dump in (" See full TensorStore details", " [tensorstore_spec="):
        text = text.split(dump)[0]
    return f"{type(err).__name__}: {text.splitlines()[0][:300]}" if text else type(err).__name__


def check(cond: bool, key: str, message: str) -> None:
    """Raise `ConfigError("key: message")` unless `cond`."""
    if not cond:
        raise ConfigError(f"{key}: {message}")

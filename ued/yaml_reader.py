"""The one reader of the project's YAML files (training configs, run folders' `config.yaml`,
evaluation suites): strict, so that a damaged or mistyped file is one clear error, not a
traceback and not a different config.

Beyond YAML's own syntax it refuses what a config never needs and what would make a typo or a
damaged file load as something else: a key repeated in a mapping (YAML would keep the last),
anchors and aliases (`&a` / `*a`: shared or exponentially repeated values), nesting deeper
than `MAX_YAML_DEPTH`, bytes that are not UTF-8, and an empty file. Errors are `ConfigError`s
in one line: the source, the problem and its line and column.
"""

from __future__ import annotations

from typing import Any

import yaml

from ued.errors import ConfigError

MAX_YAML_DEPTH = 32  # configs nest two levels; suites four


class _StrictLoader(yaml.SafeLoader):
    """SafeLoader without aliases, repeated keys or deep nesting."""

    def __init__(self, stream: str) -> None:
        super().__init__(stream)
        self._depth = 0

    def compose_node(self, parent: Any, index: Any) -> Any:
        if self.check_event(yaml.AliasEvent):
            event = self.peek_event()
            raise yaml.composer.ComposerError(
                None, None, f"aliases (*{event.anchor}) are not allowed: write the value out",
                event.start_mark)
        event = self.peek_event()
        if getattr(event, "anchor", None):
            raise yaml.composer.ComposerError(
                None, None, f"anchors (&{event.anchor}) are not allowed: write the value out",
                event.start_mark)
        self._depth += 1
        try:
            if self._depth > MAX_YAML_DEPTH:
                raise yaml.composer.ComposerError(
                    None, None, f"nested deeper than {MAX_YAML_DEPTH} levels", event.start_mark)
            return super().compose_node(parent, index)
        finally:
            self._depth -= 1

    def construct_mapping(self, node: yaml.MappingNode, deep: bool = False) -> dict:
        seen: set = set()
        for key_node, _ in node.value:
            key = self.construct_object(key_node, deep=True)
            try:
                repeated = key in seen
                seen.add(key)
            except TypeError:  # an unhashable key: SafeLoader's own error names it
                break
            if repeated:
                raise yaml.constructor.ConstructorError(
                    None, None, f"key {key!r} appears twice in one mapping (YAML would keep "
                    f"the last silently)", key_node.start_mark)
        return super().construct_mapping(node, deep=deep)


def _one_line(err: yaml.YAMLError) -> str:
    """A YAML error as one line: the problem, then where it is."""
    if isinstance(err, yaml.reader.ReaderError):
        character = err.character if isinstance(err.character, int) else ord(err.character)
        return f"a control character (#x{character:04x}) at offset {err.position}"
    if isinstance(err, yaml.MarkedYAMLError):
        problem = err.problem or err.context or "not valid YAML"
        mark = err.problem_mark or err.context_mark
        where = f" (line {mark.line + 1}, column {mark.column + 1})" if mark else ""
        context = f" {err.context}" if err.context and err.problem else ""
        return f"{problem}{context}{where}"
    return " ".join(str(err).split())


def read_yaml(content: str | bytes, source: str) -> Any:
    """The YAML document in `content` (a file's bytes or text); ConfigError naming `source`
    when it is empty, not UTF-8, not valid YAML, or uses what this reader refuses."""
    if isinstance(content, bytes):
        try:
            content = content.decode("utf-8-sig")
        except UnicodeDecodeError as err:
            raise ConfigError(f"{source}: not UTF-8 text (byte 0x{content[err.start]:02x} at "
                              f"offset {err.start}): not a YAML file, or a damaged one") from None
    if "\x00" in content:
        raise ConfigError(f"{source}: contains NUL bytes: not a YAML file, or a damaged one")
    try:
        loader = _StrictLoader(content)  # its reader refuses control characters already
        try:
            data = loader.get_single_data()
        finally:
            loader.dispose()
    except yaml.YAMLError as err:
        raise ConfigError(f"{source}: not valid YAML: {_one_line(err)}") from None
    if data is None:
        raise ConfigError(f"{source}: empty file (expected a YAML mapping of keys to values)")
    return data


__all__ = ["MAX_YAML_DEPTH", "read_yaml"]

"""The code of docs/ecosystem.md runs as written: its `python` blocks, in order, in one
namespace. The JaxMARL blocks need jaxmarl (the `peers` extra)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

PAGE = Path(__file__).resolve().parents[2] / "docs" / "ecosystem.md"
BLOCK = re.compile(r"^```python\n(.*?)^```", re.MULTILINE | re.DOTALL)


def blocks() -> list[str]:
    return BLOCK.findall(PAGE.read_text())


def uses_jaxmarl(code: str) -> bool:
    return "jaxmarl" in code or "CTRolloutManager(" in code


def run(codes: list[str]) -> dict:
    namespace: dict = {"__name__": "ecosystem_docs"}
    for i, code in enumerate(codes):
        exec(compile(code, f"{PAGE.name} block {i}", "exec"), namespace)  # noqa: S102
    return namespace


def test_the_page_has_snippets_of_each_kind():
    codes = blocks()
    assert len(codes) >= 4
    assert any(uses_jaxmarl(c) for c in codes) and any("reset_to_level" in c for c in codes)


def test_the_snippets_without_jaxmarl_run():
    namespace = run([c for c in blocks() if not uses_jaxmarl(c)])
    assert namespace["reward"].shape == ()


@pytest.mark.peers
@pytest.mark.slow
def test_every_snippet_runs():
    pytest.importorskip("jaxmarl")
    namespace = run(blocks())
    assert namespace["obs"].shape == (namespace["ued_env"].num_agents,
                                      namespace["config"].obs_size)

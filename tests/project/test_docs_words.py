"""Code and docs speak of the project as it is: no numbered rounds of work or issue numbers
(history lives in git). Cite a doc section, a benchmark file or a date instead."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
HISTORY = re.compile(r"\b(session|round)[ -]?\d+\b|\bissue ?#?\d+\b", re.IGNORECASE)
SKIP = {".git", ".venv", "runs", "build", "dist", "node_modules"}


def history_words(root: Path) -> list[str]:
    hits = []
    for path in sorted(root.rglob("*")):
        if path.suffix not in (".py", ".md", ".yaml") or SKIP & set(path.parts):
            continue
        for number, line in enumerate(path.read_text(errors="replace").splitlines(), 1):
            if HISTORY.search(line):
                hits.append(f"{path.relative_to(root)}:{number}: {line.strip()}")
    return hits


def test_no_history_words_in_code_or_docs():
    assert history_words(ROOT) == []


def test_the_check_finds_them(tmp_path):
    session, issue, round_ = "sess" + "ion 6", "iss" + "ue #7", "rou" + "nd-3"  # not literal
    (tmp_path / "a.py").write_text(f'"""Faster since {session} ({issue})."""\n')
    (tmp_path / "b.md").write_text(f"Measured in {round_}.\nSessions of play, 3 rounds.\n")
    assert [h.split(":")[:2] for h in history_words(tmp_path)] == [["a.py", "1"], ["b.md", "1"]]

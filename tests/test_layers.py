"""The plan of the house: imports run one way, `tabx` <- `level_buffer` <- `ued` <- `workers` <-
`tabx_ued` (the command line), and no two modules import each other, directly or round a loop
(docs/architecture.md). Imports inside functions count: they are dependencies all the same.
"""

from __future__ import annotations

import os
from pathlib import Path

import grimp
import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("tabx", "level_buffer", "ued", "workers", "tabx_ued")
LAYERS = PACKAGES  # lowest first


def import_cycles(graph: grimp.ImportGraph) -> list[list[str]]:
    """The strongly connected groups of more than one module (each holds an import loop), and
    modules that import themselves; Tarjan's algorithm, iterative."""
    adjacency = {m: sorted(graph.find_modules_directly_imported_by(m)) for m in graph.modules}
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    groups: list[list[str]] = []
    for root in sorted(adjacency):
        if root in index:
            continue
        work = [(root, 0)]
        while work:
            node, i = work.pop()
            if i == 0:
                index[node] = low[node] = len(index)
                stack.append(node)
                on_stack.add(node)
            children = adjacency[node]
            if i < len(children):
                work.append((node, i + 1))
                child = children[i]
                if child not in index:
                    work.append((child, 0))
                elif child in on_stack:
                    low[node] = min(low[node], index[child])
                continue
            if work:  # propagate to the parent
                parent = work[-1][0]
                low[parent] = min(low[parent], low[node])
            if low[node] == index[node]:
                group = []
                while True:
                    top = stack.pop()
                    on_stack.discard(top)
                    group.append(top)
                    if top == node:
                        break
                if len(group) > 1 or node in adjacency[node]:
                    groups.append(sorted(group))
    return groups


def upward_imports(graph: grimp.ImportGraph) -> list[str]:
    rank = {name: i for i, name in enumerate(LAYERS)}
    bad = []
    for module in sorted(graph.modules):
        for imported in sorted(graph.find_modules_directly_imported_by(module)):
            if rank[imported.split(".")[0]] > rank[module.split(".")[0]]:
                bad.append(f"{module} -> {imported}")
    return bad


@pytest.fixture(scope="module")
def graph() -> grimp.ImportGraph:
    return grimp.build_graph(*PACKAGES, cache_dir=None)


def test_no_module_imports_from_a_layer_above(graph):
    assert upward_imports(graph) == []


def test_no_import_cycles(graph):
    assert import_cycles(graph) == []


def test_import_linter_contract_is_kept():
    """The same layer rule as import-linter states it in pyproject.toml (`lint-imports`)."""
    from importlinter.cli import lint_imports

    cwd = os.getcwd()
    os.chdir(ROOT)
    try:
        assert lint_imports(config_filename=str(ROOT / "pyproject.toml"), no_cache=True) == 0
    finally:
        os.chdir(cwd)


def test_the_checks_catch_what_they_forbid():
    graph = grimp.ImportGraph()
    for module in ("tabx.a", "tabx.b", "tabx.c", "ued.d", "workers.e"):
        graph.add_module(module)
    graph.add_import(importer="tabx.a", imported="tabx.b")
    graph.add_import(importer="tabx.b", imported="tabx.c")
    graph.add_import(importer="ued.d", imported="tabx.a")
    graph.add_import(importer="workers.e", imported="ued.d")
    assert import_cycles(graph) == [] and upward_imports(graph) == []

    graph.add_import(importer="tabx.c", imported="tabx.a")  # a loop of three
    graph.add_import(importer="tabx.b", imported="ued.d")  # the simulator reaching up
    assert upward_imports(graph) == ["tabx.b -> ued.d"]
    assert import_cycles(graph) == [["tabx.a", "tabx.b", "tabx.c", "ued.d"]]

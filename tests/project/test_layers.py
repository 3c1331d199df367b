"""The plan of the house: imports run one way, `tabx` <- `level_buffer` <- `ued` <- `workers` <-
`tabx_bench` (benchmarks) <- `tabx_ued` (the command line), and no two modules import each
other, directly or round a loop (docs/architecture.md). Imports inside functions count: they are
dependencies all the same. The library packages hold the library: no benchmark, profiler or
command module lives under tabx/, level_buffer/, ued/ or workers/ (those belong to tabx_bench
and tabx_ued).
"""

from __future__ import annotations

import ast
import fnmatch
import os
from pathlib import Path

import grimp
import pytest

ROOT = Path(__file__).resolve().parents[2]
PACKAGES = ("tabx", "level_buffer", "ued", "workers", "tabx_bench", "tabx_ued")
LIBRARY = ("tabx", "level_buffer", "ued", "workers")  # below the benchmarks and the commands
LAYERS = PACKAGES  # lowest first
# `python -m tabx`: the one module of the simulator package that names a layer above it (it runs
# the command line, `tabx_ued.cli.main`), and the one that may be a command.
ENTRY_POINTS = frozenset({"tabx.__main__"})
# Module (or package) names under tabx/ that belong to the layers above: benchmarks, the
# profiler and its trace readers, other simulators' wrappers, commands.
NOT_SIMULATOR = ("bench*", "*profiler*", "stage_profile", "step_stages", "hlo_text", "xplane",
                 "peers", "cli", "*_cli", "commands", "*_commands", "__main__")


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
    for module in sorted(graph.modules - ENTRY_POINTS):
        for imported in sorted(graph.find_modules_directly_imported_by(module)):
            if rank[imported.split(".")[0]] > rank[module.split(".")[0]]:
                bad.append(f"{module} -> {imported}")
    return bad


def imports_argparse(source: str) -> bool:
    """The module imports argparse (anywhere in it): it parses a command line."""
    for node in ast.walk(ast.parse(source)):
        names = ([a.name for a in node.names] if isinstance(node, ast.Import)
                 else [node.module or ""] if isinstance(node, ast.ImportFrom) else [])
        if any(name == "argparse" or name.startswith("argparse.") for name in names):
            return True
    return False


def non_simulator_modules(package: Path) -> list[str]:
    """Modules under the simulator package `package` that are a benchmark, a profiler or a
    command: by name (`NOT_SIMULATOR`, also for a folder on the way) or because they parse a
    command line (import argparse). The entry points are exempt."""
    bad = []
    for path in sorted(package.rglob("*.py")):
        parts = path.relative_to(package.parent).with_suffix("").parts
        if parts[-1] == "__init__":
            parts = parts[:-1]
        module = ".".join(parts)
        if module in ENTRY_POINTS:
            continue
        if any(fnmatch.fnmatch(part, pattern) for part in parts[1:] for pattern in NOT_SIMULATOR):
            bad.append(f"{module} (its name)")
        elif imports_argparse(path.read_text()):
            bad.append(f"{module} (imports argparse)")
    return bad


@pytest.fixture(scope="module")
def graph() -> grimp.ImportGraph:
    return grimp.build_graph(*PACKAGES, cache_dir=None)


def test_no_module_imports_from_a_layer_above(graph):
    assert upward_imports(graph) == []


def test_no_import_cycles(graph):
    assert import_cycles(graph) == []


@pytest.mark.parametrize("package", LIBRARY)
def test_a_library_package_holds_no_benchmark_profiler_or_command(package):
    assert non_simulator_modules(ROOT / package) == []


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


def test_the_simulator_rule_catches_what_it_forbids(tmp_path):
    package = tmp_path / "tabx"
    for name, text in [("env.py", "import jax\n"), ("profiles.py", "X = 1\n"),
                       ("__main__.py", "import argparse\n"), ("bench_x.py", ""),
                       ("peers/__init__.py", ""), ("scenarios/cli.py", ""),
                       ("editor/screenshot.py",
                        "def f():\n    from argparse import ArgumentParser\n"),
                       ("stage_profile.py", ""), ("hlo_text.py", "")]:
        (package / name).parent.mkdir(parents=True, exist_ok=True)
        (package / name).write_text(text)
    assert non_simulator_modules(package) == [
        "tabx.bench_x (its name)", "tabx.editor.screenshot (imports argparse)",
        "tabx.hlo_text (its name)", "tabx.peers (its name)",
        "tabx.scenarios.cli (its name)", "tabx.stage_profile (its name)"]

    graph = grimp.ImportGraph()
    for module in ("tabx.__main__", "tabx.env", "tabx_ued.cli"):
        graph.add_module(module)
    graph.add_import(importer="tabx.__main__", imported="tabx_ued.cli")  # the entry point
    assert upward_imports(graph) == []
    graph.add_import(importer="tabx.env", imported="tabx_ued.cli")
    assert upward_imports(graph) == ["tabx.env -> tabx_ued.cli"]


# Where Ray may be imported: the placement on Ray and the sweeps (workers/__init__.py). The
# benchmarks' stand-in actors (tabx_bench) are Ray actors themselves.
RAY_PACKAGES = ("workers.ray", "workers.sweep", "tabx_bench")


def ray_importers(root: Path, packages: tuple[str, ...]) -> list[str]:
    """The modules under `packages` (folders of `root`) that import `ray` anywhere in them."""
    found = []
    for package in packages:
        for path in sorted((root / package).rglob("*.py")):
            module = ".".join(path.relative_to(root).with_suffix("").parts)
            for node in ast.walk(ast.parse(path.read_text(), str(path))):
                names = ([a.name for a in node.names] if isinstance(node, ast.Import)
                         else [node.module or ""] if isinstance(node, ast.ImportFrom) else [])
                if any(name == "ray" or name.startswith("ray.") for name in names):
                    found.append(module)
                    break
    return found


def test_only_the_ray_and_sweep_packages_import_ray():
    outside = [m for m in ray_importers(ROOT, PACKAGES)
               if not any(m == p or m.startswith(p + ".") for p in RAY_PACKAGES)]
    assert outside == []
    assert "workers.ray.start" in ray_importers(ROOT, ("workers",))  # the scan finds imports


def test_the_ray_rule_catches_an_import_outside_its_packages(tmp_path):
    (tmp_path / "workers" / "roles").mkdir(parents=True)
    (tmp_path / "workers" / "roles" / "learner.py").write_text(
        "def f():\n    from ray import get\n")
    (tmp_path / "workers" / "local.py").write_text("x = 'import ray'\n")
    assert ray_importers(tmp_path, ("workers",)) == ["workers.roles.learner"]

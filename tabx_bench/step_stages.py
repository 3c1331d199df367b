"""Which stage of a simulator step a compiled kernel's work belongs to (`tabx bench profile`).

A kernel of the compiled rollout computes one HLO instruction, or for a fusion many; each
instruction carries the Python call chain that built it (tabx_bench.hlo_text). The chain is mapped
to a stage by this table:

- an OWNER frame claims everything called beneath it, the outermost owner on the chain winning
  (the scripted policy's geometry is the policy's, not the step's vision; a mask computed for
  random actions is action sampling, wherever the mask's helpers live);
- otherwise the innermost frame the table knows decides (`in_ellipses`, in geometry.py, is
  zones even when `_advance` calls it);
- inside `TabxEnv._advance` (code inline in the step) each statement is mapped by the variable
  it assigns (`velocity` -> movement, `hp_ratio` -> rewards), read from the source with `ast`,
  so that edits to the step keep their mapping; an unknown variable falls back to the numbered
  section comment (`# 3. Zones ...`) it sits under;
- a function the table does not name falls back to its file's stage (a new helper in
  observe.py counts as observations), and frames of unknown files, generic helpers
  (selection.py, profiles.py) and the step's plumbing pass the decision on;
- nothing on the chain known: `other` (scan bookkeeping, copies XLA inserts, key splitting).

A fused kernel whose instructions come from several stages is split among them in proportion
to the output element count of each stage's instructions: an estimate of where a fusion spends
its time, not a measurement (elements are not equally costly: a division against a select).
"""

from __future__ import annotations

import ast
import collections
import functools
import re
from collections.abc import Iterable, Sequence
from pathlib import Path

from tabx_bench.hlo_text import Frame, HloModule

ACTIONS = "actions"
SCRIPTED = "scripted policy"
PHYSICS = "movement and physics"
ATTACKS = "attacks and heals"
ZONES = "zones"
VISION = "vision and targeting"
OBSERVATIONS = "observations"
REWARDS = "rewards and termination"
AUTO_RESET = "auto-reset"
OTHER = "other"
STAGES = (ACTIONS, SCRIPTED, PHYSICS, ATTACKS, ZONES, VISION, OBSERVATIONS, REWARDS,
          AUTO_RESET, OTHER)

# Folders whose files the tables below name: the simulator's, and the benchmark's own rollout.
_PACKAGES = ("tabx", "tabx_bench")

# Frames of these (file, function) decide for everything they call (outermost first).
_OWNERS: dict[tuple[str, str], str] = {
    ("heuristic.py", "*"): SCRIPTED,
    ("env.py", "random_legal_actions"): ACTIONS,
    ("env.py", "TabxEnv.action_mask"): ACTIONS,
    ("observe.py", "action_mask"): ACTIONS,
    ("observe.py", "pick_legal"): ACTIONS,
    ("env.py", "TabxEnv.observe"): OBSERVATIONS,
    ("env.py", "TabxEnv.world_state"): OBSERVATIONS,
    ("observe.py", "observe"): OBSERVATIONS,
    ("observe.py", "world_state"): OBSERVATIONS,
    # The start states, computed once per rollout call before the scan (not per step).
    ("env.py", "TabxEnv.initial_state"): OTHER,
}

# The innermost frame of these decides when no owner is on the chain. "*": any other function
# of the file. None: pass the decision on to the caller.
_LEAVES: dict[tuple[str, str], str | None] = {
    ("rng.py", "*"): ACTIONS,
    ("env.py", "materialise_actions"): ACTIONS,
    ("controllers.py", "*"): SCRIPTED,
    ("physics.py", "*"): PHYSICS,
    ("combat.py", "*"): ATTACKS,
    ("combat.py", "attackable_pairs"): VISION,
    ("combat.py", "attack_targets"): VISION,
    ("combat.py", "nearest_targets"): VISION,
    ("observe.py", "*"): OBSERVATIONS,
    ("observe.py", "cooldown_ready"): ATTACKS,
    ("zones.py", "*"): ZONES,
    ("geometry.py", "*"): VISION,
    ("geometry.py", "in_ellipses"): ZONES,
    ("reward.py", "*"): REWARDS,
    ("selection.py", "*"): None,
    ("profiles.py", "*"): None,
    ("state.py", "*"): None,
    ("env.py", "TabxEnv._refresh_geometry"): VISION,
    ("env.py", "TabxEnv.step_autoreset.<locals>.<lambda>"): AUTO_RESET,
    ("env.py", "TabxEnv.step.<locals>.<lambda>"): REWARDS,  # a finished episode frozen
    ("env.py", "TabxEnv.step"): REWARDS,
    ("env.py", "*"): None,
    ("simulator.py", "*"): OTHER,  # the benchmark's rollout (tabx_bench/simulator.py)
}

# `TabxEnv._advance`, statement by the variable it assigns.
_ADVANCE_VARIABLES: dict[str, str | None] = {
    **dict.fromkeys(("position", "touching", "wall_loss", "velocity", "drifts"), PHYSICS),
    **dict.fromkeys(("action", "table", "turn", "step_angle", "heading", "cos_t", "sin_t",
                     "fx", "fy", "rotated", "facing_vec"), ACTIONS),
    **dict.fromkeys(("attacking", "attack_loss", "hit", "interacted", "cooldown", "health",
                     "alive"), ATTACKS),
    **dict.fromkeys(("inside", "lava_loss", "speed"), ZONES),
    **dict.fromkeys(("active", "hp_ratio", "reward", "members", "eliminated", "step",
                     "truncated", "done", "won", "terminal", "info"), REWARDS),
    **dict.fromkeys(("u", "z", "ph", "dt", "able", "advanced"), None),
}
# `TabxEnv._advance`'s numbered section comments ("# 3. Zones at the new positions.").
_ADVANCE_SECTIONS = {"1": PHYSICS, "2": ACTIONS, "3": ZONES, "4": ATTACKS, "5": VISION,
                     "6": REWARDS}
_SECTION = re.compile(r"^\s*#\s*(\d)\.\s")


def _lookup(table: dict, frame: Frame) -> tuple[bool, str | None]:
    """(found, stage) of a frame in a table: its function first, then its file's default."""
    path = Path(frame.file)
    if path.parent.name not in _PACKAGES:
        return False, None
    for key in ((path.name, frame.function), (path.name, "*")):
        if key in table:
            return True, table[key]
    return False, None


@functools.lru_cache(maxsize=16)
def _advance_lines(file: str) -> dict[int, str | None]:
    """line -> stage of the statements of `TabxEnv._advance` in `file` (empty if not found)."""
    try:
        source = Path(file).read_text()
        tree = ast.parse(source)
    except (OSError, SyntaxError):
        return {}
    lines = source.splitlines()
    function = next((node for node in ast.walk(tree)
                     if isinstance(node, ast.FunctionDef) and node.name == "_advance"), None)
    if function is None:
        return {}
    stages: dict[int, str | None] = {}
    section = None
    previous_end = function.lineno  # comments from the line after `def`
    for statement in function.body:
        for text in lines[previous_end:statement.lineno - 1]:  # comments above the statement
            found = _SECTION.match(text)
            if found:
                section = _ADVANCE_SECTIONS.get(found[1])
        previous_end = statement.end_lineno or statement.lineno
        stage = section
        targets = _assigned_names(statement)
        known = [_ADVANCE_VARIABLES[name] for name in targets if name in _ADVANCE_VARIABLES]
        if known:
            stage = known[0]
        elif isinstance(statement, ast.Return):
            stage = None
        for line in range(statement.lineno, previous_end + 1):
            stages[line] = stage
    return stages


def _assigned_names(statement: ast.stmt) -> list[str]:
    targets: list[ast.expr] = []
    if isinstance(statement, ast.Assign):
        targets = list(statement.targets)
    elif isinstance(statement, (ast.AnnAssign, ast.AugAssign)):
        targets = [statement.target]
    names = []
    for target in targets:
        names.extend(node.id for node in ast.walk(target) if isinstance(node, ast.Name))
    return names


def _leaf_stage(frame: Frame) -> tuple[bool, str | None]:
    if Path(frame.file).name == "env.py" and frame.function == "TabxEnv._advance":
        stage = _advance_lines(frame.file).get(frame.line)
        return stage is not None, stage
    return _lookup(_LEAVES, frame)


def _decide(chain: Sequence[Frame]) -> tuple[str, Frame | None]:
    """(stage, the frame that decided it) of a call chain (innermost first)."""
    for frame in reversed(chain):
        found, stage = _lookup(_OWNERS, frame)
        if found and stage is not None:
            return stage, frame
    for frame in chain:
        found, stage = _leaf_stage(frame)
        if found and stage is not None:
            return stage, frame
    return OTHER, None


def stage_of(chain: Sequence[Frame]) -> str:
    """The stage of an instruction built by the call chain `chain` (innermost first)."""
    return _decide(chain)[0]


def describe(chain: Sequence[Frame], depth: int = 3) -> str:
    """`file:function:line <- ...` of a chain's innermost `depth` frames (repeats dropped),
    for `--debug-stages`."""
    parts: list[str] = []
    for frame in chain:
        part = f"{Path(frame.file).name}:{frame.function}:{frame.line}"
        if not parts or parts[-1] != part:
            parts.append(part)
    more = " <- ..." if len(parts) > depth else ""
    return " <- ".join(parts[:depth]) + more if parts else "(no source location)"


# Instructions that move or relabel data without computing anything in a fused kernel.
_NO_WORK = frozenset({"parameter", "constant", "bitcast", "get-tuple-element", "tuple",
                      "broadcast", "reshape"})


def kernel_weights(module: HloModule, kernel: str) -> dict[tuple[Frame, ...], float]:
    """{call chain: share} of the work of one kernel (shares sum to 1): by output elements
    over its instructions that compute; a kernel without such an instruction is its own."""
    top = module.instructions.get(kernel)
    if top is None:
        return {(): 1.0}
    weights: collections.Counter[tuple[Frame, ...]] = collections.Counter()
    for part in module.kernel_parts(kernel):
        if part.opcode in _NO_WORK and part is not top:
            continue
        frame = part.frame if part.frame is not None else top.frame
        weights[module.call_chain(frame)] += max(part.elements, 1)
    if not weights:
        weights[module.call_chain(top.frame)] = 1.0
    total = sum(weights.values())
    return {chain: w / total for chain, w in weights.items()}


def attribute(module: HloModule, kernel_times: Iterable[tuple[str, float]]
              ) -> tuple[dict[str, float], dict[str, dict[str, float]]]:
    """({stage: time} over STAGES, {stage: {source: time}, slowest first}) of (kernel name,
    time) pairs. The stage times sum to the total time; a source is the call chain (or, for
    time an owner claimed as `other`, the owner) that the time came from."""
    per_kernel: collections.Counter[str] = collections.Counter()
    for name, time in kernel_times:
        per_kernel[name] += time
    stages = dict.fromkeys(STAGES, 0.0)
    sources: dict[str, collections.Counter[str]] = {s: collections.Counter() for s in STAGES}
    for name, time in per_kernel.items():
        for chain, share in kernel_weights(module, name).items():
            stage, decider = _decide(chain)
            stages[stage] += time * share
            sources[stage][_source_label(module, name, chain, decider)] += time * share
    return stages, {stage: dict(c.most_common()) for stage, c in sources.items()}


def _source_label(module: HloModule, kernel: str, chain: Sequence[Frame],
                  decider: Frame | None) -> str:
    if decider is not None and _lookup(_OWNERS, decider)[0] and \
            _lookup(_OWNERS, decider)[1] == OTHER:
        return f"{Path(decider.file).name}:{decider.function} (all it calls)"
    if kernel not in module.instructions:
        return f"{kernel} (not in the HLO text)"
    if not chain:
        return f"{module.instructions[kernel].opcode} kernels without source location"
    return describe(chain)


__all__ = ["OTHER", "STAGES", "attribute", "describe", "kernel_weights", "stage_of"]

"""The parts of a compiled program's HLO text (`jitted.lower(...).compile().as_text()`) that say
where each kernel's work came from in the Python source.

Every instruction is printed as `%name = SHAPE opcode(operands), ..., metadata={op_name=...
stack_frame_id=K}`; a fusion names the computation it runs (`calls=%fused_computation.N`). The
module starts with four tables: `FileNames` and `FunctionNames` (id -> string),
`FileLocations` (id -> file_name_id, function_name_id, line) and `StackFrames`
(`K {file_location_id=L parent_frame_id=P}`), where the parent of frame K is frame P - 1 and
P = 0 or 1 means K is outermost (frame 1 prints `parent_frame_id=1`: the parent ids count from
zero). Following the parents from a frame gives the Python call chain that built the
instruction, JAX's own frames already filtered out.

Kernel names in an XLA:CPU profile (tabx_bench.xplane) are these instruction names, so a kernel's
time can be traced back to the functions whose operations it runs.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from typing import NamedTuple


class Frame(NamedTuple):
    file: str
    function: str  # qualified: `TabxEnv._advance`, `make_rollout.<locals>.rollout`
    line: int


@dataclass
class Instruction:
    name: str
    opcode: str
    elements: int  # output element count (summed over a tuple's parts)
    frame: int | None  # stack_frame_id, None without metadata
    calls: str | None  # the fused computation a fusion runs


@dataclass
class HloModule:
    instructions: dict[str, Instruction] = field(default_factory=dict)
    computations: dict[str, list[str]] = field(default_factory=dict)  # name -> instructions
    frames: dict[int, tuple[int, int]] = field(default_factory=dict)  # id -> (location, parent)
    locations: dict[int, Frame] = field(default_factory=dict)

    def call_chain(self, frame_id: int | None) -> tuple[Frame, ...]:
        """The Python frames of stack frame `frame_id`, innermost first (empty if unknown)."""
        chain: list[Frame] = []
        seen: set[int] = set()
        while frame_id is not None and frame_id in self.frames and frame_id not in seen:
            seen.add(frame_id)
            location, parent = self.frames[frame_id]
            if location in self.locations:
                chain.append(self.locations[location])
            frame_id = parent - 1 if parent > 1 else None
        return tuple(chain)

    def kernel_parts(self, name: str) -> list[Instruction]:
        """The instructions whose work kernel `name` does: the instruction itself, or for a
        fusion every instruction of its fused computation (nested fusions followed)."""
        top = self.instructions.get(name)
        if top is None:
            return []
        if top.calls is None:
            return [top]
        parts: list[Instruction] = []
        pending, visited = [top.calls], set()
        while pending:
            computation = pending.pop()
            if computation in visited:
                continue
            visited.add(computation)
            for inner in self.computations.get(computation, ()):
                instruction = self.instructions[inner]
                if instruction.calls is not None:
                    pending.append(instruction.calls)
                else:
                    parts.append(instruction)
        return parts


_TABLES = ("FileNames", "FunctionNames", "FileLocations", "StackFrames")
_COMPUTATION = re.compile(r"^(?:ENTRY\s+)?%([\w.\-]+)\s.*\{\s*$")
_INSTRUCTION = re.compile(r"^\s+(?:ROOT\s+)?%([\w.\-]+)\s+=\s+(.*)$")
_ARRAY = re.compile(r"\b[a-z]+\d*\[([\d,]*)\]")
_OPCODE = re.compile(r"\s*([\w\-]+)\(")
_CALLS = re.compile(r"\bcalls=%([\w.\-]+)")
_FRAME_ID = re.compile(r"\bstack_frame_id=(\d+)")
_TABLE_ENTRY = re.compile(r"^(\d+)\s+(.*)$")
_KEY_VALUE = re.compile(r"(\w+)=(\d+)")


def _split_shape(rest: str) -> tuple[str, str]:
    """(shape, text after it) of an instruction's right-hand side."""
    if not rest.startswith("("):
        shape, _, after = rest.partition(" ")
        return shape, after
    depth = 0
    for i, char in enumerate(rest):
        depth += char == "("
        depth -= char == ")"
        if depth == 0:
            return rest[:i + 1], rest[i + 1:]
    return rest, ""


def element_count(shape: str) -> int:
    """Elements of an HLO shape such as `f32[8,4]{1,0}` or a tuple of them (`pred[]` is 1)."""
    return sum(math.prod(int(d) for d in dims.split(",") if d) for dims in _ARRAY.findall(shape))


def parse_hlo(text: str) -> HloModule:
    """The instructions, computations and stack-frame tables of a compiled module's text."""
    module = HloModule()
    table, computation = None, None
    files: dict[int, str] = {}
    functions: dict[int, str] = {}
    raw_locations: dict[int, dict[str, int]] = {}
    for line in text.splitlines():
        stripped = line.strip()
        if stripped in _TABLES:
            table = stripped
            continue
        if table is not None:
            entry = _TABLE_ENTRY.match(stripped)
            if entry is None:
                table = None  # a blank line ends the table
            else:
                key, value = int(entry[1]), entry[2]
                if table in ("FileNames", "FunctionNames"):
                    (files if table == "FileNames" else functions)[key] = value.strip('"')
                else:
                    numbers = {k: int(v) for k, v in _KEY_VALUE.findall(value)}
                    if table == "FileLocations":
                        raw_locations[key] = numbers
                    else:
                        module.frames[key] = (numbers.get("file_location_id", 0),
                                              numbers.get("parent_frame_id", 0))
                continue
        header = _COMPUTATION.match(line)
        if header is not None and not line.startswith(" "):
            computation = header[1]
            module.computations[computation] = []
            continue
        instruction = _INSTRUCTION.match(line)
        if instruction is None:
            continue
        name, rest = instruction[1], instruction[2]
        shape, after = _split_shape(rest)
        opcode = _OPCODE.match(after)
        frame = _FRAME_ID.search(after)
        calls = _CALLS.search(after)
        module.instructions[name] = Instruction(
            name, opcode[1] if opcode else "?", element_count(shape),
            int(frame[1]) if frame else None,
            calls[1] if calls and opcode and opcode[1] == "fusion" else None)
        if computation is not None:
            module.computations[computation].append(name)
    for key, numbers in raw_locations.items():
        module.locations[key] = Frame(files.get(numbers.get("file_name_id", 0), "?"),
                                      functions.get(numbers.get("function_name_id", 0), "?"),
                                      numbers.get("line", 0))
    return module


__all__ = ["Frame", "HloModule", "Instruction", "element_count", "parse_hlo"]

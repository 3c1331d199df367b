"""`tabx bench profile`: HLO stack frames, the stage table, splitting kernels, the command."""

from __future__ import annotations

import inspect
import json
from pathlib import Path

import jax
import jax.numpy as jnp
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import tabx.env
from tabx_bench.hlo_text import Frame, element_count, parse_hlo
from tabx_bench.stage_profile import TRACEME_FLAG, analyse, child_environment, format_profile
from tabx_bench.step_stages import (
    ACTIONS,
    ATTACKS,
    OBSERVATIONS,
    OTHER,
    PHYSICS,
    REWARDS,
    SCRIPTED,
    STAGES,
    VISION,
    ZONES,
    attribute,
    stage_of,
)
from tabx_bench.xplane import exclusive_times
from tabx_ued.cli import main


def _inner(x):
    return jnp.sin(x) * 3.0


def _outer(x):
    return _inner(x) + jnp.cos(x)


def _line_of(function, text: str) -> int:
    lines, first = inspect.getsourcelines(function)
    return first + next(i for i, line in enumerate(lines) if text in line)


def test_call_chain_of_a_compiled_function_follows_the_callers():
    text = jax.jit(_outer).lower(jnp.ones(8)).compile().as_text()
    module = parse_hlo(text)
    by_opcode = {i.opcode: i for i in module.instructions.values()}
    sine = module.call_chain(by_opcode["sine"].frame)
    cosine = module.call_chain(by_opcode["cosine"].frame)
    # sin is built in _inner, called from _outer: the parent of _inner's frame (parent id P
    # names frame P - 1) is the line of _outer that calls it.
    assert [f.function for f in sine[:2]] == ["_inner", "_outer"]
    assert sine[0].line == _line_of(_inner, "jnp.sin")
    assert sine[1].line == _line_of(_outer, "_inner(x)")
    assert cosine[0].function == "_outer"
    assert all(Path(f.file).name == "test_bench_profile.py" for f in sine[:2])


def _frame(file: str, function: str, line: int = 1) -> Frame:
    return Frame(f"/src/tabx/{file}", function, line)


def _env_line(text: str) -> int:
    return _line_of(tabx.env.TabxEnv._advance, text)


def test_stage_table_owners_leaves_and_file_defaults():
    env_file = tabx.env.__file__
    advance = "TabxEnv._advance"
    # Inline statements of the step, by the variable they assign.
    assert stage_of([Frame(env_file, advance, _env_line("velocity = table"))]) == PHYSICS
    assert stage_of([Frame(env_file, advance, _env_line("heading = jnp.mod"))]) == ACTIONS
    assert stage_of([Frame(env_file, advance, _env_line("eliminated ="))]) == REWARDS
    assert stage_of([_frame("reward.py", "team_hp_ratio"),
                     Frame(env_file, advance, _env_line("hp_ratio ="))]) == REWARDS
    # The innermost known function decides: in_ellipses (geometry.py) is zones.
    assert stage_of([_frame("geometry.py", "in_ellipses"),
                     Frame(env_file, advance, _env_line("inside = in_ellipses"))]) == ZONES
    assert stage_of([_frame("selection.py", "row_argmin"), _frame("combat.py", "nearest_targets"),
                     _frame("env.py", "TabxEnv._refresh_geometry")]) == VISION
    # An owner claims what it calls: the policy's geometry and mask are the policy's.
    assert stage_of([_frame("geometry.py", "pairwise_offsets"),
                     _frame("heuristic.py", "heuristic_actions_from_bits"),
                     _frame("controllers.py", "controlled_actions")]) == SCRIPTED
    assert stage_of([_frame("observe.py", "cooldown_ready"), _frame("observe.py", "action_mask"),
                     _frame("controllers.py", "controlled_actions")]) == ACTIONS
    assert stage_of([_frame("observe.py", "cooldown_ready"),
                     Frame(env_file, advance, _env_line("attacking ="))]) == ATTACKS
    # A helper the table does not know counts for its file; unknown files pass it on.
    assert stage_of([_frame("observe.py", "a_new_helper"),
                     Frame("/src/tabx_bench/simulator.py",
                           "make_rollout.<locals>.rollout", 1)]) == OBSERVATIONS
    assert stage_of([_frame("physics.py", "a_new_helper")]) == PHYSICS
    assert stage_of([Frame("/elsewhere/physics.py", "integrate", 1)]) == OTHER
    assert stage_of([]) == OTHER


def test_advance_statements_fall_back_to_their_section_comment(tmp_path):
    source = tmp_path / "tabx" / "env.py"
    source.parent.mkdir()
    source.write_text(
        "class TabxEnv:\n"
        "    def _advance(self, state):\n"
        "        # 3. Zones at the new positions.\n"
        "        brand_new = state + 1\n"
        "        # 6. Outcome.\n"
        "        another = brand_new * 2\n"
        "        velocity = another\n"
        "        return velocity\n")
    chain = lambda line: [Frame(str(source), "TabxEnv._advance", line)]  # noqa: E731
    assert stage_of(chain(4)) == ZONES
    assert stage_of(chain(6)) == REWARDS
    assert stage_of(chain(7)) == PHYSICS  # a known variable wins over the section


def _module_text(physics_elements: int, observe_elements: int) -> str:
    """A compiled module's text, cut down: one fusion mixing a physics and an observation
    instruction, one copy without source location."""
    p, o = physics_elements, observe_elements
    return f"""HloModule test

FileNames
1 "/src/tabx_bench/simulator.py"
2 "/src/tabx/physics.py"
3 "/src/tabx/observe.py"

FunctionNames
1 "make_rollout.<locals>.rollout"
2 "integrate"
3 "observe"

FileLocations
1 {{file_name_id=1 function_name_id=1 line=10 end_line=10 column=1 end_column=2}}
2 {{file_name_id=2 function_name_id=2 line=17 end_line=17 column=1 end_column=2}}
3 {{file_name_id=3 function_name_id=3 line=90 end_line=90 column=1 end_column=2}}

StackFrames
1 {{file_location_id=1 parent_frame_id=1}}
2 {{file_location_id=2 parent_frame_id=2}}
3 {{file_location_id=3 parent_frame_id=2}}

%fused.1 (param_0.1: f32[{p}]) -> (f32[{p}], f32[{o}]) {{
  %param_0.1 = f32[{p}]{{0}} parameter(0)
  %multiply.1 = f32[{p}]{{0}} multiply(%param_0.1, %param_0.1), metadata={{stack_frame_id=2}}
  %slice.1 = f32[{o}]{{0}} slice(%param_0.1), slice={{[0:{o}]}}, metadata={{stack_frame_id=3}}
  ROOT %tuple.1 = (f32[{p}]{{0}}, f32[{o}]{{0}}) tuple(%multiply.1, %slice.1)
}}

ENTRY %main (p: f32[{p}]) -> f32[{p}] {{
  %p = f32[{p}]{{0}} parameter(0)
  %fusion.1 = (f32[{p}], f32[{o}]) fusion(%p), calls=%fused.1, metadata={{stack_frame_id=1}}
  %get-tuple-element.1 = f32[{p}]{{0}} get-tuple-element(%fusion.1), index=0
  ROOT %copy.1 = f32[{p}]{{0}} copy(%get-tuple-element.1)
}}
"""


@settings(max_examples=30, deadline=None)
@given(st.integers(1, 10_000), st.integers(1, 10_000), st.floats(0.1, 1e4), st.floats(0, 1e3))
def test_a_fused_kernel_is_split_by_output_elements(physics, observe, fusion_us, copy_us):
    module = parse_hlo(_module_text(physics, observe))
    assert module.call_chain(3)[1].function == "make_rollout.<locals>.rollout"
    stages, sources = attribute(module, [("fusion.1", fusion_us / 2), ("copy.1", copy_us),
                                         ("fusion.1", fusion_us / 2), ("bogus.7", 1.0)])
    assert set(stages) == set(STAGES)
    assert stages[PHYSICS] == pytest.approx(fusion_us * physics / (physics + observe))
    assert stages[OBSERVATIONS] == pytest.approx(fusion_us * observe / (physics + observe))
    assert stages[OTHER] == pytest.approx(copy_us + 1.0)
    assert sum(stages.values()) == pytest.approx(fusion_us + copy_us + 1.0)
    assert "bogus.7 (not in the HLO text)" in sources[OTHER]
    assert "copy kernels without source location" in sources[OTHER]


def test_element_count_of_arrays_and_tuples():
    assert element_count("f32[8,4]{1,0}") == 32
    assert element_count("pred[]") == 1
    assert element_count("(s32[], u32[2]{0}, /*index=2*/f32[3,5]{1,0})") == 18


def test_exclusive_time_of_nested_kernels():
    # A `while` running two kernels inline, one of them wrapping a third.
    events = [("while.1", 0, 100), ("fusion.1", 10, 20), ("copy.1", 15, 5),
              ("fusion.2", 40, 20), ("fusion.3", 200, 7)]
    assert exclusive_times(events) == [60, 15, 5, 20, 7]


def test_child_keeps_the_callers_xla_flags(monkeypatch):
    monkeypatch.setenv("XLA_FLAGS", "--xla_cpu_use_thunk_runtime=true")
    flags = child_environment()["XLA_FLAGS"].split()
    assert flags == ["--xla_cpu_use_thunk_runtime=true", TRACEME_FLAG]
    monkeypatch.setenv("XLA_FLAGS", TRACEME_FLAG)
    assert child_environment()["XLA_FLAGS"] == TRACEME_FLAG
    monkeypatch.delenv("XLA_FLAGS")
    assert child_environment()["XLA_FLAGS"] == TRACEME_FLAG


@pytest.fixture(scope="module")
def profiled(tmp_path_factory):
    """`tabx bench profile` on 2v2 (8 envs, 4 steps), with observations and without."""
    root = tmp_path_factory.mktemp("profile")
    runs = {}
    for name, extra in (("obs", ["--plot", str(root / "stages.png")]), ("no_obs", ["--no-obs"])):
        out = root / f"{name}.jsonl"
        assert main(["bench", "profile", "--team-sizes", "2", "--num-envs", "8", "--steps", "4",
                     "--repeats", "1", "--zones", "2", "--bandwidth-mb", "8", "--debug-stages",
                     "--json", str(out), "--trace-dir", str(root / name), *extra]) == 0
        runs[name] = [json.loads(line) for line in out.read_text().splitlines()]
    return root, runs


def test_profile_end_to_end(profiled, capsys):
    root, runs = profiled
    (with_obs,), (without,) = runs["obs"], runs["no_obs"]
    for record in (with_obs, without):
        stages = record["stages_us"]
        assert set(stages) == set(STAGES)
        assert record["kernel_us"] > 0 and record["wall_us"] > 0
        assert sum(stages.values()) / record["kernel_us"] == pytest.approx(1.0)
        assert record["bandwidth_gb_s"] > 0 and record["bound_us"] > 0
        for stage in (ACTIONS, PHYSICS, VISION, REWARDS):
            assert stages[stage] > 0, stage
    # Present with observations, gone without (shares of a 4-step trace on a busy machine are
    # too noisy for more: one preempted kernel can double a stage).
    assert with_obs["stages_us"][OBSERVATIONS] > 0
    assert without["stages_us"][OBSERVATIONS] / without["kernel_us"] < 0.01
    assert with_obs["bytes_per_env_step"] > without["bytes_per_env_step"] > 0
    assert (root / "stages.png").stat().st_size > 0
    # The real dump: a frame inside in_ellipses has its parent in _initial_fields.
    module = parse_hlo((root / "obs" / "2v2" / "hlo.txt").read_text())
    chains = [module.call_chain(k) for k in module.frames]
    in_ellipses = [c for c in chains if c and c[0].function == "in_ellipses"]
    assert in_ellipses
    assert {c[1].function for c in in_ellipses} <= {"TabxEnv._initial_fields", "TabxEnv._advance"}
    assert any(c[1].function == "TabxEnv._initial_fields" for c in in_ellipses)


def test_profile_table_names_every_stage_and_the_bound(profiled):
    root, _ = profiled
    profile = analyse(root / "obs" / "2v2")
    profile.bandwidth_gb_s = 10.0
    text = format_profile(profile, debug_stages=True)
    for stage in STAGES:
        assert f"  {stage} " in text, stage
    for words in ("kernel time (summed)", "wall time (untraced)", "bytes per env step",
                  "bandwidth 10.0 GB/s", "step time at bandwidth limit", "x the bound",
                  "where each stage's time comes from", "TabxEnv.initial_state (all it calls)"):
        assert words in text, words


@pytest.mark.parametrize("argv, message", [
    (["--team-sizes", "0"], "--team-sizes"),
    (["--enemy", "bogus"], "--ally/--enemy"),
    (["--enemy", "external"], "--ally/--enemy"),
    (["--num-envs", "0"], "--num-envs"),
    (["--trace-dir", __file__], "--trace-dir"),
])
def test_bad_arguments_are_one_error_line(argv, message, capsys):
    try:
        code = main(["bench", "profile", *argv])
    except SystemExit as exit_:  # argparse's own checks
        code = exit_.code
    err = capsys.readouterr().err
    assert code == 2
    errors = [line for line in err.splitlines() if "error:" in line]
    assert len(errors) == 1 and message in errors[0], err
    assert "Traceback" not in err


@pytest.mark.slow
def test_scripted_enemy_profile_has_a_policy_stage(tmp_path):
    out = tmp_path / "heuristic.jsonl"
    assert main(["bench", "profile", "--team-sizes", "3", "--num-envs", "16", "--steps", "8",
                 "--repeats", "1", "--enemy", "heuristic:medium", "--no-obs",
                 "--bandwidth-mb", "8", "--json", str(out)]) == 0
    (record,) = [json.loads(line) for line in out.read_text().splitlines()]
    stages = record["stages_us"]
    assert record["controllers"] == "random/heuristic:medium"
    assert stages[SCRIPTED] > 0
    assert stages[OBSERVATIONS] / record["kernel_us"] < 0.01

"""UED in one process: the curricula's branch logic, the local driver end to end for every method,
Robust PLR's gradient-free exploration, buffer snapshots, exact resume, and config errors.

The runs use the learner tests' tiny config (2 archers v 1 farmer, 4 envs x 16 steps), so they
share its compiled update; the unit specs are the free parameters (the duel has no zone slots).
"""

from __future__ import annotations

import io
import json

import jax
import numpy as np
import pytest
from test_learners_helpers import tiny_config

from level_buffer import LevelBuffer
from tabx.compile_counter import CompileCounter
from ued.config import ConfigError, config_from_dict
from ued.curricula import ACCEL, PLR, SFL, Branch, DomainRandomization, RobustPLR
from ued.run_folder import LEVELS_DIR
from workers.roles.learner import LearnerWorker
from workers.roles.level_service import snapshot_steps
from workers.train import train
from workers.ued_step import UEDRun


class Decisions:
    """A stand-in buffer whose replay decisions are scripted."""

    def __init__(self, *decisions: bool):
        self.decisions = list(decisions)

    def sample_replay_decision(self) -> bool:
        return self.decisions.pop(0)


def play(curriculum, decisions):
    buffer = Decisions(*decisions)
    out = []
    while buffer.decisions:
        branch = curriculum.next_branch(buffer)
        curriculum.observe(branch, [7, 8] if branch == Branch.REPLAY else None)
        out.append(branch)
    return out


def test_accel_follows_every_replay_with_a_mutation():
    branches = play(ACCEL(), [False, True, True, False, True, False])
    # A mutation step takes no replay decision.
    assert branches == [Branch.NEW, Branch.REPLAY, Branch.MUTATE, Branch.REPLAY,
                        Branch.MUTATE, Branch.NEW, Branch.REPLAY, Branch.MUTATE, Branch.NEW]


def test_plr_branches_follow_the_replay_decision():
    decisions = [False, True, True, False]
    assert play(PLR(), decisions) == [Branch.NEW, Branch.REPLAY, Branch.REPLAY, Branch.NEW]
    dr, buffer = DomainRandomization(), Decisions(True, True)
    assert [dr.next_branch(buffer) for _ in range(3)] == [Branch.NEW] * 3
    assert buffer.decisions == [True, True]  # DR never asks the buffer


def test_which_branches_learn():
    plr, robust, accel, dr = PLR(), RobustPLR(), ACCEL(), DomainRandomization()
    assert plr.learns(Branch.NEW) and plr.learns(Branch.REPLAY)
    assert not robust.learns(Branch.NEW) and robust.learns(Branch.REPLAY)
    assert not accel.learns(Branch.NEW) and not accel.learns(Branch.MUTATE)
    assert accel.learns(Branch.REPLAY) and dr.learns(Branch.NEW)
    assert RobustPLR(exploratory_grad_updates=True).learns(Branch.NEW)
    from ued.config import UEDSection
    from ued.registry import curriculum_for

    assert curriculum_for(UEDSection(method="robust_plr")).name == "robust_plr"
    with pytest.raises(ValueError, match="unknown UED method 'plr2'"):
        curriculum_for(UEDSection(method="plr2"))


def test_sfl_refreshes_every_update_freq_steps():
    sfl = SFL(update_freq=3)
    assert [s for s in range(10) if sfl.needs_refresh(s)] == [0, 3, 6, 9]
    assert sfl.next_branch(None) == Branch.SFL and sfl.learns(Branch.SFL)


def test_curriculum_state_round_trips():
    accel = ACCEL()
    play(accel, [True])
    state = accel.state_dict()
    fresh = ACCEL()
    fresh.load_state_dict(state)
    assert fresh.next_branch(Decisions()) == Branch.MUTATE and fresh.last_replay_ids == [7, 8]
    with pytest.raises(ValueError, match="state of 'accel', expected 'plr'"):
        PLR().load_state_dict(state)


# --- the driver ---------------------------------------------------------------------------------


TOTAL = 10 * 64  # one learning-rate schedule, so every test here shares one compiled update


def ued_config(method: str, **overrides):
    base = {"learner.total_timesteps": TOTAL, "ued.method": method, "ued.buffer_size": 8,
            "ued.min_fill_ratio": 0.5, "levels.free": "[unit_spec]", "ued.sfl_batch_size": 6,
            "ued.sfl_num_batches": 2, "ued.sfl_rollout_steps": 16, "ued.sfl_top_k": 5,
            "ued.sfl_update_freq": 2}
    base.update(overrides)
    return tiny_config(**base)


def params_of(learner: LearnerWorker):
    return jax.tree.map(np.asarray, learner.params)


def trees_equal(a, b) -> bool:
    return all(np.array_equal(x, y) for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b),
                                                    strict=True))


@pytest.mark.parametrize("method,grad_on_new", [("robust_plr", False), ("plr", True),
                                                ("dr", True)])
def test_gradient_on_new_levels_only_where_the_method_says(method, grad_on_new):
    run, ppo = UEDRun.local(ued_config(method))
    learner = LearnerWorker(ppo, ppo.init(jax.random.key(0)))
    before = params_of(learner)
    branch, metrics, levels = run.step(learner, 0, jax.random.key(1))
    assert branch == Branch.NEW  # an empty buffer is below its minimum fill
    assert trees_equal(before, params_of(learner)) != grad_on_new
    assert learner.version == int(grad_on_new)
    if run.service.buffer is not None:
        assert len(run.service.buffer) > 0  # the scored new levels went in
        assert set(run.service.buffer.column("policy_version")) == {0}


def test_every_method_runs_end_to_end_and_never_recompiles(tmp_path):
    def run_all(seed: int) -> None:
        for method in ("dr", "plr", "robust_plr", "accel", "sfl"):
            # Checkpoints at steps 3 and 6, not at each: 60 orbax saves were most of the time.
            config = ued_config(method, seed=seed, **{"run.checkpoint_every": 3})
            run_dir = train(config, run_dir=tmp_path / f"{method}-{seed}", stream=io.StringIO(),
                            max_updates=6)
            steps = snapshot_steps(run_dir / LEVELS_DIR)
            assert steps and steps[-1] == 6, method

    run_all(0)
    learner = UEDRun.local(ued_config("accel"))[1]
    sizes = learner._update_jit._cache_size(), learner._score_jit._cache_size()
    with CompileCounter() as cc:
        run_all(1)  # new seeds: other levels, other buffers, other branch sequences
    assert (learner._update_jit._cache_size(), learner._score_jit._cache_size()) == sizes
    assert sizes[0] == 1
    # Only host-side helpers may trace again (none of them is the update or the rollout).
    assert not [t for t in cc.traced if "update" in t or "score" in t], cc.traced


def test_accel_run_fills_the_buffer_with_mutations(tmp_path):
    config = ued_config("accel", **{"run.checkpoint_every": 5})  # the buffer at 10 is read
    seen = []
    run_dir = train(config, run_dir=tmp_path / "run", stream=io.StringIO(),
                    callback=lambda step, state, metrics: seen.append(metrics["ued/branch"]))
    # After every replay step comes a mutation step.
    for a, b in zip(seen, seen[1:], strict=False):
        if a == Branch.REPLAY:
            assert b == Branch.MUTATE
    assert Branch.MUTATE in seen
    buf = LevelBuffer.load(run_dir / LEVELS_DIR / "buffer-10.msgpack")
    assert (buf.column("source") == 1).any() and (buf.column("parent_id") >= 0).any()
    # Unit specs changed but each unit keeps its role: the archers still deal damage.
    assert (buf.leaf("units.damage")[:, :2] > 0).all()


def test_resume_continues_exactly(tmp_path):
    config = ued_config("accel", **{"run.checkpoint_every": 3})
    full = train(config, run_dir=tmp_path / "full", stream=io.StringIO(), max_updates=8)
    part = train(config, run_dir=tmp_path / "part", stream=io.StringIO(), max_updates=4)
    assert snapshot_steps(part / LEVELS_DIR)[-1] == 4
    train(run_dir=part, resume=True, stream=io.StringIO(), max_updates=4)
    from ued.checkpoint import Checkpoints
    from ued.run_folder import CHECKPOINT_DIR

    template = UEDRun.local(config)[1].init(jax.random.key(0))
    with Checkpoints(full / CHECKPOINT_DIR) as a, Checkpoints(part / CHECKPOINT_DIR) as b:
        state_a, key_a, step_a = a.restore(template)
        state_b, key_b, step_b = b.restore(template)
    assert step_a == step_b == 8
    # The curriculum's step counts continue too: the same state file as the uninterrupted run.
    assert (full / LEVELS_DIR / "state-8.json").read_bytes() == (
        part / LEVELS_DIR / "state-8.json").read_bytes()
    assert sum(json.loads((part / LEVELS_DIR / "state-8.json").read_text())[
        "branch_counts"].values()) == 8
    assert trees_equal(jax.tree.map(np.asarray, state_a.params),
                       jax.tree.map(np.asarray, state_b.params))
    buf_a = LevelBuffer.load(full / LEVELS_DIR / "buffer-8.msgpack")
    buf_b = LevelBuffer.load(part / LEVELS_DIR / "buffer-8.msgpack")
    assert np.array_equal(buf_a.ids, buf_b.ids)
    assert np.array_equal(buf_a.scores, buf_b.scores)


# ACCEL that replays whenever its buffer allows: NEW, REPLAY, MUTATE, REPLAY, MUTATE, ...; so
# the checkpoint after 2 steps is taken between a replay step and its mutate step.
ACCEL_REPLAYS = {"ued.replay_prob": 1.0, "run.checkpoint_every": 2}


def test_a_checkpoint_between_replay_and_mutate_keeps_the_parents_and_resumes_exactly(
        tmp_path):
    config = ued_config("accel", **ACCEL_REPLAYS)
    full = train(config, run_dir=tmp_path / "full", stream=io.StringIO(), max_updates=4)
    part = train(config, run_dir=tmp_path / "part", stream=io.StringIO(), max_updates=2)
    state = json.loads((part / LEVELS_DIR / "state-2.json").read_text())["curriculum"]
    assert state["last_branch"] == Branch.REPLAY and state["last_replay_ids"]
    parents = LevelBuffer.load(part / LEVELS_DIR / "parents-2.msgpack")
    assert len(parents) == len(state["last_replay_ids"])
    buffer = LevelBuffer.load(part / LEVELS_DIR / "buffer-2.msgpack")
    assert np.array_equal(parents.leaf("units.max_health"),
                          buffer.get(np.asarray(state["last_replay_ids"]))["units.max_health"])
    stream = io.StringIO()
    train(run_dir=part, resume=True, stream=stream, max_updates=2)
    assert "dropped" not in stream.getvalue()
    for name in ("state-4.json", "buffer-4.msgpack"):
        assert (full / LEVELS_DIR / name).read_bytes() == (part / LEVELS_DIR / name
                                                            ).read_bytes(), name


def test_a_snapshot_whose_buffer_lost_the_parents_resumes_without_that_mutate_step(
        tmp_path, monkeypatch, capsys):
    """A snapshot written between an ACCEL replay step and its mutate step by a version that
    kept no parents file, after inserts had evicted a parent (the asynchronous schedule
    commits Explorer results in between): `tabx runs check` says a resume drops the mutate
    step, and the resume does so and says it, instead of failing at the next step."""
    from tabx_ued.cli import main
    from workers.roles.level_service import LevelService

    config = ued_config("accel", **ACCEL_REPLAYS)
    save = LevelService.save

    def save_as_before(service, folder, step, state, keep=None, parents=None):
        state = json.loads(json.dumps(state))
        if parents is not None:  # as if inserts had evicted them: ids the buffer lacks
            gone = int(service.buffer.ids.max()) + 1
            state["curriculum"]["last_replay_ids"] = [gone, gone + 1]
        save(service, folder, step, state, keep)

    monkeypatch.setattr(LevelService, "save", save_as_before)
    run_dir = train(config, run_dir=tmp_path / "run", stream=io.StringIO(), max_updates=2)
    monkeypatch.setattr(LevelService, "save", save)
    ids = json.loads((run_dir / LEVELS_DIR / "state-2.json").read_text())["curriculum"][
        "last_replay_ids"]
    held = LevelBuffer.load(run_dir / LEVELS_DIR / "buffer-2.msgpack").ids.tolist()
    assert ids and not set(ids) & set(held)
    assert not (run_dir / LEVELS_DIR / "parents-2.msgpack").exists()

    capsys.readouterr()
    assert main(["runs", "check", str(run_dir)]) == 0
    assert "step 2: intact (its buffer no longer holds the replayed levels" in (
        capsys.readouterr().out)
    stream = io.StringIO()
    train(run_dir=run_dir, resume=True, stream=stream, max_updates=3)
    text = stream.getvalue()
    assert "resume: the level snapshot of step 2 names replayed levels" in text
    assert "mutation step after that replay is dropped" in text
    assert snapshot_steps(run_dir / LEVELS_DIR)[-1] == 5  # the run went on


def test_runs_check_names_a_snapshot_that_resumes_without_its_mutate_step(tmp_path, capsys,
                                                                           monkeypatch):
    from tabx_ued.cli import main
    from workers.roles.level_service import LevelService

    config = ued_config("accel", **ACCEL_REPLAYS)
    save = LevelService.save
    monkeypatch.setattr(LevelService, "save", lambda service, folder, step, state, keep=None,
                        parents=None: save(service, folder, step, state, keep))
    run_dir = train(config, run_dir=tmp_path / "run", stream=io.StringIO(), max_updates=2)
    capsys.readouterr()
    assert main(["runs", "check", str(run_dir)]) == 0
    # The parents are still in the buffer here: nothing is lost.
    assert "step 2: intact\n" in capsys.readouterr().out
    state = json.loads((run_dir / LEVELS_DIR / "state-2.json").read_text())
    buffer = LevelBuffer.load(run_dir / LEVELS_DIR / "buffer-2.msgpack")
    from workers.resume import parents_check

    state["curriculum"]["last_replay_ids"] = [int(buffer.ids.max()) + 1]
    (run_dir / LEVELS_DIR / "state-2.json").write_text(json.dumps(state))
    problem, note = parents_check(run_dir / LEVELS_DIR, 2, config)
    assert problem is None and "a resume drops that mutate step" in note


def test_resume_without_level_snapshot_is_a_clear_error(tmp_path):
    config = ued_config("robust_plr")
    run_dir = train(config, run_dir=tmp_path / "run", stream=io.StringIO(), max_updates=2)
    for path in (run_dir / LEVELS_DIR).iterdir():
        path.unlink()
    with pytest.raises(ConfigError, match="no intact checkpoint to resume from .*state-2.json: "
                                          "missing"):
        train(run_dir=run_dir, resume=True, stream=io.StringIO())


def test_ued_config_errors_name_the_key():
    with pytest.raises(ConfigError, match="ued.method: must be one of"):
        ued_config("paired")
    with pytest.raises(ConfigError, match="ued.replay_prob: must be in"):
        ued_config("plr", **{"ued.replay_prob": 1.5})
    with pytest.raises(ConfigError, match="unknown key 'ued.buffer'"):
        config_from_dict({"ued": {"buffer": 10}})
    with pytest.raises(ConfigError, match="levels.free"):
        ued_config("dr", **{"levels.free": "[wind]"})
    with pytest.raises(ConfigError, match="env.opponent: .*heuristic:novice"):
        ued_config("dr", **{"levels.free": "[heuristic]", "env.opponent": "heuristic:novice"})


def test_shipped_ued_configs_load_and_their_suites_fit():
    from pathlib import Path

    from ued.config import load_config
    from ued.suites import load_suite

    folder = Path(__file__).resolve().parents[2] / "configs" / "ued"
    files = sorted(folder.glob("*.yaml"))
    assert len(files) == 16  # 5 methods x 3 free-parameter types, and the quickstart
    for path in files:
        config = load_config(path)
        assert config.ued.enabled, path
        assert config.learner.gae_lambda == 0.99, path  # the paper's UED table
        for name in config.ued.eval_suites:
            load_suite(name)
    # The quickstart builds all its workers (the evaluator checks its suite fits the policy).
    run, _ = UEDRun.local(load_config(folder / "quickstart.yaml"))
    assert len(run.evaluators) == 1 and run.service.buffer is not None


def test_evaluator_logs_during_training_and_snapshots_are_buffer_files(tmp_path, capsys):
    from test_learners_helpers import scenario_file

    from tabx_ued.cli import main
    from ued.tensorboard import read_scalars

    suite = tmp_path / "duel.yaml"
    suite.write_text(f"name: duel\nepisodes: 2\nscenarios: ['{scenario_file()}']\n"
                     "opponents: [random, idle]\n")
    config = ued_config("robust_plr", **{"ued.eval_suites": f"['{suite}']",
                                         "ued.eval_every": 2})
    run_dir = train(config, run_dir=tmp_path / "run", stream=io.StringIO(), max_updates=4)
    scalars = read_scalars(run_dir / "events")
    # Evaluated after steps 2 and 4 (x axis: env steps, 64 per step).
    assert [step for step, _ in scalars["eval/duel/mean_win_rate"]] == [128, 256]
    assert any(tag.startswith("eval/duel/") and tag.endswith("@idle/win_rate")
               for tag in scalars)
    assert {"buffer/size", "levels/unit_max_health", "ued/branch"} <= set(scalars)
    # Steps/s split by kind (Robust PLR does not train on new levels); the old tag is the sum.
    total, trained, explored = (scalars[f"time/{kind}steps_per_s"]
                                for kind in ("", "trained_", "explored_"))
    assert [s for s, _ in total] == [s for s, _ in trained] == [s for s, _ in explored]
    for (_, all_), (_, t), (_, e) in zip(total, trained, explored, strict=True):
        assert t >= 0 and e >= 0 and all_ == pytest.approx(t + e, rel=1e-4)
    assert main(["buffer", "inspect", str(run_dir / LEVELS_DIR / "buffer-4.msgpack")]) == 0
    assert "levels" in capsys.readouterr().out

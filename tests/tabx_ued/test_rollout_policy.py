"""`tabx rollout --ally RUN_DIR` / `--enemy RUN_DIR`: a trained policy plays a team of the
simulator's rollout (`tabx.policy_team`, loaded by `ued.evaluate.load_policy_team`).

The runs are tiny policies on the mirrored 2 archers v 2 archers duel of tests/ued/test_payoff.py,
with random parameters in checkpoint 0: playing needs no training, and drawing them with numpy
needs no compilation. A greedy policy and the env are deterministic (the env's step draws
nothing), so a rollout of greedy policies must be exactly the episode `tabx eval` plays.
"""

from __future__ import annotations

import shutil
import tempfile
from pathlib import Path

import jax
import numpy as np
import pytest
from PIL import Image
from test_learners_helpers import tiny_config
from test_payoff import MIRROR, mirror_level
from test_qlearning import tiny_q_config

from tabx import constants as C
from tabx.rollout import play_episode
from tabx_ued.cli import main
from ued.checkpoint import Checkpoints
from ued.config import TrainConfig
from ued.evaluate import play, policy_team
from ued.experiment import learner_for
from ued.run_folder import CHECKPOINT_DIR, CONFIG_FILE, load_policy

STEPS = str(MIRROR.max_steps)


@pytest.fixture(scope="module")
def mirror_file() -> str:
    from tabx.scenarios import level_to_scenario, save_scenario

    path = Path(tempfile.mkdtemp(prefix="tabx-rollout-tests-")) / "mirror2a2a.json"
    save_scenario(path, level_to_scenario(mirror_level(), name="mirror2a2a"))
    return str(path)


def policy_run(folder: Path, config: TrainConfig, seed: int = 1) -> Path:
    """A run folder of `config` whose checkpoint 0 holds random parameters alone (what
    `load_policy` reads), drawn with numpy."""
    rng = np.random.default_rng(seed)
    shapes = jax.eval_shape(learner_for(config).init_params, jax.random.key(0))
    params = jax.tree.map(lambda s: rng.normal(0.0, 0.5, s.shape).astype(s.dtype), shapes)
    folder.mkdir(parents=True)
    (folder / CONFIG_FILE).write_text(config.to_yaml())
    with Checkpoints(folder / CHECKPOINT_DIR) as ck:
        ck.save(0, {"params": params}, jax.random.key(0))
    return folder


@pytest.fixture(scope="module")
def runs(tmp_path_factory, mirror_file) -> Path:
    """Folder with `ally`: a MAPPO policy trained as the allies."""
    folder = tmp_path_factory.mktemp("runs")
    policy_run(folder / "ally", tiny_config(**{"env.scenario": mirror_file,
                                                "env.max_steps": MIRROR.max_steps}))
    return folder


def cli(capsys, *argv: str) -> tuple[int, str, str]:
    code = main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


def test_greedy_policies_play_the_episode_eval_plays(runs):
    """Both teams greedy, one policy on its own team and through the team swap: the rollout's
    states are those of `tabx eval`'s episode, step for step, and the units turned."""
    policy = load_policy(runs / "ally")
    level = mirror_level()
    sides = (policy_team(policy, C.ALLY, greedy=True), policy_team(policy, C.ENEMY, greedy=True))
    assert sides[1].slots == (2, 4) and sides[1].env_config == MIRROR
    _, total, _, (states, _) = jax.device_get(
        play_episode(MIRROR, level, MIRROR.max_steps, 7, sides, trajectory=True))
    evaluated = play(MIRROR, level, policy, policy, 1, seed=7, greedy=True, record=True)
    for name in ("position", "heading", "health", "alive", "done", "won"):
        np.testing.assert_array_equal(getattr(states, name), getattr(evaluated.states, name),
                                      err_msg=name)
    # The same rewards summed by two programs, perhaps in another order: a few float32 ulps.
    np.testing.assert_allclose(total, evaluated.returns[0], rtol=1e-6)
    assert not np.allclose(states.heading[-1], np.asarray(level.units.heading), atol=0.1)


def test_rollout_cli_prints_the_eval_outcome_and_writes_the_gif(capsys, runs, tmp_path):
    """`--ally RUN --enemy RUN --greedy`: the scenario is the run's, the outcome printed is
    that of `tabx eval`'s episode with the same seed, and the GIF shows the episode."""
    gif, run = tmp_path / "policy.gif", runs / "ally"
    code, out, err = cli(capsys, "rollout", "--ally", str(run), "--enemy", str(run),
                         "--greedy", "--steps", STEPS, "--seed", "7", "--gif", str(gif))
    assert code == 0, err
    label = f"{run} (mappo, update 0)"
    assert (f"scenario mirror2a2a: 2 allies v 2 enemies, 0 zones; allies {label}, enemies "
            f"{label}, seed 7, profile tabx-ued, greedy policies") in out
    policy = load_policy(run)
    evaluated = play(MIRROR, mirror_level(), policy, policy, 1, seed=7, greedy=True,
                     record=True)  # the program of the test above
    for name, team in (("allies", C.ALLY), ("enemies", C.ENEMY)):
        assert f"return {evaluated.returns[0, team]:+.3f}" in next(
            line for line in out.splitlines() if line.startswith(f"  {name} "))
    winner = "allies" if evaluated.won[0, C.ALLY] else "enemies"
    assert f"outcome: {winner} win by " in out
    assert f"at step {evaluated.lengths[0]}" in out
    assert f"wrote {gif}" in out
    with Image.open(gif) as image:
        assert image.n_frames == evaluated.lengths[0] + 1  # the start, then every step


def test_rollout_cli_plays_a_q_learner_trained_on_the_enemies(capsys, tmp_path, mirror_file):
    """`--enemy RUN` of an IQL run trained there, the allies its training opponent (random);
    the same outcome again for the same seed."""
    run = str(policy_run(tmp_path / "iql", tiny_q_config("iql", str(tmp_path), {
        "env.scenario": mirror_file, "env.team": "enemy", "env.max_steps": MIRROR.max_steps})))
    argv = ("rollout", "--enemy", run, "--steps", STEPS, "--seed", "2")
    code, out, err = cli(capsys, *argv)
    assert code == 0, err
    assert f"allies random, enemies {run} (iql, update 0), seed 2" in out
    assert "sampled policies" in out and "outcome: " in out
    again = cli(capsys, *argv)[1]
    assert again.splitlines()[:-1] == out.splitlines()[:-1]  # all but the time taken


def test_bad_run_folders_are_one_clear_error(capsys, runs, tmp_path, mirror_file):
    shorter = policy_run(tmp_path / "shorter", tiny_config(**{"env.scenario": mirror_file,
                                                               "env.max_steps": 16}))
    empty = tmp_path / "empty"
    empty.mkdir()
    damaged = tmp_path / "damaged"
    shutil.copytree(runs / "ally", damaged)
    for path in (damaged / CHECKPOINT_DIR / "0").rglob("*"):
        if path.is_file() and path.name != "_CHECKPOINT_METADATA":
            path.write_bytes(b"")
    cases = [
        (["--ally", str(empty)], f"--ally: {empty}: not a run folder (no config.yaml)"),
        (["--enemy", str(tmp_path / "nowhere")], f"--enemy: {tmp_path / 'nowhere'}: no such "
                                                 f"run folder"),
        (["--ally", str(damaged)], f"--ally: {damaged}"),
        (["--ally", str(runs / "ally" / CONFIG_FILE)], "config.yaml: not a folder"),
        (["--enemy", "heuristic:legendary"], "--enemy: 'heuristic:legendary' is not a "
                                             "controller or a run folder (unknown heuristic "
                                             "tier"),
        # A 2 v 2 policy on a 4 v 1 scenario.
        (["pingpong", "--ally", str(runs / "ally")], f"{runs / 'ally'} (mappo, update 0) "
                                                     f"cannot play 'pingpong'"),
        (["--ally", str(runs / "ally"), "--max-steps", "100"], "plays episodes of 24 steps"),
        (["--ally", str(runs / "ally"), "--enemy", str(shorter)],
         f"{shorter} (mappo, update 0) was trained with EnvConfig(max_allies=2, max_enemies=2, "
         f"max_zones=0, max_steps=16, "),
        (["crossfire", "--greedy"], "--greedy picks a trained policy's most likely action"),
    ]
    for argv, expected in cases:
        code, out, err = cli(capsys, "rollout", *argv, "--steps", "2")
        lines = err.strip().splitlines()
        assert code == 2 and len(lines) == 1 and not out, (argv, err)
        assert lines[0].startswith("tabx rollout: error: ") and expected in lines[0], lines[0]
    assert "cannot be restored" in cli(capsys, "rollout", "--ally", str(damaged))[2]

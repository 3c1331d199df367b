"""`tabx train`, `tabx eval` and `tabx bench train` on the command line: errors, a tiny run that
resumes, evaluation against a controller and policy against policy (with a GIF)."""

from __future__ import annotations

import argparse

import jax
import pytest
from test_learners_helpers import tiny_config

from tabx_ued.cli import main
from ued.checkpoint import Checkpoints
from ued.experiment import learner_for
from ued.run_folder import CHECKPOINT_DIR, CONFIG_FILE


def run_cli(capsys, *argv: str) -> tuple[int, str, str]:
    code = main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


@pytest.fixture(scope="module")
def tiny_yaml(tmp_path_factory):
    path = tmp_path_factory.mktemp("cfg") / "tiny.yaml"
    path.write_text(tiny_config().to_yaml())
    return path


def test_train_reports_config_errors_naming_the_key(capsys, tmp_path, tiny_yaml):
    bad = tmp_path / "bad.yaml"
    bad.write_text("algorithm: mappo\nlearner:\n  clip_epsilon: 0.2\n")
    code, _, err = run_cli(capsys, "train", str(bad))
    assert code == 2 and "learner.clip_epsilon" in err and "did you mean 'learner.clip_eps'" in err
    code, _, err = run_cli(capsys, "train", str(tiny_yaml), "learner.gamma=2")
    assert code == 2 and "learner.gamma: must be in [0, 1], got 2.0" in err
    code, _, err = run_cli(capsys, "train", str(tiny_yaml), "nonsense")
    assert code == 2 and "KEY=VALUE" in err
    code, _, err = run_cli(capsys, "train")
    assert code == 2 and "give a config file" in err
    code, _, err = run_cli(capsys, "train", str(tiny_yaml), "--resume", str(tmp_path))
    assert code == 2 and "--resume continues a run with its own config.yaml" in err
    code, _, err = run_cli(capsys, "train", "--resume", str(tmp_path), "learner.lr=0.1")
    assert code == 2 and "overrides of the ray: section only" in err
    code, _, err = run_cli(capsys, "train", "--resume", str(tmp_path), "ray.explorers=2")
    assert code == 2 and "ray.* overrides on --resume go with --ray" in err
    code, _, err = run_cli(capsys, "train", "--resume", str(tmp_path))
    assert code == 2 and "not a run folder" in err
    code, _, err = run_cli(capsys, "train", str(tmp_path / "missing.yaml"))
    assert code == 2 and "cannot read the config" in err
    # More devices than this machine has (the tests run with two): an error, and no run folder.
    runs = tmp_path / "runs"
    code, _, err = run_cli(capsys, "train", str(tiny_yaml), "learner.num_envs=8",
                           "learner.num_devices=4", f"run.dir={runs}")
    assert code == 2 and "learner.num_devices: 4 devices asked for, 2 available" in err
    assert not runs.exists()


def test_eval_reports_errors(capsys, tmp_path):
    code, _, err = run_cli(capsys, "eval")
    assert code == 2 and "give a run folder" in err
    code, _, err = run_cli(capsys, "eval", "--ally", "random", "--enemy", "heuristic:nope",
                           "--scenario", "crossfire")
    assert code == 2 and "unknown heuristic tier" in err
    code, _, err = run_cli(capsys, "eval", "--ally", "random", "--enemy", "idle",
                           "--scenario", "no-such-scenario")
    assert code == 2 and "unknown scenario" in err
    code, _, err = run_cli(capsys, "eval", str(tmp_path))
    assert code == 2 and "not a run folder" in err


def test_train_resume_and_eval(capsys, tmp_path, tiny_yaml):
    run = tmp_path / "run"
    code, out, err = run_cli(capsys, "train", str(tiny_yaml), "run.log_every=2",
                             "--run-dir", str(run), "--max-updates", "2")
    assert code == 0, err
    assert out.strip().endswith(str(run))
    assert "update 2/4" in err and "steps/s" in err  # the progress line
    assert (run / CONFIG_FILE).is_file() and "log_every: 2" in (run / CONFIG_FILE).read_text()
    code, _, err = run_cli(capsys, "train", "--resume", str(run), "--quiet")
    assert code == 0, err
    with Checkpoints(run / CHECKPOINT_DIR) as ck:
        assert ck.latest() == 4 and ck.all() == [3, 4]  # keep_checkpoints: 2
    # Once more: nothing left to do, and it says so.
    code, out, err = run_cli(capsys, "train", "--resume", str(run), "--quiet")
    assert code == 0 and f"{run}: already complete (4 of 4 updates); nothing to resume" in err
    # A pattern that matched two runs: say that, not something about overrides.
    code, _, err = run_cli(capsys, "train", "--resume", str(run), str(tmp_path))
    assert code == 2 and f"--resume takes one run folder; {tmp_path} is another" in err

    # Against the medium heuristic, with a GIF of episode 0.
    gif = tmp_path / "episode.gif"
    code, out, err = run_cli(capsys, "eval", str(run), "--enemy", "heuristic:medium",
                             "--episodes", "6", "--gif", str(gif))
    assert code == 0, err
    assert "6 episodes" in out and "win rate" in out and "episode length" in out
    assert "enemy heuristic:medium" in out and f"ally  {run} (mappo, update 4)" in out
    assert gif.is_file() and gif.stat().st_size > 0
    code, _, err = run_cli(capsys, "eval", str(run), "--scenario", "crossfire")
    assert code == 2 and "do not fit" in err
    # Episodes of another length than the run trained with (8 steps): against an idle enemy
    # nobody is eliminated, so every episode lasts exactly the limit given.
    for limit in (3, 20):
        code, out, err = run_cli(capsys, "eval", str(run), "--enemy", "idle", "--episodes", "4",
                                 "--max-steps", str(limit))
        assert code == 0, err
        assert f"episode length {limit}.0 ± 0.0 steps" in out
    code, _, err = run_cli(capsys, "eval", str(run), "--max-steps", "0")
    assert code == 2 and "--max-steps must be an integer in [1," in err


@pytest.mark.slow
def test_policy_against_policy(capsys, tmp_path, tiny_yaml):
    run = tmp_path / "ally"
    assert run_cli(capsys, "train", str(tiny_yaml), "--run-dir", str(run), "--quiet",
                   "--max-updates", "1")[0] == 0
    # An enemy-team run: initialised and saved as update 0 (no training needed to play).
    enemy_config = tiny_config(**{"env.team": "enemy"})
    enemy_run = tmp_path / "enemy"
    enemy_run.mkdir()
    (enemy_run / CONFIG_FILE).write_text(enemy_config.to_yaml())
    learner = learner_for(enemy_config)
    with Checkpoints(enemy_run / CHECKPOINT_DIR) as ck:
        ck.save(0, learner.init(jax.random.key(1)), jax.random.key(2))
    code, out, err = run_cli(capsys, "eval", "--ally", str(run), "--enemy", str(enemy_run),
                             "--episodes", "4")
    assert code == 0, err
    assert f"enemy {enemy_run} (mappo, update 0)" in out and f"ally  {run}" in out
    # A policy plays only the team it was trained for.
    code, _, err = run_cli(capsys, "eval", "--ally", str(enemy_run), "--enemy", str(run))
    assert code == 2 and "trained as the enemy team" in err


def test_run_folders_from_before_matmul_dtype_keep_float32(tmp_path):
    """A resolved config without `learner.matmul_dtype` (written before the field existed)
    resumes and evaluates in float32, as it trained; a current one in its own dtype."""
    from ued.run_folder import read_run_config

    text = tiny_config().to_yaml()
    assert "matmul_dtype: bfloat16" in text
    (tmp_path / CONFIG_FILE).write_text(text)
    assert read_run_config(tmp_path).learner.matmul_dtype == "bfloat16"
    old = "\n".join(line for line in text.splitlines() if "matmul_dtype" not in line)
    (tmp_path / CONFIG_FILE).write_text(old)
    assert read_run_config(tmp_path).learner.matmul_dtype == "float32"


def test_bench_train_parser():
    from tabx_bench.train import add_train_bench

    parser = argparse.ArgumentParser()
    which = parser.add_subparsers(dest="bench_command")
    add_train_bench(which)
    args = parser.parse_args(["train", "--algorithms", "ippo", "--num-envs", "8",
                              "--num-steps", "4", "--updates", "1"])
    assert args.algorithms == ["ippo"] and args.num_envs == 8 and callable(args.func)
    assert args.matmul_dtype is None  # the config default
    assert parser.parse_args(["train", "--matmul-dtype", "float32"]).matmul_dtype == "float32"
    assert parser.parse_args(["train", "--algorithms", "iql,vdn,qmix"]).algorithms == [
        "iql", "vdn", "qmix"]
    for bad in (["--algorithms", "dqn"], ["--matmul-dtype", "float16"]):
        with pytest.raises(SystemExit):
            parser.parse_args(["train", *bad])


BENCH_WITH_A_CACHE = """
import jax, jax.numpy as jnp
jax.config.update("jax_compilation_cache_dir", {cache!r})
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
(jnp.ones(3) + 1).block_until_ready()  # the process's first compile: JAX now uses the cache
from tabx_bench.train import run_train_bench
for _ in range(2):  # each run builds its learner anew (cached=False): the second loads it
    try:
        r = run_train_bench("ippo", num_envs=4, num_steps=4, updates=1, matmul_dtype="float32")
        print("measured", r.first_update_s > 0 and r.update_s > 0 and r.steps_per_s > 0
              and r.matmul_dtype == "float32")
    except RuntimeError as err:
        print("refused:", err)
"""


def test_bench_train_refuses_a_first_update_loaded_from_a_cache(tmp_path):
    """A persistent cache that JAX took up before the benchmark started (a user's own
    setting) must not pass off a loaded program as a cold first update: the first run
    compiles (and fills the cache), the second would load the update and refuses. One process
    (a fresh one: the test session's own cache setting must not be the one under test)."""
    import subprocess
    import sys

    code = BENCH_WITH_A_CACHE.format(cache=str(tmp_path / "xla"))
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    first, second = out.stdout.splitlines()[-2:]
    assert first == "measured True", out.stdout
    assert second.startswith("refused: the first update was not compiled"), out.stdout


def test_an_unexpected_error_is_one_line_and_debug_shows_the_traceback(capsys, monkeypatch):
    from tabx_ued.cli import run

    def add_boom(subparsers):
        boom = subparsers.add_parser("boom")
        boom.set_defaults(func=lambda args: {}["missing key"])

    assert run(["boom"], [add_boom]) == 1
    err = capsys.readouterr().err
    assert err.startswith("tabx boom: error: KeyError: 'missing key' (unexpected: run `tabx "
                          "--debug boom ...`") and "Traceback" not in err
    with pytest.raises(KeyError):
        run(["--debug", "boom"], [add_boom])
    monkeypatch.setenv("TABX_DEBUG", "1")
    with pytest.raises(KeyError):
        run(["boom"], [add_boom])


def test_overrides_may_follow_options(capsys, tmp_path, tiny_yaml):
    # `tabx train CONFIG --max-updates 1 seed=7`: argparse alone would refuse the override.
    run = tmp_path / "run"
    code, _, err = run_cli(capsys, "train", str(tiny_yaml), "--max-updates", "1", "seed=7",
                           "--run-dir", str(run), "--quiet")
    assert code == 0, err
    assert "seed: 7" in (run / CONFIG_FILE).read_text()
    with pytest.raises(SystemExit):  # anything else after the options is still refused
        run_cli(capsys, "train", str(tiny_yaml), "--quiet", "--bogus")
    assert "unrecognized arguments: --bogus" in capsys.readouterr().err


def test_a_finished_run_prints_a_summary(tmp_path):
    """What `tabx train` prints at the end (stderr, before the folder on stdout): the last
    win rate, each suite's zero-shot mean, where the checkpoints are."""
    from tabx_ued.train_eval_commands import run_summary_lines
    from ued.tensorboard import SummaryWriter

    run = tmp_path / "run"
    writer = SummaryWriter(run / "events")
    writer.scalars({"episode/win_rate": 0.25, "eval/zones/mean_win_rate": 0.5}, step=64)
    writer.scalars({"episode/win_rate": 0.75}, step=128)
    writer.close()
    for step in (2, 4):
        (run / "checkpoints" / str(step)).mkdir(parents=True)
    text = run_summary_lines(run)
    assert "win rate (training, at env step 128): 0.750" in text
    assert "zero-shot mean win rate, zones (env step 64): 0.500" in text
    assert f"checkpoints: {run / 'checkpoints'} (steps 2, 4)" in text
    assert run_summary_lines(tmp_path / "nothing").startswith("summary of")


def test_the_summary_says_when_no_episode_ended(tmp_path):
    """Rollouts shorter than an episode (`learner.num_steps` below `env.max_steps`) end one
    only by an elimination: an update that ended none logs no win rate. The summary says so
    rather than show an older update's rate as the run's (1.000 over one episode)."""
    from tabx_ued.train_eval_commands import run_summary_lines
    from ued.tensorboard import SummaryWriter

    run = tmp_path / "run"
    writer = SummaryWriter(run / "events")
    writer.scalars({"episode/count": 1.0, "episode/win_rate": 1.0}, step=64)
    writer.scalars({"episode/count": 0.0}, step=128)
    writer.close()
    text = run_summary_lines(run)
    assert ("win rate (training): none; no episode ended within the rollouts of the last "
            "logged update (env step 128); the last that had one, at env step 64: 1.000 over "
            "1 episode") in text, text
    writer = SummaryWriter(run / "events")
    writer.scalars({"episode/count": 8.0, "episode/win_rate": 0.25}, step=192)
    writer.close()
    assert "win rate (training, at env step 192): 0.250 over 8 episodes" in run_summary_lines(run)


def test_a_ray_run_resumed_without_ray_continues_on_the_local_driver(capsys, tmp_path):
    """`tabx train --resume RUN` of a run trained with `--ray`: the local driver continues it
    (Ray is not started, no `ray.json` is written), as `ray.enabled=false` says too; the run's
    own config.yaml keeps its `ray:` section. The run folder is made by the local driver from
    a config with `ray.enabled: true`: the same files a Ray run leaves."""
    import io

    from test_ued_train import ued_config

    from ued.run_folder import read_run_config
    from workers.local import LocalDriver
    from workers.ray.driver import RAY_RECORD
    from workers.train import train

    config = ued_config("robust_plr", **{"ray.enabled": "true", "run.checkpoint_every": 1})
    run = train(config, run_dir=tmp_path / "run", driver=LocalDriver(), stream=io.StringIO(),
                max_updates=1)
    assert read_run_config(run).ray.enabled
    code, _, err = run_cli(capsys, "train", "--resume", str(run), "--max-updates", "1")
    assert code == 0, err[-2000:]
    assert "resuming robust_plr" in err and " on Ray " not in err
    code, _, err = run_cli(capsys, "train", "--resume", str(run), "--max-updates", "1",
                           "ray.enabled=false")
    assert code == 0, err[-2000:]
    assert not (run / RAY_RECORD).exists()
    code, _, err = run_cli(capsys, "train", "--resume", str(run), "--ray", "ray.enabled=false")
    assert code == 2 and "ray.enabled=false: --ray resumes the run on Ray" in err
    with Checkpoints(run / CHECKPOINT_DIR) as checkpoints:
        assert checkpoints.latest() == 3
    assert read_run_config(run).ray.enabled  # config.yaml is the run's own


def test_an_error_raised_in_a_ray_actor_is_shown_by_its_cause():
    # An Explorer's call whose argument was a level-service call that raised: Ray wraps the
    # service's error in the Explorer's, each text a coloured traceback.
    from ray.exceptions import RayTaskError

    from tabx_ued.cli import error_line

    try:
        raise KeyError("level ids [11] are not in the buffer")
    except KeyError as cause:
        inner = RayTaskError("mutate", "\x1b[36mray::LevelServiceActor.mutate()\x1b[39m "
                             "(pid=7, ip=127.0.0.1)\nTraceback (most recent call last): ...",
                             cause).as_instanceof_cause()
    outer = RayTaskError("score_levels", "\x1b[36mray::ExplorerActor.score_levels()\x1b[39m "
                         "(pid=8)\nTraceback ...", inner).as_instanceof_cause()
    assert error_line(outer) == ("KeyError: 'level ids [11] are not in the buffer' (raised in "
                                 "the Ray actor call LevelServiceActor.mutate())")
    assert error_line(ValueError("bad\nsecond line")) == "ValueError: bad"

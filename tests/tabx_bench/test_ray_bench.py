"""`tabx bench ued` over a local Ray: the same work on the local and the Ray driver, the
timing of an Explorer restart, and the command's argument checks.

One Ray (3 logical CPUs) serves the module, as in tests/workers/ray/test_ray_driver.py.
"""

from __future__ import annotations

import io
import os

os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")

import pytest  # noqa: E402
import ray  # noqa: E402
from test_ued_train import ued_config  # noqa: E402

# Every test here runs on the module's local Ray (tests/conftest.py).
pytestmark = pytest.mark.usefixtures("local_ray")


def test_ued_bench_measures_the_same_work_on_both_drivers():
    from tabx_bench.ued import format_table, ray_overhead, run_ued_bench

    out = io.StringIO()
    results = run_ued_bench(ued_config("accel"), explorers=[1], warmup=2, steps=3, stream=out)
    assert [r.label for r in results] == ["local", "ray, 0 explorers, deterministic",
                                          "ray, 1 explorer"]
    local, deterministic, asynchronous = results
    # The deterministic schedule replays the local driver's steps: the same branches, the
    # same env steps trained and explored.
    assert deterministic.branches == local.branches and sum(local.branches.values()) == 3
    assert (deterministic.trained_steps, deterministic.explored_steps) == (
        local.trained_steps, local.explored_steps)
    assert local.trained_steps + local.explored_steps == 3 * 4 * 16  # 4 envs x 16 steps each
    assert asynchronous.trained_steps > 0 and asynchronous.seconds > 0
    assert 0 < asynchronous.learner_busy_fraction <= 1
    assert ray_overhead(results) is not None
    table = format_table(results)
    assert "Ray overhead on the local driver's work" in table and "ray, 1 explorer " in table
    assert out.getvalue().count("env steps/s") == 3  # one progress line per setting



def test_ued_bench_cli_rejects_bad_arguments(capsys):
    from tabx_ued.cli import main

    with pytest.raises(SystemExit) as exit_:
        main(["bench", "ued", "--explorers", "1,-2"])
    assert exit_.value.code == 2 and "--explorers" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exit_:
        main(["bench", "ued", "--steps", "0"])
    assert exit_.value.code == 2 and "--steps" in capsys.readouterr().err
    for bad in (["--simulate", "0,8"], ["--simulate", "8", "--batch-s", "0"]):
        with pytest.raises(SystemExit) as exit_:
            main(["bench", "ued", *bad])
        assert exit_.value.code == 2 and bad[-2] in capsys.readouterr().err
    assert main(["bench", "ued", "configs/marl/mappo_grid.yaml"]) == 2
    assert "ued.method: tabx bench ued needs a UED config" in capsys.readouterr().err



def test_ued_bench_times_an_explorer_restart():
    from tabx_bench.ued import bench_restart

    out = io.StringIO()
    # The session's compilation cache (tests/conftest.py): the Explorer's programs load.
    result = bench_restart(ray, ued_config("robust_plr"), True, out,
                           cache_dir=os.environ["TABX_COMPILE_CACHE_DIR"])
    assert result.first_score_s > 0 and 0 < result.ready_s <= result.restarted_score_s
    assert result.service_commits == 50 and result.service_ready_s > 0  # none lost, or raises
    assert "restart, compilation cache on: Explorer back in" in out.getvalue()


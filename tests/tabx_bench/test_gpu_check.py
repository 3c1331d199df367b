"""`tabx bench gpu` (tools/gpu_check.sh): every part at tiny sizes on the CPU.

The GPU numbers come from the script on a GPU machine; here each part runs for real at a few
envs and steps (the simulator at 3v3 and 10v10, MAPPO's update, the UED trial as `tabx train`
processes, one and then two at once) and the test checks what the check writes: the JSON,
the summary's tables and the projections computed from the trials' own logged timings.
"""

from __future__ import annotations

import json
import math
import os
import subprocess
from pathlib import Path

import pytest

from tabx_bench.gpu import PAPER_STEPS, TrialTiming, summarise, trial_command
from tabx_ued.cli import main

ROOT = Path(__file__).resolve().parents[2]


def test_the_gpu_check_runs_every_part_and_projects_minutes_per_trial(tmp_path, capsys):
    """Every part for real at tiny sizes: the simulator at 3v3 and 10v10, IPPO's update, and
    a UED trial (a `tabx train` process; several at once are the same code, their summary
    is the next test's)."""
    out = tmp_path / "out"
    code = main(["bench", "gpu", "--out", str(out), "--team-sizes", "3,10", "--sim-envs", "2",
                 "--sim-steps", "2", "--sim-repeats", "1", "--algorithms", "ippo",
                 "--train-envs", "4", "--train-steps", "4", "--train-updates", "1",
                 "--ued-envs", "4", "--ued-steps", "8", "--ued-updates", "2",
                 "--eval-episodes", "1", "--concurrency", "1"])
    printed, err = capsys.readouterr()
    assert code == 0, printed + err
    result = json.loads((out / "gpu_check.json").read_text())
    assert [(r["team_size"], r["num_envs"]) for r in result["simulator"]] == [(3, 2), (10, 2)]
    assert all(r["steps_per_s"] > 0 for r in result["simulator"])
    (ippo,) = result["learners"]
    assert (ippo["algorithm"], ippo["num_envs"], ippo["num_steps"]) == ("ippo", 4, 4)
    trials = result["ued"]
    assert [(t["concurrent"], t["index"]) for t in trials] == [(1, 0)]
    for t in trials:
        assert t["returncode"] == 0 and t["env_steps"] == 2 * 4 * 8
        assert t["first_update_s"] > 0 and t["steady_steps_per_s"] > 0
        assert 0 <= t["zero_shot_win_rate"] <= 1 and (out / t["log"]).is_file()
        # the projection: start-up, first update and evaluation, then the steady rate
        rest = (PAPER_STEPS - 32) / t["steady_steps_per_s"]
        assert t["projected_minutes"] * 60 == pytest.approx(
            t["overhead_s"] + t["first_update_s"] + rest)
        assert t["overhead_s"] == pytest.approx(max(0.0, t["wall_s"] - t["first_update_s"]
                                                    - 32 / t["steady_steps_per_s"]))
    summary = (out / "summary.txt").read_text()
    assert summary in printed
    for text in ("3v3", "10v10", "ippo", "5m", "18-47 min per UED trial", "22 min"):
        assert text in summary


def test_the_summary_sums_the_steady_rates_of_trials_run_at_once():
    row = {"overhead_s": 0.0, "projected_minutes": 0.0, "steps_per_update": 100,
           "env_steps": 200, "returncode": 0, "log": "x.log"}
    trials = [{**row, "concurrent": 1, "index": 0, "wall_s": 60.0, "first_update_s": 30.0,
               "steady_steps_per_s": 1000.0},
              {**row, "concurrent": 2, "index": 0, "wall_s": 80.0, "first_update_s": 10.0,
               "steady_steps_per_s": 700.0},
              {**row, "concurrent": 2, "index": 1, "wall_s": 90.0, "first_update_s": 12.0,
               "steady_steps_per_s": 500.0}]
    result = {"machine": "m", "date": "d", "load_avg": 0.5, "paper_steps": 1_000_100,
              "simulator": [], "learners": [], "ued": trials,
              "ued_settings": {"num_envs": 1, "num_steps": 100, "updates": 2}}
    lines = summarise(result).splitlines()
    one = next(line.split() for line in lines if line.split()[:1] == ["1"])
    two = next(line.split() for line in lines if line.split()[:1] == ["2"])
    per = [TrialTiming(**{k: v for k, v in t.items()
                          if k in TrialTiming.__dataclass_fields__}) for t in trials]
    assert one[1:5] == ["60", "30.0", "1,000", "1,000"]
    assert two[1:5] == ["90", "11.0", "600", "1,200"]  # the slower's wall; mean; mean; sum
    minutes = (per[1].projected_minutes(1_000_100) + per[2].projected_minutes(1_000_100)) / 2
    assert two[5:] == [f"{minutes:.1f}", f"{2 * 60 / minutes:.1f}"]


def test_trial_timing_projection_and_command():
    t = TrialTiming(concurrent=1, index=0, wall_s=100.0, first_update_s=40.0,
                    steady_steps_per_s=1000.0, env_steps=20_000, steps_per_update=10_000,
                    returncode=0, log="x.log")
    assert t.overhead_s == pytest.approx(50.0)  # 100 - 40 - 10,000 / 1,000
    assert t.projected_minutes(1_010_000) == pytest.approx((50 + 40 + 1000) / 60)
    assert math.isnan(TrialTiming(1, 0, 1.0, 1.0, math.nan, 1, 1, 1, "").projected_minutes())
    command = trial_command(Path("/r"), 128, 512, 16, 0)
    assert command[3:5] == ["train", "ued/robust_plr_zone"] and "/r" in command
    assert "learner.total_timesteps=1048576" in command and "ued.eval_every=16" in command


def test_the_script_writes_its_files_under_out(tmp_path):
    """tools/gpu_check.sh: its folder, a fresh compilation cache, the options passed on (here
    every part skipped, so it only writes what it writes)."""
    out = tmp_path / "out"
    done = subprocess.run(["bash", str(ROOT / "tools" / "gpu_check.sh"), str(out),
                           "--team-sizes", "none", "--algorithms", "none", "--concurrency",
                           "none"], capture_output=True, text=True, cwd=tmp_path,
                          env={**os.environ, "PYTHONPATH": str(ROOT)}, timeout=300)
    assert done.returncode == 0, done.stdout + done.stderr
    assert {p.name for p in out.iterdir()} == {"gpu_check.json", "summary.txt",
                                               "nvidia-smi.txt"}
    result = json.loads((out / "gpu_check.json").read_text())
    assert result["simulator"] == result["learners"] == result["ued"] == []
    assert "# tabx bench gpu on" in done.stdout

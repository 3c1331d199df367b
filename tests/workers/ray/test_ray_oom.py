"""A real out-of-memory kill by Ray's memory monitor, on a Ray of this module's own: the run
restarts from its newest checkpoint and finishes.

The Ray is started with a low `RAY_memory_usage_threshold` (4 GiB above what the machine uses
when it starts) and a 100 ms `RAY_memory_monitor_refresh_ms`. After step 3 (checkpoints every 2
steps) a process of the test allocates enough to cross the threshold; the memory monitor then
kills the workers running tasks (Ray 2.60 kills several per decision: here the learner, which
scores too, and the level service), and the test frees that memory at the first death the run
reports. The stand-in for this kill (Ray's kill of the learner actor) is in the default suite:
test_ray_driver.py `test_a_lost_learner_restarts_the_run_from_its_newest_checkpoint_by_
default`; this one repeats it with the memory monitor's own kill, so it is `slow` (about a
minute: a Ray, two starts of the run's actors).
"""

from __future__ import annotations

import io
import json
import os
import re
import subprocess
import sys

os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")

import psutil  # noqa: E402
import pytest  # noqa: E402
from test_ued_train import ued_config  # noqa: E402

from workers.ray.driver import RAY_RECORD  # noqa: E402
from workers.train import train  # noqa: E402

pytestmark = pytest.mark.slow

GIB = 2**30
# Above the machine's use when Ray starts: the run's actors, and what other processes of the
# machine may add meanwhile, fit under it.
HEADROOM = 4 * GIB
OVER = 1 * GIB  # the test's allocation crosses the threshold by this much

# Allocates what crosses the threshold (a fraction of the machine's memory), touches every page
# (so the memory is used, not only reserved), says so and holds it until it is killed (at most
# 120 s).
HOG = """
import sys, time, psutil
threshold, over = float(sys.argv[1]), int(sys.argv[2])
vm = psutil.virtual_memory()
need = max(int(threshold * vm.total) - (vm.total - vm.available) + over, over)
block = bytearray(need)
for i in range(0, need, 4096):
    block[i] = 1
print(need, flush=True)
time.sleep(120)
"""


class FreeOnDeath(io.StringIO):
    """The run's stream: frees the test's allocation at the first death it reports (Ray would
    otherwise kill every restarted actor again while the memory stays used)."""

    def __init__(self) -> None:
        super().__init__()
        self.hog: subprocess.Popen | None = None

    def write(self, text: str) -> int:
        if self.hog is not None and text.startswith("ray: ") and " died (" in text:
            self.hog.kill()
            self.hog.wait()
        return super().write(text)


@pytest.fixture
def ray_that_kills_early(monkeypatch):
    """A Ray of the test's own whose memory monitor kills at the machine's use + HEADROOM."""
    import ray

    if ray.is_initialized():
        pytest.skip("a Ray is already running in this process")
    vm = psutil.virtual_memory()
    threshold = (vm.total - vm.available + HEADROOM) / vm.total
    if threshold > 0.9:
        pytest.skip(f"the machine has too little free memory ({vm.available / GIB:.1f} GiB)")
    # Read by the raylet, which inherits this process's environment.
    monkeypatch.setenv("RAY_memory_usage_threshold", f"{threshold:.4f}")
    monkeypatch.setenv("RAY_memory_monitor_refresh_ms", "100")
    ray.init(address="local", num_cpus=2, include_dashboard=False,
             object_store_memory=128 * 2**20, logging_level="ERROR")
    yield threshold
    ray.shutdown()


def test_a_memory_monitor_kill_of_the_learner_restarts_the_run_from_its_checkpoint(
        tmp_path, ray_that_kills_early):
    threshold = ray_that_kills_early
    run_dir, out = tmp_path / "oom", FreeOnDeath()

    def allocate_after_step_3(done, train_state, values):
        if done == 3 and out.hog is None:
            out.hog = subprocess.Popen([sys.executable, "-c", HOG, f"{threshold}", f"{OVER}"],
                                       stdout=subprocess.PIPE, text=True)
            out.hog.stdout.readline()  # allocated: the next step's tasks cross the threshold

    # Robust PLR with the learner scoring too (no Explorers): the learner runs a task at
    # almost every moment of a step, so the monitor finds it running.
    config = ued_config("robust_plr", **{"ray.enabled": "true", "ray.explorers": 0,
                                         "run.checkpoint_every": 2})
    try:
        train(config, run_dir=run_dir, stream=out, max_updates=6,
              callback=allocate_after_step_3)
    finally:
        if out.hog is not None and out.hog.poll() is None:
            out.hog.kill()
            out.hog.wait()
        print(out.getvalue())  # the run's own report (pytest -s shows it)
    text = out.getvalue()
    record = json.loads((run_dir / RAY_RECORD).read_text())
    assert record["status"] == "finished" and record["steps"][1] == 6, text[-3000:]
    assert record["learner_restarts"] >= 1, text[-3000:]
    # The kill after step 3: the learner named, with the memory monitor's cause; the run
    # continues from the checkpoint of step 2 (or 4, where the kill came a step later).
    restart = next(line for line in text.splitlines() if ": restart " in line
                   and "while the run started" not in line)
    assert restart.startswith("ray: learner died ("), restart
    assert "running low on memory" in restart, restart
    assert re.search(r"the run continues from its checkpoint at step [24]; \d+ steps lost",
                     restart), restart

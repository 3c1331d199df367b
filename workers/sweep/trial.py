"""One trial of a sweep, as Ray Tune runs it: a function trainable around `workers.train.train`.

The trial trains its run folder, `SWEEP_DIR/runs/<trial>`: a new run when the folder holds none,
else a resume from its newest intact checkpoint (a finished run returns at once). It reports its
progress to Tune after logged updates (at most every `REPORT_EVERY_S` seconds) and its final
metrics at the end, and keeps its record (`workers.sweep.folder`) up to date. A trial whose config
or files are wrong (a `UserError`: a scenario or suite that does not exist, ...) ends with its error
in its record and in its last report, without an exception, so that Tune neither retries it nor
stops the others; any other exception is Tune's to retry (`FailureConfig`), from the last
checkpoint.

This module imports nothing of JAX at import time: Tune unpickles the trainable in a fresh
worker process, which sets its XLA settings (the sweep's runtime environment) before JAX starts.
"""

from __future__ import annotations

import math
import time
from pathlib import Path
from typing import Any

REPORT_EVERY_S = 2.0
LOCK_WAIT_S = 600.0  # how long a trial waits for another process to let go of its run folder


def final_eval_rates(run_dir: Path) -> dict[str, float]:
    """The last logged zero-shot mean win rate of each suite of a run: {suite: rate}."""
    from ued.plot import load_runs

    out: dict[str, float] = {}
    for seeds in load_runs([str(run_dir)]).values():
        for scalars in seeds:
            for tag, points in scalars.items():
                if tag.startswith("eval/") and tag.endswith("/mean_win_rate") and points:
                    out.setdefault(tag[len("eval/"):-len("/mean_win_rate")], points[-1][1])
    return out


def run_trial(params: dict[str, Any], *, sweep_dir: str, configs: dict[str, str]) -> None:
    """The trainable: train the trial `params["trial"]`, whose config (YAML) is
    `configs[trial]`, in its run folder under `sweep_dir`."""
    import ray
    from ray import tune

    from tabx.errors import UserError
    from ued.config import config_from_dict
    from ued.run_folder import CONFIG_FILE, lock_run_dir
    from ued.yaml_reader import read_yaml
    from workers.sweep.folder import SweepFolder

    name = params["trial"]
    folder = SweepFolder(sweep_dir)
    run_dir = folder.run_dir(name)
    run_dir.mkdir(parents=True, exist_ok=True)
    # The run folder's own lock (the one `tabx train` holds), taken before the record is
    # touched: a trial process of a killed sweep still winding down ends before this one goes
    # on, and `train` below (told so) does not lock it again.
    with lock_run_dir(run_dir, wait_s=LOCK_WAIT_S):
        record = folder.record(name)
        record.sessions += 1
        record.state, record.error = "running", ""
        node = ray.get_runtime_context().get_node_id()
        if node not in record.nodes:
            record.nodes.append(node)
        config = config_from_dict(read_yaml(configs[name].encode(), f"trial {name}"),
                                  source=f"trial {name}")
        steps_per_update = config.learner.steps_per_update
        record.total_steps = config.learner.num_updates * steps_per_update
        folder.write_record(name, record)
        prior_s, start = record.seconds, time.monotonic()
        last_report = -math.inf
        latest: dict[str, float] = {}
        since: list[float] = []  # (time, steps) of this session's first logged update

        def eta_s(now: float) -> float:
            """The remaining steps at this session's mean rate since its first logged update
            (compilation left out: it would make the first ETAs far too long)."""
            if not since or record.steps <= since[1]:
                return math.nan
            rate = (record.steps - since[1]) / max(now - since[0], 1e-9)
            return (record.total_steps - record.steps) / rate

        def progress(update: int, train_state: Any, metrics: dict[str, float]) -> None:
            nonlocal last_report
            for key in ("episode/win_rate", "time/steps_per_s"):
                if key in metrics and math.isfinite(metrics[key]):
                    latest[key] = float(metrics[key])
            record.steps = update * steps_per_update
            now = time.monotonic()
            if not since:
                since.extend((now, record.steps))
            if now - last_report < REPORT_EVERY_S and record.steps < record.total_steps:
                return
            last_report = now
            record.seconds = prior_s + (now - start)
            folder.write_record(name, record)
            tune.report({"steps": record.steps, "total_steps": record.total_steps,
                         "steps_per_s": latest.get("time/steps_per_s", math.nan),
                         "win_rate": latest.get("episode/win_rate", math.nan),
                         "eta_s": eta_s(now), "seconds": record.seconds, "failed": 0})

        resume = (run_dir / CONFIG_FILE).is_file()
        with open(folder.log_path(name), "a") as log:
            log.write(f"--- session {record.sessions}: "
                      f"{'resume' if resume else 'new run'} {run_dir}\n")
            log.flush()
            try:
                from workers.train import train

                train(config, run_dir=run_dir, resume=resume, progress=True, stream=log,
                      callback=progress, locked=True)
            except UserError as err:
                text = str(err).strip().splitlines()[0] if str(err).strip() else repr(err)
                log.write(f"error: {text}\n")
                record.state, record.error = "failed", text
                record.seconds = prior_s + (time.monotonic() - start)
                folder.write_record(name, record)
                tune.report({"steps": record.steps, "total_steps": record.total_steps,
                             "seconds": record.seconds, "failed": 1, "error": text})
                return
        record.seconds = prior_s + (time.monotonic() - start)
        record.steps, record.state = record.total_steps, "finished"
        folder.write_record(name, record)
        final = {f"eval/{suite}": rate for suite, rate in final_eval_rates(run_dir).items()}
        tune.report({"steps": record.steps, "total_steps": record.total_steps,
                     "steps_per_s": latest.get("time/steps_per_s", math.nan),
                     "win_rate": latest.get("episode/win_rate", math.nan),
                     "seconds": record.seconds, "failed": 0, **final})


__all__ = ["LOCK_WAIT_S", "REPORT_EVERY_S", "final_eval_rates", "run_trial"]

"""`tabx sweep SPEC`: the trials of a sweep file scheduled with Ray Tune, each an ordinary run.

    from workers.sweep.spec import read_sweep_spec
    from workers.sweep.tune import run_sweep
    outcome = run_sweep(read_sweep_spec("configs/sweeps/smoke_ued.yaml"))

Each trial is a function trainable (`workers.sweep.trial.run_trial`) holding the sweep file's
`resources` (a placement group: the trial's CPUs and GPU fraction, one more CPU per Explorer),
that trains its run folder under the sweep folder (`workers.sweep.folder`) with the one training
entry, `workers.train.train`. Tune runs as many at once as the resources allow (or
`max_concurrent`): on a Ray started here by default, or on the cluster at `address`.

Resuming is the sweep folder's, not Tune's experiment state: `resume=True` submits the trials
that are not finished (their record and their run folder agree), and each continues from its
run folder's newest checkpoint; finished trials are not run again. A trial that fails for a
config or a file fails alone (its record holds the error, the table shows it); an exception
of another kind (a lost node, a killed process) makes Tune retry the trial from its last
checkpoint, up to `max_failures` times.
"""

from __future__ import annotations

import contextlib
import logging
import math
import os
import sys
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TextIO

from ued.config import ConfigError
from workers.process_guard import ProcessGuard
from workers.sweep.folder import SweepFolder
from workers.sweep.spec import SweepSpec
from workers.sweep.table import SweepTable

MAX_FAILURES = 2  # Tune's retries of a trial that raised (not a failed config: that is final)


@dataclass
class SweepOutcome:
    """What a sweep session did."""

    folder: Path
    finished: list[str] = field(default_factory=list)
    failed: dict[str, str] = field(default_factory=dict)  # trial -> its error
    skipped: list[str] = field(default_factory=list)  # finished before this session
    stopped: list[str] = field(default_factory=list)  # not finished (the sweep was stopped)

    @property
    def ok(self) -> bool:
        return not self.failed and not self.stopped


def is_finished(folder: SweepFolder, trial: str) -> bool:
    """A trial whose record says finished and whose run folder has its last checkpoint."""
    if folder.record(trial).state != "finished":
        return False
    from ued.run_folder import read_run_config
    from workers.train import finished_at

    run_dir = folder.run_dir(trial)
    try:
        return finished_at(run_dir, read_run_config(run_dir)) is not None
    except Exception:  # noqa: BLE001 - a damaged or missing run folder is not finished
        return False


def worker_env(spec: SweepSpec) -> dict[str, str]:
    """The environment of the trials' processes: JAX on the CPU unless a trial holds a GPU
    (and then no preallocation, since trials may share one), and one XLA CPU device per CPU
    the trial holds (`tabx.xla_flags`: the learner splits its envs over them); the folders of
    the classes the trials' configs name by path (`ued.registry.import_env`)."""
    from ued.registry import import_env

    flags = [f for f in os.environ.get("XLA_FLAGS", "").split()
             if not f.startswith("--xla_force_host_platform_device_count")]
    cpus = int(spec.resources.cpus)
    if cpus > 1:
        flags.append(f"--xla_force_host_platform_device_count={cpus}")
    env = {"XLA_FLAGS": " ".join(flags), "TABX_KEEP_XLA_FLAGS": "1"}
    if spec.resources.gpus == 0:
        env["JAX_PLATFORMS"] = "cpu"
    else:
        env["XLA_PYTHON_CLIENT_PREALLOCATE"] = "false"
    for name in ("PYTHONPATH", "TABX_COMPILE_CACHE_DIR", "RAY_USAGE_STATS_ENABLED"):
        if os.environ.get(name):
            env[name] = os.environ[name]
    return {**env, **import_env()}


def import_tune() -> Any:
    """Ray, with Tune importable, or a ConfigError that says how to install it."""
    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
    # Tune's own console output: the sweep draws its table instead.
    os.environ.setdefault("RAY_AIR_NEW_OUTPUT", "0")
    try:
        import ray
        from ray import tune  # noqa: F401 - fail here, with the install hint, if absent
    except ImportError:
        raise ConfigError("tabx sweep needs Ray Tune: pip install -e '.[ray]'") from None
    return ray


def _bundle_text(bundle: dict[str, float]) -> str:
    return " and ".join(f"{v:g} {k}" for k, v in bundle.items() if v) or "nothing"


def check_local_fit(spec: SweepSpec, num_cpus: int | None) -> None:
    """On a Ray started here (one node, nothing joins it): refuse trials that node cannot hold,
    before the sweep folder is written (Tune would keep every trial pending for ever). The
    machine's CPUs and GPUs as `tabx train --ray` reads them (`workers.ray.start`)."""
    from workers.ray.start import local_resources

    ray = import_tune()
    if ray.is_initialized():  # a Ray this process started before (tests): what it has
        resources = ray.cluster_resources()
        have = {k: float(resources.get(k, 0.0)) for k in ("CPU", "GPU")}
    else:
        cpus, gpus = local_resources()
        have = {"CPU": float(num_cpus or cpus), "GPU": float(gpus)}
    bundles = spec.resources.bundles()
    need = {k: sum(b.get(k, 0.0) for b in bundles) for k in ("CPU", "GPU")}
    short = [k for k in need if need[k] > have[k] + 1e-9]
    if short:
        what = {"CPU": "--num-cpus, or fewer CPUs a trial (--cpus, resources.cpus"
                       + (", resources.explorers" if spec.resources.explorers else "") + ")",
                "GPU": "a smaller GPU fraction a trial (--gpus, resources.gpus), or a cluster "
                       "with GPUs (--address)"}[short[0]]
        raise ConfigError(f"resources: a trial holds {need[short[0]]:g} {short[0]}"
                          + (f" ({spec.resources.cpus:g} and one per Explorer)"
                             if short[0] == "CPU" and spec.resources.explorers else "")
                          + f", but the Ray started here has {have[short[0]]:g}: no trial could "
                          f"start; give {what}")


def warn_unfit_cluster(ray: Any, spec: SweepSpec, stream: TextIO) -> None:
    """On a cluster (nodes may join: an autoscaler): say so where no node that is up now can
    hold a trial's own bundle, or the cluster all of its bundles; its trials wait."""
    nodes = [n.get("Resources", {}) for n in ray.nodes() if n.get("Alive")]
    own, *rest = spec.resources.bundles()
    total = {k: sum(n.get(k, 0.0) for n in nodes) for k in ("CPU", "GPU")}
    need = {k: sum(b.get(k, 0.0) for b in (own, *rest)) for k in ("CPU", "GPU")}
    if not any(all(n.get(k, 0.0) + 1e-9 >= v for k, v in own.items()) for n in nodes):
        stream.write(f"sweep: warning: no node of the cluster can hold a trial "
                     f"({_bundle_text(own)} on one node); the trials wait until one joins\n")
    elif any(need[k] > total[k] + 1e-9 for k in need):
        stream.write(f"sweep: warning: a trial holds {_bundle_text(need)} but the cluster has "
                     f"{_bundle_text(total)}; the trials wait until nodes join\n")
    stream.flush()


def connect(spec: SweepSpec, address: str | None, num_cpus: int | None) -> tuple[Any, bool]:
    """Ray, connected to `address` or started here; (ray, whether this call started it)."""
    ray = import_tune()
    if ray.is_initialized():
        return ray, False
    kwargs: dict[str, Any] = {"logging_level": "ERROR", "log_to_driver": False,
                              "runtime_env": {"env_vars": worker_env(spec)}}
    if address:
        from workers.ray.start import check_reachable

        check_reachable(address, name="--address")
        kwargs["address"] = address
    else:
        kwargs.update(address="local", include_dashboard=False)
        if num_cpus:
            kwargs["num_cpus"] = num_cpus
    logging.getLogger("ray._private.authentication.authentication_token_setup").setLevel(
        logging.ERROR)
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=r"os\.fork\(\) was called",
                                category=RuntimeWarning)
        try:
            ray.init(**kwargs)
        except ConnectionError as err:
            raise ConfigError(f"--address: cannot join the cluster at {address!r} ({err}); a "
                              "cluster started with `ray start` checks a token: set "
                              "RAY_AUTH_MODE=token and give this machine its "
                              "~/.ray/auth_token") from None
    return ray, True


def _table_callback(table: SweepTable) -> Any:
    from ray.tune import Callback

    class TableCallback(Callback):
        """Tune's trial events -> the sweep's table."""

        def on_trial_start(self, iteration, trials, trial, **info):
            table.update(trial.config["trial"], state="running")

        def on_trial_result(self, iteration, trials, trial, result, **info):
            name = trial.config["trial"]
            values: dict[str, Any] = {}
            for key, attr in (("steps", "steps"), ("total_steps", "total_steps"),
                              ("steps_per_s", "steps_per_s"), ("win_rate", "win_rate"),
                              ("eta_s", "reported_eta_s")):
                value = result.get(key)
                if isinstance(value, int | float) and math.isfinite(value):
                    values[attr] = int(value) if attr.endswith("steps") else float(value)
            if result.get("failed"):
                values.update(state="failed", error=str(result.get("error", "")))
            table.update(name, **values)

        def on_trial_complete(self, iteration, trials, trial, **info):
            name = trial.config["trial"]
            if table.rows[name].state != "failed":
                row = table.rows[name]
                table.update(name, state="finished", steps=row.total_steps or row.steps)

        def on_trial_error(self, iteration, trials, trial, **info):
            table.update(trial.config["trial"], state="error",
                         error=_error_line(trial))

        def on_trial_recover(self, iteration, trials, trial, **info):
            table.update(trial.config["trial"], state="retrying", error=_error_line(trial))

        def on_step_end(self, iteration, trials, **info):
            table.draw()

    return TableCallback()


def _error_line(trial: Any) -> str:
    """The last line of a Tune trial's error (its traceback's exception)."""
    text = ""
    path = getattr(trial, "error_file", None) or ""
    try:
        text = Path(path).read_text() if path else ""
    except OSError:
        text = ""
    text = text or str(getattr(trial, "error_msg", "") or "")
    lines = [line.strip() for line in text.strip().splitlines() if line.strip()]
    return lines[-1][:300] if lines else "failed (no error text)"


def run_sweep(spec: SweepSpec, folder: str | Path | None = None, *, resume: bool = False,
              address: str | None = None, num_cpus: int | None = None,
              stream: TextIO | None = None, table_every_s: float = 30.0,
              reuse_processes: bool = False) -> SweepOutcome:
    """Run (or, with `resume`, continue) the sweep `spec` in `folder` (default: the sweep
    file's own, `SweepSpec.folder`); the table goes to `stream` (default stderr).
    `reuse_processes`: a trial process runs the next trial when its own ends (Tune's
    `reuse_actors`), which saves starting a process and importing JAX per trial: for many
    short trials (tests). Off by default: a process keeps what JAX compiled for every trial it
    ran."""
    out = sys.stderr if stream is None else stream
    sweep = SweepFolder(spec.folder() if folder is None else folder)
    if resume and not sweep.exists():
        raise ConfigError(f"{sweep.path}: no sweep to resume (no sweep.json); start it "
                          f"without --resume")
    if not address:
        check_local_fit(spec, num_cpus)
    sweep.write(spec, resume=resume)
    outcome = SweepOutcome(sweep.path)
    pending = []
    for trial in spec.trials:
        if resume and is_finished(sweep, trial.name):
            outcome.skipped.append(trial.name)
        else:
            pending.append(trial)
    table = SweepTable([t.name for t in spec.trials], stream=out, every_s=table_every_s)
    for name in outcome.skipped:
        record = sweep.record(name)
        table.rows[name].state, table.rows[name].steps = "done", record.total_steps
        table.rows[name].total_steps = record.total_steps
    if outcome.skipped:
        out.write(f"{sweep.path}: {len(outcome.skipped)} of {len(spec.trials)} trials finished "
                  f"before; {len(pending)} to run\n")
    if not pending:
        out.write(f"{sweep.path}: every trial is finished; `tabx sweep report {sweep.path}`\n")
        return outcome

    # A Ray started here ends with this process, however it ends (`workers.process_guard`).
    guard = None if address or import_tune().is_initialized() else ProcessGuard()
    try:
        with guard.marking() if guard is not None else contextlib.nullcontext():
            ray, started = connect(spec, address, num_cpus)
    except BaseException:
        if guard is not None:
            guard.close()
        raise
    if address:
        warn_unfit_cluster(ray, spec, out)
    try:
        from ray import tune

        from workers.sweep.trial import run_trial

        trainable = tune.with_parameters(
            run_trial, sweep_dir=str(sweep.path.resolve()),
            configs={t.name: t.config.to_yaml() for t in pending})
        trainable = tune.with_resources(trainable,
                                        tune.PlacementGroupFactory(spec.resources.bundles()))
        names = [t.name for t in pending]
        tuner = tune.Tuner(
            trainable,
            param_space={"trial": tune.grid_search(names)},
            tune_config=tune.TuneConfig(
                max_concurrent_trials=spec.max_concurrent or None,
                reuse_actors=reuse_processes,
                trial_name_creator=lambda t: t.config["trial"],
                trial_dirname_creator=lambda t: t.config["trial"]),
            run_config=tune.RunConfig(
                name=f"session-{time.strftime('%Y%m%d-%H%M%S')}",
                storage_path=str(sweep.tune_dir.resolve()),
                verbose=0, callbacks=[_table_callback(table)],
                failure_config=tune.FailureConfig(max_failures=MAX_FAILURES)))
        table.draw(force=True)
        results = tuner.fit()
    finally:
        if started:
            ray.shutdown()
        if guard is not None:
            guard.close()
    seen = set()
    for result in results:
        if result.config is None:  # Ctrl-C before Tune started it: no config, no record
            continue
        name = result.config["trial"]
        seen.add(name)
        record = sweep.record(name)
        if result.error is not None:
            outcome.failed[name] = record.error or _result_error(result)
        elif record.state == "failed":
            outcome.failed[name] = record.error
        elif record.state == "finished":
            outcome.finished.append(name)
        else:  # Ctrl-C: Tune ends the session with the trials where they are
            outcome.stopped.append(name)
    outcome.stopped += [t.name for t in pending if t.name not in seen]
    table.draw(force=True)
    for name, error in outcome.failed.items():
        out.write(f"trial {name} failed: {error} (log: {sweep.log_path(name)})\n")
    if outcome.stopped:
        out.write(f"{len(outcome.stopped)} trials stopped before their end; `tabx sweep SPEC "
                  f"--resume` continues them\n")
    return outcome


def _result_error(result: Any) -> str:
    lines = [line for line in str(result.error).strip().splitlines() if line.strip()]
    return lines[-1].strip()[:300] if lines else "failed"


__all__ = ["MAX_FAILURES", "SweepOutcome", "connect", "is_finished", "run_sweep", "worker_env"]

"""`tabx eval RUN_DIR --suite NAME --ray`: a zero-shot suite played on a Ray actor.

The command reads the run folder and the suite here, hands the policy's parameters (numpy) to
one `SuiteEvaluatorActor` placed by Ray (on this machine, or on a cluster with `--address`; on
a GPU where the cluster has one, as the learner of a Ray run is), and prints what comes back.
The actor builds the same Evaluator the local path builds, so with the same seed both give the
same table.
"""

from __future__ import annotations

import dataclasses
import sys
from typing import Any, TextIO

import jax

from ued.config import RaySection
from ued.run_folder import TrainedPolicy
from ued.suites import EvalSuite
from workers.ray.actors import SuiteEvaluatorActor
from workers.ray.start import actor_env, connect, learner_gpus
from workers.roles.evaluator import SuiteResult


def evaluate_on_ray(policy: TrainedPolicy, suite: EvalSuite, key: jax.Array, *,
                    episodes: int | None = None, greedy: bool = False,
                    address: str = "", stream: TextIO | None = None,
                    profile: str | None = None) -> SuiteResult:
    """`suite` played by `policy` on a Ray actor; Ray is started here unless `address` joins a
    cluster. The run's own `ray:` section gives the rest (CPUs, object store, GPUs); `profile`
    (default: the run's) the behaviour profile."""
    stream = sys.stderr if stream is None else stream
    section: RaySection = dataclasses.replace(policy.config.ray, enabled=True, address=address)
    ray, connected_here = connect(section)
    try:
        gpus = learner_gpus(ray, section)
        actor: Any = ray.remote(SuiteEvaluatorActor).options(
            num_cpus=0 if gpus else 1, num_gpus=gpus, max_restarts=0,
            runtime_env={"env_vars": actor_env(gpus > 0)},
        ).remote(policy.config, suite, episodes, greedy, profile)
        stream.write(f"ray: evaluating {suite.name} on a {'GPU' if gpus else 'CPU'} actor\n")
        stream.flush()
        try:
            params = jax.device_get(policy.params)
            return ray.get(actor.evaluate.remote(params, key))
        finally:
            ray.kill(actor)
    finally:
        if connected_here:
            ray.shutdown()


__all__ = ["evaluate_on_ray"]

"""The Ray driver: a UED run's workers as Ray actors, on this machine or a cluster.

    tabx train CONFIG --ray                  start Ray on this machine
    tabx train CONFIG --ray --address auto   join a running cluster (or HOST:PORT)

The driver process coordinates. It runs the curriculum, owns the JAX key chain and every object
ref that matters, and decides every batch: batch `s` is curriculum step `s`, played with the
key the chain gives that step, so any batch can be recomputed from the ledger. The actors wrap
the local classes (`workers.actors`):

    LevelService  one, CPU: generator, ACCEL mutator, level buffer (the buffer's only writer)
    Learner       one, on a GPU where the cluster has one (`ray.learner_gpus`): the jitted
                  rollout + PPO update on the levels it is given
    Explorer      `ray.explorers` of them, CPU: score new and mutated levels (Robust PLR,
                  ACCEL), rank SFL's random batches by learnability, with the newest policy
                  the learner published
    Evaluator     one, CPU: the zero-shot suites, on its own schedule (`ued.eval_every`)

Levels and scores cross as numpy pytrees and come back as return values (owned by the driver);
policy parameters are fetched from the learner once per version and handed to Explorers as a
ref they pull only when it is newer than the one they hold. Every score carries the policy
version that produced it and its batch id; the buffer keeps the version.

Two modes (`ray.deterministic`):

- **asynchronous** (default): batches the learner does not train on go to Explorers and run
  beside the learner, each Explorer at most `ray.max_inflight` batches ahead. A result is
  committed when it arrives; one whose policy is more than `ray.max_policy_lag` versions older
  than the learner's is re-scored with the current policy instead (counted, `ray/rescored`).
- **deterministic**: every batch in step order, each committed before the next is decided,
  exactly the local driver's schedule: parameters and buffer equal the local driver's.

`ray.schedule: continuous` replaces the asynchronous mode's steps with continuous scoring
(`workers.continuous`, handed to `RayDriver` by `workers.train.driver_for`).
"""

from __future__ import annotations

import logging
import os
import socket
import sys
import threading
import time
import uuid
import warnings
from collections import Counter, deque
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TextIO, TypeVar

import jax
import numpy as np

from tabx.files import atomic_write_json
from ued.config import ConfigError, RaySection, TrainConfig
from ued.curricula import Branch
from ued.run_folder import LEVELS_DIR
from ued.tensorboard import SummaryWriter
from workers.actor_manager import ActorDeaths, ActorManager, Call, death_cause, is_lost
from workers.actors import (
    EvaluatorActor,
    ExplorerActor,
    LearnerActor,
    LevelServiceActor,
    ParamsRef,
)
from workers.driver import Callback, Driver, RunStopped
from workers.learner_group import LearnerGroup, Restarts, start_group
from workers.ray_restarts import SERVICE, Chaos, RemoteService
from workers.training_loop import Output, Report, Runner, train_loop
from workers.ued_step import LevelRequest, UEDRun, branch_text

RAY_ENV = {"RAY_USAGE_STATS_ENABLED": "0"}
RAY_RECORD = "ray.json"  # in the run folder: where the actors run, what was committed
RAY_NAMESPACE = "tabx-ued"  # of the named actors of runs (`tabx runs buffer` finds them)

T = TypeVar("T")


def import_ray() -> Any:
    """Ray, or a ConfigError that says how to install it."""
    for name, value in RAY_ENV.items():
        os.environ.setdefault(name, value)
    try:
        import ray
    except ImportError:
        raise ConfigError("ray.enabled: Ray is not installed; pip install -e '.[ray]'") from None
    return ray


def keep_driver_off_accelerators() -> bool:
    """JAX on the CPU in the driver process, set before JAX starts its backends: the driver
    splits keys and moves small host arrays, and on a GPU head it must take none of the GPU
    memory the learner needs. False where the backends had started already (a caller that
    ran JAX first, such as a test session): then nothing changes."""
    from jax._src import xla_bridge

    if xla_bridge.backends_are_initialized():
        return False
    jax.config.update("jax_platforms", "cpu")
    return True


def join_address(section: RaySection) -> str:
    """The cluster a run joins: `ray.address`, else `RAY_ADDRESS` as Ray's own tools read it
    (a `ray job submit` entrypoint has it), else "": a Ray of the run's own on this machine."""
    return section.address or os.environ.get("RAY_ADDRESS", "")


def connect(section: RaySection, num_cpus: int | None = None) -> tuple[Any, bool]:
    """Ray, connected: to `join_address(section)` if any, else a Ray started here (with
    `num_cpus`, default `section.num_cpus`). Returns (ray, whether this call started the
    connection, so the caller shuts it down)."""
    ray = import_ray()
    if ray.is_initialized():
        return ray, False
    kwargs: dict[str, Any] = {"logging_level": "WARNING", "log_to_driver": True}
    address = join_address(section)
    if address:
        check_reachable(address)
        kwargs["address"] = address
    else:
        # "local": a new Ray, even where `ray start` left a cluster that ray.init would join.
        kwargs["address"] = "local"
        kwargs["include_dashboard"] = False
        cpus = num_cpus if num_cpus is not None else section.num_cpus
        if cpus:
            kwargs["num_cpus"] = cpus
        kwargs["object_store_memory"] = section.object_store_mb * 2**20
        # A Ray of our own keeps Ray's default token authentication; its notice about that
        # default is noise on every run.
        logging.getLogger("ray._private.authentication.authentication_token_setup").setLevel(
            logging.ERROR)
    try:
        with warnings.catch_warnings():
            # Ray starts its processes with fork + exec, which is safe beside JAX's threads.
            warnings.filterwarnings("ignore", message=r"os\.fork\(\) was called",
                                    category=RuntimeWarning)
            ray.init(**kwargs)
    except ConnectionError as err:
        hint = ("" if os.environ.get("RAY_AUTH_MODE") else
                "; a cluster started with `ray start` checks a token: set RAY_AUTH_MODE=token "
                "and give this machine its ~/.ray/auth_token")
        raise ConfigError(f"ray.address: cannot join the cluster at {address!r} "
                          f"({err}){hint}") from None
    return ray, True


# What a gRPC server (a Ray head's GCS) answers first to a client's HTTP/2 connection preface:
# a SETTINGS frame (9-byte frame header, type 0x4). A web server or anything else answers
# otherwise, or not at all; Ray itself would retry such an address for many minutes.
_HTTP2_PREFACE = b"PRI * HTTP/2.0\r\n\r\nSM\r\n\r\n" + bytes([0, 0, 0, 4, 0, 0, 0, 0, 0])
_SETTINGS_FRAME = 4


def check_reachable(address: str, timeout_s: float = 5.0) -> None:
    """Fail fast, in one line, where no Ray head answers at HOST:PORT: nothing listens, or
    something that is not a gRPC server (a Ray head's GCS speaks gRPC)."""
    if address in ("auto", "local") or "://" in address:
        return
    host, sep, port = address.rpartition(":")
    if not sep or not port.isdigit():
        raise ConfigError(f"ray.address: expected 'auto' or HOST:PORT, got {address!r}")
    try:
        with socket.create_connection((host, int(port)), timeout=timeout_s) as sock:
            sock.sendall(_HTTP2_PREFACE)
            answer = b""
            while len(answer) < 9:
                chunk = sock.recv(9 - len(answer))
                if not chunk:
                    break
                answer += chunk
    except OSError as err:
        if not isinstance(err, TimeoutError) and not isinstance(err, socket.timeout):
            raise ConfigError(f"ray.address: no Ray head answers at {address} "
                              f"({err.strerror or err}); start one there (ray start --head "
                              f"--port={port}) or give another address") from None
        answer = b""
    if len(answer) < 9 or answer[3] != _SETTINGS_FRAME:
        raise ConfigError(f"ray.address: {address} is not a Ray head (something listens there "
                          f"but does not speak Ray's gRPC); give the head's GCS address "
                          f"(ray start --head prints it)") from None


def actor_env(gpu: bool) -> dict[str, str]:
    """Environment of an actor process: JAX on CPU unless it holds a GPU; a GPU holder does not
    preallocate, so several JAX processes can share a node; the compilation cache shared."""
    env = dict(RAY_ENV)
    if gpu:
        env["XLA_PYTHON_CLIENT_PREALLOCATE"] = "false"
    else:
        env["JAX_PLATFORMS"] = "cpu"
    cache = os.environ.get("TABX_COMPILE_CACHE_DIR")
    if cache:
        env["TABX_COMPILE_CACHE_DIR"] = cache
    return env


def learner_gpus(ray: Any, section: RaySection) -> float:
    """GPUs for the learner actor: the config's, or (auto, -1) one if the cluster has any."""
    if section.learner_gpus >= 0:
        return float(section.learner_gpus)
    return 1.0 if ray.cluster_resources().get("GPU", 0) >= 1 else 0.0


MIN_EXPLORER_CPUS = 0.25  # below this share an Explorer only waits for its turn


@dataclass(frozen=True)
class LocalPlan:
    """A Ray started on this machine: its CPUs, the learner's GPUs, each Explorer's CPUs, and
    a line saying what was chosen ("" where every actor has a CPU of its own)."""

    cpus: int
    gpus: float
    explorer_cpus: float
    note: str


def local_resources() -> tuple[int, int]:
    """(CPUs, GPUs) a Ray started here would find, without starting it."""
    import_ray()
    from ray._private.accelerators import NvidiaGPUAcceleratorManager
    from ray._private.utils import get_num_cpus

    try:
        gpus = int(NvidiaGPUAcceleratorManager.get_current_node_num_accelerators())
    except Exception:  # no driver, no nvidia-smi: no GPU Ray could use
        gpus = 0
    return int(get_num_cpus()), gpus


def local_plan(section: RaySection, cpus: int, gpus_here: int) -> LocalPlan:
    """How the run's actors fit a Ray started on a machine of `cpus` CPUs and `gpus_here`
    GPUs, decided before anything starts: Explorers short of a CPU each share what the
    learner leaves (they wait on the learner's policy much of the time); a run that cannot
    fit at all is refused."""
    gpus = (float(section.learner_gpus) if section.learner_gpus >= 0
            else 1.0 if gpus_here >= 1 else 0.0)
    if gpus * section.learners > gpus_here:
        raise ConfigError(f"ray.learner_gpus: the learner asks for {gpus * section.learners:g} "
                          f"GPU but this machine has {gpus_here}; set ray.learner_gpus=-1 "
                          f"(auto) or 0, or join a cluster that has one (--address)")
    cpus = section.num_cpus or cpus
    learner = "GPU" if gpus else "CPU"
    left = cpus - (0 if gpus else section.learners)
    n = section.explorers
    if n == 0 or left >= n:
        return LocalPlan(cpus, gpus, 1.0, "")
    share = int(100 * left / n) / 100  # Ray keeps 4 decimals; 2 read better
    if share < MIN_EXPLORER_CPUS:
        raise ConfigError(f"ray.explorers: {n} Explorers and a {learner} learner do not fit a "
                          f"Ray of {cpus} CPUs (each Explorer would have {share:g} CPU, under "
                          f"{MIN_EXPLORER_CPUS:g}); lower ray.explorers or raise ray.num_cpus "
                          f"(logical CPUs may exceed the cores)")
    return LocalPlan(cpus, gpus, share,
                     f"ray: a Ray of {cpus} CPUs on this machine: {n} Explorers share {left:g} "
                     f"CPU ({share:g} each) beside the {learner} learner; "
                     f"ray.num_cpus={n + cpus - left} gives each a CPU of its own")


def requests(section: RaySection, gpus: float, explorer_cpus: float) -> dict[str, dict]:
    """Actor name -> the resources it reserves (the service and evaluator reserve none)."""
    out: dict[str, dict] = {("learner" if i == 0 else f"learner-{i}"):
                            {"GPU": gpus} if gpus else {"CPU": 1.0}
                            for i in range(section.learners)}
    for i in range(section.explorers):
        out[f"explorer-{i}"] = {"CPU": explorer_cpus}
    return out


def wait_for_resources(ray: Any, needs: dict[str, dict], timeout_s: float, stream: TextIO,
                       poll_s: float = 1.0) -> None:
    """Wait until the cluster holds, in all, what the actors reserve (an autoscaler may add
    nodes), at most `timeout_s`; then fail in one line naming the missing resource and who
    asks for it (Ray would keep the actors pending for ever)."""
    total: Counter = Counter()
    for need in needs.values():
        total.update(need)
    t0 = time.monotonic()
    said = False
    while True:
        have = ray.cluster_resources()
        missing = {k: v for k, v in total.items() if have.get(k, 0) + 1e-9 < v}
        if not missing:
            return
        waited = time.monotonic() - t0
        resource, need = next(iter(missing.items()))
        askers = ", ".join(f"{name} {n[resource]:g}" for name, n in needs.items()
                           if n.get(resource))
        if waited >= timeout_s:
            raise ConfigError(f"ray.placement_timeout_s: after {waited:.0f} s the cluster has "
                              f"{have.get(resource, 0):g} {resource} of the {need:g} the run "
                              f"reserves ({askers}); add nodes with {resource}, or ask for "
                              f"less (ray.learner_gpus, ray.explorers)")
        if not said:
            stream.write(f"ray: waiting up to {timeout_s:g} s for {need:g} {resource} "
                         f"({askers}); the cluster has {have.get(resource, 0):g}\n")
            stream.flush()
            said = True
        time.sleep(min(poll_s, max(timeout_s - waited, 0.01)))


def explorer_selector(ray: Any, gpus: float, allow_gpu_nodes: bool,
                      stream: TextIO) -> dict[str, str] | None:
    """Where a GPU learner's Explorers may go: any node but the GPU nodes (a label selector),
    while the cluster has a CPU-only node; None: anywhere (a CPU learner, asked for, or only
    GPU nodes, which is then said)."""
    if not gpus or allow_gpu_nodes:
        return None
    nodes = [n for n in ray.nodes() if n.get("Alive")]
    gpu_nodes = [n["NodeID"] for n in nodes if n["Resources"].get("GPU", 0) > 0]
    if not any(n["Resources"].get("CPU", 0) > 0 and n["NodeID"] not in gpu_nodes
               for n in nodes):
        stream.write("ray: no CPU-only node: the Explorers share the GPU node(s) with the "
                     "learner\n")
        return None
    return {"ray.io/node-id": f"!in({','.join(gpu_nodes)})"}


@dataclass
class Workers:
    """The actor handles of one run."""

    service: Any
    learner: Any
    explorers: list[Any]
    evaluator: Any | None
    gpus: float

    def all(self) -> list[Any]:
        return [self.service, self.learner, *self.explorers,
                *([self.evaluator] if self.evaluator is not None else [])]

    def names(self) -> list[str]:
        return ["service", "learner", *(f"explorer-{i}" for i in range(len(self.explorers))),
                *(["evaluator"] if self.evaluator is not None else [])]

    def placement(self, ray: Any) -> dict[str, str]:
        """Actor name -> id of the node it runs on."""
        nodes = ray.get([a.node.remote() for a in self.all()])
        return dict(zip(self.names(), nodes, strict=True))

    def scorers(self) -> list[Any]:
        """Who scores new levels: the Explorers, or the learner when there are none."""
        return self.explorers or [self.learner]

    def scorer_names(self) -> list[str]:
        return [f"explorer-{i}" for i in range(len(self.explorers))] or ["learner"]

    def register(self, actors: ActorManager) -> None:
        """Add the learner, Explorers and Evaluator to `actors` (the service adds itself,
        `RemoteService`): Ray restarts the Explorers and the Evaluator, not the learner."""
        actors.add("learner", self.learner, restarts=False)
        for i, explorer in enumerate(self.explorers):
            actors.add(f"explorer-{i}", explorer, restarts=True)
        if self.evaluator is not None:
            actors.add("evaluator", self.evaluator, restarts=True)


def start_workers(ray: Any, config: TrainConfig, stream: TextIO,
                  run_name: str | None = None, levels_dir: Path | None = None,
                  explorer_cpus: float | None = None) -> Workers:
    """The run's actors, constructed (their constructors build each one's part of the run).
    With `run_name` they are named actors, `RUN_NAME/ROLE` in `RAY_NAMESPACE`, so that another
    process (`tabx runs buffer`) can reach them. With `levels_dir` the service logs its
    commits there (and may restart: it replays them). `explorer_cpus`: each Explorer's CPUs
    as `local_plan` chose them for a Ray started here (None: one, checked here)."""
    section = config.ray
    gpus = learner_gpus(ray, section)
    if explorer_cpus is None and not join_address(section):
        check_resources(ray, config, gpus)
    explorer_cpus = 1.0 if explorer_cpus is None else explorer_cpus
    wait_for_resources(ray, requests(section, gpus, explorer_cpus),
                       section.placement_timeout_s, stream)
    selector = explorer_selector(ray, gpus, section.explorers_on_gpu_nodes, stream)

    def spawn(cls: type, name: str, *args: Any, num_gpus: float = 0.0, restarts: int = 0,
              **options: Any) -> Any:
        # Calls are never retried by Ray (max_task_retries=0): a retry would reuse the
        # original arguments, stale parameters included; the driver re-issues instead.
        remote = ray.remote(cls)
        if run_name is not None:
            options.update(name=f"{run_name}/{name}", namespace=RAY_NAMESPACE)
        return remote.options(num_cpus=options.pop("num_cpus", 1),
                              num_gpus=num_gpus, max_restarts=restarts, max_task_retries=0,
                              runtime_env={"env_vars": actor_env(num_gpus > 0)},
                              **options).remote(*args)

    # Explorers and the evaluator hold nothing that a restart loses (their parameters come
    # with each call); the service restores its state from its snapshot and commit log; the
    # learner is not restarted: its death stops the run (resume from the last checkpoint).
    restarts = section.actor_restarts
    # The service sits on the driver's node, which calls it every step and whose loss ends
    # the run anyway (it reserves no CPU, so it always fits there; a soft affinity was not
    # honoured for actors with a runtime_env in Ray 2.60). A CPU learner prefers that node
    # too (the launcher files make the head the learner's node); a GPU one goes to a GPU.
    from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy

    driver_node = ray.get_runtime_context().get_node_id()
    # The service and evaluator are light: they share CPUs with the others.
    service = spawn(LevelServiceActor, "service", config,
                    None if levels_dir is None else str(levels_dir), run_name or "",
                    num_cpus=0, restarts=restarts if levels_dir is not None else 0,
                    scheduling_strategy=NodeAffinitySchedulingStrategy(driver_node, soft=False))
    if section.learners > 1:  # a learner group, placed by its own placement group
        learner = start_group(ray, section.learners, gpus, lambda i, group, strategy: spawn(
            LearnerActor, "learner" if i == 0 else f"learner-{i}", config, group,
            num_gpus=gpus, num_cpus=1 if not gpus else 0, scheduling_strategy=strategy))
    else:
        learner = spawn(LearnerActor, "learner", config, num_gpus=gpus,
                        num_cpus=1 if not gpus else 0,
                        **({} if gpus else {"scheduling_strategy": NodeAffinitySchedulingStrategy(
                            driver_node, soft=True)}))
    # Off a GPU learner's nodes unless asked (`explorer_selector`).
    placement: dict[str, Any] = ({"label_selector": selector} if selector else {})
    explorers = [spawn(ExplorerActor, f"explorer-{i}", config, num_cpus=explorer_cpus,
                       scheduling_strategy="SPREAD", restarts=restarts, **placement)
                 for i in range(section.explorers)]
    evaluator = (spawn(EvaluatorActor, "evaluator", config, num_cpus=0, restarts=restarts)
                 if config.ued.eval_suites else None)
    workers = Workers(service, learner, explorers, evaluator, gpus)
    wait_until_ready(ray, workers, stream)
    return workers


def cpus_needed(config: TrainConfig, gpus: float) -> int:
    """CPUs the run's actors reserve: one per Explorer, one per CPU learner."""
    return config.ray.explorers + (0 if gpus else config.ray.learners)


def check_resources(ray: Any, config: TrainConfig, gpus: float) -> None:
    """On a Ray started here nothing will join: refuse a run whose actors cannot all be placed
    (Ray would keep them pending for ever)."""
    have = ray.cluster_resources().get("CPU", 0)
    need = cpus_needed(config, gpus)
    if need > have:
        raise ConfigError(f"ray.explorers: {config.ray.explorers} Explorers and a "
                          f"{'GPU' if gpus else 'CPU'} learner reserve {need} CPUs, but this "
                          f"Ray has {have:g}; lower ray.explorers or raise ray.num_cpus "
                          f"(logical CPUs may exceed the cores)")


def wait_until_ready(ray: Any, workers: Workers, stream: TextIO,
                     report_every_s: float = 30.0) -> None:
    """Wait for every actor's constructor (errors raise here). On a cluster that is short of
    resources actors stay pending (an autoscaler may yet add nodes): say which, periodically."""
    pending = {a.ready.remote(): name for a, name in zip(workers.all(), workers.names(),
                                                          strict=True)}
    t0 = time.perf_counter()
    while pending:
        ready, _ = ray.wait(list(pending), num_returns=len(pending), timeout=report_every_s)
        for ref in ready:
            ray.get(ref)
            pending.pop(ref)
        if pending:
            resources = ray.available_resources()
            stream.write(f"ray: waited {time.perf_counter() - t0:.0f} s for "
                         f"{', '.join(sorted(pending.values()))} to start (cluster has "
                         f"{resources.get('CPU', 0):g} CPUs and {resources.get('GPU', 0):g} "
                         f"GPUs free)\n")
            stream.flush()


# --- the deterministic mode: the local step logic over blocking calls -------------------------


class RemoteLearner:
    """The learner actor behind `workers.learner.LearnerWorker`'s interface, with the policy version
    counted here and the parameters fetched once per version (a ref owned by the driver)."""

    def __init__(self, ray: Any, actor: Any, version: int = 0,
                 actors: ActorManager | None = None):
        self._actors = ActorManager(ray) if actors is None else actors
        self._actors.add("learner", actor, restarts=False)
        self._actor = actor
        self.version = int(version)
        self._params: ParamsRef | None = None

    def train(self, levels: Any, key: jax.Array) -> tuple[dict[str, Any], None]:
        metrics = self._actors.call("learner", "train", levels, key)
        self.version += 1
        return metrics, None

    def train_scored(self, levels: Any, key: jax.Array, score: str,
                     max_returns: Any = None) -> tuple[dict[str, Any], np.ndarray, np.ndarray]:
        out = self._actors.call("learner", "train_scored", levels, key, score, max_returns)
        self.version += 1
        return out

    @property
    def params(self) -> ParamsRef:
        if self._params is None or self._params.version != self.version:
            self._params = ParamsRef(self.version, [self._actor.params.remote()])
        return self._params

    @property
    def train_state(self) -> Any:
        return self._actors.call("learner", "train_state")


class ExplorerPool:
    """Explorer actors behind `workers.explorer.Explorer`'s interface: calls go round-robin and
    wait (the deterministic mode). A call whose Explorer dies runs again on its restart with
    the same arguments: in this mode they are what the schedule asks for. `actors`: the run's
    ActorManager (where the Explorers restart); without one, a death raises."""

    def __init__(self, ray: Any, actors: list[Any], names: list[str] | None = None,
                 manager: ActorManager | None = None):
        self._manager = ActorManager(ray) if manager is None else manager
        self._names = names or [f"scorer-{i}" for i in range(len(actors))]
        for name, actor in zip(self._names, actors, strict=True):
            self._manager.add(name, actor, restarts=False)
        self._next = 0

    def _send(self, method: str, *args: Any, then: str) -> Call:
        name = self._names[self._next % len(self._names)]
        self._next += 1
        return self._manager.send(Call.of(name, method, *args, then=then))

    def _call(self, method: str, *args: Any) -> Any:
        return self._manager.get(self._send(method, *args,
                                            then=f"{method} runs again on its restart"))

    def score_levels(self, params: ParamsRef, levels: Any, key: jax.Array, score: str,
                     max_returns: Any = None, num_steps: int | None = None) -> Any:
        return self._call("score_levels", params, levels, key, score, max_returns, num_steps)

    def learnability(self, params: ParamsRef, levels: Any, key: jax.Array,
                     num_steps: int | None = None) -> np.ndarray:
        return self._call("learnability", params, levels, key, num_steps)

    def learnability_batches(self, params: ParamsRef, batches: list[tuple[Any, jax.Array]],
                             num_steps: int | None = None) -> list[np.ndarray]:
        """SFL's batches spread over the Explorers at once, results in batch order (so the
        same as one after another); a batch whose Explorer died runs again on its restart."""
        then = "its learnability batches run again on its restart"
        calls = [self._send("learnability", params, levels, key, num_steps, then=then)
                 for levels, key in batches]
        return [self._manager.get(call) for call in calls]


class RemoteEvaluator:
    """The evaluator actor behind `workers.evaluator.Evaluator`'s interface (one per suite).
    An evaluation whose actor dies runs again on its restart (same parameters and key)."""

    def __init__(self, ray: Any, actor: Any, index: int, suite_name: str,
                 actors: ActorManager | None = None):
        self._actors = ActorManager(ray) if actors is None else actors
        self._actors.add("evaluator", actor, restarts=False)
        self.index = index
        self.suite = _SuiteName(suite_name)

    def evaluate(self, params: ParamsRef, key: jax.Array) -> Any:
        return self._actors.call("evaluator", "evaluate", self.index, params, key,
                                 then="evaluate runs again on its restart")

    def log(self, writer: SummaryWriter, step: int, result: Any) -> None:
        from workers.evaluator import log

        log(writer, step, result)


@dataclass(frozen=True)
class _SuiteName:
    name: str


# --- the asynchronous mode ------------------------------------------------------------------


@dataclass
class Batch:
    """One curriculum step handed to an Explorer: what is needed to commit or re-issue it."""

    step: int
    request: LevelRequest  # the service call that made the levels, how they are filed
    key: jax.Array
    version: int  # of the policy it was (last) sent with
    explorer: int
    levels: Call  # to the service: its ref is the numpy levels
    score: Call | None = None  # to the Explorer (its arguments: the current policy)
    issued_s: float = field(default_factory=time.perf_counter)
    rescored: int = 0


@dataclass
class Evaluation:
    """One suite's evaluation at one step, on the Evaluator (its call runs it again)."""

    step: int
    suite: str
    call: Call


RATE_WINDOW_S = 60.0  # rates in ray.json, `tabx runs status` and ray/*_per_s: over this window


class RateWindow:
    """Rates of running counts averaged over the last `window_s` seconds (the whole session
    while it is younger): the rate a run holds, not one step's burst."""

    def __init__(self, window_s: float = RATE_WINDOW_S,
                 clock: Callable[[], float] = time.perf_counter, start: tuple = ()):
        self.window_s, self.clock = window_s, clock
        self.samples: deque[tuple[float, tuple[float, ...]]] = deque()
        if start:
            self.samples.append((clock(), tuple(start)))

    def add(self, *counts: float) -> tuple[float, ...]:
        """Record `counts` now; their rates per second over the window (0 until there are two
        readings)."""
        now = self.clock()
        self.samples.append((now, counts))
        while len(self.samples) > 2 and self.samples[1][0] <= now - self.window_s:
            self.samples.popleft()
        t0, base = self.samples[0]
        span = now - t0
        return tuple((c - b) / span if span > 0 else 0.0 for c, b in zip(counts, base,
                                                                         strict=True))

    @property
    def span_s(self) -> float:
        """Seconds the last rates were averaged over."""
        return self.samples[-1][0] - self.samples[0][0] if self.samples else 0.0


def live_actors(ray: Any, actors: ActorManager, names: list[str]) -> int:
    """Of `names`, the actors answering: not given up by the ActorManager and alive in Ray's
    actor table (one dead or restarting is not)."""
    from ray._private import state

    live = 0
    for name in names:
        if not actors.available(name):
            continue
        actor_id = actors.members[name].actor_id()
        try:
            info = state.actors(actor_id=actor_id) if actor_id else {}
        except Exception:  # the table unreadable: count on the manager's word
            info = {"State": "ALIVE"}
        live += info.get("State") == "ALIVE"
    return live


@dataclass
class RayStats:
    """What the progress line and `ray/*` scalars report."""

    trained_steps: int = 0
    explored_steps: int = 0
    committed: int = 0
    rescored: int = 0
    reissued: int = 0  # batches submitted again after their Explorer died
    evaluations_rerun: int = 0  # evaluations run again after their Evaluator died
    evaluations_lost: int = 0  # evaluations given up
    staleness: Counter = field(default_factory=Counter)  # version lag at commit -> batches
    learner_busy_s: float = 0.0
    wait_for_levels_s: float = 0.0
    t0: float = field(default_factory=time.perf_counter)
    window: RateWindow = field(default_factory=lambda: RateWindow(start=(0, 0)))
    rates: tuple[float, ...] = (0.0, 0.0)  # trained, explored env steps/s over the window

    def scalars(self, live_explorers: int, inflight: int) -> dict[str, float]:
        """The `ray/*` scalars of a logged step (reads the rates: once per logged step)."""
        elapsed = max(time.perf_counter() - self.t0, 1e-9)
        self.rates = self.window.add(self.trained_steps, self.explored_steps)
        lags = list(self.staleness.elements())
        out = {"ray/trained_steps_per_s": self.rates[0],
               "ray/explored_steps_per_s": self.rates[1],
               "ray/rate_window_s": self.window.span_s,
               "ray/live_explorers": float(live_explorers),
               "ray/inflight_batches": float(inflight),
               "ray/committed_batches": float(self.committed),
               "ray/rescored": float(self.rescored),
               "ray/reissued": float(self.reissued),
               "ray/learner_busy_fraction": self.learner_busy_s / elapsed,
               "ray/wait_for_levels_s": self.wait_for_levels_s}
        if lags:
            out["ray/staleness_mean"] = float(np.mean(lags))
            out["ray/staleness_max"] = float(max(lags))
        return out

    def text(self, live_explorers: int, buffer_size: int | None) -> str:
        """The progress line's part (after `scalars`: its rates)."""
        lags = list(self.staleness.elements())
        parts = [f"trained {self.rates[0]:,.0f}/s",
                 f"explored {self.rates[1]:,.0f}/s over {self.window.span_s:.0f} s",
                 f"explorers {live_explorers} live"]
        if buffer_size is not None:
            parts.append(f"buffer {buffer_size}")
        if lags:
            parts.append(f"lag {np.mean(lags):.1f}")
        return ", ".join(parts)


class AsyncRun:
    """The asynchronous schedule over the actors of one run (see the module doc). Its calls go
    through the run's ActorManager (`service.actors`): a batch or an evaluation lost with its
    actor is sent again on the restart. `start`: the session's first step (a schedule of its
    own key chain uses it; this one takes its keys from the steps)."""

    def __init__(self, ray: Any, config: TrainConfig, run: UEDRun, learner: RemoteLearner,
                 workers: Workers, service: RemoteService, start: int = 0):
        self.ray, self.config, self.run, self.learner, self.workers = (ray, config, run,
                                                                       learner, workers)
        self.scorers = workers.scorers()
        self.names = workers.scorer_names()
        # The run's service too: one numbering of the state-changing calls per actor.
        self.service = service
        self.actors = service.actors
        workers.register(self.actors)
        self.service.on_restart.append(self.ask_again_for_lost_levels)
        self.pending: dict[Any, Batch] = {}
        self.inflight = [0] * len(self.scorers)
        self.stats = RayStats()
        self.ledger: dict[int, str] = {}  # step -> "issued" | "committed"
        self.recent_lags: deque[int] = deque(maxlen=1000)
        self.evaluations: list[Evaluation] = []  # running

    # Evaluation runs beside training: submitted at its steps, logged when it is done -------

    def submit_evaluation(self, done: int) -> None:
        if self.workers.evaluator is None or not self.actors.available("evaluator"):
            return
        key = jax.random.fold_in(jax.random.key(self.config.seed ^ 0x5EED), done)
        params = self.learner.params
        for i, name in enumerate(self.config.ued.eval_suites):
            # The same parameters and key on a re-run; given up rather than stopping the run.
            call = Call.of("evaluator", "evaluate", i, params, jax.random.fold_in(key, i),
                           then=f"its evaluation of {name} after step {done} runs again on "
                                f"its restart")
            call.optional = True
            self.evaluations.append(Evaluation(done, name, self.actors.send(call)))

    def log_evaluations(self, writer: SummaryWriter, stream: TextIO | None,
                        block: bool = False) -> None:
        """Log the evaluations that are done. One whose Evaluator died runs again, with the
        same parameters and key, once the Evaluator is back; one the ActorManager gives up
        is counted (`evaluations_lost`) and training goes on."""
        from workers.evaluator import log

        waiting, self.evaluations = self.evaluations, []
        for evaluation in waiting:
            ready, _ = self.ray.wait([evaluation.call.ref], timeout=None if block else 0)
            if not ready:
                self.evaluations.append(evaluation)
                continue
            try:
                result = self.ray.get(evaluation.call.ref)
            except Exception as err:
                if self.actors.recover(evaluation.call, err):
                    self.stats.evaluations_rerun += 1
                    self.actors.send(evaluation.call)
                    self.evaluations.append(evaluation)
                else:
                    self.stats.evaluations_lost += 1
                continue
            log(writer, evaluation.step * self.config.learner.steps_per_update, result)
            if stream is not None:
                stream.write(f"  eval {evaluation.suite} after step {evaluation.step}: mean "
                             f"win rate {result.mean_win_rate:.2f}\n")
                stream.flush()
        if block and self.evaluations:  # re-run ones: wait for them too
            self.log_evaluations(writer, stream, block=True)

    def record(self) -> dict[str, Any]:
        """What `ray.json` keeps of the schedule: batches, re-scores, the staleness histogram."""
        states = Counter(self.ledger.values())
        return {"committed_batches": self.stats.committed, "rescored": self.stats.rescored,
                "staleness": {str(k): v for k, v in sorted(self.stats.staleness.items())},
                "ledger": dict(states), "trained_steps": self.stats.trained_steps,
                "reissued": self.stats.reissued,
                "evaluations_rerun": self.stats.evaluations_rerun,
                "evaluations_lost": self.stats.evaluations_lost,
                "explored_steps": self.stats.explored_steps,
                "learner_busy_s": self.stats.learner_busy_s,
                "wait_for_levels_s": self.stats.wait_for_levels_s}

    # Explorer work ------------------------------------------------------------------------

    def _free_explorer(self) -> int:
        """An explorer with room, waiting for results (and committing them) until one has."""
        limit = self.config.ray.max_inflight
        while True:
            free = [i for i, n in enumerate(self.inflight) if n < limit]
            if free:
                return min(free, key=lambda i: self.inflight[i])
            self.collect(block=True)

    def _submit(self, batch: Batch) -> None:
        """Send (again) `batch`'s scoring to its Explorer, with the current policy."""
        batch.version = self.learner.version
        ref = self.actors.send(batch.score).ref
        self.pending[ref] = batch
        self.inflight[batch.explorer] += 1

    def explore(self, learner: RemoteLearner, step: int, request: LevelRequest,
                key: jax.Array) -> tuple[None, None]:
        """Issue step `step` (the schedule's `explore`): the service makes its levels
        (`request`), an Explorer scores them; the driver holds only the refs. Committed when
        the result arrives (`collect`)."""
        i = self._free_explorer()
        levels = self.actors.send(Call.of(SERVICE, request.method, *request.args))
        batch = Batch(step, request, key, learner.version, i, levels)
        score = self.config.ued.score
        # Rebuilt at every sending: the current policy, the levels as asked for last (the
        # closure holds the levels' call, not the batch: no cycle keeps refs alive).
        batch.score = Call(self.names[i], "score_levels",
                           lambda: (self.learner.params, levels.ref, key, score, None, None),
                           then="its batches are re-issued with the current policy on its "
                                "restart", after=(levels,))
        self.ledger[step] = "issued"
        self._submit(batch)
        return None, None

    def learn(self, step: int, train: Callable[[], T]) -> T:
        """Step `step`'s learner part (the schedule's `learn`): now, committed when done."""
        t0 = time.perf_counter()
        out = train()
        self.stats.learner_busy_s += time.perf_counter() - t0
        self.stats.trained_steps += self.config.learner.steps_per_update
        self.ledger[step] = "committed"
        return out

    def ask_again_for_lost_levels(self) -> None:
        """After a restart of the service: ask again, in step order and before anything else,
        for the levels of every batch that died with it. Same calls, same keys: the restored
        service makes the same levels (an ACCEL parent is still in the buffer, since the
        inserts after it run after it, as before)."""
        for batch in sorted(self.pending.values(), key=lambda b: b.step):
            if self.actors.lost_with_restart(batch.levels):
                self.actors.send(batch.levels)

    def collect(self, block: bool) -> None:
        """Commit the explorer results that are ready (wait for one if `block`)."""
        if not self.pending:
            return
        t0 = time.perf_counter()
        ready, _ = self.ray.wait(list(self.pending), num_returns=1,
                                 timeout=None if block else 0)
        if block:
            self.stats.wait_for_levels_s += time.perf_counter() - t0
        for ref in ready:
            accepted = self.accept(ref)
            if accepted is not None:
                self.commit(*accepted)

    def accept(self, ref: Any, result: Any = None) -> tuple[Batch, Any, Any, int] | None:
        """Take the finished Explorer call `ref` (its `result` when already fetched) off the
        pending ones: (batch, scores, best, policy lag) to commit, or None when the call
        failed (re-issued) or its policy is too old (scored again)."""
        batch = self.pending.pop(ref)
        self.inflight[batch.explorer] -= 1
        try:
            _, scores, best = self.ray.get(ref) if result is None else result
        except Exception as err:
            self.reissue(batch, err)
            return None
        batch.score.failures = 0
        lag = self.learner.version - batch.version
        if lag > self.config.ray.max_policy_lag:
            # Too old to trust: score the same levels again with the current policy.
            self.stats.rescored += 1
            batch.rescored += 1
            self._submit(batch)
            return None
        return batch, scores, best, lag

    def reissue(self, batch: Batch, err: Exception) -> None:
        """`batch` was lost (its Explorer died, or the service before it made the levels): once
        the ActorManager has the actor back, submit it again with the current parameters (Ray's
        own retry would reuse the old ones); levels lost with the service are asked for
        again first (`ActorManager.send`)."""
        t0 = time.perf_counter()
        self.actors.recover(batch.score, err)  # raises where the run stops
        self.stats.wait_for_levels_s += time.perf_counter() - t0
        self.stats.reissued += 1
        self._submit(batch)

    def commit(self, batch: Batch, scores: np.ndarray, best: np.ndarray, lag: int) -> None:
        self.run.commit(batch.request, batch.levels.ref, scores, best, batch.version)
        self.ledger[batch.step] = "committed"
        self.stats.committed += 1
        self.stats.staleness[lag] += 1
        self.recent_lags.append(lag)
        self.stats.explored_steps += self.config.learner.steps_per_update

    def drain(self) -> None:
        while self.pending:
            self.collect(block=True)

    # One step -----------------------------------------------------------------------------

    def step(self, step: int, key: jax.Array) -> tuple[Branch, dict[str, Any] | None, Any]:
        """Decide and issue curriculum step `step` (`UEDRun.step` on this schedule): Explorer
        batches return at once (metrics and levels None); learner batches wait for the
        update. Results that arrived meanwhile are committed first."""
        self.collect(block=False)
        return self.run.step(self.learner, step, key, schedule=self)


def driver_refs(ray: Any) -> int:
    """Object refs this process holds (`ray/driver_refs`): flat over a healthy run, whatever
    its length; a count that grows with the steps is a leak (objects pinned in the store)."""
    return len(ray._private.worker.global_worker.core_worker.get_all_reference_counts())


def stop_reason(ray: Any, err: BaseException) -> str | None:
    """Why the run stops where `err` means it cannot go on but can be resumed: a RunStopped
    (a learner lost, a call's failure budget spent, an actor not back) or a loss the
    ActorManager did not see (an actor or node lost at start-up, the driver's own raylet);
    None for any other error."""
    if isinstance(err, RunStopped):
        return str(err)
    if is_lost(ray, err) or isinstance(err, ray.exceptions.LocalRayletDiedError):
        return f"an actor of the run died ({death_cause(err)})"
    return None


def need_ued(config: TrainConfig) -> None:
    if not config.ued.enabled:
        raise ConfigError("ray.enabled: the Ray driver runs UED runs (ued.method); a plain "
                          "MARL run trains in one process: drop ray.enabled")


class RunRecord:
    """`RUN_DIR/ray.json`: written when the actors are up (`status: running`, the cluster's
    address and the actors' names, so that `tabx runs status` and `tabx runs buffer` can find
    the run), refreshed at every logged step, and final when the run ends or stops. A logged
    step's refresh (`background=True`) is written by a thread, off the step path; every other
    update waits until the file holds it."""

    def __init__(self, path: Path):
        self.path = path
        self.data: dict[str, Any] = {}
        self._lock = threading.Lock()
        self._writer: threading.Thread | None = None

    def update(self, background: bool = False, **fields: Any) -> None:
        self.data.update(fields, updated=time.strftime("%Y-%m-%dT%H:%M:%S%z"))
        snapshot = dict(self.data)  # the values are replaced, never changed in place
        if self._writer is not None and self._writer.is_alive():
            if background:
                return  # the next refresh writes it; a logged step never waits for a write
            self._writer.join()
        if background:
            self._writer = threading.Thread(target=self._write, args=(snapshot,), daemon=True)
            self._writer.start()
        else:
            self._write(snapshot)

    def _write(self, snapshot: dict[str, Any]) -> None:
        with self._lock:
            atomic_write_json(self.path, snapshot)


class RayDriver(Driver):
    """Runs a UED run's workers as Ray actors (see the module doc). `schedules`: the
    asynchronous schedules other than the sequential `AsyncRun`, by `ray.schedule` name
    (`workers.train.driver_for` adds `workers.continuous`'s)."""

    name = "ray"

    def __init__(self, schedules: dict[str, type[AsyncRun]] | None = None):
        self.schedules = dict(schedules or {})

    def check(self, config: TrainConfig) -> None:
        """Every refusal that needs no Ray: made before the run folder exists."""
        keep_driver_off_accelerators()
        need_ued(config)
        ray = import_ray()
        address = join_address(config.ray)
        if address:
            check_reachable(address)
        elif not ray.is_initialized():
            local_plan(config.ray, *local_resources())

    def run(self, config: TrainConfig, run_dir: Path, *, resume: bool = False,
            max_updates: int | None = None, progress: bool = True,
            stream: TextIO | None = None, callback: Callback | None = None) -> Path:
        """The run, continued from its last checkpoint after each stop for a lost actor (a
        learner above all: Ray restarts the others in place) up to `ray.learner_restarts`
        times (`workers.learner_group.Restarts`)."""
        need_ued(config)
        keep_driver_off_accelerators()
        stream = sys.stderr if stream is None else stream
        restarts = Restarts(config.ray.learner_restarts)
        while True:
            self.runner: RayRunner | None = None
            try:
                return self.session(config, run_dir, resume=resume, max_updates=max_updates,
                                    progress=progress, stream=stream, callback=callback,
                                    restarts=restarts)
            except RunStopped as stopped:
                runner = self.runner
                if runner is None or not restarts.left():
                    raise
                max_updates = restarts.restart(run_dir, runner.start, runner.reached,
                                               max_updates, stopped, stream)
                resume = True

    def session(self, config: TrainConfig, run_dir: Path, *, resume: bool,
                max_updates: int | None, progress: bool, stream: TextIO,
                callback: Callback | None, restarts: Restarts) -> Path:
        """One start of the run's actors and `train_loop` over them."""
        ray = import_ray()
        plan = (None if join_address(config.ray) or ray.is_initialized()
                else local_plan(config.ray, *local_resources()))
        if plan is not None and plan.note:
            stream.write(plan.note + "\n")
            stream.flush()
        ray, started = connect(config.ray, None if plan is None else plan.cpus)
        workers = None
        record = RunRecord(run_dir / RAY_RECORD)
        run_name = f"{run_dir.name}-{uuid.uuid4().hex[:8]}"
        try:
            workers = start_workers(ray, config, stream, run_name, run_dir / LEVELS_DIR,
                                    None if plan is None else plan.explorer_cpus)
            record.update(status="running", driver_pid=os.getpid(),
                          address=ray.get_runtime_context().gcs_address,
                          namespace=RAY_NAMESPACE,
                          actors={name: f"{run_name}/{name}" for name in workers.names()},
                          **restarts.fields())
            self.runner = RayRunner(ray, workers, config, record, stream, self.schedules)
            run_dir = train_loop(self.runner, run_dir, resume=resume, max_updates=max_updates,
                                 progress=progress, stream=stream, callback=callback)
            record.update(status="finished")
            return run_dir
        except BaseException as err:
            reason = stop_reason(ray, err)
            if reason is None:  # an error or Ctrl-C: the record says the run is over
                if record.data:
                    record.update(status="stopped", error=f"{type(err).__name__}: {err}")
                raise
            stream.write(f"ray: the run stops: {reason}\n")
            stream.flush()
            record.update(status="stopped", error=reason)
            raise RunStopped(f"{run_dir}: {reason}; continue from the last checkpoint with: "
                             f"tabx train --resume {run_dir}") from err
        finally:
            if workers is not None:
                for actor in workers.all():
                    actor.kill(ray) if isinstance(actor, LearnerGroup) else ray.kill(actor)
            if started:
                ray.shutdown()


class RayRunner(Runner):
    """A UED run over the actors of `workers`, in `train_loop`: the deterministic mode plays
    each step as the local driver does (`UEDRun.step` over blocking calls), the asynchronous
    one on `AsyncRun`'s schedule."""

    snapshots = True
    explores = True

    def __init__(self, ray: Any, workers: Workers, config: TrainConfig, record: RunRecord,
                 stream: TextIO, schedules: dict[str, type[AsyncRun]] | None = None):
        super().__init__(config)
        self.schedules = {"sequential": AsyncRun, **(schedules or {})}
        self.ray, self.workers, self.record, self.stream = ray, workers, record, stream
        self.deaths = ActorDeaths(stream)  # logged even when quiet: a death is news
        # Every call to the run's actors goes through one manager (restarts, re-issue).
        self.actors = ActorManager(ray, self.deaths)
        workers.register(self.actors)
        self.service = RemoteService(ray, workers.service, self.actors)
        evaluators = [RemoteEvaluator(ray, workers.evaluator, i, name, self.actors)
                      for i, name in enumerate(config.ued.eval_suites)]
        pool = ExplorerPool(ray, workers.scorers(), workers.scorer_names(), self.actors)
        self.run = UEDRun(config, self.service, pool, evaluators)
        self.deterministic = config.ray.deterministic
        self.version, self.start = 0, 0
        self.counts = {b: 0 for b in Branch}  # this session's steps per branch
        self.metrics: dict[str, Any] = {}  # of the newest step that trained
        self.levels: Any = None  # played by the newest step, None if it went to an Explorer
        self.learner: RemoteLearner | None = None
        self.asynchronous: AsyncRun | None = None
        self.chaos: Chaos | None = None
        self._asked: tuple[Call, Call] | None = None  # the service's statistics, asked for
        self.reached = 0  # steps done (a restart after a loss counts those since the checkpoint)
        self.rate = RateWindow()  # env steps/s in ray.json, over RATE_WINDOW_S
        self.learner_first_s: float | None = None  # the learner's first update, compile included
        self.first_said = False

    @property
    def eval_every(self) -> int:
        return self.config.ued.eval_every if self.run.evaluators else 0

    def needs_buffer(self) -> bool:
        return self.service.buffer_size() is not None

    def init(self, key: jax.Array) -> None:
        self.actors.call("learner", "init", key)

    def template(self) -> Any:
        return self.actors.call("learner", "train_state")

    def restore(self, run_dir: Path, train_state: Any, start: int) -> None:
        self.version = self.run.resume(run_dir, start)
        self.actors.call("learner", "set_train_state", train_state, self.version)

    def begin(self, start: int) -> None:
        ray, workers, config = self.ray, self.workers, self.config
        self.start = self.reached = start
        self.rate = RateWindow(start=(start * config.learner.steps_per_update,))
        self.learner = RemoteLearner(ray, workers.learner, self.version, self.actors)
        placement = workers.placement(ray)
        group = workers.learner if isinstance(workers.learner, LearnerGroup) else None
        self.record.update(mode=self.mode, learner_gpus=workers.gpus,
                           learners=config.ray.learners, placement=placement, steps=[start, start],
                           **({"learner_nodes": group.nodes(ray)} if group else {}),
                           total_steps=config.learner.num_updates)
        if self.deterministic:
            self.asynchronous = None
        else:
            schedule = self.schedules.get(config.ray.schedule)
            if schedule is None:
                raise ConfigError(f"ray.schedule: {config.ray.schedule!r} is not among this "
                                  f"driver's schedules ({', '.join(self.schedules)})")
            self.asynchronous = schedule(ray, config, self.run, self.learner, workers,
                                         self.service, start=start)
        self.chaos = Chaos(ray, config.ray, list(zip(workers.names(), workers.all(),
                                                     strict=True)), self.stream)

    @property
    def mode(self) -> str:
        """deterministic, asynchronous (the sequential schedule) or continuous."""
        if self.deterministic:
            return "deterministic"
        return "continuous" if self.config.ray.schedule == "continuous" else "asynchronous"

    def headline(self, run_dir: Path, start: int) -> str:
        config, workers = self.config, self.workers
        mode = self.mode
        return (f"{config.ued.method} + {config.algorithm} on Ray ({mode}, "
                f"{len(workers.explorers)} explorers, learner "
                f"{'GPU' if workers.gpus else 'CPU'}) in {run_dir}; "
                f"{config.learner.num_updates} steps of {config.learner.steps_per_update:,} "
                f"env steps{f', from step {start}' if start else ''}")

    def schedule_fields(self) -> dict[str, Any]:
        """What `ray.json` says of the schedule so far (this session's branches)."""
        fields = {"branches": {b.name.lower(): n for b, n in self.counts.items()},
                  "restarts": dict(sorted(self.deaths.count.items()))}
        return {**fields, **(self.asynchronous.record() if self.asynchronous else {})}

    def step(self, index: int, key: jax.Array, *, last: bool, checkpoint_due: bool) -> bool:
        asynchronous = self.asynchronous
        t0 = time.perf_counter()
        if asynchronous is None:
            branch, metrics, self.levels = self.run.step(self.learner, index, key)
        else:
            branch, metrics, self.levels = asynchronous.step(index, key)
        self.counts[branch] += 1
        self.run.branch_counts[branch] += 1
        self.chaos.after_step(index + 1, last)
        if metrics is not None:
            self.metrics = metrics
            if self.learner_first_s is None:  # the first step the learner trained on
                self.learner_first_s = time.perf_counter() - t0
        if asynchronous is not None and checkpoint_due:
            asynchronous.drain()  # a snapshot holds every issued batch's result
        self.reached = index + 1
        return self.run.curriculum.learns(branch)

    def host_metrics(self) -> dict[str, Any]:
        return dict(jax.device_get(self.metrics))

    def buffer_view(self, last: bool) -> tuple[dict[str, float], int | None]:
        """The level service's statistics and buffer size, off the step path: asked for at a
        logged step, read at the next one (so a logged step does not wait behind the
        service's queue); the first and the last logged step wait for them."""
        def ask() -> tuple[Call, Call]:
            return (self.actors.send(Call.of(SERVICE, "stats")),
                    self.actors.send(Call.of(SERVICE, "buffer_size")))

        asked = ask() if self._asked is None or last else self._asked
        view = self.actors.get(asked[0]), self.actors.get(asked[1])
        self._asked = None if last else ask()
        return view

    def log(self, values: dict[str, Any], report: Report) -> None:
        run, asynchronous = self.run, self.asynchronous
        values.update(report.timing)
        stats, buffer_size = self.buffer_view(report.last)
        values.update(run.logged_metrics(self.levels, stats))
        extra = branch_text(run.branch_counts, buffer_size)
        values["ray/driver_refs"] = float(driver_refs(self.ray))
        if asynchronous is not None:
            live = live_actors(self.ray, self.actors, self.workers.scorer_names()
                               if self.workers.explorers else [])
            values.update(asynchronous.stats.scalars(live, len(asynchronous.pending)))
            extra = asynchronous.stats.text(live, buffer_size)
        if self.learner_first_s is not None and not self.first_said:
            # The learner compiles at its first update, which may come steps after the first
            # logged one (new levels first): say so when it happens.
            self.first_said = True
            values["time/learner_first_update_s"] = self.learner_first_s
            if report.output.notes is not None:
                report.output.notes.write(f"  learner's first update: {self.learner_first_s:.1f}"
                                          f" s (compilation included)\n")
                report.output.notes.flush()
        report.show(values, None, extra=extra, callback=False)
        (rate,) = self.rate.add(report.done * self.config.learner.steps_per_update)
        self.record.update(background=True, steps=[self.start, report.done],
                           env_steps_per_s=rate, rate_window_s=round(self.rate.span_s, 1),
                           buffer_size=buffer_size, **self.schedule_fields())
        callback = report.output.callback
        if callback is not None:
            callback(report.done, self.learner.train_state,
                     {k: float(v) for k, v in values.items()})

    def evaluate(self, done: int, due: bool, output: Output) -> None:
        if due:
            if self.asynchronous is None:
                self.run.evaluate(self.learner, output.writer, done, output.notes)
            else:
                self.asynchronous.submit_evaluation(done)
        if self.asynchronous is not None:
            self.asynchronous.log_evaluations(output.writer, output.notes)

    def checkpoint(self, done: int, run_dir: Path) -> tuple[Any, int]:
        if self.asynchronous is not None:  # a snapshot holds every issued batch's result
            self.asynchronous.drain()  # (done already at a due checkpoint; one after Ctrl-C)
        self.run.save(run_dir, done, self.learner)
        return self.learner.train_state, self.learner.version

    def finish(self, stop: int, output: Output) -> None:
        ray, workers = self.ray, self.workers
        if self.asynchronous is not None:
            self.asynchronous.drain()
            self.asynchronous.log_evaluations(output.writer, output.notes, block=True)
        try:  # where the actors ended (a restarted one may have moved)
            for name in workers.names():
                restarts = name.startswith("explorer") or name == "evaluator"
                if restarts and self.actors.available(name):
                    self.actors.wait_back(name, timeout_s=60)
            placement_end = workers.placement(ray)
        except Exception as err:
            if not (isinstance(err, RunStopped) or is_lost(ray, err)):
                raise
            placement_end = None
        self.record.update(placement_end=placement_end, steps=[self.start, stop],
                           chaos_kills=self.chaos.kills, **self.schedule_fields())


__all__ = ["RAY_NAMESPACE", "RAY_RECORD", "RayDriver", "RayRunner", "RunRecord", "connect",
           "import_ray"]

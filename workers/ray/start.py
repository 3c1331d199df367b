"""Starting a Ray run: joining or starting Ray, checking the resources before anything starts,
placing the actors (learner, learner group, level service, Explorers, evaluator) and waiting
until they answer.

Every refusal that can be made before a run folder exists or Ray starts is made here
(`local_plan`, `check_reachable`); the rest waits at most `ray.placement_timeout_s` and names
the resource that is missing (`wait_for_resources`).
"""

from __future__ import annotations

import logging
import os
import socket
import time
import warnings
from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TextIO

import jax

from ued.config import ConfigError, RaySection, TrainConfig
from workers.driver import RunStopped
from workers.ray.actor_manager import ActorManager, death_cause, is_lost
from workers.ray.actors import (
    EvaluatorActor,
    ExplorerActor,
    LearnerActor,
    LevelServiceActor,
)
from workers.ray.learner_group import LearnerGroup, start_group

RAY_ENV = {"RAY_USAGE_STATS_ENABLED": "0"}
RAY_NAMESPACE = "tabx-ued"  # of the named actors of runs (`tabx runs buffer` finds them)


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
    return address_setting(section)[0]


def address_setting(section: RaySection) -> tuple[str, str]:
    """(`join_address`, the setting it comes from: `ray.address` or `RAY_ADDRESS`), for an
    error to name the one the user set."""
    if section.address:
        return section.address, "ray.address"
    return os.environ.get("RAY_ADDRESS", ""), "RAY_ADDRESS"


def connect(section: RaySection, num_cpus: int | None = None) -> tuple[Any, bool]:
    """Ray, connected: to `join_address(section)` if any, else a Ray started here (with
    `num_cpus`, default `section.num_cpus`). Returns (ray, whether this call started the
    connection, so the caller shuts it down)."""
    ray = import_ray()
    if ray.is_initialized():
        return ray, False
    kwargs: dict[str, Any] = {"logging_level": "WARNING", "log_to_driver": True}
    address, setting = address_setting(section)
    if address:
        check_reachable(address, setting)
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
        raise ConfigError(f"{setting}: cannot join the cluster at {address!r} "
                          f"({err}){hint}") from None
    return ray, True


# What a gRPC server (a Ray head's GCS) answers first to a client's HTTP/2 connection preface:
# a SETTINGS frame (9-byte frame header, type 0x4). A web server or anything else answers
# otherwise, or not at all; Ray itself would retry such an address for many minutes.
_HTTP2_PREFACE = b"PRI * HTTP/2.0\r\n\r\nSM\r\n\r\n" + bytes([0, 0, 0, 4, 0, 0, 0, 0, 0])
_SETTINGS_FRAME = 4


def _host_port(target: str, address: str, setting: str) -> tuple[str, int]:
    """(host, port) of HOST:PORT, [IPv6]:PORT included; a ConfigError naming `setting`."""
    host, sep, port = target.rpartition(":")
    if host.startswith("[") and host.endswith("]"):
        host = host[1:-1]
    if not sep or not host or not port.isdigit() or not 1 <= int(port) <= 65535:
        raise ConfigError(f"{setting}: expected 'auto' or HOST:PORT (the head's GCS address, "
                          f"a port in 1..65535), got {address!r:.200}")
    return host, int(port)


def check_reachable(address: str, setting: str | None = None, timeout_s: float = 5.0,
                    name: str | None = None) -> None:
    """Fail fast, in one line naming `setting` (where the address came from; default
    `ray.address`, or `RAY_ADDRESS` where the address is that variable's), where no Ray head
    answers at HOST:PORT ([IPv6]:PORT too): nothing listens, or something that is not a gRPC
    server (a Ray head's GCS speaks gRPC). A URL is refused as it is: `http(s)://` is a
    dashboard's address (for `ray job submit`), `ray://` a Ray Client server's, and the driver
    of a run must join the GCS itself (it reads Ray's own reference table and the actors' node
    ids)."""
    setting = setting or name or (
        "RAY_ADDRESS" if os.environ.get("RAY_ADDRESS") == address else "ray.address")
    if address in ("auto", "local"):
        return
    scheme, sep, _ = address.partition("://")
    if sep:
        scheme = scheme.lower()
        what = ("a dashboard's (HTTP) address, for `ray job submit`" if scheme in
                ("http", "https") else
                "a Ray Client address (the driver must run on a node of the cluster: "
                "ray exec, ray job submit)" if scheme == "ray" else
                f"a URL ({scheme}://)")
        raise ConfigError(f"{setting}: {address!r:.200} is {what}; a run joins the head's GCS "
                          f"address HOST:PORT (ray start --head prints it; port 6379 by "
                          f"default) or 'auto'")
    host, port = _host_port(address, address, setting)
    try:
        with socket.create_connection((host, port), timeout=timeout_s) as sock:
            sock.sendall(_HTTP2_PREFACE)
            answer = b""
            while len(answer) < 9:
                chunk = sock.recv(9 - len(answer))
                if not chunk:
                    break
                answer += chunk
    except OSError as err:
        if not isinstance(err, TimeoutError) and not isinstance(err, socket.timeout):
            raise ConfigError(f"{setting}: no Ray head answers at {address} "
                              f"({err.strerror or err}); start one there (ray start --head "
                              f"--port={port}) or give another address") from None
        answer = b""
    if len(answer) < 9 or answer[3] != _SETTINGS_FRAME:
        raise ConfigError(f"{setting}: {address} is not a Ray head (something listens there "
                          f"but does not speak Ray's gRPC); give the head's GCS address "
                          f"(ray start --head prints it)") from None


def actor_env(gpu: bool) -> dict[str, str]:
    """Environment of an actor process: JAX on CPU unless it holds a GPU; a GPU holder does not
    preallocate, so several JAX processes can share a node; the compilation cache shared; the
    folders of the classes the config names by path (`ued.registry.import_env`: a learner or
    curriculum defined outside the project imports there as here)."""
    from ued.registry import import_env

    env = {**RAY_ENV, **import_env()}
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
            num_gpus=gpus, num_cpus=1 if not gpus else 0, scheduling_strategy=strategy),
            section.placement_timeout_s)
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
    """Wait for every actor's constructor (errors raise here; an actor lost meanwhile, to the
    memory monitor or with its node, is a RunStopped naming it: `lost` is "learner" for any
    member of a learner group). On a cluster that is short of resources actors stay pending
    (an autoscaler may yet add nodes): say which, periodically."""
    members = workers.learner.members if isinstance(workers.learner, LearnerGroup) else []
    actors = [*workers.all(), *members[1:]]
    names = [*workers.names(), *(f"learner-{i}" for i in range(1, len(members)))]
    pending = {a.ready.remote(): name for a, name in zip(actors, names, strict=True)}
    t0 = time.perf_counter()
    while pending:
        ready, _ = ray.wait(list(pending), num_returns=len(pending), timeout=report_every_s)
        for ref in ready:
            name = pending.pop(ref)
            try:
                ray.get(ref)
            except Exception as err:
                if not is_lost(ray, err):
                    raise
                role = "learner" if name.startswith("learner") else name
                raise RunStopped(f"{name} died ({death_cause(err)})", lost=role) from err
        if pending:
            resources = ray.available_resources()
            stream.write(f"ray: waited {time.perf_counter() - t0:.0f} s for "
                         f"{', '.join(sorted(pending.values()))} to start (cluster has "
                         f"{resources.get('CPU', 0):g} CPUs and {resources.get('GPU', 0):g} "
                         f"GPUs free)\n")
            stream.flush()

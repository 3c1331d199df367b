"""Training configs: YAML files validated into typed, frozen dataclasses.

A config has six sections and top-level keys (`seed`, or `seeds` for several):

    algorithm: mappo          # mappo, ippo, mappo_rnd, iql, vdn, qmix, or a class: module:Class
    seed: 0                   # or seeds: [0, 1, 2]: several seeds in one program (PPO family)
    env:     {scenario, team, opponent, max_steps, profile}
    learner: {num_envs, num_steps, total_timesteps, optimiser, PPO's and RND's own} (LearnerConfig)
    qlearning: {replay buffer, epsilon, target network, mixer}   (iql, vdn, qmix only)
    run:     {name, dir, checkpoint_every, keep_checkpoints, log_every}
    ray:     {enabled, address, explorers, staleness bounds, deterministic}  (RaySection)
    ued:     {method (a registered curriculum), score, buffer and SFL settings, evaluation suites}
    levels:  {free parameters and their ranges}                  (ued.levels.LevelSpace)

Every field has a default (the paper's table "IPPO and MAPPO hyperparameters" and the
reference's defaults; docs/differences.md lists where we differ), so a file only lists what
differs. Which learner and curriculum names exist is `ued.registry`'s; which sections and
fields a learner reads, its class's (ued.learners.ppo.PPOLearner). A learner or a curriculum
given by path with a section of its own (`settings_section` of its class) reads it from the
top-level key of that name, validated as a built-in section is.

`key=value` overrides address a field as `section.field` (`learner.lr=1e-3`) or by its bare
name when that is unambiguous (`lr=1e-3`); values are read as YAML. Unknown keys, wrong types
and out-of-range values raise `ConfigError`, whose message names the file and the key.
"""

from __future__ import annotations

import dataclasses
import difflib
import functools
import math
import re
import types
import typing
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from level_buffer.prioritization import PRIORITIZATIONS
from ued.config_files import resolve_config
from ued.errors import ConfigError
from ued.errors import check as _check
from ued.levels import LevelSpace
from ued.registry import (
    CURRICULA,
    LEARNERS,
    curriculum_class,
    is_import_path,
    learner_class,
    learners_where,
)
from ued.yaml_reader import read_yaml

# `learner` fields only the PPO learners read (`PPOLearner.ppo_settings`): another learner's
# config must leave them as they are.
PPO_ONLY_FIELDS = ("gae_lambda", "clip_eps", "clip_value", "ent_coef", "vf_coef",
                   "num_minibatches", "normalize_advantages")
MATMUL_DTYPES = ("bfloat16", "float32")  # learner.matmul_dtype
TEAMS = ("ally", "enemy")
MAX_SEED = 2**63  # `seed` and `seeds`: what jax.random.key takes
MAX_LR = 1.0  # Adam's step size: the paper's are 4e-3 (PPO) and 5e-5 (Q-learners)
# A run folder is `<run.name>-<YYYYmmdd-HHMMSS>[-N]`: file systems allow 255 bytes a name.
MAX_RUN_NAME_BYTES = 200


@dataclass(frozen=True)
class EnvSection:
    """What is played: the scenario(s), the learner's team and who plays the other team."""

    scenario: tuple[str, ...] = ("crossfire",)  # names, compositions or files; envs cycle them
    team: str = "ally"  # the learner's team; "enemy" is the reference's flipped setting
    opponent: str = "heuristic:medium"  # the other team: heuristic[:TIER], random or idle
    max_steps: int = 512  # episode limit
    profile: str = "tabx-ued"  # behaviour profile (tabx.profiles): tabx-ued | reference

    def validate(self, prefix: str = "env") -> None:
        _check(len(self.scenario) > 0, f"{prefix}.scenario", "needs at least one scenario")
        _check(all(isinstance(s, str) and s for s in self.scenario), f"{prefix}.scenario",
               "scenario names must be non-empty strings")
        _check(self.team in TEAMS, f"{prefix}.team",
               f"must be one of {', '.join(TEAMS)}, got {self.team!r}")
        from tabx.controllers import Controller

        try:
            Controller.parse_scripted(self.opponent, "an opponent (policy against policy is an "
                                      "evaluation: tabx eval --ally RUN_A --enemy RUN_B)")
        except ValueError as err:
            raise ConfigError(f"{prefix}.opponent: {err}") from None
        from tabx.constants import MAX_STEPS

        _check(1 <= self.max_steps <= MAX_STEPS, f"{prefix}.max_steps",
               f"must be in [1, 2**31 - 1] (the step counter is int32), got {self.max_steps}")
        from tabx.profiles import PROFILE_NAMES

        _check(self.profile in PROFILE_NAMES, f"{prefix}.profile",
               f"must be one of {', '.join(PROFILE_NAMES)}, got {self.profile!r}")


@dataclass(frozen=True)
class LearnerConfig:
    """The `learner:` section, read by every learner: the batch (num_envs x num_steps), the
    run's length, the optimiser, the network width and the devices; then the fields only the
    PPO learners read (`PPO_ONLY_FIELDS`) and MAPPO+RND's (`rnd_*`). A learner's settings
    beyond these have a section of their own (`qlearning:`, `PPOLearner.settings_section`).
    Defaults: the paper's table, and the reference for the rest."""

    num_envs: int = 128
    num_steps: int = 512  # rollout length per update
    total_timesteps: int = 50_000_000  # env steps over the whole run (num_envs x num_steps each)
    lr: float = 4e-3
    anneal_lr: bool = True  # linear decay to 0 over the run
    hidden_dim: int = 128  # embedding, GRU and post-GRU width
    gamma: float = 0.99
    gae_lambda: float = 0.95
    clip_eps: float = 0.05  # policy ratio clip, and value clip when clip_value
    clip_value: bool = True
    ent_coef: float = 0.01
    vf_coef: float = 0.5
    max_grad_norm: float = 0.25
    adam_eps: float = 1e-5
    update_epochs: int = 4
    num_minibatches: int = 4  # minibatches over envs (all agents of an env stay together)
    normalize_advantages: bool = True  # per minibatch, over valid agent steps
    # Envs split over this many local devices (data parallel; one gradient, summed across
    # them). 0: as many as divide the envs evenly (ued/learners/ppo/train.py `learner_devices`).
    num_devices: int = 0
    # The networks' matrix products: inputs rounded to this type, float32 accumulation
    # (bfloat16 = JAX's default precision on TPUs; about 1.3x faster updates on an AMX CPU);
    # "float32" for full precision. Parameters, gradients and the optimiser stay float32.
    matmul_dtype: str = "bfloat16"
    # MAPPO+RND (algorithm mappo_rnd; the paper's table "RND Hyperparameters";
    # ued/learners/rnd.py). Other algorithms refuse values other than these defaults.
    rnd_reward_coef: float = 0.5  # beta: intrinsic reward = beta * mean((f(s') - g(s'))^2)
    rnd_gae_coef: float = 0.01  # advantage = extrinsic GAE + rnd_gae_coef * intrinsic GAE
    rnd_loss_coef: float = 0.01  # predictor loss = rnd_loss_coef * mean squared error
    rnd_lr: float = 3e-4  # the predictor's Adam
    rnd_update_epochs: int = 1  # predictor epochs per update (minibatches as PPO's)
    rnd_hidden_dim: int = 128
    rnd_output_dim: int = 256
    rnd_layers: int = 3  # hidden Dense + ReLU layers of the predictor and the target

    @property
    def steps_per_update(self) -> int:
        return self.num_envs * self.num_steps

    @property
    def num_updates(self) -> int:
        return max(1, self.total_timesteps // self.steps_per_update)

    def validate(self, prefix: str = "learner", ppo: bool = True) -> None:
        """`ppo`: also check the fields only PPO reads (minibatches)."""
        for name in ("num_envs", "num_steps", "total_timesteps", "hidden_dim", "update_epochs",
                     "num_minibatches", "rnd_update_epochs", "rnd_hidden_dim",
                     "rnd_output_dim", "rnd_layers"):
            value = getattr(self, name)
            _check(value >= 1, f"{prefix}.{name}", f"must be >= 1, got {value}")
        if ppo:
            _check(self.num_envs % self.num_minibatches == 0, f"{prefix}.num_minibatches",
                   f"must divide num_envs ({self.num_envs}), got {self.num_minibatches}")
        _check(self.num_devices >= 0, f"{prefix}.num_devices",
               f"must be >= 0 (0: automatic), got {self.num_devices}")
        if self.num_devices and ppo:
            _check(self.num_envs % (self.num_devices * self.num_minibatches) == 0,
                   f"{prefix}.num_devices",
                   f"num_envs ({self.num_envs}) must split into num_devices x num_minibatches "
                   f"({self.num_devices} x {self.num_minibatches}) equal parts")
        _check(self.matmul_dtype in MATMUL_DTYPES, f"{prefix}.matmul_dtype",
               f"must be one of {', '.join(MATMUL_DTYPES)}, got {self.matmul_dtype!r}")
        for name in ("lr", "rnd_lr"):
            value = getattr(self, name)
            _check(0 < value <= MAX_LR, f"{prefix}.{name}",
                   f"must be in (0, {MAX_LR:g}], got {value}")
        for name in ("gamma", "gae_lambda"):
            value = getattr(self, name)
            _check(0.0 <= value <= 1.0, f"{prefix}.{name}", f"must be in [0, 1], got {value}")
        for name in ("clip_eps", "ent_coef", "vf_coef", "rnd_reward_coef", "rnd_gae_coef",
                     "rnd_loss_coef"):
            value = getattr(self, name)
            _check(value >= 0.0, f"{prefix}.{name}", f"must be >= 0, got {value}")
        _check(self.max_grad_norm > 0, f"{prefix}.max_grad_norm",
               f"must be > 0, got {self.max_grad_norm}")
        _check(self.adam_eps > 0, f"{prefix}.adam_eps", f"must be > 0, got {self.adam_eps}")


@dataclass(frozen=True)
class QLearningConfig:
    """Settings of the Q-learners (iql, vdn, qmix) beyond the `learner` fields they share with
    PPO (num_envs, num_steps, total_timesteps, lr, anneal_lr, hidden_dim, gamma, max_grad_norm,
    adam_eps, update_epochs = gradient steps per update, matmul_dtype). Defaults: the paper's
    table "IQL and QMIX Hyperparameters" and the reference for the rest (docs/differences.md
    lists where we differ); the mixer fields are QMIX's."""

    buffer_size: int = 5000  # trajectories kept (one per env per update, num_steps long)
    batch_size: int = 32  # trajectories per gradient step
    eps_start: float = 1.0  # epsilon-greedy exploration, linear from start to finish
    eps_finish: float = 0.05
    eps_decay: float = 0.1  # over this fraction of the run's updates
    target_update_interval: int = 10  # updates between target-network updates
    tau: float = 1.0  # target <- tau online + (1 - tau) target (1: a copy)
    learning_starts: int = 10_000  # env steps before the first gradient step
    reward_scale: float = 10.0  # rewards are multiplied by this in the TD targets
    mixer_embed_dim: int = 64  # QMIX: mixing-network width
    mixer_hidden_dim: int = 256  # QMIX: hypernetwork hidden width
    mixer_init_scale: float = 0.001  # QMIX: orthogonal init scale of the hypernetworks

    def capacity(self, num_envs: int) -> int:
        """Trajectories the buffer holds: `buffer_size // num_envs` per env."""
        return (self.buffer_size // num_envs) * num_envs

    def validate(self, num_envs: int, prefix: str = "qlearning") -> None:
        for name in ("buffer_size", "batch_size", "target_update_interval", "mixer_embed_dim",
                     "mixer_hidden_dim"):
            value = getattr(self, name)
            _check(value >= 1, f"{prefix}.{name}", f"must be >= 1, got {value}")
        _check(self.buffer_size >= num_envs, f"{prefix}.buffer_size",
               f"must hold at least one trajectory per env (learner.num_envs {num_envs}), "
               f"got {self.buffer_size}")
        _check(self.capacity(num_envs) >= self.batch_size, f"{prefix}.buffer_size",
               f"must hold at least one batch (batch_size {self.batch_size} trajectories; "
               f"the buffer keeps buffer_size // num_envs per env, "
               f"{self.capacity(num_envs)} in all), got {self.buffer_size}")
        for name in ("eps_start", "eps_finish", "eps_decay", "tau"):
            value = getattr(self, name)
            _check(0.0 <= value <= 1.0, f"{prefix}.{name}", f"must be in [0, 1], got {value}")
        _check(self.tau > 0, f"{prefix}.tau", f"must be > 0, got {self.tau}")
        _check(self.learning_starts >= 0, f"{prefix}.learning_starts",
               f"must be >= 0, got {self.learning_starts}")
        _check(self.reward_scale > 0, f"{prefix}.reward_scale",
               f"must be > 0, got {self.reward_scale}")
        _check(self.mixer_init_scale > 0, f"{prefix}.mixer_init_scale",
               f"must be > 0, got {self.mixer_init_scale}")


# The paper's `learner` settings of the Q-learners (table "IQL and QMIX Hyperparameters"; the
# reference's gradient clipping, RAdam epsilon and constant learning rate), where they differ
# from PPO's defaults: configs/marl/{iql,vdn,qmix}_*.yaml and `tabx bench train` use them.
Q_LEARNER_SETTINGS = {"lr": 5e-5, "anneal_lr": False, "hidden_dim": 512, "max_grad_norm": 10.0,
                      "adam_eps": 1e-8, "update_epochs": 8}


@dataclass(frozen=True)
class RunSection:
    """Where and how often the run writes: run folder, checkpoints, logs."""

    # Run folder name prefix; empty: [METHOD_FREE_]ALGORITHM_SCENARIO. `{key}` stands for the
    # config's value of that key (`{ued.method}`, `{levels.free}`: `fill_run_name`).
    name: str = ""
    dir: str = "runs"  # parent folder of run folders
    checkpoint_every: int = 50  # updates between checkpoints (the last update always saves)
    keep_checkpoints: int = 3  # checkpoints kept (the newest)
    log_every: int = 1  # updates between TensorBoard / progress writes
    compile_cache: bool = True  # keep compiled programs on disk (ued/compile_cache.py)
    # Value error |V - V*| (ued/value_error.py) logged every this many updates of a plain
    # MARL run, per scenario; 0: never. States x rollouts as the paper's protocol by default.
    value_error_every: int = 0
    value_error_states: int = 128
    value_error_rollouts: int = 128

    def validate(self, prefix: str = "run") -> None:
        _check(self.value_error_every >= 0, f"{prefix}.value_error_every",
               f"must be >= 0 (0: never), got {self.value_error_every}")
        for name in ("checkpoint_every", "keep_checkpoints", "log_every", "value_error_states",
                     "value_error_rollouts"):
            value = getattr(self, name)
            _check(value >= 1, f"{prefix}.{name}", f"must be >= 1, got {value}")
        _check("/" not in self.name and "\\" not in self.name
               and all(ch.isprintable() for ch in self.name), f"{prefix}.name",
               f"must be a plain folder name, got {self.name!r:.80}")
        size = len(self.name.encode("utf-8", "surrogatepass"))
        _check(size <= MAX_RUN_NAME_BYTES, f"{prefix}.name",
               f"must be at most {MAX_RUN_NAME_BYTES} bytes (a folder name), got {size}")


UED_SCORES = ("max_mc", "pvl")


@dataclass(frozen=True)
class UEDSection:
    """Unsupervised environment design: the curriculum, its level buffer and its evaluation.

    Defaults: the paper's table "UED Hyperparameters" (buffer 4000, staleness 0.3, rank
    prioritisation, temperature 0.3, replay rate 0.8) and the reference code for what the
    paper does not state (minimum fill 0.5, duplicate check, MaxMC, top-k 4, SFL settings).
    `method: none` trains on the scenarios of `env.scenario` as they are."""

    method: str = "none"  # none, or a registered curriculum (ued.registry): dr, plr, ...
    score: str = "max_mc"  # max_mc | pvl: the regret estimate that ranks buffer levels
    buffer_size: int = 4000
    replay_prob: float = 0.8
    staleness_coef: float = 0.3
    min_fill_ratio: float = 0.5
    prioritization: str = "rank"  # rank | topk | uniform (level_buffer.prioritization)
    temperature: float = 0.3
    topk: int = 4  # levels in the softmax of top-k prioritisation
    duplicate_check: bool = True
    exploratory_grad_updates: bool | None = None  # None: the method's own (PLR yes, else no)
    sfl_batch_size: int = 5000  # random levels scored per learnability batch
    sfl_num_batches: int = 5
    sfl_rollout_steps: int = 2000  # steps each learnability level is played
    sfl_top_k: int = 1000  # size of the learnable set
    sfl_update_freq: int = 64  # steps between rebuilds of the learnable set
    sfl_fresh_fraction: float = 0.5  # share of fresh random levels in each SFL batch
    eval_suites: tuple[str, ...] = ()  # zero-shot suites (configs/eval) run during training
    eval_every: int = 10  # steps between evaluations (and at the end)
    eval_episodes: int = 0  # episodes per suite entry; 0: each suite's own

    @property
    def enabled(self) -> bool:
        return self.method != "none"

    def validate(self, prefix: str = "ued") -> None:
        methods = ("none", *CURRICULA)
        _check(self.method in methods or is_import_path(self.method), f"{prefix}.method",
               f"must be one of {', '.join(methods)} or an import path module:Class, got "
               f"{self.method!r}")
        if is_import_path(self.method):
            curriculum_class(self.method, f"{prefix}.method")  # imports it: a clear error
        _check(self.score in UED_SCORES, f"{prefix}.score",
               f"must be one of {', '.join(UED_SCORES)}, got {self.score!r}")
        _check(self.prioritization in PRIORITIZATIONS, f"{prefix}.prioritization",
               f"must be one of {', '.join(PRIORITIZATIONS)}, got {self.prioritization!r}")
        for name in ("buffer_size", "topk", "sfl_batch_size", "sfl_num_batches",
                     "sfl_rollout_steps", "sfl_top_k", "sfl_update_freq", "eval_every"):
            value = getattr(self, name)
            _check(value >= 1, f"{prefix}.{name}", f"must be >= 1, got {value}")
        for name in ("replay_prob", "staleness_coef", "min_fill_ratio", "sfl_fresh_fraction"):
            value = getattr(self, name)
            _check(0.0 <= value <= 1.0, f"{prefix}.{name}", f"must be in [0, 1], got {value}")
        _check(self.temperature > 0, f"{prefix}.temperature",
               f"must be > 0, got {self.temperature}")
        _check(self.eval_episodes >= 0, f"{prefix}.eval_episodes",
               f"must be >= 0 (0: the suite's own), got {self.eval_episodes}")
        _check(all(isinstance(s, str) and s for s in self.eval_suites), f"{prefix}.eval_suites",
               "suite names must be non-empty strings")


CHAOS_ROLES = ("explorer", "service", "evaluator")  # the actors a run restarts


RAY_SCHEDULES = ("sequential", "continuous")
MAX_INFLIGHT = 64  # ray.max_inflight: the docs' settings are 1 to 4
MAX_PLACEMENT_TIMEOUT_S = 86400.0  # ray.placement_timeout_s


@dataclass(frozen=True)
class RaySection:
    """Running a UED run's workers as Ray actors (docs/distributed.md). Off by default: the
    local driver runs everything in one process and Ray is never imported."""

    enabled: bool = False  # tabx train --ray
    address: str = ""  # "": start Ray on this machine; "auto" or HOST:PORT: join a cluster
    explorers: int = 1  # Explorer actors scoring new and mutated levels (0: the learner's)
    max_inflight: int = 2  # batches each Explorer may run ahead of the driver
    max_policy_lag: int = 4  # a score this many policy versions older is re-scored
    deterministic: bool = False  # the local driver's schedule, step by step (equal results)
    # "sequential": the paper's steps, one batch per step (scored by an Explorer or trained);
    # "continuous": Explorers score new levels without pause, every step trains (Robust PLR,
    # ACCEL; docs/distributed.md, "Continuous scoring")
    schedule: str = "sequential"
    learner_gpus: float = -1.0  # GPUs of the learner actor; -1: one if the cluster has any
    learners: int = 1  # learner actors that run each update together (a JAX process group)
    # times a run stopped by its lost learner (or any actor lost at start-up) starts again
    # from its newest intact checkpoint (0: it stops, with the --resume command)
    learner_restarts: int = 2
    learner_share_cores: bool = False  # group members on one node pin to their share of it
    num_cpus: int = 0  # CPUs of a Ray started here (0: Ray's own count)
    object_store_mb: int = 512  # object store of a Ray started here
    placement_timeout_s: float = 120.0  # wait this long for the actors' resources, then fail
    explorers_on_gpu_nodes: bool = False  # Explorers may share a GPU learner's nodes
    actor_restarts: int = -1  # restarts of each Explorer and the Evaluator (-1: no limit)
    chaos_kill_every: int = 0  # kill one of `chaos_roles`' actors every N steps (0: never)
    chaos_kill_every_s: float = 0.0  # ... or every N seconds (0: never)
    chaos_roles: str = "explorer"  # whose actors chaos kills, in turn: explorer,service,evaluator

    def validate(self, prefix: str = "ray") -> None:
        _check(self.explorers >= 0, f"{prefix}.explorers",
               f"must be >= 0 (0: the learner actor scores too), got {self.explorers}")
        _check(1 <= self.max_inflight <= MAX_INFLIGHT, f"{prefix}.max_inflight",
               f"must be in [1, {MAX_INFLIGHT}] (batches an Explorer runs ahead, each a "
               f"batch of levels in memory), got {self.max_inflight}")
        _check(self.max_policy_lag >= 0, f"{prefix}.max_policy_lag",
               f"must be >= 0, got {self.max_policy_lag}")
        _check(self.schedule in RAY_SCHEDULES, f"{prefix}.schedule",
               f"must be one of {', '.join(RAY_SCHEDULES)}, got {self.schedule!r}")
        _check(not (self.deterministic and self.schedule == "continuous"),
               f"{prefix}.schedule", "continuous scoring runs beside the learner: it cannot "
               "be deterministic (drop ray.deterministic or use schedule sequential)")
        _check(self.learner_gpus == -1.0 or self.learner_gpus >= 0, f"{prefix}.learner_gpus",
               f"must be -1 (auto) or >= 0, got {self.learner_gpus}")
        _check(self.num_cpus >= 0, f"{prefix}.num_cpus", f"must be >= 0, got {self.num_cpus}")
        _check(self.learners >= 1, f"{prefix}.learners", f"must be >= 1, got {self.learners}")
        _check(self.learner_restarts >= 0, f"{prefix}.learner_restarts",
               f"must be >= 0, got {self.learner_restarts}")
        _check(self.object_store_mb >= 64, f"{prefix}.object_store_mb",
               f"must be >= 64, got {self.object_store_mb}")
        _check(0 < self.placement_timeout_s <= MAX_PLACEMENT_TIMEOUT_S,
               f"{prefix}.placement_timeout_s",
               f"must be in (0, {MAX_PLACEMENT_TIMEOUT_S:g}] seconds (a day), got "
               f"{self.placement_timeout_s:g}")
        _check(self.actor_restarts >= -1, f"{prefix}.actor_restarts",
               f"must be -1 (no limit) or >= 0, got {self.actor_restarts}")
        _check(self.chaos_kill_every >= 0, f"{prefix}.chaos_kill_every",
               f"must be >= 0 (0: never), got {self.chaos_kill_every}")
        _check(self.chaos_kill_every_s >= 0, f"{prefix}.chaos_kill_every_s",
               f"must be >= 0 (0: never), got {self.chaos_kill_every_s}")
        roles = [r.strip() for r in self.chaos_roles.split(",")]
        _check(bool(roles) and all(r in CHAOS_ROLES for r in roles), f"{prefix}.chaos_roles",
               f"must be a comma-separated list of {', '.join(CHAOS_ROLES)} (the actors that "
               f"restart), got {self.chaos_roles!r}")


@dataclass(frozen=True)
class TrainConfig:
    """A whole training run."""

    algorithm: str = "mappo"  # a built-in learner (ued.registry.LEARNERS) or module:Class
    seed: int = 0
    # Several seeds of one plain MARL run trained side by side in one compiled program
    # (vmapped over seeds; workers.local.train_marl_seeds). Empty: the one `seed`.
    seeds: tuple[int, ...] = ()
    env: EnvSection = field(default_factory=EnvSection)
    learner: LearnerConfig = field(default_factory=LearnerConfig)
    qlearning: QLearningConfig = field(default_factory=QLearningConfig)
    run: RunSection = field(default_factory=RunSection)
    ued: UEDSection = field(default_factory=UEDSection)
    levels: LevelSpace = field(default_factory=LevelSpace)
    ray: RaySection = field(default_factory=RaySection)
    # The own section of a learner given by path, when TrainConfig has no field for it: the
    # (field, value) pairs of its class's `settings_type`, read from and written to the
    # top-level key `settings_section` (not a key of its own). Plain values, so that a
    # config unpickles in a process that has not imported the learner's module yet.
    algorithm_settings: tuple[tuple[str, Any], ...] = field(
        default=(), metadata={"config_key": False})
    # The same for the curriculum's own section (`ued.curricula.Curriculum.settings_section`).
    method_settings: tuple[tuple[str, Any], ...] = field(
        default=(), metadata={"config_key": False})

    def validate(self) -> TrainConfig:
        learner = learner_class(self.algorithm)
        self.env.validate()
        self.learner.validate(ppo=learner.ppo_settings)
        self._validate_algorithm_settings()
        self.run.validate()
        self.ued.validate()
        self._validate_method_settings()
        self.levels.validate()
        self.ray.validate()
        if self.ray.enabled and self.ray.learners > 1:
            share = self.ray.learners * max(self.learner.num_devices, 1) * (
                self.learner.num_minibatches)
            _check(learner.devices and self.learner.num_envs % share == 0, "ray.learners",
                   f"{self.ray.learners} learners split each minibatch of learner.num_envs "
                   f"({self.learner.num_envs}) over their devices: it must divide by "
                   f"learners x num_devices x num_minibatches ({share}), for a learner that "
                   f"runs on several devices")
        self._validate_seeds()
        _check(not self.run.value_error_every or learner.value_head,
               "run.value_error_every", f"the value error compares a value head with Monte-Carlo "
               f"returns; {self.algorithm} has no value head")
        _check(not self.run.value_error_every or not self.ued.enabled, "run.value_error_every",
               "the value error is logged during plain MARL runs (ued.method: none); analyse "
               "a UED run with tabx analyse value-error")
        _check(not self.ray.enabled or self.ued.enabled, "ray.enabled",
               "the Ray driver runs UED runs (set ued.method); a plain MARL run trains in "
               "one process")
        if self.ued.enabled and "heuristic" in self.levels.free_params:
            from tabx.controllers import Controller

            _check(Controller.parse(self.env.opponent).tier is None, "env.opponent",
                   f"{self.env.opponent!r} writes its tier into every level, which would undo "
                   "the generated heuristic parameters (levels.free includes heuristic): use "
                   "'heuristic' (the level's own parameters)")
        return self

    def _validate_seeds(self) -> None:
        """`seed`: an integer in [0, 2**63); `seeds`: distinct ones, for a plain MARL run of
        the PPO family."""
        _check(0 <= self.seed < MAX_SEED, "seed",
               f"must be an integer in [0, 2**63), got {self.seed:.4g}"
               if abs(self.seed) >= 10**12 else f"must be an integer in [0, 2**63), got "
               f"{self.seed}")
        if not self.seeds:
            return
        for seed in self.seeds:
            _check(0 <= seed < MAX_SEED, "seeds", f"seeds must be integers in [0, 2**63), got "
                   f"{seed}")
            _check(self.seeds.count(seed) == 1, "seeds",
                   f"seeds must be distinct, got {seed} more than once")
        _check(self.seed == 0, "seed", f"a multi-seed config lists its seeds in `seeds` only; "
               f"drop seed: {self.seed} (seeds: {list(self.seeds)})")
        supported = (f"several seeds train in one program for the PPO learners "
                     f"({', '.join(learners_where(lambda c: c.seeds))}) on plain MARL runs")
        _check(learner_class(self.algorithm).seeds, "seeds",
               f"{supported}; {self.algorithm} trains one seed per run (give `seed`)")
        _check(not self.ray.enabled, "seeds",
               f"{supported} on the local driver; ray.enabled trains one seed per run")
        _check(not self.ued.enabled, "seeds",
               f"{supported}; a UED run (ued.method: {self.ued.method}) trains one seed per run "
               "(give `seed`)")

    def _validate_algorithm_settings(self) -> None:
        """Settings the algorithm would ignore are mistakes: another learner's section
        (`qlearning` on PPO), PPO's `learner` fields on a Q-learner, another learner's own
        settings (QMIX's mixer on IQL, RND's on MAPPO). What each learner reads and supports
        is its class's (ued.learners.ppo.PPOLearner)."""
        learner = learner_class(self.algorithm)
        changed = lambda section, names: [n for n in names if getattr(section, n) != getattr(
            type(section)(), n)]
        builtin = [learner_class(name) for name in LEARNERS]
        for section in dict.fromkeys(c.settings_section for c in builtin if c.settings_section):
            if section == learner.settings_section:
                continue
            owners = learners_where(lambda c, section=section: c.settings_section == section)
            values = getattr(self, section)
            for name in changed(values, [f.name for f in dataclasses.fields(values)]):
                raise ConfigError(f"{section}.{name}: a setting of the "
                                  f"{learner_class(owners[0]).family} ({', '.join(owners)}); "
                                  f"{self.algorithm} does not use it")
        if not learner.ppo_settings:
            for name in changed(self.learner, PPO_ONLY_FIELDS):
                raise ConfigError(f"learner.{name}: a PPO setting; {self.algorithm} does not "
                                  "use it")
        for other in builtin:
            for key in other.own_settings:
                if key in learner.own_settings:
                    continue
                section, name = key.split(".")
                _check(not changed(getattr(self, section), [name]), key,
                       other.refusal.format(algorithm=self.algorithm))
        settings = self.learner_settings()
        if settings is not None:
            learner.validate_settings(settings, self.learner)
        _check(learner.devices or self.learner.num_devices <= 1, "learner.num_devices",
               f"{self.algorithm} runs on one device (its replay buffer lives there), got "
               f"{self.learner.num_devices}")
        _check(learner.curricula or not self.ued.enabled, "ued.method",
               f"the UED curricula train MAPPO or IPPO; {self.algorithm} trains on the "
               f"scenarios of env.scenario (ued.method: none)")

    def learner_settings(self) -> Any:
        """The algorithm's own settings section (`settings_section` of its class: the
        Q-learners' `qlearning`; a by-path learner's, built from `algorithm_settings`), or
        None."""
        cls = learner_class(self.algorithm)
        if cls.settings_section is None:
            return None
        if cls.settings_section in _sections():
            return getattr(self, cls.settings_section)
        return cls.settings_type(**dict(self.algorithm_settings))

    def _validate_method_settings(self) -> None:
        """The curriculum's own settings, by its class's `validate_settings`; settings kept for
        a method that reads none (a config changed in code) are a mistake."""
        settings = self.curriculum_settings()
        if settings is None:
            _check(not self.method_settings, "ued.method",
                   f"{self.ued.method} reads no settings section of its own, but the config "
                   f"holds {', '.join(name for name, _ in self.method_settings)}")
            return
        curriculum_class(self.ued.method).validate_settings(settings, self.ued)

    def curriculum_settings(self) -> Any:
        """The curriculum's own settings section (`settings_type` of its class, built from
        `method_settings`), or None (no curriculum, or one without a section)."""
        if not self.ued.enabled:
            return None
        cls = curriculum_class(self.ued.method)
        if cls.settings_type is None:
            return None
        return cls.settings_type(**dict(self.method_settings))

    @property
    def run_name(self) -> str:
        if self.run.name:
            return self.run.name
        scenario = Path(self.env.scenario[0]).stem
        more = f"+{len(self.env.scenario) - 1}" if len(self.env.scenario) > 1 else ""
        method = (f"{self.ued.method.rpartition(':')[2]}_{_name_part(self.levels.free)}_"
                  if self.ued.enabled else "")
        algorithm = self.algorithm.rpartition(":")[2]  # a class by path: its name
        return f"{method}{algorithm}_{scenario}{more}"

    def to_dict(self) -> dict[str, Any]:
        out = dataclasses.asdict(self)
        del out["algorithm_settings"], out["method_settings"]
        built = {"algorithm_settings": self.learner_settings,
                 "method_settings": self.curriculum_settings}
        for kept, (section, _) in _own_sections(self.algorithm, self.ued.method).items():
            settings = built[kept]()  # under its own key, every field written out
            out[section] = {f.name: list(v) if isinstance(v := getattr(settings, f.name), tuple)
                            else v for f in dataclasses.fields(settings)}
        out["env"]["scenario"] = list(self.env.scenario)
        if self.seeds:
            out["seeds"] = list(self.seeds)
        else:  # a single-seed config's file (and its hash, ued.run_folder) has no `seeds`
            del out["seeds"]
        out["ued"]["eval_suites"] = list(self.ued.eval_suites)
        out["levels"] = self.levels.to_dict()
        return out

    def to_yaml(self) -> str:
        return yaml.safe_dump(self.to_dict(), sort_keys=False)


# --- reading ---------------------------------------------------------------------------------


def _type_name(tp: Any) -> str:
    return {int: "an integer", float: "a number", bool: "true or false", str: "a string"}.get(
        tp, str(tp))


def _shown(value: Any, limit: int = 80) -> str:
    """`value` as an error message quotes it: its repr, cut short (a config value can be a
    whole pasted file)."""
    text = repr(value)
    return text if len(text) <= limit else f"{text[:limit]}... ({len(text)} characters)"


def _coerce(value: Any, tp: Any, key: str) -> Any:
    """`value` as the field type `tp` (int, float, bool, str, tuple[str, ...], str | None)."""
    origin = typing.get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        if value is None:
            return None
        return _coerce(value, args[0], key)
    if origin is tuple:
        (item,) = [a for a in typing.get_args(tp) if a is not Ellipsis]
        items = [value] if isinstance(value, str) else value
        if not isinstance(items, Sequence) or isinstance(items, str | bytes):
            raise ConfigError(f"{key}: expected {_type_name(item)} or a list of them, got "
                              f"{_shown(value)}")
        return tuple(_coerce(v, item, key) for v in items)
    if tp is bool:
        if isinstance(value, bool):
            return value
        raise ConfigError(f"{key}: expected true or false, got {_shown(value)}")
    if tp is int:
        number = value
        if isinstance(value, str):  # YAML 1.1 reads 5e7 as a string
            try:
                number = float(value)
            except ValueError:
                number = None
        if isinstance(number, bool) or not isinstance(number, int | float) or (
                isinstance(number, float) and not (math.isfinite(number)
                                                   and number == int(number))):
            raise ConfigError(f"{key}: expected an integer, got {_shown(value)}")
        return int(number)
    if tp is float:
        number = value
        if isinstance(value, str):
            try:
                number = float(value)
            except ValueError:
                number = None
        try:  # an integer beyond a float's range is no number either
            finite = (isinstance(number, int | float) and not isinstance(number, bool)
                      and math.isfinite(number))
        except OverflowError:
            finite = False
        if not finite:
            raise ConfigError(f"{key}: expected a number, got {_shown(value)}")
        return float(number)
    if tp is str:
        if isinstance(value, str):
            return value
        raise ConfigError(f"{key}: expected a string, got {_shown(value)}")
    raise TypeError(f"unsupported config field type {tp!r}")  # a bug here, not a user error


def _unknown(key: str, allowed: Sequence[str]) -> ConfigError:
    close = difflib.get_close_matches(key.rsplit(".", 1)[-1], allowed, n=1)
    section = key.rsplit(".", 1)[0] + "." if "." in key else ""
    hint = f"; did you mean {section + close[0]!r}?" if close else ""
    return ConfigError(f"unknown key {key!r}{hint} (allowed in this section: "
                       f"{', '.join(section + a for a in allowed)})")


def _build(cls: type, data: Any, prefix: str) -> Any:
    if data is None:
        data = {}
    if not isinstance(data, Mapping):
        raise ConfigError(f"{prefix or 'config'}: expected a mapping of keys to values, got "
                          f"{type(data).__name__}")
    hints = _type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls) if f.metadata.get("config_key", True)}
    values = {}
    for key, value in data.items():
        full = f"{prefix}.{key}" if prefix else str(key)
        if key not in fields:
            raise _unknown(full, list(fields))
        tp = hints[key]
        if full == "seeds" and (not isinstance(value, Sequence) or isinstance(value, str)
                                or not value):
            raise ConfigError(f"seeds: expected a non-empty list of seeds, e.g. [0, 1, 2], got "
                              f"{_shown(value)}")
        if dataclasses.is_dataclass(tp):
            values[key] = _build(tp, value, full)
        else:
            values[key] = _coerce(value, tp, full)
    return cls(**values)


def config_from_dict(data: Any, source: str = "config") -> TrainConfig:
    """A validated TrainConfig from a parsed YAML mapping, its `run.name` filled in
    (`fill_run_name`); errors name `source`."""
    try:
        own = _own_sections(*_named_classes(data)) if isinstance(data, Mapping) else {}
        settings = {}
        for kept, (section, kind) in own.items():  # read with their own fields
            data = dict(data)
            values = _build(kind, data.pop(section, None), section)
            settings[kept] = tuple((f.name, getattr(values, f.name))
                                   for f in dataclasses.fields(values))
        config = _build(TrainConfig, data, "")
        if settings:
            config = dataclasses.replace(config, **settings)
        return fill_run_name(config).validate()
    except ConfigError as err:
        raise ConfigError(f"{source}: {err}") from None


_NAME_FIELD = re.compile(r"\{([^{}]*)\}")
_NAME_UNSAFE = re.compile(r"[^A-Za-z0-9._+=-]+")


def _name_part(value: Any) -> str:
    if isinstance(value, list | tuple):
        return "+".join(_name_part(v) for v in value)
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str) and ("/" in value or value.endswith(".json")):
        value = Path(value).stem  # a scenario file: its name
    return _NAME_UNSAFE.sub("_", str(value))


def fill_run_name(config: TrainConfig) -> TrainConfig:
    """`config` with each `{key}` of `run.name` replaced by its value of that config key
    (`ued.method`, `levels.free`, `algorithm`, `seed`, a bare field name: lists joined with
    `+`, a scenario file by its name), so that a run is named from what it trains:
    `quickstart_{ued.method}_{levels.free}` is `quickstart_sfl_zone` with `ued.method=sfl`."""
    name = config.run.name
    if "{" not in name and "}" not in name:
        return config
    paths = _field_paths()

    def value(match: re.Match) -> str:
        key = match.group(1).strip()
        path = paths[key][0] if "." not in key and len(paths.get(key, [])) == 1 else key
        found: Any = config
        for part in path.split(".") if path else ["?"]:
            if not dataclasses.is_dataclass(found) or part not in {
                    f.name for f in dataclasses.fields(found)}:
                raise ConfigError(f"run.name: {{{key}}} names no config key (e.g. "
                                  f"{{ued.method}}, {{levels.free}}, {{algorithm}})")
            found = getattr(found, part)
        if dataclasses.is_dataclass(found):
            raise ConfigError(f"run.name: {{{key}}} is a section; name a key of it")
        return _name_part(found)

    filled = _NAME_FIELD.sub(value, name)
    if "{" in filled or "}" in filled:
        raise ConfigError(f"run.name: unbalanced braces in {name!r:.80} ({{key}} names a "
                          f"config key)")
    return dataclasses.replace(config, run=dataclasses.replace(config.run, name=filled))


@functools.cache
def _sections() -> frozenset[str]:
    """The names of TrainConfig's sections (fields that are dataclasses)."""
    hints = _type_hints(TrainConfig)
    return frozenset(f.name for f in dataclasses.fields(TrainConfig)
                     if dataclasses.is_dataclass(hints[f.name]))


def _own_section(cls: Any, key: str, ref: str, shared: bool = False
                 ) -> tuple[str, type] | None:
    """(top-level key, dataclass) of the own section (`settings_section`, `settings_type`) of
    `cls`, the class `ref` names at the config key `key` (a learner's `algorithm`, a
    curriculum's `ued.method`), when TrainConfig has no field for it; None when it has none,
    or (`shared`: a learner) when it reads a built-in section of that type (a Q-learner's
    `qlearning`). A section that is no new top-level key, or a type that is no dataclass, is
    one ConfigError naming `key`."""
    section, kind = cls.settings_section, cls.settings_type
    if section is None:
        return None
    if shared and section in _sections():  # a built-in section (a Q-learner's `qlearning`)
        _check(kind is _type_hints(TrainConfig)[section], key,
               f"{ref} reads the section {section!r}, whose type is "
               f"{_type_hints(TrainConfig)[section].__name__}, not {kind!r}")
        return None
    _check(isinstance(section, str) and section not in {
        f.name for f in dataclasses.fields(TrainConfig)} and isinstance(kind, type)
        and dataclasses.is_dataclass(kind), key,
        f"{ref} names its settings section {section!r} with settings_type {kind!r}: the "
        f"section must be a new top-level key, its type a dataclass")
    return section, kind


def _own_sections(algorithm: Any, method: Any) -> dict[str, tuple[str, type]]:
    """The own sections (`_own_section`) of the learner `algorithm` and the curriculum
    `method`, by the TrainConfig field that keeps each one's values (`algorithm_settings`,
    `method_settings`). Only a class given by path (or a registered curriculum) can have one;
    any other value, refused by validation later, has none. Both reading one key is a
    ConfigError."""
    out = {}
    if isinstance(algorithm, str) and ":" in algorithm:
        learner = _own_section(learner_class(algorithm), "algorithm", algorithm, shared=True)
        if learner is not None:
            out["algorithm_settings"] = learner
    if isinstance(method, str) and (method in CURRICULA or is_import_path(method)):
        own = _own_section(curriculum_class(method, "ued.method"), "ued.method", method)
        if own is not None:
            _check("algorithm_settings" not in out or out["algorithm_settings"][0] != own[0],
                   "ued.method", f"{method} reads the section {own[0]!r}, which algorithm "
                   f"{algorithm} reads too: one of them must name it otherwise")
            out["method_settings"] = own
    return out


def _named_classes(data: Mapping) -> tuple[Any, Any]:
    """(`algorithm`, `ued.method`) of a parsed config mapping, None where it has none."""
    ued = data.get("ued")
    return data.get("algorithm"), ued.get("method") if isinstance(ued, Mapping) else None


def load_config(path: str | Path, overrides: Sequence[str] = ()) -> TrainConfig:
    """Read a YAML config file (a path, or a shipped config's name: `ued.config_files`) and
    apply `key=value` overrides."""
    path = resolve_config(path)
    data = apply_overrides(read_config_file(path), overrides, source=str(path))
    try:
        return config_from_dict(data, source=str(path))
    except ConfigError as err:
        raise _blame_override(err, str(path), overrides) from None


def _blame_override(err: ConfigError, source: str, overrides: Sequence[str]) -> ConfigError:
    """`err` (a value refused in the config as overridden) naming the override that set the
    value, not the file; unchanged when no override set it."""
    text = str(err)
    inner = text[len(source) + 2:] if text.startswith(f"{source}: ") else text
    paths = _field_paths()
    for item in reversed(overrides):  # the last override of a key is the one that counts
        key = item.partition("=")[0].strip()
        key = paths[key][0] if "." not in key and len(paths.get(key, [])) == 1 else key
        if inner.startswith(f"{key}: ") or inner.startswith(f"{key}["):
            shown = repr(item) if len(item) <= 100 else f"{item[:80]!r}..."
            return ConfigError(f"override {shown}: {inner}")
    return err


def check_levels_admitted(config: TrainConfig) -> None:
    """Refuse a new UED run whose level buffer may admit no level. A level enters the buffer
    only with a finite score, and it has one only where an episode ended within the rollout
    that scored it (`ued.scores`: -inf otherwise, which no slot's score is below). A rollout of
    `learner.num_steps` below `env.max_steps` ends an episode only where a team is eliminated
    first, so the buffer may stay empty for ever: Robust PLR, which trains on buffer levels
    alone, then trains nothing, and PLR and ACCEL are domain randomisation in effect. (Checked
    for new runs, not in `validate`: a run folder of such a config still reads.)"""
    if not config.ued.enabled or not curriculum_class(config.ued.method).uses_buffer:
        return
    _check(config.learner.num_steps >= config.env.max_steps, "learner.num_steps",
           f"{config.learner.num_steps} steps per rollout, below env.max_steps "
           f"({config.env.max_steps}): a level enters {config.ued.method}'s buffer only when "
           f"one of its episodes ends within the rollout that scores it, so the buffer may stay "
           f"empty (Robust PLR then trains nothing); set learner.num_steps >= env.max_steps, "
           f"or lower env.max_steps")


def check_ray_overrides(config: TrainConfig, overrides: Sequence[str]) -> None:
    """Refuse overrides of the `ray:` section for a run that is not on Ray (`ray.enabled`
    false): the local driver reads none of them, so they would be dropped without a word."""
    if config.ray.enabled:
        return
    paths = _field_paths()
    for item in overrides:
        key = item.partition("=")[0].strip()
        key = paths[key][0] if "." not in key and len(paths.get(key, [])) == 1 else key
        if key.startswith("ray.") and key != "ray.enabled":
            shown = repr(item) if len(item) <= 100 else f"{item[:80]!r}..."
            raise ConfigError(f"override {shown}: {key}: a setting of runs on Ray, and this run "
                              f"is not on Ray (ray.enabled is false): train on Ray (tabx train "
                              f"--ray, or ray.enabled=true), or drop {key}")


def read_config_file(path: str | Path) -> Any:
    """The parsed YAML of a config file (strict: `ued.yaml_reader`); ConfigError naming the
    file when it cannot be read or parsed."""
    path = Path(path)
    try:
        content = path.read_bytes()
    except OSError as err:
        raise ConfigError(f"{path}: cannot read the config ({err.strerror or err})") from None
    return read_yaml(content, str(path))


# A config class's field types, read once: typing evaluates the annotations' strings on every
# call, which made reading a sweep of hundreds of configs take seconds per hundred.
_type_hints = functools.cache(typing.get_type_hints)


@functools.cache
def _field_paths() -> dict[str, list[str]]:
    """Bare field name -> its dotted paths."""
    out: dict[str, list[str]] = {}
    hints = _type_hints(TrainConfig)
    for f in dataclasses.fields(TrainConfig):
        if not f.metadata.get("config_key", True):
            continue
        tp = hints[f.name]
        if dataclasses.is_dataclass(tp):
            for sub in dataclasses.fields(tp):
                out.setdefault(sub.name, []).append(f"{f.name}.{sub.name}")
        else:
            out.setdefault(f.name, []).append(f.name)
    return out


def _override_sections(data: Mapping, overrides: Sequence[str]) -> list[tuple[str, type]]:
    """The own sections (`_own_sections`) of the learner and the curriculum the overrides leave
    (the last `algorithm=` and `ued.method=` overrides, or the file's)."""
    paths = _field_paths()
    named = dict(zip(("algorithm", "ued.method"), _named_classes(data), strict=True))
    for item in overrides:
        key, sep, text = item.partition("=")
        key = key.strip()
        key = paths[key][0] if "." not in key and len(paths.get(key, [])) == 1 else key
        if sep and key in named:
            try:
                named[key] = yaml.safe_load(text)
            except yaml.YAMLError:
                named[key] = text
    found = []
    for args in ((named["algorithm"], None), (None, named["ued.method"])):  # each alone
        try:
            found += _own_sections(*args).values()
        except ConfigError:
            pass  # refused, naming the override, when the config is validated
    return list(dict.fromkeys(found))


def apply_overrides(data: Any, overrides: Sequence[str], source: str = "config") -> dict:
    """`data` (a parsed config mapping) with `key=value` overrides applied (values as YAML)."""
    if not isinstance(data, Mapping):
        raise ConfigError(f"{source}: expected a mapping of keys to values at the top level")
    out = {k: dict(v) if isinstance(v, Mapping) else v for k, v in data.items()}
    paths = _field_paths()
    sections = set(_sections())
    valid = sorted(p for ps in paths.values() for p in ps)
    for section, kind in _override_sections(data, overrides):  # own sections: their keys too
        sections.add(section)
        valid += [f"{section}.{f.name}" for f in dataclasses.fields(kind)]
    for item in overrides:
        key, sep, text = item.partition("=")
        key = key.strip()
        if not sep or not key:
            raise ConfigError(f"override {item!r}: expected KEY=VALUE, e.g. learner.lr=1e-3")
        try:
            value = yaml.safe_load(text) if text.strip() else ""
        except yaml.YAMLError:
            value = text
        if "." not in key:
            if key in sections:
                raise ConfigError(f"override {item!r}: {key} is a section; give "
                                  f"{key}.FIELD=VALUE")
            if key not in paths:
                close = difflib.get_close_matches(key, sorted(paths), n=1)
                hint = (f"; did you mean {close[0]!r} ({', '.join(paths[close[0]])})?"
                        if close else "")
                raise ConfigError(f"override {item!r}: unknown key {key!r}{hint}")
            if len(paths[key]) > 1:
                raise ConfigError(f"override {key!r} is ambiguous: use one of "
                                  f"{', '.join(paths[key])}")
            key = paths[key][0]
        parts = key.split(".")
        if len(parts) > 2 or (len(parts) == 2 and (parts[0] not in sections
                                                   or key not in valid)):
            # Named here, as the override's mistake, not the config file's.
            close = difflib.get_close_matches(key, valid, n=1)
            hint = f"; did you mean {close[0]!r}?" if close else ""
            raise ConfigError(f"override {item!r}: unknown key {key!r}{hint}")
        if len(parts) == 2:
            section = out.setdefault(parts[0], {})
            if not isinstance(section, dict):
                raise ConfigError(f"{source}: {parts[0]} must be a mapping")
            section[parts[1]] = value
        else:
            out[key] = value
    return out


__all__ = ["PPO_ONLY_FIELDS", "Q_LEARNER_SETTINGS", "TEAMS", "UED_SCORES",
           "ConfigError", "EnvSection", "LearnerConfig", "QLearningConfig", "RaySection",
           "RunSection", "TrainConfig", "UEDSection", "apply_overrides", "check_levels_admitted",
           "check_ray_overrides", "config_from_dict", "fill_run_name", "load_config",
           "read_config_file"]

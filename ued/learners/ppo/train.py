"""The PPO learner: the rollout and the jitted update (GAE and the loss terms are
`ued.learners.ppo.losses`, the data-parallel placement `ued.learners.ppo.devices`).

`PPOLearner` holds everything static (env sizes, hyperparameters, which team learns, who plays
the other team, the optimiser); `MAPPO` (ued.learners.mappo) and `IPPO` (ued.learners.ippo)
add their networks. The one entry point UED needs is

    train_state, metrics, rollout_stats = learner.update(train_state, levels, key)

jitted once: `levels` is a batch of `num_envs` levels (EnvParams with a leading axis), a jit
*argument*, so any batch of the same EnvConfig runs through the same compiled update. Each
update resets every env into its level, rolls out `num_steps` steps (a finished episode
restarts in the same level), computes GAE, and runs `update_epochs` epochs of
`num_minibatches` minibatches over envs (all agents of an env stay in one minibatch, so
sequences are whole and the recurrent state starts from zeros at the rollout start).

With several local devices (one per core on a CPU, see tabx/xla_flags.py) the envs are split
over them (`learner_devices`): each device plays and learns on its share inside a `shard_map`,
the loss means divide by counts over all devices and the gradients are summed (`lax.psum`),
so the parameters stay replicated; results come back on the first device.

Agents are the unit slots of the learner's team (ally slots 0..A-1, or the enemy slots after
them in the flipped setting); one network is shared by all of them, with a one-hot agent id
appended to the observation. What the masks mean:

- an agent is *valid* at step t when its unit is alive at the observation (dead and padded
  slots have IDLE as their only action): only valid agent steps enter the policy loss, the
  entropy, the advantage normalisation and (IPPO) the value loss;
- the hidden states are reset at every episode boundary (the reference resets them only on
  a unit's death, docs/differences.md); invalid actions get logits -1e10.

Rewards are the team reward `reward[:, team]`; a win is `info["won"][:, team]`. Episode
metrics (win rate, return, length, first-kill rate) count the episodes that ended during the
rollout; the first-kill rate is the fraction in which the first unit to die was an opponent's
(a simultaneous first death counts as no first kill).
"""

from __future__ import annotations

import functools
from typing import Any

import jax
import jax.numpy as jnp
import optax
from flax import struct

from tabx import constants as C
from tabx.controllers import Controller, controlled_actions, with_tiers
from tabx.env import TabxEnv
from tabx.jit_options import learner_jit
from tabx.params import EnvConfig, EnvParams
from tabx.state import EnvState
from ued.config import LearnerConfig
from ued.learners import distributed
from ued.learners.ppo.devices import ENVS, env_mesh, local_devices, on_devices, psum_flat
from ued.learners.ppo.losses import (
    gae,
    masked_logits,
    masked_mean,
    moments,
    policy_terms,
    ppo_policy_loss,
    team_mean,
    valid_count,
    value_loss,
)

START_KEY_STREAM = 0x5741  # folded into a rollout's first keys to draw its start positions


@struct.dataclass
class TrainState:
    """What an update changes: parameters, optimiser state, and the number of updates done."""

    params: Any
    opt_state: Any
    update: jax.Array  # int32 scalar


@struct.dataclass
class RolloutStats:
    """Per env and step (time-major, (num_steps, num_envs)), what UED scoring needs
    (ued.scores): the team value V(s_t), the GAE advantage, whether step t ended an episode,
    the team reward, and whether the team won the episode that ended at t. For IPPO the value
    and the advantage are the mean over the team's living agents."""

    values: jax.Array
    advantages: jax.Array
    dones: jax.Array
    rewards: jax.Array
    wins: jax.Array


@struct.dataclass
class Transition:
    """One rollout step of all envs (leading axes (E,) or (T, E) once stacked)."""

    obs: jax.Array  # (E, A, obs_size) the agents' observations (without the agent id)
    world: jax.Array  # (E, state_size) world state (MAPPO) or (E, 0)
    mask: jax.Array  # (E, A, 8) legal actions
    alive: jax.Array  # (E, A) the agent's unit is alive (valid agent step)
    action: jax.Array  # (E, A) int32
    logp: jax.Array  # (E, A) log-probability of the action under the rollout policy
    value: jax.Array  # (E,) MAPPO or (E, A) IPPO
    reward: jax.Array  # (E,) team reward
    done: jax.Array  # (E,) the step ended the episode
    won: jax.Array  # (E,) the team won the episode that ended




class PPOLearner:
    """Static description of a PPO learner for one EnvConfig; subclasses add the networks.

    `update` is jitted at construction (the learner itself is the static part); its train-state
    argument is donated, so do not reuse a train state after passing it to `update`."""

    name = "ppo"
    centralised = False  # the critic reads the world state (MAPPO)
    param_groups: tuple[str, ...] = ("net",)  # optimiser groups, each clipped on its own
    frozen_groups: tuple[str, ...] = ()  # parameter groups the PPO optimiser leaves alone

    # What the learner reads and supports, read from the class (config validation in
    # ued.config, the drivers, the commands) before anything is built; a subclass, built in
    # or given by import path (`algorithm: module:Class`), overrides what differs.
    family = "PPO learners"  # how config errors name its kind
    # Its own config section beside `learner` (None: `learner` only): a top-level config key
    # and the frozen dataclass of its fields, passed to the class as its fifth argument. A
    # section TrainConfig has no field for (a learner given by path) is read into
    # `TrainConfig.algorithm_settings`.
    settings_section: str | None = None
    settings_type: type | None = None
    ppo_settings = True  # reads the `learner` fields only PPO reads (ued.config.PPO_ONLY_FIELDS)
    # "section.field" settings only this learner (and its subclasses) reads: every other
    # learner must leave them at their defaults, or the config is refused with `refusal`
    # (formatted with `algorithm`).
    own_settings: tuple[str, ...] = ()
    refusal = ""
    value_head = True  # has a value head (run.value_error_every, tabx analyse value-error)
    seeds = True  # several seeds train in one vmapped program (`seeds`)
    curricula = True  # the UED curricula can train it (ued.method)
    devices = True  # data parallel over several devices (learner.num_devices, ray.learners)

    @classmethod
    def validate_settings(cls, settings: Any, learner: LearnerConfig) -> None:
        """Refuse values of its own settings section (`settings_type`) that cannot work with
        the `learner` section, by a ConfigError naming the field; the section's field types
        are checked when the config is read. Nothing to check here."""

    def __init__(self, env_config: EnvConfig, ppo: LearnerConfig | None = None,
                 team: str | int = "ally", opponent: str | Controller = "heuristic:medium"):
        self.env_config = env_config
        self.ppo = ppo if ppo is not None else LearnerConfig()
        self.team = team if isinstance(team, int) else ("ally", "enemy").index(team)
        self.opponent = opponent if isinstance(opponent, Controller) else Controller.parse(
            opponent)
        if self.opponent.kind == "external":
            raise ValueError("the opponent of a learner must be heuristic, random or idle")
        self.controllers = ((Controller("external"), self.opponent) if self.team == C.ALLY
                            else (self.opponent, Controller("external")))
        self.env = TabxEnv(env_config)
        if self.team == C.ALLY:
            self.slots = slice(0, env_config.max_allies)
        else:
            self.slots = slice(env_config.max_allies, env_config.num_units)
        self.num_agents = self.slots.stop - self.slots.start
        self.obs_dim = env_config.obs_size + self.num_agents  # + one-hot agent id
        self.state_dim = env_config.state_size
        self.matmul_dtype = jnp.dtype(self.ppo.matmul_dtype)  # the networks' (networks.py)
        self.optimizer = self._make_optimizer()
        self._update_jit = self.jit(self._update, donate_argnums=0)
        self._score_jit = None
        self._init_jit = None
        self._update_seeds_jit = None

    def jit(self, fn: Any, **jit_kwargs: Any) -> Any:
        """`jax.jit` with the compiler options for this learner's networks
        (`tabx.jit_options.learner_jit`): use it for programs that run them."""
        return learner_jit(fn, self.ppo.matmul_dtype, **jit_kwargs)

    # --- to be provided by MAPPO / IPPO ------------------------------------------------------

    def init_params(self, key: jax.Array) -> Any:
        raise NotImplementedError

    def initial_hidden(self, num_envs: int) -> Any:
        raise NotImplementedError

    def act_step(self, params: Any, x: jax.Array, world: jax.Array, hidden: Any
                 ) -> tuple[Any, jax.Array, jax.Array]:
        """One step: (new hidden, logits (E, A, 8), value (E,) or (E, A))."""
        raise NotImplementedError

    def act(self, params: Any, keys: jax.Array, x: jax.Array, world: jax.Array,
            mask: jax.Array, hidden: Any) -> tuple[Any, jax.Array, jax.Array, jax.Array]:
        """The rollout's choice at one step, one key per env: (new hidden, actions (E, A),
        their log-probabilities, value). PPO samples its masked policy; the Q-learners
        (ued.learners.qlearning) act epsilon-greedily."""
        hidden, logits, value = self.act_step(params, x, world, hidden)
        logits = masked_logits(logits, mask)
        action = jax.vmap(jax.random.categorical)(keys, logits).astype(jnp.int32)
        logp = jnp.take_along_axis(jax.nn.log_softmax(logits), action[..., None], -1)[..., 0]
        return hidden, action, logp, value

    def policy_step(self, params: Any, x: jax.Array, hidden: Any) -> tuple[Any, jax.Array]:
        """The actor alone (evaluation): (new hidden, logits (E, A, 8))."""
        raise NotImplementedError

    def evaluate_sequence(self, params: Any, x: jax.Array, world: jax.Array, starts: jax.Array
                          ) -> tuple[jax.Array, jax.Array]:
        """Whole sequences from zero hidden states: (logits (T, B, A, 8), values)."""
        raise NotImplementedError

    def value_terms(self, values: jax.Array, last_value: jax.Array, alive: jax.Array,
                    last_alive: jax.Array) -> tuple[jax.Array, jax.Array]:
        """Values used by GAE (and their bootstrap); see IPPO for dead agents."""
        return values, last_value

    def returns(self, params: Any, traj: Transition, last: Transition
                ) -> tuple[jax.Array, jax.Array, jax.Array, dict[str, jax.Array]]:
        """GAE of a rollout: (values as GAE saw them, advantages, value targets, extra
        (T, E, ...) batch entries for `optimise`). MAPPO: one value and advantage per env;
        IPPO: per agent, the team reward and done for every agent."""
        values, last_value = self.value_terms(traj.value, last.value, traj.alive, last.alive)
        dones, rewards = traj.done, traj.reward
        if values.ndim == 3:  # per-agent values: the team reward and done for every agent
            dones, rewards = dones[..., None], rewards[..., None]
        adv, targets = gae(rewards, values, dones, last_value, self.ppo.gamma,
                           self.ppo.gae_lambda)
        return values, adv, targets, {}

    def critic_loss(self, values: jax.Array, batch: dict[str, jax.Array],
                    valid: jax.Array, count: jax.Array, axis_name: str | None
                    ) -> tuple[jax.Array, dict[str, jax.Array]]:
        """The value loss of a minibatch (before `vf_coef`) and its metrics. `valid`,
        `count`: the valid agent steps and their count over all shards."""
        ppo = self.ppo
        if values.ndim == valid.ndim:
            value_valid, value_count = valid, count
        else:  # one value per env (MAPPO): every step of the env
            value_valid = jnp.ones(values.shape, bool)
            # Known without counting: the shards' sizes (psum of a constant is the axis size).
            shards = 1 if axis_name is None else jax.lax.psum(1, axis_name)
            value_count = jnp.asarray(values.size * shards, jnp.int32)
        v_loss = value_loss(values, batch["value"], batch["targets"], value_valid,
                            ppo.clip_eps, ppo.clip_value, value_count)
        return v_loss, {"loss/value": v_loss}

    def team_value(self, value: jax.Array, alive: jax.Array) -> jax.Array:
        """The team's value V(s) per env from `act_step`'s value: MAPPO's own, the mean over
        living agents for per-agent values (IPPO), as in `RolloutStats`."""
        return value if value.ndim == 1 else team_mean(value, alive)

    def label_params(self, params: Any) -> Any:
        """Optimiser labels (one of `param_groups` per leaf): each group has its own gradient
        clipping and Adam state, as the reference's separate actor and critic train states."""
        return jax.tree.map(lambda _: "net", params)

    # --- shared machinery --------------------------------------------------------------------

    @property
    def num_updates(self) -> int:
        return self.ppo.num_updates

    def _make_optimizer(self) -> optax.GradientTransformation:
        ppo = self.ppo
        steps_per_update = ppo.update_epochs * ppo.num_minibatches

        def schedule(count: jax.Array) -> jax.Array:
            # Linear decay to 0 over the run (the reference's formula); 0 past the end, never
            # negative, should a caller (a curriculum) run more updates than planned.
            frac = 1.0 - (count // steps_per_update) / self.num_updates
            return ppo.lr * jnp.maximum(frac, 0.0)

        lr = schedule if ppo.anneal_lr else ppo.lr

        def tx() -> optax.GradientTransformation:
            return optax.chain(optax.clip_by_global_norm(ppo.max_grad_norm),
                               optax.adam(lr, eps=ppo.adam_eps))

        transforms = {group: tx() for group in self.param_groups}
        transforms.update({group: optax.set_to_zero() for group in self.frozen_groups})
        return optax.multi_transform(transforms, self.label_params)

    def init(self, key: jax.Array) -> TrainState:
        """A fresh train state. Jitted: one compilation (1.8 s for MAPPO, and cacheable)
        instead of some sixty small ones op by op (2.9 s); the same values bit for bit."""
        if self._init_jit is None:
            self._init_jit = self.jit(self._init)
        return self._init_jit(key)

    def _init(self, key: jax.Array) -> TrainState:
        params = self.init_params(key)
        return TrainState(params=params, opt_state=self.optimizer.init(params),
                          update=jnp.zeros((), jnp.int32))

    def prepare_levels(self, levels: EnvParams) -> EnvParams:
        """The levels with the opponent's tier written in (a no-op for a bare `heuristic`)."""
        return with_tiers(levels, self.controllers)

    def agent_inputs(self, obs: jax.Array) -> jax.Array:
        """(..., A, obs_size) -> (..., A, obs_size + A): the one-hot agent id appended."""
        ids = jnp.broadcast_to(jnp.eye(self.num_agents, dtype=obs.dtype),
                               (*obs.shape[:-1], self.num_agents))
        return jnp.concatenate([obs, ids], axis=-1)

    def _world(self, states: EnvState, levels: EnvParams) -> jax.Array:
        if self.centralised:
            return jax.vmap(self.env.world_state)(states, levels)
        return jnp.zeros((states.step.shape[0], 0), jnp.float32)

    def _join_actions(self, env_keys: jax.Array, states: EnvState, levels: EnvParams,
                      learner_actions: jax.Array) -> tuple[jax.Array, EnvState]:
        num_envs = learner_actions.shape[0]
        external = jnp.zeros((num_envs, self.env_config.num_units), jnp.int32)
        external = external.at[:, self.slots].set(learner_actions)
        controllers = self.controllers
        return jax.vmap(lambda k, s, lv, e: controlled_actions(k, s, lv, e, controllers))(
            env_keys, states, levels, external)

    @staticmethod
    def rollout_keys(key: jax.Array, num_steps: int, num_envs: int) -> jax.Array:
        """(num_steps + 1, num_envs) keys: one per env and scan step of `rollout`. Each env
        draws only from its own keys, so a rollout does not depend on how its envs are split
        over devices."""
        return jax.random.split(key, (num_steps + 1) * num_envs).reshape(num_steps + 1,
                                                                          num_envs)

    def rollout(self, params: Any, levels: EnvParams, key: jax.Array,
                num_steps: int | None = None
                ) -> tuple[Transition, dict[str, jax.Array], Transition]:
        """Reset every env into its level and play `num_steps` steps (default: the PPO
        config's rollout length).

        Returns (transitions (T, E, ...), per-step episode records (T, E), the bootstrap: the
        observation, world state, value and alive agents of the state after the last step, as
        a Transition (E, ...) whose action, reward and done are not used).

        Each scan step observes the state it acts on (the observation is a function of the
        state; the auto-reset's start states are passed in, so the env step computes none).
        The scan runs one step more than the rollout: the first half of that step, the
        observation and network pass of the state after the last step, is the bootstrap; its
        env step is discarded. The program thus holds one copy of the observation, world
        state and network step instead of two, which compiles faster (1/T more env steps)."""
        num_envs = levels.reward_mode.shape[0]
        num_steps = self.ppo.num_steps if num_steps is None else num_steps
        return self.rollout_with_keys(params, levels,
                                      self.rollout_keys(key, num_steps, num_envs))

    def rollout_with_keys(self, params: Any, levels: EnvParams, keys: jax.Array
                          ) -> tuple[Transition, dict[str, jax.Array], Transition]:
        """`rollout` with its keys given: (num_steps + 1, num_envs) from `rollout_keys` (or
        the envs' columns of them: a data-parallel shard plays its own envs)."""
        env, team = self.env, self.team
        num_envs = levels.reward_mode.shape[0]
        # Each rollout draws its levels' randomised starts (tabx.starts; off by default, when
        # the start is the level's own) from a stream of its first keys no step consumes.
        start_keys = jax.vmap(jax.random.fold_in, (0, None))(keys[0], START_KEY_STREAM)
        states = jax.vmap(env.start_state)(start_keys, levels)
        start_states = states
        observe = jax.vmap(env.observe)
        zeros_f = jnp.zeros(num_envs, jnp.float32)
        zeros_i = jnp.zeros(num_envs, jnp.int32)
        carry = (states, self.initial_hidden(num_envs), zeros_f, zeros_i, zeros_i)

        def body(carry, env_keys):
            states, hidden, ep_return, ep_length, first = carry
            k_act, k_other = jnp.unstack(jax.vmap(jax.random.split)(env_keys), axis=1)
            ob = observe(states, levels)[:, self.slots]
            mask = jax.vmap(env.action_mask)(states, levels)[:, self.slots]
            world = self._world(states, levels)
            hidden, action, logp, value = self.act(params, k_act, self.agent_inputs(ob), world,
                                                   mask, hidden)
            actions, states_h = self._join_actions(k_other, states, levels, action)
            _, next_states, reward, done, info = jax.vmap(env.step_autoreset)(
                env_keys, states_h, actions, levels, start_states)
            hidden = jax.tree.map(
                lambda h: jnp.where(done.reshape(done.shape + (1,) * (h.ndim - 1)), 0.0, h),
                hidden)
            r = reward[:, team]
            won = info["won"][:, team] & done
            # Episode records: return, length, and who lost a unit first.
            dead = info["dead_units"]
            ep_return = ep_return + r
            ep_length = ep_length + 1
            someone_died = (dead[:, 0] + dead[:, 1]) > 0
            we_killed_first = (dead[:, 1 - team] > 0) & (dead[:, team] == 0)
            first = jnp.where((first == 0) & someone_died,
                              jnp.where(we_killed_first, 1, 2), first)
            record = {"done": done, "won": won, "return": jnp.where(done, ep_return, 0.0),
                      "length": jnp.where(done, ep_length, 0),
                      "first_kill": done & (first == 1)}
            transition = Transition(obs=ob, world=world, mask=mask,
                                    alive=states.alive[:, self.slots], action=action, logp=logp,
                                    value=value, reward=r, done=done, won=won)
            carry = (next_states, hidden, jnp.where(done, 0.0, ep_return),
                     jnp.where(done, 0, ep_length), jnp.where(done, 0, first))
            return carry, (transition, record)

        _, (traj, records) = jax.lax.scan(body, carry, keys)
        last = jax.tree.map(lambda x: x[-1], traj)
        traj, records = jax.tree.map(lambda x: x[:-1], (traj, records))
        return traj, records, last

    def _loss(self, params: Any, batch: dict[str, jax.Array], axis_name: str | None = None
              ) -> tuple[jax.Array, dict[str, jax.Array]]:
        """The PPO loss of a minibatch. On a data-parallel shard (`axis_name`), every mean
        divides by the count over all shards, so the shards' losses (and gradients) sum to
        those of the whole minibatch."""
        ppo = self.ppo
        logits, values = self.evaluate_sequence(
            params, self.agent_inputs(batch["obs"]), batch["world"], batch["starts"])
        valid = batch["alive"]
        logp, entropy = policy_terms(logits, batch["mask"], batch["action"])
        adv = batch["adv"]
        if adv.ndim < valid.ndim:  # one advantage per env (MAPPO): every agent of the env
            adv = jnp.broadcast_to(adv[..., None], valid.shape)
        if ppo.normalize_advantages:  # the valid count comes with the moments
            count, mean, var = moments(adv, valid, axis_name)
            adv = (adv - mean) / (jnp.sqrt(var) + 1e-8)
        else:
            count = valid_count(valid, axis_name)
        pg_loss, approx_kl, clip_frac = ppo_policy_loss(logp, batch["logp"], adv, valid,
                                                        ppo.clip_eps, count)
        v_loss, v_metrics = self.critic_loss(values, batch, valid, count, axis_name)
        ent = masked_mean(entropy, valid, count)
        total = pg_loss + ppo.vf_coef * v_loss - ppo.ent_coef * ent
        return total, {"loss/total": total, "loss/policy": pg_loss, **v_metrics,
                       "loss/entropy": ent, "loss/approx_kl": approx_kl,
                       "loss/clip_frac": clip_frac}

    def learner_devices(self, num_envs: int, minibatches: int | None = None,
                        strict: bool = True) -> tuple[jax.Device, ...]:
        """The local devices `num_envs` envs are split over (data parallel): `ppo.num_devices`
        of them, or with 0 the most that split the envs into equal shares of each of
        `minibatches` (default: the config's) minibatches. Not `strict` (scoring batches of
        any size): at most `ppo.num_devices`, as many as divide the envs evenly. On CPU,
        the `tabx` command makes one device per core (tabx/xla_flags.py). In a learner group
        (`ued.learners.distributed`) an update's devices are those of every process, each
        choosing for its share of the envs; scoring stays on this process's devices."""
        if minibatches is None:
            minibatches = self.ppo.num_minibatches
        processes = jax.process_count()
        if strict and processes > 1:  # a learner group: the same share on every process
            if num_envs % processes:
                raise ValueError(f"{num_envs} envs do not split over {processes} learner "
                                 f"processes")
            local = self._local_devices(num_envs // processes, minibatches, strict)
            return distributed.group_devices(len(local))
        return self._local_devices(num_envs, minibatches, strict)

    def _local_devices(self, num_envs: int, minibatches: int, strict: bool
                       ) -> tuple[jax.Device, ...]:
        wanted = self.ppo.num_devices
        available = local_devices(wanted if strict else 0)
        if wanted and strict:
            if num_envs % (wanted * minibatches):
                raise ValueError(f"learner.num_devices: {num_envs} envs do not split into "
                                 f"{wanted} devices x {minibatches} minibatches")
            return tuple(available[:wanted])
        most = min(wanted, len(available)) if wanted else len(available)
        count = max(d for d in range(1, most + 1) if num_envs % (d * minibatches) == 0)
        return tuple(available[:count])

    def update(self, train_state: TrainState, levels: EnvParams, key: jax.Array
               ) -> tuple[TrainState, dict[str, jax.Array], RolloutStats]:
        """One PPO update on `levels` (a batch of `num_envs` levels): (train state, metrics,
        rollout stats). Jitted once per learner; other levels never recompile it.

        Split over several devices (`learner_devices`), the arguments are placed on them and
        the results come back on the first one, where the caller's arrays live; on one device
        the train state is donated (do not reuse a train state passed in)."""
        num_envs = levels.reward_mode.shape[0]
        if num_envs % self.ppo.num_minibatches:
            raise ValueError(f"{num_envs} envs do not split into {self.ppo.num_minibatches} "
                             f"minibatches")
        return on_devices(self._update_jit, self.learner_devices(num_envs), train_state,
                           levels, key)

    def init_seeds(self, keys: jax.Array) -> TrainState:
        """Fresh train states of several seeds, stacked on a leading seed axis: entry i is
        `init(keys[i])`, bit for bit. Each seed runs `init`'s program in turn (initialisation
        happens once a run): a vmapped initialisation would batch the orthogonal
        initialisers' QR decompositions, and on a CPU with two devices that batched program
        was seen to hang for MAPPO+RND's networks."""
        states = [self.init(key) for key in keys]
        return jax.tree.map(lambda *leaves: jnp.stack(leaves), *states)

    def update_seeds(self, train_states: TrainState, levels: EnvParams, keys: jax.Array
                     ) -> tuple[TrainState, dict[str, jax.Array], RolloutStats]:
        """`update` of several seeds at once: `train_states` and `keys` carry a leading seed
        axis (`init_seeds`, one key per seed), the levels are shared; the results carry the
        seed axis too (metrics: one value per seed). One compiled program, `update` vmapped
        over the seeds (each seed's rollout, GAE and minibatch epochs as `update` does them,
        the seeds side by side in every array op), jitted once per learner and seed count.
        Entry i equals `update(train_states[i], levels, keys[i])` up to float rounding
        (batched matrix products may sum in another order). Split over devices and donated
        as `update`."""
        num_envs = levels.reward_mode.shape[0]
        if num_envs % self.ppo.num_minibatches:
            raise ValueError(f"{num_envs} envs do not split into {self.ppo.num_minibatches} "
                             f"minibatches")
        if self._update_seeds_jit is None:
            self._update_seeds_jit = self.jit(jax.vmap(self._update, in_axes=(0, None, 0)),
                                              donate_argnums=0)
        return on_devices(self._update_seeds_jit, self.learner_devices(num_envs),
                           train_states, levels, keys)

    def _update(self, train_state: TrainState, levels: EnvParams, key: jax.Array
                ) -> tuple[TrainState, dict[str, jax.Array], RolloutStats]:
        ppo = self.ppo
        levels = self.prepare_levels(levels)
        num_envs = levels.reward_mode.shape[0]
        k_rollout, k_train = jax.random.split(key)
        keys = self.rollout_keys(k_rollout, ppo.num_steps, num_envs)
        params, opt_state = train_state.params, train_state.opt_state
        devices = self.learner_devices(num_envs)
        if len(devices) == 1:
            out = self._train(params, opt_state, levels, keys, k_train)
        else:
            # Data parallel: each device plays and learns on its share of the envs; the
            # gradient of a minibatch is summed over the devices (`_train`), so every device
            # applies the same update and the parameters stay replicated.
            P = jax.sharding.PartitionSpec
            by_env, by_time_env = P(ENVS), P(None, ENVS)
            out = jax.shard_map(
                functools.partial(self._train, axis_name=ENVS),
                mesh=env_mesh(devices),
                in_specs=(P(), P(), by_env, by_time_env, P()),
                out_specs=(P(), P(), P(), by_time_env, by_time_env), check_vma=False,
            )(params, opt_state, levels, keys, k_train)
        params, opt_state, aux, records, stats = out
        metrics = {k: jnp.mean(v) for k, v in aux.items()}
        metrics.update(episode_metrics(records))
        metrics["value/mean"] = jnp.mean(stats.values)
        new_state = TrainState(params=params, opt_state=opt_state,
                               update=train_state.update + 1)
        return new_state, metrics, stats

    def _train(self, params: Any, opt_state: Any, levels: EnvParams, keys: jax.Array,
               key: jax.Array, axis_name: str | None = None) -> tuple[Any, ...]:
        """Rollout, GAE and the epochs of minibatch updates on (a shard of) the envs:
        (params, opt_state, per-minibatch losses, episode records, rollout stats). With
        `axis_name`, one data-parallel shard: minibatches take the same share of every
        shard's envs, and gradients and losses are summed over the shards."""
        num_envs = levels.reward_mode.shape[0]
        traj, records, last = self.rollout_with_keys(params, levels, keys)
        values, adv, targets, extras = self.returns(params, traj, last)
        stats = self._stats(traj, values, adv)
        starts = jnp.concatenate([jnp.ones((1, num_envs), bool), traj.done[:-1]], axis=0)
        batch = {"obs": traj.obs, "world": traj.world, "mask": traj.mask, "alive": traj.alive,
                 "action": traj.action, "logp": traj.logp, "value": traj.value,
                 "adv": adv, "targets": targets, "starts": starts, **extras}
        params, opt_state, aux = self.optimise(params, opt_state, batch, key, axis_name)
        return params, opt_state, aux, records, stats

    def optimise(self, params: Any, opt_state: Any, batch: dict[str, jax.Array],
                 key: jax.Array, axis_name: str | None = None
                 ) -> tuple[Any, Any, dict[str, jax.Array]]:
        """The PPO epochs over a rollout's `batch` (time-major, envs on axis 1): (params,
        opt_state, per-minibatch losses (epochs, minibatches))."""
        return self.minibatch_epochs(functools.partial(self._loss, axis_name=axis_name),
                                     self.optimizer, params, opt_state, batch, key,
                                     self.ppo.update_epochs, axis_name)

    def minibatch_epochs(self, loss_fn: Any, optimizer: optax.GradientTransformation,
                         params: Any, opt_state: Any, batch: dict[str, jax.Array],
                         key: jax.Array, epochs: int, axis_name: str | None = None
                         ) -> tuple[Any, Any, dict[str, jax.Array]]:
        """`epochs` passes of `num_minibatches` gradient steps of `loss_fn(params, minibatch)
        -> (loss, metrics)` over `batch`, split by env (axis 1, all steps of an env in one
        minibatch). On a data-parallel shard (`axis_name`) the gradients and metrics are
        summed over the shards. Returns (params, opt_state, metrics (epochs, minibatches)),
        the metrics with `grad_norm`."""
        num_envs = batch["starts"].shape[1]
        grad_fn = jax.value_and_grad(loss_fn, has_aux=True)
        total = (lambda x: x) if axis_name is None else functools.partial(psum_flat,
                                                                           axis_name=axis_name)
        minibatches = self.ppo.num_minibatches
        if axis_name is not None:  # each shard its own order of its envs
            key = jax.random.fold_in(key, jax.lax.axis_index(axis_name))

        def epoch(carry, k):
            def minibatch(carry, idx):
                params, opt_state = carry
                mb = jax.tree.map(lambda x: jnp.take(x, idx, axis=1), batch)
                (_, aux), grads = grad_fn(params, mb)
                aux, grads = total((aux, grads))
                aux["grad_norm"] = optax.tree.norm(grads)
                updates, opt_state = optimizer.update(grads, opt_state, params)
                return (optax.apply_updates(params, updates), opt_state), aux

            order = jax.random.permutation(k, num_envs).reshape(minibatches,
                                                                 num_envs // minibatches)
            return jax.lax.scan(minibatch, carry, order)

        (params, opt_state), aux = jax.lax.scan(
            epoch, (params, opt_state), jax.random.split(key, epochs))
        return params, opt_state, aux

    @staticmethod
    def _stats(traj: Transition, values: jax.Array, adv: jax.Array) -> RolloutStats:
        team_values = values if values.ndim == 2 else team_mean(values, traj.alive)
        team_adv = adv if adv.ndim == 2 else team_mean(adv, traj.alive)
        return RolloutStats(values=team_values, advantages=team_adv, dones=traj.done,
                            rewards=traj.reward, wins=traj.won)

    def _score(self, params: Any, levels: EnvParams, key: jax.Array, num_steps: int
               ) -> tuple[dict[str, jax.Array], RolloutStats]:
        levels = self.prepare_levels(levels)
        num_envs = levels.reward_mode.shape[0]
        keys = self.rollout_keys(key, num_steps, num_envs)
        devices = self.learner_devices(num_envs, minibatches=1, strict=False)
        if len(devices) == 1:
            records, stats = self._score_envs(params, levels, keys)
        else:  # each device plays its share of the envs
            P = jax.sharding.PartitionSpec
            records, stats = jax.shard_map(
                self._score_envs, mesh=env_mesh(devices),
                in_specs=(P(), P(ENVS), P(None, ENVS)),
                out_specs=(P(None, ENVS), P(None, ENVS)), check_vma=False,
            )(params, levels, keys)
        return episode_metrics(records), stats

    def _score_envs(self, params: Any, levels: EnvParams, keys: jax.Array
                    ) -> tuple[dict[str, jax.Array], RolloutStats]:
        traj, records, last = self.rollout_with_keys(params, levels, keys)
        values, adv, _, _ = self.returns(params, traj, last)
        return records, self._stats(traj, values, adv)

    def score(self, params: Any, levels: EnvParams, key: jax.Array,
              num_steps: int | None = None) -> tuple[dict[str, jax.Array], RolloutStats]:
        """Roll the policy out on `levels` like `update` does, without learning: (episode
        metrics, RolloutStats) for scoring new or mutated levels (Robust PLR, ACCEL, SFL).
        `num_steps` (default: the PPO rollout length) is static: one compile per length.
        The envs are split over devices as in `update` (any count that divides them)."""
        num_steps = self.ppo.num_steps if num_steps is None else int(num_steps)
        if num_steps < 1:
            raise ValueError(f"num_steps must be >= 1, got {num_steps}")
        if self._score_jit is None:
            self._score_jit = self.jit(self._score, static_argnums=3)
        devices = self.learner_devices(levels.reward_mode.shape[0], minibatches=1,
                                       strict=False)
        return on_devices(lambda p, lv, k: self._score_jit(p, lv, k, num_steps), devices,
                           params, levels, key)


def episode_metrics(records: dict[str, jax.Array]) -> dict[str, jax.Array]:
    """Means over the episodes that ended in the rollout (NaN when none did)."""
    done = records["done"]
    count = jnp.sum(done).astype(jnp.float32)
    per = lambda x: jnp.where(count > 0, jnp.sum(x.astype(jnp.float32)) / jnp.maximum(count, 1),
                              jnp.nan)
    return {"episode/count": count, "episode/win_rate": per(records["won"]),
            "episode/return": per(records["return"]), "episode/length": per(records["length"]),
            "episode/first_kill_rate": per(records["first_kill"])}


@functools.lru_cache(maxsize=16)
def _cached(cls: type, env_config: EnvConfig, ppo: LearnerConfig, team: int,
            opponent: Controller, *settings: Any) -> PPOLearner:
    return cls(env_config, ppo, team, opponent, *settings)


def cached_learner(cls: type, env_config: EnvConfig, ppo: LearnerConfig, team: str | int,
                   opponent: str | Controller, *settings: Any) -> PPOLearner:
    """One learner (and so one compiled update) per distinct static setting in a process;
    `settings`: the learner's own config section, for a learner that has one (a Q-learner's
    QLearningConfig)."""
    team = team if isinstance(team, int) else ("ally", "enemy").index(team)
    opponent = opponent if isinstance(opponent, Controller) else Controller.parse(opponent)
    return _cached(cls, env_config, ppo, team, opponent, *settings)


__all__ = ["START_KEY_STREAM", "PPOLearner", "RolloutStats", "TrainState", "Transition",
           "cached_learner", "episode_metrics"]

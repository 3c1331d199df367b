"""Heuristic tier tournaments: tier-vs-tier tables (the `tabx eval heuristics` command is
tabx_ued.heuristics).

Row tier plays the allies, column tier the enemies, both with the scripted policy; each cell is
`episodes` full episodes on the scenario. The tiers and the behaviour profile are data in the
level, so the whole table runs through one compiled function: each row is one batch of
(columns x episodes) envs stepped until every episode has ended (the episode player,
`tabx.episodes.play`, with `until_done`, so short battles finish early).

Per matchup: the allies' win rate with a 95 % Wilson interval, the fraction of time-outs, the
mean episode length, the mean team health ratios at the end (the level's formula), the mean
step of the first death and which team suffered it, and how often each team was eliminated.
A draw (time limit with equal team health ratios) counts as an enemy win, as in the reward's
tie-break; the table reports ally wins, so the diagonal of a mirror scenario sits a little
below one half when draws happen.
"""

from __future__ import annotations

import functools
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np

from tabx import constants as C
from tabx.controllers import Controller
from tabx.env import TabxEnv
from tabx.episodes import LOOP_KEYS, play
from tabx.intervals import wilson
from tabx.jit_options import simulator_jit
from tabx.params import HEURISTIC_TIERS, EnvConfig, EnvParams, heuristic_params, stack_levels
from tabx.profiles import DEFAULT_PROFILE, with_profile

BOTH_HEURISTIC = (Controller("heuristic"), Controller("heuristic"))
# Per-episode outcomes a batch run returns, in order (`make_batch_runner`).
OUTCOMES = ("ally_won", "length", "ally_return", "timeout", "hp_ratio", "first_death",
            "first_dead", "eliminated")


@dataclass
class TierTable:
    """Results per (ally tier, enemy tier), each array (A, E) or (A, E, 2) per team."""

    ally_tiers: list[str]
    enemy_tiers: list[str]
    episodes: int
    win_rate: np.ndarray  # allies' wins / episodes
    length: np.ndarray  # mean episode length (steps)
    ally_return: np.ndarray  # mean undiscounted ally return
    timeout: np.ndarray  # fraction of episodes ended by the time limit
    hp_ratio: np.ndarray  # (A, E, 2) mean team health ratio at the end
    first_death: np.ndarray  # mean step of the first death (NaN: nobody died)
    first_dead: np.ndarray  # (A, E, 2) fraction of episodes whose first death was the
    #                         team's (both teams' on a simultaneous first death)
    eliminated: np.ndarray  # (A, E, 2) fraction of episodes the team was wiped out
    profile: str = DEFAULT_PROFILE

    def win_interval(self) -> np.ndarray:
        """(A, E, 2) low and high ends of each win rate's 95 % Wilson interval."""
        wins = np.rint(self.win_rate * self.episodes).astype(int)
        return np.array([[wilson(int(w), self.episodes)[1:] for w in row] for row in wins])

    def to_json(self) -> dict:
        out = dict(ally_tiers=self.ally_tiers, enemy_tiers=self.enemy_tiers,
                   episodes=self.episodes, profile=self.profile)
        out["win_rate"] = self.win_rate.tolist()
        out["win_interval"] = self.win_interval().tolist()
        for name in ("timeout", "length", "ally_return", "hp_ratio", "first_death",
                     "first_dead", "eliminated"):
            value = np.asarray(getattr(self, name), np.float64)  # NaN (nobody died) as null
            out[name] = np.where(np.isnan(value), None, value).tolist()
        return out

    def format(self) -> str:
        """The win-rate matrix, then one line per matchup with the other outcomes."""
        width = max(18, *(len(t) + 2 for t in self.enemy_tiers))
        lines = ["ally \\ enemy".ljust(12) + "".join(t.rjust(width) for t in self.enemy_tiers)]
        ci = self.win_interval()
        for i, tier in enumerate(self.ally_tiers):
            cells = [f"{self.win_rate[i, j]:.2f} [{ci[i, j, 0]:.2f}, {ci[i, j, 1]:.2f}]"
                     .rjust(width) for j in range(len(self.enemy_tiers))]
            lines.append(tier.ljust(12) + "".join(cells))
        lines += ["", "ally      enemy      win   timeout  length  hp ally  hp enemy  "
                      "1st death  ally 1st  ally elim  enemy elim"]
        for i, ally in enumerate(self.ally_tiers):
            for j, enemy in enumerate(self.enemy_tiers):
                death = ("-" if np.isnan(self.first_death[i, j])
                         else f"{self.first_death[i, j]:.0f}")
                lines.append(
                    f"{ally:9s} {enemy:9s} {self.win_rate[i, j]:5.2f} "
                    f"{self.timeout[i, j]:8.2f} {self.length[i, j]:7.0f} "
                    f"{self.hp_ratio[i, j, 0]:8.2f} {self.hp_ratio[i, j, 1]:9.2f} "
                    f"{death:>10s} {self.first_dead[i, j, 0]:9.2f} "
                    f"{self.eliminated[i, j, 0]:10.2f} {self.eliminated[i, j, 1]:11.2f}")
        return "\n".join(lines)


@functools.lru_cache(maxsize=8)
def make_batch_runner(config: EnvConfig):
    """A jitted `run(levels, keys) -> dict of per-episode OUTCOMES` over a batch of envs, each
    playing one episode with the heuristic on both teams until all have ended (the episode
    player, `tabx.episodes.play`, with `until_done`)."""
    env = TabxEnv(config)

    def dead_per_team(states, levels):
        u = levels.units
        dead = u.active & ~states.alive  # (B, N)
        return jnp.stack([jnp.sum(dead & (u.team == t), -1) for t in range(C.NUM_TEAMS)], -1)

    def first_death(tracked, states, levels):
        """(step of the first death (0: none yet), (B, 2) whose it was), updated after a step."""
        step, whose = tracked
        dead = dead_per_team(states, levels) > 0  # (B, 2)
        new = (step == 0) & jnp.any(dead, -1)
        return jnp.where(new, states.step, step), jnp.where(new[:, None], dead, whose)

    def run(levels: EnvParams, keys: jax.Array):
        batch = keys.shape[0]
        tracked = (jnp.zeros(batch, jnp.int32), jnp.zeros((batch, C.NUM_TEAMS), bool))
        out = play(env, levels, keys[0], config.max_steps, BOTH_HEURISTIC, keys=LOOP_KEYS,
                   start=jax.vmap(env.initial_state)(levels), until_done=True,
                   track=(tracked, first_death))
        states, (death_step, first_dead) = out.states, out.tracked
        members = jnp.stack([jnp.sum(levels.units.active & (levels.units.team == t), -1)
                             for t in range(C.NUM_TEAMS)], -1)
        eliminated = dead_per_team(states, levels) >= members
        timeout = states.done & ~jnp.any(eliminated, -1)
        return dict(ally_won=states.won[:, C.ALLY], length=states.step,
                    ally_return=out.returns[:, C.ALLY], timeout=timeout,
                    hp_ratio=states.hp_ratio, first_death=death_step, first_dead=first_dead,
                    eliminated=eliminated)

    return simulator_jit(run)


def tier_table(config: EnvConfig, level: EnvParams, episodes: int, seed: int = 0,
               ally_tiers: Sequence[str] = tuple(HEURISTIC_TIERS),
               enemy_tiers: Sequence[str] = tuple(HEURISTIC_TIERS),
               progress: bool = False, profile: str = DEFAULT_PROFILE) -> TierTable:
    """Play `episodes` episodes for every (ally tier, enemy tier) pair on one level, under
    behaviour profile `profile`."""
    for tier in (*ally_tiers, *enemy_tiers):
        if tier not in HEURISTIC_TIERS:
            raise ValueError(f"unknown heuristic tier {tier!r}; expected one of "
                             f"{', '.join(HEURISTIC_TIERS)}")
    level = with_profile(level, profile)
    run = make_batch_runner(config)
    cols = len(enemy_tiers)
    rows: list[dict[str, np.ndarray]] = []
    key = jax.random.key(seed)
    start = time.perf_counter()
    for i, ally in enumerate(ally_tiers):
        levels = stack_levels([level.replace(heuristic=heuristic_params(ally, enemy))
                               for enemy in enemy_tiers for _ in range(episodes)])
        key, sub = jax.random.split(key)
        out = jax.device_get(run(levels, jax.random.split(sub, cols * episodes)))
        rows.append({k: np.asarray(v).reshape(cols, episodes, *np.shape(v)[1:])
                     for k, v in out.items()})
        if progress:
            elapsed = time.perf_counter() - start
            eta = elapsed / (i + 1) * (len(ally_tiers) - i - 1)
            print(f"  row {i + 1}/{len(ally_tiers)} ({ally}) done: {elapsed:.0f} s elapsed, "
                  f"ETA {eta:.0f} s", file=sys.stderr, flush=True)
    stat = {k: np.stack([r[k] for r in rows]) for k in OUTCOMES}  # (A, E, episodes, ...)
    died = stat["first_death"] > 0
    with np.errstate(invalid="ignore"):
        first_death = np.where(died, stat["first_death"], 0).sum(-1) / died.sum(-1)
    return TierTable(
        list(ally_tiers), list(enemy_tiers), episodes,
        win_rate=stat["ally_won"].mean(-1), length=stat["length"].mean(-1),
        ally_return=stat["ally_return"].mean(-1), timeout=stat["timeout"].mean(-1),
        hp_ratio=stat["hp_ratio"].mean(2), first_death=first_death,
        first_dead=stat["first_dead"].mean(2), eliminated=stat["eliminated"].mean(2),
        profile=profile)


__all__ = ["TierTable", "make_batch_runner", "tier_table"]


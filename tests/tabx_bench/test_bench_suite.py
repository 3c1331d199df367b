"""`tabx bench scale | reconfig | compare`: argument errors, the random scenario
generator, zero recompilations across scenarios (with a counter shown to move), the JSON lines
and plot of `scale`, and the comparison table with fake simulators (no jaxmarl needed)."""

from __future__ import annotations

import builtins
import json
import sys

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from tabx import constants as C
from tabx.compile_counter import CompileCounter
from tabx.env import TabxEnv
from tabx.params import EnvConfig, levels_equal
from tabx.random_levels import composition, random_levels
from tabx.scenarios.format import level_to_scenario
from tabx_bench.simulator import BenchResult, make_rollout
from tabx_bench.suite import (
    ReconfigResult,
    compare_rows,
    format_compare,
    plot_compare,
    reconfig_ratio,
    run_compare,
    run_reconfig,
)
from tabx_ued.cli import main

SMALL = EnvConfig(max_allies=4, max_enemies=4, max_zones=3, max_steps=32)


# --- argument errors ---------------------------------------------------------------------------


@pytest.mark.parametrize("argv, message", [
    (["bench", "scale", "--num-envs", "0,4"], "every value must be >= 1, got 0"),
    (["bench", "scale", "--num-envs", "1,,4"], "comma-separated list of integers"),
    (["bench", "scale", "--num-envs", "1,x"], "comma-separated list of integers"),
    (["bench", "scale", "--team-sizes", "-3"], "every value must be >= 1, got -3"),
    (["bench", "scale", "--steps", "0"], "expected an integer >= 1, got 0"),
    (["bench", "scale", "--enemy", ""], "comma-separated controllers"),
    (["bench", "reconfig", "--scenarios", "-1"], "expected an integer >= 1, got -1"),
    (["bench", "reconfig", "--num-envs", "0"], "expected an integer >= 1, got 0"),
    (["bench", "reconfig", "--steps", "ten"], "expected an integer, got 'ten'"),
    (["bench", "compare", "--num-envs", "-5"], "expected an integer >= 1, got -5"),
    (["bench", "compare", "--peer-scenarios", "0"], "expected an integer >= 1, got 0"),
])
def test_bad_arguments_give_clear_messages(argv, message, capsys):
    with pytest.raises(SystemExit) as exc:
        main(argv)
    assert exc.value.code == 2
    assert message in capsys.readouterr().err


def test_bad_controller_is_a_user_error(capsys):
    assert main(["bench", "scale", "--enemy", "heuristic:legendary", "--num-envs", "1"]) == 2
    err = capsys.readouterr().err
    assert "unknown heuristic tier 'legendary'" in err and "Traceback" not in err
    assert main(["bench", "scale", "--enemy", "external", "--num-envs", "1"]) == 2
    assert "no learner" in capsys.readouterr().err


def test_compare_without_jaxmarl_says_how_to_install(monkeypatch, capsys):
    real_import = builtins.__import__

    def no_jaxmarl(name, *args, **kwargs):
        if name == "jaxmarl" or name.startswith("jaxmarl."):
            raise ModuleNotFoundError(f"No module named {name!r}", name=name)
        return real_import(name, *args, **kwargs)

    for mod in [m for m in sys.modules if m.startswith(("jaxmarl", "tabx_bench.peers.smax"))]:
        monkeypatch.delitem(sys.modules, mod)
    monkeypatch.setattr(builtins, "__import__", no_jaxmarl)
    assert main(["bench", "compare", "--team-sizes", "3", "--num-envs", "1"]) == 2
    err = capsys.readouterr().err
    assert 'pip install -e ".[peers]"' in err and "jaxmarl" in err
    assert "Traceback" not in err


# --- the random scenario generator -------------------------------------------------------------


@settings(max_examples=5, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 2**31 - 1), lo=st.integers(1, 5), span=st.integers(0, 5),
       zones=st.integers(0, 6))
def test_random_levels_are_valid_distinct_and_in_range(seed, lo, span, zones):
    hi = min(lo + span, 10)
    levels = random_levels(4, seed=seed, min_units=lo, max_units=hi, max_zones=zones)
    for level in levels:
        active = np.asarray(level.units.active)
        n_allies, n_enemies = active[:10].sum(), active[10:].sum()
        assert lo <= n_allies <= hi and lo <= n_enemies <= hi
        ztypes = np.asarray(level.zones.zone_type)
        assert (ztypes > 0).sum() <= zones and set(ztypes[ztypes > 0]) <= {1, 2, 3}
        assert set(np.asarray(level.units.unit_type)[active]) <= set(range(C.NUM_UNIT_TYPES))
        level_to_scenario(level).validate()  # what `tabx scenarios validate` checks
        assert np.asarray(level.units.position).shape == (20, 2)
    for i in range(len(levels)):
        for j in range(i):
            assert not levels_equal(levels[i], levels[j])
    # seedable: the same seed gives the same levels
    again = random_levels(4, seed=seed, min_units=lo, max_units=hi, max_zones=zones)
    assert all(levels_equal(a, b) for a, b in zip(levels, again, strict=True))


def test_random_levels_cover_all_units_and_zone_types():
    levels = random_levels(30, seed=3)
    types = set()
    zone_types = set()
    for level in levels:
        active = np.asarray(level.units.active)
        types |= set(np.asarray(level.units.unit_type)[active].tolist())
        zone_types |= set(np.asarray(level.zones.zone_type).tolist())
    assert types == set(range(9)) and zone_types >= {1, 2, 3}
    assert len({composition(lv) for lv in levels}) == 30


def test_random_levels_reject_bad_ranges():
    with pytest.raises(ValueError, match="exceeds the slots"):
        random_levels(1, max_units=11)
    with pytest.raises(ValueError, match="min_units"):
        random_levels(1, min_units=5, max_units=4)
    with pytest.raises(ValueError, match="max_zones"):
        random_levels(1, config=SMALL, max_units=4, max_zones=4)
    with pytest.raises(ValueError, match="count"):
        random_levels(0)


# --- reconfiguration: one compiled function ----------------------------------------------------


@pytest.fixture(scope="module")
def small_rollout():
    """One jitted rollout of SMALL shared by the reconfiguration tests (compiled once)."""
    return make_rollout(TabxEnv(SMALL), 3, with_obs=False)


def test_reconfig_runs_scenarios_with_zero_recompilations(small_rollout):
    levels = random_levels(3, seed=1, config=SMALL, max_units=4, max_zones=3)
    lines: list[str] = []
    result = run_reconfig(levels, SMALL, num_envs=2, steps=3, seed=0, rollout=small_rollout,
                          log=lines.append)
    # Scenarios overlap (the next is dispatched before the running one is awaited), yet each is
    # logged once, in order.
    assert [line.split()[1] for line in lines] == ["1", "2", "3"]
    assert result.compilations == 1 and result.recompilations == 0
    assert small_rollout._cache_size() == 1
    assert result.scenarios == 3 and result.env_steps == 3 * 2 * 3
    assert result.total_s >= result.first_s > 0 and result.effective_steps_per_s > 0
    assert result.compile_s > 0
    again = run_reconfig(levels[::-1], SMALL, num_envs=2, steps=3, rollout=small_rollout)
    assert again.compilations == 0  # the compiled rollout is reused: levels are data


def test_the_compile_counter_really_moves(small_rollout):
    """Changing a static thing (the zone slots: a shape) between scenarios must show up."""
    level = random_levels(1, seed=2, config=SMALL, max_units=4, max_zones=3)[0]
    other = random_levels(1, seed=5, config=EnvConfig(max_allies=4, max_enemies=4, max_zones=2),
                          max_units=4, max_zones=2)[0]
    with CompileCounter() as cc:
        mixed = run_reconfig([level, other, level], SMALL, num_envs=2, steps=3,
                             rollout=small_rollout)
    assert cc.compiles == mixed.compilations >= 1 and cc.seconds > 0
    assert mixed.recompilations == 1 and small_rollout._cache_size() == 2


def test_reconfig_cli_writes_a_row(tmp_path, capsys):
    out = tmp_path / "reconfig.jsonl"
    assert main(["bench", "reconfig", "--scenarios", "2", "--num-envs", "1", "--steps", "2",
                 "--no-obs", "--json", str(out)]) == 0
    text = capsys.readouterr().out
    assert "0 after the first" in text and "scenario   2" in text
    row = json.loads(out.read_text())
    assert row["scenarios"] == 2 and row["recompilations"] == 0 and row["env_steps"] == 4
    assert {"total_s", "compile_s", "effective_steps_per_s", "machine", "load_avg"} <= set(row)


# --- scale -------------------------------------------------------------------------------------


def test_scale_writes_rows_and_a_plot(tmp_path, capsys):
    out, png = tmp_path / "scale.jsonl", tmp_path / "scale.png"
    assert main(["bench", "scale", "--team-sizes", "1", "--num-envs", "1,2", "--steps", "2",
                 "--repeats", "1", "--enemy", "random,idle", "--no-obs", "--json",
                 str(out), "--plot", str(png)]) == 0
    text = capsys.readouterr().out
    assert "[4/4, eta 0s]" in text
    rows = [json.loads(line) for line in out.read_text().splitlines()]
    assert len(rows) == 4
    fields = {"team_size", "units", "num_envs", "controllers", "compile_s", "run_s",
              "steps_per_s", "steps", "with_obs", "zones", "load_avg", "machine"}
    assert all(fields <= set(r) for r in rows)
    assert {r["controllers"] for r in rows} == {"random/random", "random/idle"}
    assert {r["num_envs"] for r in rows} == {1, 2} and all(r["units"] == 2 for r in rows)
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


# --- compare -----------------------------------------------------------------------------------


def _result(team, envs, sps, ctrl="random/random"):
    return BenchResult(team, 0, envs, True, 128, 1.0, envs * 128 / sps, sps, ctrl, 0.5)


def _reconfig(sim, sps, extrapolated=False):
    total = 100 * 128 * 128 / sps
    return ReconfigResult(sim, 100, 128, 128, total, 1.0, 1.0, 1, 0, sps, 10 if extrapolated
                          else 100, extrapolated)


class FakeSim:
    def __init__(self, name, per_team, reconfig_sps, extrapolated=False):
        self.name, self.per_team, self.reconfig_sps = name, per_team, reconfig_sps
        self.extrapolated = extrapolated
        self.calls = []

    def version(self):
        return "fake 1.0"

    def throughput(self, team_size, num_envs, steps, repeats, with_obs):
        self.calls.append(("fixed", team_size, num_envs))
        return _result(team_size, num_envs, self.per_team[team_size])

    def reconfig(self, scenarios, num_envs, steps, seed, with_obs, measure=None, log=None):
        self.calls.append(("reconfig", scenarios, measure))
        return _reconfig(self.name, self.reconfig_sps, self.extrapolated)


def test_compare_table_and_ratios_with_fake_peers(tmp_path):
    ours = FakeSim("tabx", {3: 400_000, 10: 50_000}, 20_000)
    peer = FakeSim("SMAX", {3: 100_000, 10: 40_000}, 500, extrapolated=True)
    logs = []
    fixed_o, fixed_p, rc_o, rc_p = run_compare(ours, peer, [3, 10], 1024, 128, 3, True, 100,
                                               128, 128, 0, 10, log=logs.append)
    assert ("reconfig", 100, 10) in peer.calls and len(logs) == 6
    rows = compare_rows(fixed_o, fixed_p)
    assert [(r.team_size, round(r.ratio, 2)) for r in rows] == [(3, 4.0), (10, 1.25)]
    assert reconfig_ratio(rc_o, rc_p) == pytest.approx(40.0)
    text = format_compare(rows, "SMAX", rc_o, rc_p)
    assert "4.00x" in text and "1.25x" in text and "40.0x;" in text
    assert "extrapolated from 10" in text
    assert "met" not in text and "target" not in text  # targets live in docs/benchmarks.md
    png = tmp_path / "compare.png"
    plot_compare(rows, str(png), "SMAX", rc_o, rc_p)
    assert png.read_bytes()[:4] == b"\x89PNG"


def test_compare_rows_need_matching_peer_results():
    with pytest.raises(ValueError, match="no peer result for 5v5"):
        compare_rows([_result(5, 1024, 1.0)], [_result(5, 512, 1.0)])


def test_compare_cli_with_a_fake_peer(monkeypatch, tmp_path, capsys):
    import tabx_bench.suite as suite

    monkeypatch.setattr(suite, "load_peer",
                        lambda name, devices=0: FakeSim("SMAX", {3: 1e5, 5: 5e4}, 100))
    monkeypatch.setattr(suite, "TabxSimulator",
                        lambda devices=0: FakeSim("tabx", {3: 3e5, 5: 1e5}, 4e3))
    out, png = tmp_path / "c.jsonl", tmp_path / "c.png"
    assert main(["bench", "compare", "--team-sizes", "3,5", "--json", str(out), "--plot",
                 str(png)]) == 0
    text = capsys.readouterr().out
    assert "3.00x" in text and "2.00x" in text and "40.0x" in text
    kinds = [json.loads(line)["kind"] for line in out.read_text().splitlines()]
    assert kinds.count("fixed") == 4 and kinds.count("ratio") == 2
    assert "reconfig_ratio" in kinds and png.exists()

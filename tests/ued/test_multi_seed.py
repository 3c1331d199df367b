"""Multi-seed runs (`seeds:` in a plain MARL config): the config's checks, every seed in one
compiled program that equals single-seed runs, resume, each seed's events and policy, and
`tabx plot`'s mean and standard-error band over seeds."""

from __future__ import annotations

import jax
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from test_learners_helpers import (
    BFLOAT16_STEP,
    restore_both_and_compare,
    rounding_bound,
    tiny_config,
)

from tabx.compile_counter import CompileCounter
from tabx_ued.cli import main
from ued.checkpoint import Checkpoints
from ued.config import ConfigError
from ued.experiment import learner_for, seed_keys
from ued.plot import curve, load_runs, plot_runs
from ued.run_folder import CHECKPOINT_DIR, load_policy, seed_dir
from ued.tensorboard import SummaryWriter, read_scalars
from workers.train import train

SEEDS = (3, 5)  # tiny_config's own seed is 3: its single-seed runs share the compiled update


def multi_config(seeds=SEEDS, **overrides):
    return tiny_config(seed=0, seeds=f"[{', '.join(map(str, seeds))}]", **overrides)


# --- the config ------------------------------------------------------------------------------


def test_seeds_round_trip_and_single_seed_files_keep_their_form():
    config = multi_config()
    assert config.seeds == SEEDS
    assert "seeds:\n- 3\n- 5\n" in config.to_yaml()
    single = tiny_config()
    assert single.seeds == () and "seeds" not in single.to_yaml()


@pytest.mark.parametrize(("overrides", "message"), [
    ({"seeds": "[]"}, "seeds: expected a non-empty list of seeds, e.g. [0, 1, 2], got []"),
    ({"seeds": "4"}, "seeds: expected a non-empty list of seeds, e.g. [0, 1, 2], got 4"),
    ({"seeds": "[1, 2, 1]"}, "seeds: seeds must be distinct, got 1 more than once"),
    ({"seeds": "[0, -1]"}, "seeds: seeds must be integers in [0, 2**63), got -1"),
    ({"seeds": "[0, 1.5]"}, "seeds: expected an integer, got 1.5"),
    ({"seeds": "[0, 1]", "seed": 3}, "seed: a multi-seed config lists its seeds in `seeds` "
                                     "only; drop seed: 3"),
    ({"seeds": "[0, 1]", "algorithm": "qmix", "learner.num_minibatches": 4},
     "seeds: several seeds train in one program for the PPO learners (mappo, ippo, mappo_rnd) "
     "on plain MARL runs; qmix trains one seed per run"),
    ({"seeds": "[0, 1]", "ued.method": "dr"}, "seeds: several seeds train in one program for "
     "the PPO learners (mappo, ippo, mappo_rnd) on plain MARL runs; a UED run (ued.method: dr) "
     "trains one seed per run"),
    ({"seeds": "[0, 1]", "ued.method": "dr", "ray.enabled": "true"},
     "seeds: several seeds train in one program for the PPO learners (mappo, ippo, mappo_rnd) "
     "on plain MARL runs on the local driver; ray.enabled"),
])
def test_bad_seeds_name_the_field(overrides, message):
    with pytest.raises(ConfigError) as err:
        tiny_config(**{"seed": 0, **overrides})
    assert message in str(err.value)


@settings(max_examples=40, deadline=None)
@given(st.lists(st.integers(-2**64, 2**64), min_size=1, max_size=6))
def test_any_list_of_integers_is_accepted_exactly_when_distinct_and_in_range(seeds):
    good = len(set(seeds)) == len(seeds) and all(0 <= s < 2**63 for s in seeds)
    try:
        config = multi_config(seeds)
    except ConfigError as err:
        assert not good and str(err).startswith("tiny config: seeds: ")
    else:
        assert good and config.seeds == tuple(seeds)


# --- training --------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """An uninterrupted multi-seed run, one stopped after 2 of its 4 updates and resumed, and
    single-seed runs of its seeds; with the compilations of the resumed part."""
    base = tmp_path_factory.mktemp("seeds")
    config = multi_config(**{"run.checkpoint_every": 2})  # 4 updates; checkpoints 2, 4
    full = train(config, run_dir=base / "full", progress=False)
    part = train(config, run_dir=base / "part", progress=False, max_updates=2)
    with CompileCounter() as resumed:
        train(run_dir=part, resume=True, progress=False)
    # tiny_config's settings (one checkpoint, at the end): the single-seed update other test
    # modules compile too.
    singles = [train(tiny_config(seed=s, **{"run.checkpoint_every": 4}),
                     run_dir=base / f"seed{s}", progress=False) for s in SEEDS]
    return config, full, part, singles, resumed


def test_each_seed_equals_its_single_seed_run(trained):
    """Seed s of the vmapped program trains as a run with `seed: s`: the same key chain, bit
    for bit, and parameters nearer to that run's than the seeds are to each other. Not equal:
    batched matrix products may sum in another order, and after the first update the rollouts
    follow parameters a rounding apart, so an action may be sampled otherwise and the runs
    part (`test_a_seeds_update_equals_its_single_seed_update` bounds one update)."""
    config, full, _, singles, _ = trained
    learner = learner_for(config)
    keys = seed_keys(SEEDS)
    with Checkpoints(full / CHECKPOINT_DIR) as ck:
        stacked, stacked_keys, update = ck.restore(learner.init_seeds(keys), key_template=keys)
    assert update == 4
    flat = [np.concatenate([np.ravel(leaf[i]) for leaf in jax.tree.leaves(stacked.params)])
            for i in range(len(SEEDS))]
    for i, single in enumerate(singles):
        with Checkpoints(single / CHECKPOINT_DIR) as ck:
            state, key, _ = ck.restore(learner.init(jax.random.key(0)))
        assert np.array_equal(jax.random.key_data(key), jax.random.key_data(stacked_keys)[i])
        assert int(state.update) == int(stacked.update[i]) == 4
        own = np.concatenate([np.ravel(leaf) for leaf in jax.tree.leaves(state.params)])
        assert np.max(np.abs(own - flat[i])) < 0.1 * np.max(np.abs(own - flat[1 - i]))


@pytest.mark.parametrize("algorithm", ["mappo", pytest.param("ippo", marks=pytest.mark.slow),
                                       pytest.param("mappo_rnd", marks=pytest.mark.slow)])
def test_a_seeds_update_equals_its_single_seed_update(algorithm):
    """Every PPO learner vmaps over seeds: from the same states, entry i of `update_seeds`
    plays the episodes `update` plays for seed i (exactly) and lands within `rounding_bound`
    of its parameters (the products sum in another order; the bound's docstring derives it)."""
    config = multi_config(algorithm=algorithm)
    learner = learner_for(config)
    from ued.experiment import split_seed_keys, training_levels

    _, levels = training_levels(config)
    keys, init = split_seed_keys(seed_keys(SEEDS))
    _, now = split_seed_keys(keys)
    stacked, metrics, stats = learner.update_seeds(learner.init_seeds(init), levels, now)
    assert metrics["loss/total"].shape == (len(SEEDS),)
    bound = rounding_bound(config.learner)
    for i in range(len(SEEDS)):
        state, _, single = learner.update(learner.init(init[i]), levels, now[i])
        for name in ("dones", "rewards", "wins"):
            np.testing.assert_array_equal(getattr(single, name), getattr(stats, name)[i])
        for a, b in zip(jax.tree.leaves(state.params), jax.tree.leaves(stacked.params),
                        strict=True):
            np.testing.assert_allclose(a, b[i], rtol=0, atol=bound)


def test_resume_continues_every_seed_bit_for_bit_without_compiling(trained):
    config, full, part, _, resumed = trained
    keys = seed_keys(SEEDS)
    _, update = restore_both_and_compare(full, part, learner_for(config).init_seeds(keys), keys)
    assert update == 4
    # A checkpoint restored, two more updates, a checkpoint saved: the update compiled for
    # neither. What did compile is JAX lifting the restored host arrays onto the device
    # (`lax.stage`, once per array shape in a process).
    assert set(resumed.traced) <= {"stage"}, resumed.traced


def test_one_program_for_all_seeds_and_each_seed_logs_to_its_folder(trained):
    config, full, _, singles, _ = trained
    learner = learner_for(config)
    assert learner._update_seeds_jit._cache_size() == 1
    assert not (full / "events").exists()
    steps = [u * config.learner.steps_per_update for u in range(1, 5)]
    logged = {}
    for seed in SEEDS:
        scalars = read_scalars(seed_dir(full, seed))
        assert [s for s, _ in scalars["loss/total"]] == steps
        logged[seed] = [v for _, v in scalars["loss/total"]]
        assert "time/first_update_s" in scalars
        # As a single-seed run: a rate from the second update on, none (not NaN) before.
        rates = scalars["time/steps_per_s"]
        assert [s for s, _ in rates] == steps[1:] and all(np.isfinite([v for _, v in rates]))
    assert logged[3] != logged[5]
    single = [v for _, v in read_scalars(singles[0] / "events")["loss/total"]]
    # The first update's loss: the same episodes from the same parameters, a mean of terms
    # that may round one bfloat16 step (2**-8) apart (later updates may part: see above).
    np.testing.assert_allclose(logged[3][0], single[0], rtol=BFLOAT16_STEP)


def test_a_seed_folder_is_that_seeds_policy(trained, capsys):
    config, full, _, _, _ = trained
    learner = learner_for(config)
    keys = seed_keys(SEEDS)
    with Checkpoints(full / CHECKPOINT_DIR) as ck:
        stacked = ck.restore(learner.init_seeds(keys), key_template=keys)[0]
    policy = load_policy(seed_dir(full, 5))
    assert policy.seed == 5 and policy.update == 4 and "seed 5" in str(policy)
    for a, b in zip(jax.tree.leaves(policy.params), jax.tree.leaves(stacked.params),
                    strict=True):
        assert np.array_equal(a, b[1])
    with pytest.raises(ConfigError, match="a run of seeds 3, 5, one policy each: name one by "
                                          "its folder, e.g. .*seed-3"):
        load_policy(full)
    (full / "seed-4").mkdir()
    with pytest.raises(ConfigError, match="this run has no seed 4 \\(its seeds: 3, 5\\)"):
        load_policy(full / "seed-4")
    from ued.payoff import side_labels

    assert side_labels([str(seed_dir(full, 3)), str(seed_dir(full, 5)), "random"]) == [
        "full/seed-3", "full/seed-5", "random"]
    assert main(["eval", str(full)]) == 2
    assert "name one by its folder" in capsys.readouterr().err
    assert main(["runs", "check", str(full)]) == 0
    assert "seeds 3, 5" in main_output(capsys, "runs", "show", str(full))


def main_output(capsys, *argv):
    assert main(list(argv)) == 0
    return capsys.readouterr().out


@pytest.mark.slow
def test_eval_plays_one_seed_of_a_multi_seed_run(trained, capsys):
    _, full, _, _, _ = trained
    out = main_output(capsys, "eval", str(seed_dir(full, 3)), "--episodes", "2")
    assert "seed 3" in out


# --- tabx plot -------------------------------------------------------------------------------


def fake_seeds(run, curves):
    """A multi-seed run folder's events: seed -> [(step, win rate), ...]."""
    for seed, points in curves.items():
        with SummaryWriter(seed_dir(run, seed)) as writer:
            for step, value in points:
                writer.scalars({"episode/win_rate": value, "loss/total": -value}, step=step)
    return str(run)


def test_plot_draws_the_mean_and_standard_error_over_seeds(tmp_path, capsys):
    run = fake_seeds(tmp_path / "multi", {
        0: [(100, 0.1), (200, 0.5), (300, 0.9)],
        1: [(100, 0.3), (200, 0.7)],  # its step 300 not logged (a NaN win rate)
        10: [(100, 0.2), (200, 0.6), (300, 0.7)]})
    single = tmp_path / "single"
    with SummaryWriter(single / "events") as writer:
        for step, value in [(100, 0.4), (200, 0.2), (200, 0.3)]:  # 200 again after a resume
            writer.scalars({"episode/win_rate": value}, step=step)
    runs = load_runs([run, str(single), str(seed_dir(run, 10))])
    assert [len(seeds) for seeds in runs.values()] == [3, 1, 1]
    drawn = plot_runs(runs, ["episode/win_rate"], str(tmp_path / "out.png"))
    multi = drawn["episode/win_rate"]["multi"]
    np.testing.assert_array_equal(multi.steps, [100, 200, 300])
    np.testing.assert_array_equal(multi.seeds, [3, 3, 2])
    np.testing.assert_allclose(multi.mean, [0.2, 0.6, 0.8], rtol=1e-6)
    expected = [np.std([0.1, 0.3, 0.2], ddof=1) / np.sqrt(3),
                np.std([0.5, 0.7, 0.6], ddof=1) / np.sqrt(3),
                np.std([0.9, 0.7], ddof=1) / np.sqrt(2)]
    np.testing.assert_allclose(multi.stderr, expected, rtol=1e-5)
    one = drawn["episode/win_rate"]["single"]  # a single-seed run: its values, no band
    np.testing.assert_allclose(one.mean, [0.4, 0.3], rtol=1e-6)
    np.testing.assert_array_equal(one.stderr, [0.0, 0.0])
    np.testing.assert_allclose(drawn["episode/win_rate"]["multi/seed-10"].mean, [0.2, 0.6, 0.7],
                               rtol=1e-6)
    assert curve(runs["single"], "loss/total") is None
    assert main(["plot", run, "--tag", "loss/*", "--out", str(tmp_path / "b.png")]) == 0
    assert "wrote 1 panels (loss/total)" in capsys.readouterr().out
    assert main(["plot", str(tmp_path / "nothing"), "--out", str(tmp_path / "c.png")]) == 2
    assert "nor a multi-seed run (no seed-<s>/ folders)" in capsys.readouterr().err


@pytest.mark.slow
def test_each_seed_logs_its_own_value_error(tmp_path):
    config = multi_config(**{"run.value_error_every": 2, "run.value_error_states": 8,
                             "run.value_error_rollouts": 4})
    run = train(config, run_dir=tmp_path / "run", progress=False)
    for seed in SEEDS:
        points = read_scalars(seed_dir(run, seed))["value_error/duel2a1f/mean_abs_error"]
        assert [s for s, _ in points] == [2 * config.learner.steps_per_update,
                                          4 * config.learner.steps_per_update]
        assert all(v >= 0 for _, v in points)

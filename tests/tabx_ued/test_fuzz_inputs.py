"""Every command that reads a file, fed damaged and malformed ones: training configs and
overrides, evaluation suites, scenario files (beyond `tabx scenarios`), level-buffer files,
and run folders with damaged or missing pieces (config.yaml, orbax checkpoints and their
`_METADATA`, level snapshots, `ray.json`, events/).

Each case asserts what docs/reliability.md promises: a non-zero exit, one `tabx CMD: error:`
line naming the file (`tabx train --resume` may first say which steps it passed over;
`tabx runs check` reports instead, with exit code 1), no traceback, and no file changed, added
or removed. The commands run in-process (`tabx_ued.cli.main`); two subprocesses check that
nothing is printed at interpreter exit either. Hypothesis mutates valid files beyond the fixed
corpus. The scenario-file corpus itself lives in tests/tabx/test_scenario_fuzz.py.
"""

from __future__ import annotations

import hashlib
import io
import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import jax
import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from test_scenario_fuzz import CORPUS as SCENARIO_CORPUS
from test_ued_train import ued_config

from level_buffer import LevelBuffer
from tabx_ued.cli import main
from ued.checkpoint import CheckpointError, Checkpoints
from ued.config import ConfigError, load_config
from ued.run_folder import CHECKPOINT_DIR, CONFIG_FILE, LEVELS_DIR, read_run_config
from ued.suites import parse_suite
from workers.resume import check_run_folder, snapshot_problem
from workers.train import train

ROOT = Path(__file__).resolve().parents[2]
STEPS = 4  # checkpoints and snapshots at steps 2 and 4
RUN_CONFIG = {"run.checkpoint_every": 2, "run.keep_checkpoints": 3}
# Orbax's reads left in flight by a failed restore end in a closed event loop; the command line
# keeps them quiet (ued/checkpoint.py), but pytest swaps its own unraisable-exception hook in for
# each test and reports them as warnings.
pytestmark = pytest.mark.filterwarnings("ignore::pytest.PytestUnraisableExceptionWarning")
FUZZ = settings(max_examples=int(os.environ.get("TABX_HYPOTHESIS_EXAMPLES", "25")),
                deadline=None, suppress_health_check=[HealthCheck.too_slow,
                                                      HealthCheck.function_scoped_fixture])


# --- helpers -----------------------------------------------------------------------------------


def tree(folder: Path) -> dict[str, str]:
    """Every file and folder under `folder`: relative path -> SHA-256 (folders: 'dir', links:
    their target, never followed: one may name a device)."""
    out = {}
    for path in sorted(folder.rglob("*")):
        rel = str(path.relative_to(folder))
        out[rel] = (f"link -> {os.readlink(path)}" if path.is_symlink() else "dir"
                    if path.is_dir() else hashlib.sha256(path.read_bytes()).hexdigest())
    return out


def run_cli(capsys, argv: list[str]) -> tuple[int, str, str]:
    try:
        code = main(argv)
    except SystemExit as exc:  # argparse
        code = exc.code
    out, err = capsys.readouterr()
    return code, out, err


def assert_one_error(code, out: str, err: str, argv: list[str], names: str,
                     pattern: str | None = None) -> str:
    """A non-zero exit, no traceback, and the error as the last line of stderr, naming
    `names`; any other stderr lines are resume's reports of steps it passed over."""
    lines = [line for line in err.splitlines() if line.strip()]
    assert code not in (0, None), (argv, out[-500:], err[-2000:])
    assert "Traceback" not in out + err, (argv, err[-3000:])
    assert lines, (argv, out[-500:])
    command = argv[0]
    assert lines[-1].startswith(f"tabx {command}: error: "), (argv, err[-2000:])
    assert "(unexpected:" not in lines[-1], lines[-1]  # a known kind of bad input, not a bug
    assert all(line.startswith("resume: ") for line in lines[:-1]), (argv, err[-2000:])
    assert names in lines[-1], (argv, names, lines[-1][:500])
    if pattern is not None:
        assert re.search(pattern, lines[-1]), (argv, pattern, lines[-1][:500])
    assert len(lines[-1]) < 2000, "the error line echoes too much"
    return lines[-1]


@pytest.fixture(autouse=True)
def no_browser_no_server(monkeypatch, tmp_path):
    """The editor must refuse a bad file before it serves; reaching the server is a failure."""
    import tabx.editor.server as server

    def refuse(*args, **kwargs):
        raise AssertionError("the editor started serving a bad file")

    monkeypatch.setattr(server, "make_server", refuse)
    monkeypatch.setenv("TABX_SCENARIO_DIR", str(tmp_path / "user-scenarios"))


# --- a finished run folder ---------------------------------------------------------------------


@pytest.fixture(scope="module")
def finished(tmp_path_factory) -> Path:
    """A 4-step Robust PLR run: checkpoints and level snapshots at steps 2 and 4."""
    run_dir = tmp_path_factory.mktemp("runs") / "run"
    train(ued_config("robust_plr", **RUN_CONFIG), run_dir=run_dir, stream=io.StringIO(),
          max_updates=STEPS)
    return run_dir


def truncate(path: Path) -> None:
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])


def truncate_after(path: Path, text: str) -> None:
    data = path.read_bytes()
    path.write_bytes(data[: data.index(text.encode()) + len(text)])


def flip(path: Path, at: float = 0.5) -> None:
    data = bytearray(path.read_bytes())
    i = int(len(data) * at)
    data[i] ^= 0x20
    path.write_bytes(bytes(data))


def flip_array(item: Path) -> None:
    """One bit in the bytes of the largest array data file of a checkpoint item."""
    data_file = max((p for p in item.rglob("*") if p.is_file() and p.parent.name == "d"),
                    key=lambda p: p.stat().st_size)
    flip(data_file, 0.1)


def each_step(run: Path, rel: str, harm) -> None:
    for step in (2, STEPS):
        harm(run / rel.format(step=step))


def remove(path: Path) -> None:
    shutil.rmtree(path) if path.is_dir() else path.unlink()


def link_to_device(path: Path) -> None:
    path.unlink()
    path.symlink_to("/dev/zero")


def edit_config(run: Path, old: str, new: str) -> None:
    path = run / CONFIG_FILE
    text = path.read_text()
    assert old in text
    path.write_text(text.replace(old, new, 1))


# What resume and evaluation need: damaged, every command that reads it must stop cleanly.
#   name -> (harm, what the error line names beyond the run folder, commands)
CHECK, EVAL, EVAL_AT_2, RESUME, STATUS, LIVE, PLOT, ROLLOUT = (
    "check", "eval", "eval@2", "resume", "status", "live", "plot", "rollout")
CONFIG_READERS = (CHECK, EVAL, EVAL_AT_2, RESUME, ROLLOUT)
CHECKPOINT_READERS = (CHECK, EVAL, EVAL_AT_2, RESUME, ROLLOUT)
SNAPSHOT_READERS = (CHECK, RESUME)
RUN_DAMAGE = {
    "config missing": (lambda r: remove(r / CONFIG_FILE), r"not a run folder", CONFIG_READERS),
    "config empty": (lambda r: (r / CONFIG_FILE).write_bytes(b""), r"config\.yaml: empty file",
                     CONFIG_READERS),
    # Cut after a key, before its value (a cut between two sections would leave a shorter
    # config that is valid: the missing fields take their defaults): a YAML error with its
    # place, or the field left without its value.
    "config truncated": (lambda r: truncate_after(r / CONFIG_FILE, "num_envs:"),
                         r"config\.yaml: (not valid YAML: .*\(line \d+, column \d+\)|"
                         r"[\w.]+: expected .*, got None)",
                         CONFIG_READERS),
    "config binary": (lambda r: (r / CONFIG_FILE).write_bytes(bytes(range(256))),
                      r"config\.yaml: not UTF-8", CONFIG_READERS),
    "config a list": (lambda r: (r / CONFIG_FILE).write_text("- 1\n- 2\n"),
                      r"config\.yaml: .*expected a mapping", CONFIG_READERS),
    "config repeated key": (lambda r: edit_config(r, "learner:\n", "learner:\n  lr: 0.5\n"),
                            r"config\.yaml: .*key 'lr' appears twice", CONFIG_READERS),
    "config out of range": (lambda r: edit_config(r, "num_envs: 4", "num_envs: -4"),
                            r"config\.yaml: learner\.num_envs: must be >= 1", CONFIG_READERS),
    "config wrong type": (lambda r: edit_config(r, "gamma: 0.99", "gamma: [0.99]"),
                          r"config\.yaml: learner\.gamma: expected a number", CONFIG_READERS),
    "config unknown method": (lambda r: edit_config(r, "method: robust_plr", "method: robust"),
                              r"ued\.method: must be one of", CONFIG_READERS),
    "no checkpoints": (lambda r: remove(r / CHECKPOINT_DIR), r"no checkpoint yet",
                       (EVAL, EVAL_AT_2, ROLLOUT)),
    "_METADATA truncated": (lambda r: each_step(r, "checkpoints/{step}/default/_METADATA",
                                                truncate), r"cannot be restored",
                            CHECKPOINT_READERS),
    "_METADATA bit flip": (lambda r: each_step(r, "checkpoints/{step}/default/_METADATA",
                                               lambda p: flip(p, 0.3)), r"cannot be restored",
                           CHECKPOINT_READERS),
    "_METADATA empty": (lambda r: each_step(r, "checkpoints/{step}/default/_METADATA",
                                            lambda p: p.write_bytes(b"")),
                        r"cannot be restored", CHECKPOINT_READERS),
    "manifest truncated": (lambda r: each_step(r, "checkpoints/{step}/default/manifest.ocdbt",
                                               truncate), r"cannot be restored",
                           CHECKPOINT_READERS),
    # A policy's parameters are restored as host arrays, without the sharding file: `eval`
    # plays; resuming needs the whole train state.
    "sharding truncated": (lambda r: each_step(r, "checkpoints/{step}/default/_sharding",
                                               truncate), r"cannot be restored",
                           (CHECK, RESUME)),
    "array data missing": (lambda r: each_step(r, "checkpoints/{step}/default/ocdbt.process_0",
                                               remove),
                           r"cannot be restored", CHECKPOINT_READERS),
    "checkpoint item missing": (lambda r: each_step(r, "checkpoints/{step}/default", remove),
                                r"cannot be restored", CHECKPOINT_READERS),
    # Orbax keeps no checksum of the values: a flip that decodes is caught by the digests
    # recorded at saving (tests/tabx_ued/test_fuzz_files.py shows which catches it).
    "array data bit flip": (lambda r: each_step(r, "checkpoints/{step}/default", flip_array),
                            r"checkpoints/4: cannot be restored", (CHECK, RESUME)),
    "state files edited": (lambda r: each_step(r, "levels/state-{step}.json", lambda p: (
        p.write_text(json.dumps({**json.loads(p.read_text()), "version": 1})))),
        r"state-4\.json: changed after checkpoint 4 was saved", SNAPSHOT_READERS),
    "buffer snapshots truncated": (lambda r: each_step(r, "levels/buffer-{step}.msgpack",
                                                       truncate), r"buffer-4\.msgpack",
                                   SNAPSHOT_READERS),
    "buffer snapshots bit flip": (lambda r: each_step(r, "levels/buffer-{step}.msgpack", flip),
                                  r"buffer-4\.msgpack: checksum mismatch", SNAPSHOT_READERS),
    "state files truncated": (lambda r: each_step(r, "levels/state-{step}.json", truncate),
                              r"state-4\.json: unreadable", SNAPSHOT_READERS),
    "state files of another shape": (lambda r: each_step(r, "levels/state-{step}.json",
                                                         lambda p: p.write_text("[]")),
                                     r"state-4\.json: expected a JSON object",
                                     SNAPSHOT_READERS),
    "state files deeply nested": (lambda r: each_step(r, "levels/state-{step}.json",
                                                      lambda p: p.write_text("[" * 100_000)),
                                  r"state-4\.json: unreadable", SNAPSHOT_READERS),
    "state without version": (lambda r: each_step(r, "levels/state-{step}.json", lambda p: (
        p.write_text(p.read_text().replace('"version"', '"versio"')))),
        r"state-4\.json: version: expected", SNAPSHOT_READERS),
    "levels folder missing": (lambda r: remove(r / LEVELS_DIR), r"state-4\.json: missing",
                              SNAPSHOT_READERS),
    "ray.json missing": (lambda r: None, r"ray\.json: no Ray record", (STATUS, LIVE)),
    "ray.json truncated": (lambda r: (r / "ray.json").write_text('{"status": {"actors": ['),
                           r"ray\.json: not a readable Ray record", (STATUS, LIVE)),
    "ray.json deeply nested": (lambda r: (r / "ray.json").write_text("[" * 100_000),
                               r"ray\.json: not a readable Ray record", (STATUS, LIVE)),
    "ray.json a list": (lambda r: (r / "ray.json").write_text("[1, 2]"),
                        r"ray\.json: not a Ray record", (STATUS, LIVE)),
    "events missing": (lambda r: remove(r / "events"), r"no events/ folder", (PLOT,)),
    # A valid config that is not the one the checkpoints were trained with (a value cut short).
    "config changed": (lambda r: edit_config(r, "gamma: 0.99", "gamma: 0.9"),
                       r"config\.yaml: differs from the config checkpoint 4 was trained with",
                       (RESUME,)),
    "events a file": (lambda r: (remove(r / "events"), (r / "events").write_text("x")),
                      r"events: not a folder", (RESUME,)),
    "levels a file": (lambda r: (remove(r / LEVELS_DIR), (r / LEVELS_DIR).write_text("x")),
                      r"levels: not a folder", (RESUME,)),
    "events damaged": (lambda r: [p.write_bytes(bytes(range(256)) * 4)
                                  for p in (r / "events").iterdir()],
                       r"no scalars in their event folders", (PLOT,)),
    # A link to a device is named as what it is, never opened (it would never end).
    "config a link to a device": (lambda r: link_to_device(r / CONFIG_FILE),
                                  r"config\.yaml: a character device, not a file \(through a "
                                  r"symbolic link\)", CONFIG_READERS),
    "state files links to a device": (lambda r: each_step(r, "levels/state-{step}.json",
                                                          link_to_device),
                                      r"state-4\.json: a character device", SNAPSHOT_READERS),
    "buffer snapshots links to a device": (lambda r: each_step(
        r, "levels/buffer-{step}.msgpack", link_to_device), r"buffer-4\.msgpack: a character "
        r"device", SNAPSHOT_READERS),
}


def command_line(which: str, run: Path, tmp_path: Path) -> list[str]:
    return {CHECK: ["runs", "check", str(run)],
            EVAL: ["eval", str(run), "--episodes", "2"],
            EVAL_AT_2: ["eval", str(run), "--episodes", "2", "--checkpoint", "2"],
            RESUME: ["train", "--resume", str(run), "--quiet", "--max-updates", "1"],
            STATUS: ["runs", "status", str(run)],
            LIVE: ["runs", "buffer", str(run)],
            PLOT: ["plot", str(run), "--out", str(tmp_path / "curves.png")],
            ROLLOUT: ["rollout", "--ally", str(run), "--steps", "2"]}[which]


@pytest.mark.parametrize("damage", list(RUN_DAMAGE))
def test_damaged_run_folder_is_one_clear_error_in_every_command(damage, finished, tmp_path,
                                                                capsys):
    run = tmp_path / "run"
    shutil.copytree(finished, run)
    harm, pattern, commands = RUN_DAMAGE[damage]
    harm(run)
    before = tree(run)
    for which in commands:
        argv = command_line(which, run, tmp_path)
        code, out, err = run_cli(capsys, argv)
        if which == CHECK and code == 1:
            # `tabx runs check` reports every step (exit 1 when one is damaged).
            assert "Traceback" not in out + err and not err.strip(), err[-2000:]
            assert "no intact step: the run cannot be resumed" in out, out
            assert re.search(pattern, out), (pattern, out)
        else:
            assert_one_error(code, out, err, argv, str(run), pattern)
        assert tree(run) == before, f"{argv} changed the run folder"
        assert not (tmp_path / "curves.png").exists()


def test_an_undamaged_copy_passes_every_command(finished, tmp_path, capsys):
    """The cases above damage a folder that works: each command reads the intact copy."""
    run = tmp_path / "run"
    shutil.copytree(finished, run)
    for which in (CHECK, EVAL_AT_2, PLOT):
        code, out, err = run_cli(capsys, command_line(which, run, tmp_path))
        assert code == 0, err[-2000:]
    assert "newest intact step: 4" in run_cli(capsys, command_line(CHECK, run, tmp_path))[1]


# --- configs, overrides and suites -------------------------------------------------------------


@pytest.fixture(scope="module")
def config_text(finished) -> str:
    return (finished / CONFIG_FILE).read_text()


def config_corpus(valid: str) -> dict[str, tuple[bytes, str]]:
    """name -> (a config file's content, what its error line must match)."""
    nested = "seed: " + "[" * 40 + "]" * 40 + "\n"
    return {
        "empty": (b"", r"empty file"),
        "comments only": (b"# nothing here\n", r"empty file"),
        "binary": (bytes(range(256)), r"not UTF-8"),
        "nul bytes": (valid.encode()[:40] + b"\x00\x00", r"NUL bytes"),
        "truncated": (valid.encode()[: valid.index("num_envs:") + len("num_envs:")],
                      r"learner\.num_envs: expected an integer, got None"),
        "a list": (b"- algorithm: mappo\n", r"expected a mapping"),
        "a number": (b"3\n", r"expected a mapping"),
        "tab indent": (b"learner:\n\tlr: 0.1\n", r"not valid YAML: .*'\\t'"),
        "repeated top key": ((valid + "seed: 9\n").encode(), r"key 'seed' appears twice"),
        "repeated nested key": (valid.replace("learner:\n", "learner:\n  lr: 0.1\n", 1).encode(),
                                r"key 'lr' appears twice .*line \d+"),
        "deep nesting": (nested.encode(), r"nested deeper than 32"),
        "very deep nesting": (("a: " + "[" * 100_000).encode(), r"nested deeper than 32"),
        "alias bomb": (b"a: &a [1, 1, 1, 1, 1, 1, 1, 1]\nb: &b [*a, *a, *a, *a, *a, *a, *a]\n"
                       b"c: [*b, *b, *b, *b, *b, *b, *b, *b]\n", r"anchors \(&a\) are not"),
        "python tag": (b"seed: !!python/object/apply:os.system ['true']\n",
                       r"not valid YAML: could not determine a constructor"),
        "unhashable key": (b"? [1, 2]\n: 3\n", r"not valid YAML: .*unhashable key"),
        "unknown section": ((valid + "learnr:\n  lr: 0.1\n").encode(), r"unknown key 'learnr'"),
        "unknown key": (valid.replace("clip_eps:", "clip_epsilon:").encode(),
                        r"unknown key 'learner\.clip_epsilon'; did you mean 'learner\.clip_eps'"),
        "section a list": (valid.replace("learner:\n", "learner: []\nold:\n", 1).encode(),
                           r"learner: expected a mapping"),
        "wrong type": (valid.replace("num_envs: 4", "num_envs: four").encode(),
                       r"learner\.num_envs: expected an integer, got 'four'"),
        "not an integer": (valid.replace("num_envs: 4", "num_envs: 4.5").encode(),
                           r"learner\.num_envs: expected an integer, got 4\.5"),
        "NaN": (valid.replace("gamma: 0.99", "gamma: .nan").encode(),
                r"learner\.gamma: expected a number, got nan"),
        "infinity": (valid.replace("gamma: 0.99", "gamma: .inf").encode(),
                     r"learner\.gamma: expected a number, got inf"),
        "out of range": (valid.replace("gamma: 0.99", "gamma: 1.5").encode(),
                         r"learner\.gamma: must be in \[0, 1\]"),
        "zero envs": (valid.replace("num_envs: 4", "num_envs: 0").encode(),
                      r"learner\.num_envs: must be >= 1"),
        "huge count": (valid.replace("num_envs: 4", "num_envs: " + "9" * 30).encode(),
                       r"learner\.num_"),
        "long value": (valid.replace("gamma: 0.99", "gamma: '" + "x" * 50_000 + "'").encode(),
                       r"learner\.gamma: expected a number, got 'xxx.*\(50002 characters\)"),
        "unknown method": (valid.replace("method: robust_plr", "method: robust").encode(),
                           r"ued\.method: must be one of"),
        "unknown opponent": (valid.replace("opponent: random", "opponent: heuristic:godlike")
                             .encode(), r"env\.opponent"),
        "stale key": (valid.replace("scenario:\n", "old_scenario:\n", 1).encode(),
                      r"unknown key 'env\.old_scenario'"),
    }


def test_config_corpus_damages_a_valid_config(config_text, tmp_path):
    path = tmp_path / "ok.yaml"
    path.write_text(config_text)
    assert load_config(path).ued.method == "robust_plr"
    for name, (content, _) in config_corpus(config_text).items():
        assert content != config_text.encode(), name


def test_damaged_config_is_one_clear_error_in_every_command(config_text, tmp_path, capsys):
    """`tabx train CONFIG`, `tabx levels sample CONFIG`, `tabx bench ued CONFIG`."""
    for name, (content, pattern) in config_corpus(config_text).items():
        path = tmp_path / f"{name.replace(' ', '-')}.yaml"
        path.write_bytes(content)
        runs = tmp_path / "runs"
        before = tree(tmp_path)
        for argv in (["train", str(path), f"run.dir={runs}", "--quiet", "--max-updates", "1"],
                     ["levels", "sample", str(path), "--n", "1",
                      "--out", str(tmp_path / "levels.png")],
                     ["bench", "ued", str(path), "--steps", "1", "--warmup", "1",
                      "--explorers", "0", "--json", str(tmp_path / "bench.json")]):
            code, out, err = run_cli(capsys, argv)
            assert_one_error(code, out, err, argv, str(path), pattern)
            assert tree(tmp_path) == before, (name, argv, "a file was written")


OVERRIDES = {
    "lr=nan": r"learner\.lr: expected a number, got 'nan'",
    "learner.lr=.inf": r"learner\.lr: expected a number, got inf",
    "learner.lr=[1, 2]": r"learner\.lr: expected a number, got \[1, 2\]",
    "seed=1e400": r"seed: expected an integer",
    "num_envs=0": r"learner\.num_envs: must be >= 1",
    "=3": r"override '=3': expected KEY=VALUE",
    "learner.lrr=1e-3": r"override 'learner\.lrr=1e-3': unknown key 'learner\.lrr'; did you "
                        r"mean 'learner\.lr'",
    "lrr=1e-3": r"override 'lrr=1e-3': unknown key 'lrr'; did you mean 'lr' \(learner\.lr\)",
    "learner=3": r"override 'learner=3': learner is a section",
    "learner.lr.x=3": r"unknown key 'learner\.lr\.x'",
    "env.team=both": r"env\.team: must be one of ally, enemy",
    "env.scenario=": r"env\.scenario",
    "env.scenario=/nonexistent/x.json": r"no such scenario file",
    "ued.buffer_size=-3": r"ued\.buffer_size: must be >= 1",
    "levels.free=[nope]": r"levels\.free: unknown free parameter 'nope'",
    "levels.zone_count=-1": r"levels\.zone_count: expected an integer or a list of them",
    "seed=\x00": r"seed: expected an integer",
    # Values that pass the type check must still be refused before a run folder exists.
    "seed=-1": r"seed: must be an integer in \[0, 2\*\*63\)",
    "seed=1e30": r"seed: must be an integer in \[0, 2\*\*63\)",
    "seed=18446744073709551616": r"seed: must be an integer in \[0, 2\*\*63\)",
    "run.name=" + "n" * 10_000: r"run\.name: must be at most 200 bytes",
    "learner.lr=1e308": r"learner\.lr: must be in \(0, 1\]",
    "learner.lr=1" + "0" * 400: r"learner\.lr: expected a number, got 1000",
    # A learner class by path that does not import, or is not a learner.
    "algorithm=no_such_module:Learner": r"algorithm: no module 'no_such_module'",
    "algorithm=os.path:join": r"algorithm: os\.path:join is not a learner class",
    "algorithm=ued.learners:Nope": r"algorithm: ued\.learners \(.*\) has no 'Nope'",
    # A curriculum class by path that is not one, and a settings section no method here reads.
    "ued.method=os.path:join": r"ued\.method: 'os\.path:join' is not a ued\.curricula\.",
    "novelty.bonus_weight=0.1": r"override 'novelty\.bonus_weight=0\.1': unknown key "
                                r"'novelty\.bonus_weight'",
}


@pytest.mark.parametrize("override", list(OVERRIDES), ids=lambda o: o[:40])
def test_bad_override_is_one_clear_error(override, config_text, tmp_path, capsys):
    path = tmp_path / "ok.yaml"
    path.write_text(config_text)
    before = tree(tmp_path)
    for argv in (["train", str(path), override, f"run.dir={tmp_path / 'runs'}", "--quiet"],
                 ["levels", "sample", str(path), override, "--n", "1",
                  "--out", str(tmp_path / "levels.png")]):
        code, out, err = run_cli(capsys, argv)
        line = assert_one_error(code, out, err, argv, "", OVERRIDES[override])
        assert "allowed in this section" not in line  # the hint, not a list of every field
        assert tree(tmp_path) == before


SUITES = {
    "empty": (b"", r"empty file"),
    "binary": (bytes(range(256)), r"not UTF-8"),
    "a list": (b"- crossfire\n", r"expected a mapping"),
    "repeated key": (b"name: a\nname: b\nentries: []\n", r"key 'name' appears twice"),
    "deep": (b"name: " + b"[" * 60 + b"]" * 60 + b"\n", r"nested deeper than 32"),
    "truncated": ((ROOT / "ued/data/suites/zones-2F1M2Avs2S1K.yaml").read_bytes()[:90],
                  r"not valid YAML|empty file|expected|missing"),
    "unknown scenario": (b"name: x\nentries:\n  - scenario: nope\n",
                         r"entries\[0\]\.scenario: unknown scenario 'nope'"),
}


def test_damaged_suite_is_one_clear_error(finished, tmp_path, capsys):
    for name, (content, pattern) in SUITES.items():
        path = tmp_path / f"{name.replace(' ', '-')}.yaml"
        path.write_bytes(content)
        before = tree(tmp_path)
        argv = ["eval", str(finished), "--suite", str(path), "--episodes", "1",
                "--json", str(tmp_path / "out.json")]
        assert_one_error(*run_cli(capsys, argv), argv, str(path), pattern)
        assert tree(tmp_path) == before


# --- scenario files in the commands that play them ---------------------------------------------


def test_damaged_scenario_is_one_clear_error_in_every_command(config_text, tmp_path, capsys):
    """The scenario corpus of tests/tabx/test_scenario_fuzz.py (there fed to `tabx scenarios`), fed
    to every other command that reads a scenario file."""
    config = tmp_path / "ok.yaml"
    config.write_text(config_text)
    for name, (content, pattern) in SCENARIO_CORPUS.items():
        path = tmp_path / f"{name}.json"
        path.write_bytes(content)
        before = tree(tmp_path)
        for argv in (["rollout", str(path), "--steps", "2", "--gif", str(tmp_path / "a.gif")],
                     ["eval", "--ally", "random", "--enemy", "idle", "--scenario", str(path),
                      "--episodes", "1"],
                     ["bench", "train", "--scenario", str(path), "--algorithms", "ippo",
                      "--num-envs", "2", "--num-steps", "2", "--updates", "1"],
                     ["editor", str(path), "--no-browser", "--no-warmup", "--port", "0"],
                     ["train", str(config), f"env.scenario={path}",
                      f"run.dir={tmp_path / 'runs'}", "--quiet"],
                     ["levels", "sample", str(config), f"env.scenario={path}", "--n", "1",
                      "--out", str(tmp_path / "levels.png")]):
            code, out, err = run_cli(capsys, argv)
            assert_one_error(code, out, err, argv, str(path), pattern)
            assert tree(tmp_path) == before, (name, argv)


# --- level-buffer files ------------------------------------------------------------------------


def buffer_corpus(valid: bytes) -> dict[str, tuple[bytes, str]]:
    return {
        "empty": (b"", r"not a readable level-buffer file"),
        "truncated": (valid[: len(valid) // 2], r"not a readable level-buffer file|truncated"),
        "truncated by one": (valid[:-1], r"not a readable level-buffer file|truncated"),
        "payload bit flip": (valid[:-40] + bytes([valid[-40] ^ 1]) + valid[-39:],
                             r"checksum mismatch|corrupted|not a readable"),
        "header bit flip": (valid[:5] + bytes([valid[5] ^ 1]) + valid[6:],
                            r"not a level-buffer file"),
        "binary": (bytes(range(256)) * 8, r"not a readable level-buffer file"),
        "json": (b'{"magic": "tabx-level-buffer"}', r"not a readable level-buffer file"),
        "scenario file": ((ROOT / "tabx/data/scenarios/challenges/crossfire.json").read_bytes(),
                          r"not a readable level-buffer file"),
    }


BUFFER_COMMANDS = (["inspect"], ["top"], ["show", "{file}", "0"],
                   ["export", "{file}", "0", "--out", "{out}/level.json"],
                   ["hist", "{file}", "units.health"],
                   ["render", "{file}", "--id", "0", "--out", "{out}/level.png"],
                   ["diff", "{file}", "0", "1"])


def buffer_argvs(path: Path, out: Path) -> list[list[str]]:
    argvs = []
    for command in BUFFER_COMMANDS:
        rest = command[1:] if len(command) > 1 else ["{file}"]
        argvs.append(["buffer", command[0], *(a.format(file=path, out=out) for a in rest)])
    return argvs


def test_damaged_buffer_file_is_one_clear_error_in_every_command(finished, tmp_path, capsys):
    valid = (finished / LEVELS_DIR / f"buffer-{STEPS}.msgpack").read_bytes()
    for name, (content, pattern) in buffer_corpus(valid).items():
        path = tmp_path / f"{name.replace(' ', '-')}.msgpack"
        path.write_bytes(content)
        before = tree(tmp_path)
        for argv in buffer_argvs(path, tmp_path):
            assert_one_error(*run_cli(capsys, argv), argv, str(path), pattern)
            assert tree(tmp_path) == before, (name, argv)
    # The valid file works in each (the corpus is damage, not a broken command).
    path = tmp_path / "valid.msgpack"
    path.write_bytes(valid)
    for argv in buffer_argvs(path, tmp_path):
        code, _, err = run_cli(capsys, argv)
        assert code == 0, (argv, err)


# --- hypothesis: mutations of valid files ------------------------------------------------------


@st.composite
def mutated_bytes(draw, base: bytes) -> bytes:
    data = bytearray(base)
    kind = draw(st.sampled_from(["truncate", "flip", "splice"]))
    if kind == "truncate":
        return bytes(data[: draw(st.integers(0, len(data) - 1))])
    if kind == "flip":
        for _ in range(draw(st.integers(1, 3))):
            i = draw(st.integers(0, len(data) - 1))
            data[i] ^= 1 << draw(st.integers(0, 7))
        return bytes(data)
    i = draw(st.integers(0, len(data)))
    return bytes(data[:i]) + draw(st.binary(min_size=1, max_size=12)) + bytes(data[i:])


@pytest.fixture(scope="module")
def scratch(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("mutants")


@FUZZ
@given(data=st.data())
def test_mutated_buffer_file_is_refused_in_one_line(finished, scratch, data, capsys):
    """Any change to a buffer snapshot is refused (its SHA-256 and structure checks), by the
    reader and by `tabx buffer inspect`, as resume's snapshot check reports it."""
    valid = (finished / LEVELS_DIR / f"buffer-{STEPS}.msgpack").read_bytes()
    content = data.draw(mutated_bytes(valid))
    path = scratch / "buffer-4.msgpack"
    path.write_bytes(content)
    if content == valid:
        return
    with pytest.raises(ValueError, match=re.escape(str(path))):
        LevelBuffer.load(path)
    argv = ["buffer", "inspect", str(path)]
    assert_one_error(*run_cli(capsys, argv), argv, str(path))
    (scratch / "state-4.json").write_bytes((finished / LEVELS_DIR / "state-4.json").read_bytes())
    assert str(path) in snapshot_problem(scratch, STEPS, needs_buffer=True)


@FUZZ
@given(data=st.data())
def test_mutated_config_loads_or_is_one_config_error(config_text, scratch, data):
    """A config file with flipped, cut or inserted bytes either loads (the change was
    harmless: a comment, a digit) or raises ConfigError naming the file: nothing else."""
    content = data.draw(mutated_bytes(config_text.encode()))
    path = scratch / "config.yaml"
    path.write_bytes(content)
    try:
        load_config(path)
    except ConfigError as err:
        assert str(err).startswith(f"{path}: "), str(err)[:300]
        assert "\n" not in str(err)


@FUZZ
@given(data=st.data())
def test_mutated_suite_loads_or_is_one_config_error(data):
    base = (ROOT / "ued/data/suites/zones-2F1M2Avs2S1K.yaml").read_bytes()
    content = data.draw(mutated_bytes(base))
    try:
        parse_suite(content, source="suite.yaml")
    except ConfigError as err:
        assert "suite.yaml" in str(err) and "\n" not in str(err), str(err)[:300]


@settings(max_examples=int(os.environ.get("TABX_HYPOTHESIS_EXAMPLES", "8")), deadline=None,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])
@given(data=st.data())
def test_mutated_checkpoint_restores_or_is_one_checkpoint_error(finished, tmp_path_factory,
                                                               data):
    """A checkpoint with one of its files cut, flipped or emptied either restores (the change
    hit bytes no array is read from, or metadata orbax does without; a changed array value is
    caught by the digests, docs/reliability.md) or raises CheckpointError naming the step;
    `check_run_folder` reports it as resume would, without raising."""
    run = tmp_path_factory.mktemp("ck") / "run"
    shutil.copytree(finished, run)
    files = sorted(p for p in (run / CHECKPOINT_DIR / str(STEPS)).rglob("*") if p.is_file())
    target = data.draw(st.sampled_from(files), label="file")
    content = target.read_bytes()
    if content:
        target.write_bytes(data.draw(mutated_bytes(content)))
    else:
        target.write_bytes(b"\xff")
    config = read_run_config(run)
    from ued.experiment import learner_for

    template = learner_for(config).init(jax.random.key(0))
    with Checkpoints(run / CHECKPOINT_DIR, create=False) as checkpoints:
        try:
            checkpoints.restore(template, STEPS)
            restored = True
        except CheckpointError as err:
            assert str(err).startswith(f"{run / CHECKPOINT_DIR / str(STEPS)}: cannot be "
                                       f"restored"), str(err)[:300]
            assert "\n" not in str(err)
            restored = False
    step = {c.step: c for c in check_run_folder(run)}[STEPS]
    assert (step.checkpoint is None) == restored


def test_a_step_metadata_file_orbax_rejects_is_one_checkpoint_error(finished, tmp_path):
    """A flipped byte in a key of step 4's `_CHECKPOINT_METADATA` (JSON that orbax's parser
    refuses as it opens the checkpoints, for every step at once): the folder still opens,
    step 4 is a CheckpointError naming it in `restore` and in the check, and step 2 restores
    (resume's step before). The mutation test above meets this case only by chance."""
    run = tmp_path / "run"
    shutil.copytree(finished, run)
    metadata = run / CHECKPOINT_DIR / str(STEPS) / "_CHECKPOINT_METADATA"
    text = metadata.read_text()
    assert '"init_timestamp_nsecs"' in text
    metadata.write_text(text.replace('"init_timestamp_nsecs"', '"init_timestamp_nsecx"'))
    from ued.experiment import learner_for

    template = learner_for(read_run_config(run)).init(jax.random.key(0))
    with Checkpoints(run / CHECKPOINT_DIR, create=False) as checkpoints:
        assert checkpoints.all() == [2, STEPS]
        with pytest.raises(CheckpointError, match=re.escape(
                f"{run / CHECKPOINT_DIR / str(STEPS)}: cannot be restored (ValueError: ")):
            checkpoints.restore(template, STEPS)
        assert checkpoints.restore(template, 2)[2] == 2
    steps = {c.step: c for c in check_run_folder(run)}
    assert steps[2].intact and "cannot be restored" in steps[STEPS].checkpoint


# --- nothing at exit ---------------------------------------------------------------------------


def test_no_traceback_at_exit(finished, tmp_path):
    """A whole process: orbax's reads left in flight by a failed restore print nothing, neither
    while resume tries the step before nor at interpreter exit."""
    run = tmp_path / "run"
    shutil.copytree(finished, run)
    each_step(run, "checkpoints/{step}/default/manifest.ocdbt", truncate)
    suite = tmp_path / "deep.yaml"
    suite.write_bytes(b"a: " + b"[" * 100_000)
    script = (
        "import sys\n"
        "from tabx_ued.cli import main\n"
        f"codes = [main(['train', '--resume', {str(run)!r}, '--quiet']),\n"
        f"         main(['eval', {str(run)!r}, '--episodes', '1']),\n"
        f"         main(['train', {str(suite)!r}])]\n"
        "print(codes)\n"
        "sys.exit(max(codes))\n")
    env = {**os.environ, "PYTHONPATH": str(ROOT), "TF_CPP_MIN_LOG_LEVEL": "3"}
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                          env=env, timeout=600, cwd=tmp_path)
    assert done.returncode == 2, done.stderr[-3000:]
    assert done.stdout.strip().endswith("[2, 2, 2]"), done.stdout
    err = done.stderr
    for leftover in ("Traceback", "exception was never retrieved", "Event loop is closed",
                     "sys.meta_path is None"):
        assert leftover not in err, err[-3000:]
    errors = [line for line in err.splitlines() if ": error: " in line]
    assert len(errors) == 3, err[-3000:]
    assert "no intact checkpoint to resume from (steps 2, 4)" in errors[0]
    assert "checkpoints/4: cannot be restored" in errors[1]
    assert "nested deeper than 32" in errors[2]
    assert sum(line.startswith("resume: step ") for line in err.splitlines()) == 2


def test_strict_yaml_reads_what_yaml_reads():
    """No false alarms: every shipped config and suite reads as PyYAML reads it."""
    from ued.yaml_reader import read_yaml

    files = sorted((ROOT / "configs").rglob("*.yaml")) + sorted(
        (ROOT / "ued/data/suites").glob("*.yaml"))
    assert len(files) > 30
    for path in files:
        assert read_yaml(path.read_bytes(), str(path)) == yaml.safe_load(path.read_text()), path


def test_a_wrong_value_in_an_override_is_blamed_on_the_override():
    """The override that set a refused value is named, not the config file it overrode."""
    for item, words in (("learner.gamma=[0.5]", "learner.gamma: expected a number"),
                        ("lr=abc", "learner.lr: expected a number"),
                        ("seed=-1", "seed: must be an integer")):
        with pytest.raises(ConfigError) as caught:
            load_config("configs/marl/mappo_crossfire.yaml", [item])
        assert str(caught.value).startswith(f"override {item!r}: {words}"), str(caught.value)
    with pytest.raises(ConfigError, match=r"mappo_crossfire\.yaml: learner\.num_minibatches"):
        load_config("configs/marl/mappo_crossfire.yaml", ["learner.num_envs=3"])


def test_a_config_that_is_not_a_regular_file_is_named_as_such(tmp_path, capsys):
    """`tabx train /dev/zero` or a folder: one line saying what it is (not "no such file")."""
    for path, words in (("/dev/zero", "not a regular file"), (str(tmp_path), "a folder")):
        argv = ["train", path, "--quiet"]
        code, out, err = run_cli(capsys, argv)
        assert_one_error(code, out, err, argv, path, rf"cannot read the config \({words}")


def test_an_extra_argument_shows_the_commands_own_usage(tmp_path, capsys):
    """`tabx eval RUN_A RUN_B`: the usage of `tabx eval`, not the list of every command."""
    code, out, err = run_cli(capsys, ["eval", str(tmp_path / "a"), str(tmp_path / "b")])
    assert code == 2 and "usage: tabx eval" in err, err
    last = err.strip().splitlines()[-1]
    assert last == f"tabx eval: error: unrecognized arguments: {tmp_path / 'b'}", last


def test_envs_that_cannot_fit_in_memory_are_refused_before_the_run_folder(tmp_path, capsys):
    """`learner.num_envs: 100000000`: one line with the memory it needs at least and what the
    machine has, before a run folder exists (shapes only: nothing allocated or compiled)."""
    argv = ["train", "marl/mappo_crossfire", "learner.num_envs=100000000",
            f"run.dir={tmp_path / 'runs'}", "--quiet"]
    code, out, err = run_cli(capsys, argv)
    assert_one_error(code, out, err, argv, "learner.num_envs",
                     r"100000000 envs x 512 steps need at least \d+\.\d GiB .*; this machine's "
                     r"\w+ memory is \d+\.\d GiB")
    assert not (tmp_path / "runs").exists()


def free_port() -> int:
    import socket

    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


# An address a run cannot join (`RAY_ADDRESS`, else `ray.address`): one line naming the setting
# the user set, at once, before a run folder exists (Ray itself would fail with a cut
# ValueError, or retry a closed `ray://` port for half a minute and blame the token).
ADDRESSES = {
    ("RAY_ADDRESS", "http://127.0.0.1:8265"): r"RAY_ADDRESS: 'http://127\.0\.0\.1:8265' is a "
                                               r"dashboard's \(HTTP\) address",
    ("RAY_ADDRESS", "ray://127.0.0.1:{port}"): r"RAY_ADDRESS: 'ray://127\.0\.0\.1:\d+' is a Ray "
                                               r"Client address",
    ("RAY_ADDRESS", "garbage"): r"RAY_ADDRESS: expected 'auto' or HOST:PORT .*'garbage'",
    ("RAY_ADDRESS", "127.0.0.1:{port}"): r"RAY_ADDRESS: no Ray head answers at 127\.0\.0\.1:",
    ("ray.address", "garbage"): r"ray\.address: expected 'auto' or HOST:PORT.*'garbage'",
}


@pytest.mark.parametrize("setting,address", list(ADDRESSES), ids=lambda v: v.split(":")[0])
def test_an_address_no_run_can_join_is_one_line_naming_its_setting(setting, address, tmp_path,
                                                                   capsys, monkeypatch):
    config = tmp_path / "tiny.yaml"
    config.write_text(ued_config("robust_plr").to_yaml())
    value = address.format(port=free_port())
    argv = ["train", str(config), "--ray", "--run-dir", str(tmp_path / "never"), "--quiet"]
    if setting == "RAY_ADDRESS":
        monkeypatch.setenv("RAY_ADDRESS", value)
    else:
        monkeypatch.delenv("RAY_ADDRESS", raising=False)
        argv.append(f"ray.address={value}")
    code, out, err = run_cli(capsys, argv)
    assert_one_error(code, out, err, argv, f"{setting}: ", ADDRESSES[setting, address])
    assert not (tmp_path / "never").exists()


# --- options and settings a run would take silently, or fail on late ---------------------------


TRAIN_ARGUMENTS = {
    # The local driver reads no ray.* setting: dropped without a word before.
    "ray overrides without --ray": (["ray.learners=4", "ray.schedule=continuous"],
                                    r"override 'ray\.learners=4': ray\.learners: a setting of "
                                    r"runs on Ray, and this run is not on Ray"),
    "a bare ray field without --ray": (["explorers=3"], r"override 'explorers=3': "
                                                        r"ray\.explorers: a setting of runs"),
    "--address empty": (["--ray", "--address", ""], r"--address: empty"),
    "--address host:": (["--ray", "--address", "localhost:"],
                        r"ray\.address: expected 'auto' or HOST:PORT .*got 'localhost:'"),
    "--address port 99999": (["--ray", "--address", "127.0.0.1:99999"],
                             r"ray\.address: expected .*a port in 1\.\.65535"),
    "--address http://": (["--ray", "--address", "http://127.0.0.1:{port}"],
                          r"ray\.address: 'http://127\.0\.0\.1:\d+' is a dashboard's"),
    "--address ray:// closed": (["--ray", "--address", "ray://127.0.0.1:{port}"],
                                r"ray\.address: 'ray://127\.0\.0\.1:\d+' is a Ray Client address"),
    # An IPv6 host in brackets is reached (not looked up as the name "[::1]"): what listens
    # there is no Ray head.
    "--address [::1] of another server": (["--ray", "--address", "[::1]:{v6port}"],
                                          r"ray\.address: \[::1\]:\d+ is not a Ray head"),
    "ray.max_inflight 1e9": (["--ray", "ray.max_inflight=1000000000"],
                             r"ray\.max_inflight: must be in \[1, 64\]"),
    "ray.placement_timeout_s 1e308": (["--ray", "ray.placement_timeout_s=1e308"],
                                      r"ray\.placement_timeout_s: must be in \(0, 86400\]"),
    "env.max_steps 10^12": (["env.max_steps=1000000000000"],
                            r"env\.max_steps: must be in \[1, 2\*\*31 - 1\]"),
    # A rollout shorter than an episode ends one only by an elimination: a buffer that may
    # admit no level (Robust PLR then trains nothing, and exited 0).
    "a buffer that may admit no level": (["learner.num_steps=4", "learner.total_timesteps=64"],
                                         r"learner\.num_steps: 4 steps per rollout, below "
                                         r"env\.max_steps \(8\): a level enters robust_plr's "
                                         r"buffer only when"),
}


@pytest.mark.parametrize("case", list(TRAIN_ARGUMENTS))
def test_train_refuses_what_it_would_drop_or_fail_on_late(case, config_text, tmp_path, capsys):
    """One line before a run folder exists (the address checks are immediate)."""
    import contextlib
    import socket
    import threading

    path = tmp_path / "ok.yaml"
    path.write_text(config_text)
    args, pattern = TRAIN_ARGUMENTS[case]
    with socket.socket(socket.AF_INET6) as server:  # a web server, as far as Ray can tell
        try:
            server.bind(("::1", 0))
        except OSError:
            pytest.skip("no IPv6 loopback here")
        server.listen()

        def refuse() -> None:
            with contextlib.suppress(OSError):  # the server closed
                while True:
                    connection = server.accept()[0]
                    with connection:
                        connection.recv(4096)
                        connection.sendall(b"HTTP/1.1 400 Bad Request\r\n\r\n")

        threading.Thread(target=refuse, daemon=True).start()
        ports = {"port": free_port(), "v6port": server.getsockname()[1]}
        argv = ["train", str(path), *(a.format(**ports) for a in args),
                f"run.dir={tmp_path / 'runs'}", "--quiet", "--max-updates", "1"]
        before = tree(tmp_path)
        assert_one_error(*run_cli(capsys, argv), argv, "", pattern)
        assert tree(tmp_path) == before


@pytest.mark.parametrize("option,value", [("--seconds", "inf"), ("--batch-s", "inf"),
                                          ("--batch-s", "1e308"), ("--learner-s", "nan"),
                                          ("--simulate", "100000000")])
def test_bench_ued_simulate_bounds_its_options(option, value, capsys):
    """`--seconds inf` ran until killed, `--batch-s inf` ended in an "unexpected"
    OverflowError, `--simulate 100000000` in a MemoryError: each is one usage line."""
    argv = ["bench", "ued", "--simulate", "1", option, value]
    code, out, err = run_cli(capsys, argv)
    lines = [line for line in err.splitlines() if line.strip()]
    assert code == 2 and "Traceback" not in err, err[-2000:]
    assert re.fullmatch(rf"tabx bench ued: error: argument {option}: .*(<=|in \().*", lines[-1])


def test_run_folders_are_named_from_what_they_train():
    """A shipped config names its runs by `{key}`s of what they train: an override of the
    method or the free parameter changes the name (`quickstart` wrote
    quickstart_robust_plr_zone-* for an SFL run)."""
    assert load_config("quickstart").run_name == "quickstart_robust_plr_zone"
    assert load_config("quickstart", ["ued.method=sfl"]).run_name == "quickstart_sfl_zone"
    assert (load_config("quickstart", ["levels.free=[unit_spec]"]).run_name
            == "quickstart_robust_plr_unit_spec")
    assert load_config("ued/accel_zone", ["ued.method=dr"]).run_name == "dr_zone"
    assert load_config("marl/mappo_crossfire", ["algorithm=ippo"]).run_name == "ippo_crossfire"
    assert load_config("marl/mappo_crossfire").to_dict()["run"]["name"] == "mappo_crossfire"
    with pytest.raises(ConfigError, match=r"run\.name: \{nope\} names no config key"):
        load_config("quickstart", ["run.name=x_{nope}"])
    with pytest.raises(ConfigError, match=r"run\.name: \{learner\} is a section"):
        load_config("quickstart", ["run.name=x_{learner}"])


MAKE_ENV = {
    "max_steps 10^12": ({"max_steps": 10**12}, r"max_steps must be an integer in \[1, 2\*\*31"),
    "max_steps 10.7": ({"max_steps": 10.7}, r"max_steps must be an integer"),
    "max_steps True": ({"max_steps": True}, r"max_steps must be an integer"),
    "start_noise NaN": ({"start_noise": float("nan")}, r"start_noise must be a number"),
    "start_noise negative": ({"start_noise": -1.0}, r"start_noise must be a number"),
    "start_noise 1e30": ({"start_noise": 1e30}, r"start_noise must be a number .*\[0, 1000\]"),
    "shuffle_positions 'no'": ({"shuffle_positions": "no"},
                               r"shuffle_positions must be True or False, got 'no'"),
}


@pytest.mark.parametrize("case", list(MAKE_ENV))
def test_make_env_refuses_arguments_out_of_range(case):
    pytest.importorskip("jaxmarl")
    from tabx.compat.jaxmarl import make_env

    kwargs, pattern = MAKE_ENV[case]
    with pytest.raises(ValueError, match=pattern):
        make_env("crossfire", **kwargs)
    make_env("crossfire", max_steps=10.0, start_noise=2, shuffle_positions=False)  # fine


def test_a_step_folder_orbax_never_wrote_is_reported_without_warnings(finished, tmp_path,
                                                                       capsys, caplog):
    """A bogus `checkpoints/999/`: `runs check` names it damaged, with no orbax warning about
    its missing metadata file before (six of them, one per look)."""
    run = tmp_path / "run"
    shutil.copytree(finished, run)
    (run / CHECKPOINT_DIR / "999").mkdir()
    argv = ["runs", "check", str(run)]
    code, out, err = run_cli(capsys, argv)
    assert code == 1 and "step 999: damaged" in out and "newest intact step: 4" in out, out
    assert not [r for r in caplog.records if "Metadata file does not exist" in r.getMessage()]
    assert "WARNING" not in err, err


def test_runs_check_says_which_intact_steps_are_unchecked(finished, tmp_path, capsys):
    """A checkpoint without `_CHECKPOINT_METADATA` restores, but its digests are gone: the
    step is intact as far as it was checked, and the line says its arrays were not."""
    run = tmp_path / "run"
    shutil.copytree(finished, run)
    (run / CHECKPOINT_DIR / str(STEPS) / "_CHECKPOINT_METADATA").unlink()
    code, out, err = run_cli(capsys, ["runs", "check", str(run)])
    assert code == 0, out + err
    assert "  step 2: intact\n" in out, out
    assert re.search(r"step 4: intact as far as it was checked: .*no digests .*unchecked", out)


def test_abandoned_orbax_reads_are_not_reported():
    """Orbax's read coroutines closed unfinished (a truncated array file) turn their
    GeneratorExit into an exception Python can only report: one traceback each, 459 to 1261
    lines after `runs check` and `--resume` had said what was wrong. The unraisable hook of
    ued/checkpoint.py drops those reports, and only those."""
    import inspect
    import types

    from orbax.checkpoint._src.serialization import serialization

    from ued.checkpoint import _is_abandoned_read

    read = serialization._read_array_index_and_device_put
    arguments = {name: None for name, p in inspect.signature(read).parameters.items()
                 if p.default is inspect.Parameter.empty}
    coroutine = read(**arguments)  # never started: its body does not run
    try:
        def report(exc: BaseException, where: object) -> types.SimpleNamespace:
            return types.SimpleNamespace(exc_type=type(exc), exc_value=exc, exc_traceback=None,
                                         err_msg=None, object=where)

        closed = Exception("Encountered error while reading array index: (slice(0, 16, 1),)")
        closed.__cause__ = GeneratorExit()
        assert _is_abandoned_read(report(closed, coroutine))
        assert _is_abandoned_read(report(RuntimeError("Event loop is closed"), None))
        assert not _is_abandoned_read(report(ValueError("something else"), coroutine))
        other = Exception("mine")
        other.__cause__ = GeneratorExit()
        assert not _is_abandoned_read(report(other, report))  # not an orbax coroutine
    finally:
        coroutine.close()

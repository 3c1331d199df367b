"""`tabx buffer ...`: output of every action and clear user errors. One test goes through
`tabx_ued.cli.main` (the registrar is found and wired); the others use a parser holding only
`tabx_ued.buffer_commands`, so that sibling registrars being edited cannot break these tests."""

from __future__ import annotations

import argparse
import json
import sys

import numpy as np
import pytest

import tabx_ued.cli as tabx_cli
from level_buffer import LevelBuffer, Source
from tabx.errors import UserError
from tabx_ued import buffer_commands as buffer_cli


@pytest.fixture
def buffer_file(tmp_path):
    template = {"units": {"health": np.zeros(3, np.float32), "kind": np.zeros(3, np.int32)},
                "arena": np.zeros(2, np.float32)}
    buf = LevelBuffer(template, capacity=10, seed=0)
    batch = {"units": {"health": np.array([[10, 20, 30], [10, 25, 30], [1, 2, 3]], np.float32),
                       "kind": np.array([[0, 1, 2], [0, 1, 2], [5, 5, 5]], np.int32)},
             "arena": np.full((3, 2), 1.1, np.float32)}
    buf.insert_batch(batch, [0.5, 0.9, 0.1], policy_versions=[3, 4, 4], max_returns=1.0)
    child = {"units": {k: v[:1] + 1 for k, v in batch["units"].items()},
             "arena": batch["arena"][:1]}
    buf.insert_batch(child, [0.7], sources=Source.MUTATION, parent_ids=0)
    buf.sample(4)
    return buf.save(tmp_path / "buffer.msgpack")


def main(argv: list[str]) -> int:
    """tabx_ued.cli.main's dispatch, with only the buffer registrar."""
    parser = argparse.ArgumentParser(prog="tabx")
    sub = parser.add_subparsers(dest="command")
    buffer_cli.add_parser(sub)
    args = parser.parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except UserError as err:
        print(f"tabx {args.command}: error: {err}", file=sys.stderr)
        return 2


def run(capsys, *argv):
    code = main(["buffer", *map(str, argv)])
    out = capsys.readouterr()
    return code, out.out, out.err


def test_through_tabx_cli_main(capsys, buffer_file):
    assert tabx_cli.main(["buffer", "top", str(buffer_file), "-k", "1"]) == 0
    assert "0.9" in capsys.readouterr().out
    assert tabx_cli.main(["buffer", "show", str(buffer_file), "42"]) == 2
    assert "no level with id 42" in capsys.readouterr().err


def test_inspect(capsys, buffer_file):
    code, out, _ = run(capsys, "inspect", buffer_file)
    assert code == 0
    assert "4 / 10 levels" in out and "clock 8" in out
    assert "score" in out and "median" in out and "staleness" in out
    assert "random 3 (75.0%)" in out and "mutation 1 (25.0%)" in out
    assert "lineage depth: 0: 3, 1: 1" in out
    assert "policy versions: 2 distinct" in out
    assert "gradient updates when it scored the level, not the run's update count" in out


def test_top(capsys, buffer_file):
    code, out, _ = run(capsys, "top", buffer_file, "-k", 2)
    lines = out.strip().splitlines()
    assert code == 0 and len(lines) == 3
    assert lines[1].split()[:3] == ["1", "1", "0.9"] and lines[2].split()[:3] == ["2", "3", "0.7"]


def test_show_and_export(capsys, buffer_file, tmp_path):
    code, out, _ = run(capsys, "show", buffer_file, 3)
    data = json.loads(out)
    assert code == 0 and data["id"] == 3
    assert data["record"]["source"] == "mutation" and data["record"]["parent_id"] == 0
    assert data["level"]["units.health"] == [11.0, 21.0, 31.0]
    assert data["level"]["arena"] == [1.1, 1.1]  # float32 shown by its shortest repr
    target = tmp_path / "out" / "level.json"
    code, out, _ = run(capsys, "export", buffer_file, 3, "--out", target)
    assert code == 0 and json.loads(target.read_text()) == data


def test_hist(capsys, buffer_file, tmp_path):
    code, out, _ = run(capsys, "hist", buffer_file, "units.kind")
    assert code == 0 and "12 values from 4 levels" in out
    assert any(line.split()[:2] == ["5", "3"] for line in out.splitlines())
    code, out, _ = run(capsys, "hist", buffer_file, "units.health", "--bins", 3)
    assert code == 0 and out.count("#") > 0
    pytest.importorskip("matplotlib")
    png = tmp_path / "h.png"
    code, _, _ = run(capsys, "hist", buffer_file, "units.health", "--png", png)
    assert code == 0 and png.read_bytes()[:4] == b"\x89PNG"


def test_diff(capsys, buffer_file):
    code, out, _ = run(capsys, "diff", buffer_file, 0, 1)
    assert code == 0
    assert "units.health (1 of 3 differ): [1] 20.0 -> 25.0" in out
    assert "1 of 3 fields differ" in out
    code, out, _ = run(capsys, "diff", buffer_file, 0, 0)
    assert "identical" in out


def test_user_errors(capsys, buffer_file, tmp_path):
    code, _, err = run(capsys, "show", buffer_file, 99)
    assert code == 2 and "no level with id 99" in err and str(buffer_file) in err
    code, _, err = run(capsys, "hist", buffer_file, "units.nope")
    assert code == 2 and "no level field 'units.nope'" in err and "units.health" in err
    code, _, err = run(capsys, "inspect", tmp_path / "missing.msgpack")
    assert code == 2 and "cannot read" in err
    bad = tmp_path / "bad.msgpack"
    data = bytearray(buffer_file.read_bytes())
    data[-100] ^= 0xFF
    bad.write_bytes(bytes(data))
    code, _, err = run(capsys, "inspect", bad)
    assert code == 2 and "bad.msgpack" in err and "Traceback" not in err
    code, _, err = run(capsys, "top", buffer_file, "-k", 0)
    assert code == 2


def test_png_without_matplotlib(capsys, buffer_file, tmp_path, monkeypatch):
    import builtins

    real_import = builtins.__import__

    def no_matplotlib(name, *args, **kwargs):
        if name.startswith("matplotlib"):
            raise ImportError("no matplotlib")
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_matplotlib)
    code, _, err = run(capsys, "hist", buffer_file, "units.health", "--png", tmp_path / "x.png")
    assert code == 2 and "--png needs matplotlib" in err


def test_show_and_export_tabx_levels_as_scenarios(capsys, tmp_path):
    """A buffer of TABX levels exports scenario files that `tabx rollout` opens."""
    import jax

    from tabx.scenarios import load_file, load_named

    scenario = load_named("crossfire")
    level = jax.tree.map(np.asarray, scenario.to_level())
    buf = LevelBuffer(level, capacity=4)
    result = buf.insert(level, 0.5)
    path = tmp_path / "tabx_levels.msgpack"
    buf.save(path)
    level_id = int(np.asarray(result.ids).reshape(-1)[0])

    assert tabx_cli.main(["buffer", "show", str(path), str(level_id)]) == 0
    assert '"format": "tabx-scenario/1"' in capsys.readouterr().out
    out_file = tmp_path / "exported.json"
    argv = ["buffer", "export", str(path), str(level_id), "--out", str(out_file)]
    assert tabx_cli.main(argv) == 0
    exported = load_file(out_file)
    assert [u.unit for u in exported.units] == [u.unit for u in scenario.units]
    assert tabx_cli.main(["rollout", str(out_file), "--steps", "5"]) == 0
    assert "outcome: still running after 5 steps" in capsys.readouterr().out

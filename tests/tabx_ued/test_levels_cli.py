"""`tabx levels sample`: a grid picture of generated levels (or a chain of ACCEL mutations)."""

from __future__ import annotations

from pathlib import Path

from PIL import Image

from tabx_ued.cli import main

CONFIG = str(Path(__file__).resolve().parents[2] / "configs" / "ued" / "quickstart.yaml")


def test_sample_writes_a_grid_of_levels(tmp_path, capsys):
    out = tmp_path / "levels.png"
    assert main(["levels", "sample", CONFIG, "--n", "3", "--columns", "2", "--scale", "2",
                 "--out", str(out)]) == 0
    assert "wrote 3 generated levels (free: zone)" in capsys.readouterr().out
    one = Image.open(out)
    # Two columns, two rows of equal tiles.
    assert one.width > one.height * 0.9 and one.width % 2 == 0
    out2 = tmp_path / "chain.png"
    assert main(["levels", "sample", CONFIG, "levels.free=[unit_spec]", "--mutate", "--n", "2",
                 "--columns", "2", "--scale", "2", "--out", str(out2)]) == 0
    assert "a level and its ACCEL children (free: unit_spec)" in capsys.readouterr().out
    assert Image.open(out2).size[0] == one.size[0]


def test_sample_reports_bad_input(tmp_path, capsys):
    out = str(tmp_path / "x.png")
    assert main(["levels", "sample", CONFIG, "--n", "0", "--out", out]) == 2
    assert "--n: expected 1 to 64 levels, got 0" in capsys.readouterr().err
    assert main(["levels", "sample", CONFIG, "levels.nois=0.2", "--out", out]) == 2
    assert "levels.nois" in capsys.readouterr().err
    assert main(["levels", "sample", CONFIG, "--out", str(tmp_path / "x.gif")]) == 2
    assert "--out" in capsys.readouterr().err

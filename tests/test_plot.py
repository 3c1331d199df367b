"""`tabx plot`: learning curves of run folders as a PNG, tags with wildcards, clear errors."""

from __future__ import annotations

from PIL import Image

from tabx.cli import main
from ued.plot import matching
from ued.tensorboard import SummaryWriter


def fake_run(folder, win_rates):
    with SummaryWriter(folder / "events") as writer:
        for i, w in enumerate(win_rates):
            writer.scalars({"episode/win_rate": w, "eval/zones-x/mean_win_rate": w / 2,
                            "eval/units-y/mean_win_rate": w / 3}, step=(i + 1) * 100)
    return str(folder)


def test_plot_draws_one_panel_per_matched_tag(tmp_path, capsys):
    a = fake_run(tmp_path / "a", [0.1, 0.5, 0.9])
    b = fake_run(tmp_path / "b", [0.2, 0.3])
    out = tmp_path / "curves.png"
    assert main(["plot", a, b, "--tag", "episode/win_rate", "--tag", "eval/*/mean_win_rate",
                 "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "wrote 3 panels (episode/win_rate, eval/units-y/mean_win_rate, " \
           "eval/zones-x/mean_win_rate)" in text
    width, height = Image.open(out).size
    assert width > height  # two columns, two rows


def test_plot_errors_name_the_problem(tmp_path, capsys):
    run = fake_run(tmp_path / "a", [0.1])
    assert main(["plot", str(tmp_path / "nope"), "--out", str(tmp_path / "x.png")]) == 2
    assert "not a run folder (no events/ folder)" in capsys.readouterr().err
    assert main(["plot", run, "--tag", "loss/zzz", "--out", str(tmp_path / "x.png")]) == 2
    assert "none of the tags loss/zzz is in these runs" in capsys.readouterr().err
    assert main(["plot", run, "--out", str(tmp_path / "x.jpg")]) == 2
    assert "--out must name a .png file" in capsys.readouterr().err


def test_matching_wildcards():
    tags = ["eval/a/mean_win_rate", "eval/a/b@c/win_rate", "episode/win_rate"]
    assert matching(tags, "eval/*/mean_win_rate") == ["eval/a/mean_win_rate"]
    assert matching(tags, "episode/win_rate") == ["episode/win_rate"]
    assert matching(tags, "loss/*") == []


def test_matmul_dtype_plot_tool_draws_the_learning_comparison(tmp_path):
    """tools/plot_matmul_dtype.py (the figure of docs/learners.md, "Matmul precision")."""
    import json
    import subprocess
    import sys
    from pathlib import Path

    battle, crossfire = tmp_path / "battle.jsonl", tmp_path / "crossfire.jsonl"
    battle.write_text("".join(
        json.dumps({"algorithm": a, "dtype": d, "seed": s, "win_rate": [0.1, 0.5 + s / 10]}) + "\n"
        for a in ("mappo", "ippo") for d in ("float32", "bfloat16") for s in range(2)))
    metrics = [{"episode/length": 150.0 + i, "loss/entropy": 2.0 - i / 10} for i in range(3)]
    crossfire.write_text("".join(
        json.dumps({"algorithm": a, "dtype": d, "metrics": metrics}) + "\n"
        for a in ("mappo", "ippo") for d in ("float32", "bfloat16")))
    out = tmp_path / "img" / "dtype.png"
    tool = Path(__file__).resolve().parent.parent / "tools" / "plot_matmul_dtype.py"
    done = subprocess.run([sys.executable, str(tool), str(battle), str(crossfire), "--out",
                           str(out)], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    width, height = Image.open(out).size
    assert width > 2 * height  # three panels side by side

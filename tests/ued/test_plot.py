"""`tabx plot`: learning curves of run folders as a PNG, tags with wildcards, clear errors."""

from __future__ import annotations

from PIL import Image

from tabx_ued.cli import main
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

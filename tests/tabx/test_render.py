"""`tabx.render`: what a frame shows (zones, units, teams, the dead, view wedges, hurtboxes),
image sizes, trajectories and GIFs, atomic writes, and the `render` CLI commands."""

from __future__ import annotations

import jax
import numpy as np
import pytest
from PIL import Image

import tabx_ued.cli as tabx_cli
from level_buffer import LevelBuffer
from tabx import constants as C
from tabx import render
from tabx.env import TabxEnv
from tabx.params import make_level
from tabx.render import (
    render_frame,
    render_level,
    render_trajectory,
    save_gif,
    save_png,
    world_to_pixel,
)
from tabx.scenarios import config_for, load_named

ARCHER, MAMMOTH, KING = 0, 1, 3  # crossfire's slots: archer, mammoth, archer | 3 kings


@pytest.fixture(scope="module")
def crossfire():
    scenario = load_named("crossfire")
    config = config_for([scenario])
    level = scenario.to_level(config)
    state = jax.device_get(jax.jit(TabxEnv(config).initial_state)(level))
    return config, level, state


@pytest.fixture(scope="module")
def start_image(crossfire):
    config, level, _ = crossfire
    return np.asarray(render_level(config, level))


def disc_pixels(image: np.ndarray, level, slot: int, frac: float = 0.8) -> np.ndarray:
    """RGB pixels within frac * radius of a unit's centre (default scale 8)."""
    position = np.asarray(level.units.position)[slot]
    cx, cy = world_to_pixel(level, position)
    r = frac * float(level.units.radius[slot]) * 8.0
    ys, xs = np.mgrid[0:image.shape[0], 0:image.shape[1]]
    inside = (xs + 0.5 - cx) ** 2 + (ys + 0.5 - cy) ** 2 <= r * r
    return image[inside].astype(int)


def share_near(pixels: np.ndarray, colour: tuple[int, int, int], tol: int = 40) -> float:
    return float(np.mean(np.abs(pixels - np.array(colour)).max(-1) <= tol))


def pixel(image: np.ndarray, level, xy) -> np.ndarray:
    x, y = world_to_pixel(level, np.asarray(xy, float))
    return image[int(y), int(x)].astype(int)


def test_size_and_arena_placement(crossfire, start_image):
    config, level, _ = crossfire
    h, w, channels = start_image.shape
    assert channels == 3
    assert 121 * 8 <= w <= 121 * 8 + 60 and 78 * 8 <= h <= 78 * 8 + 140
    small = render_level(config, level, scale=4.0)
    assert abs(small.width - (121 * 4 + (w - 121 * 8) / 2)) <= 20 and small.height < h
    # The arena's floor fills its rectangle; outside it is the (lighter) margin.
    floor = pixel(start_image, level, (45.0, 25.0))  # off the 10-unit grid
    assert np.abs(floor - render.ARENA_FILL).max() <= 12
    outside = pixel(start_image, level, (61.5, 0.0))  # in the margin
    assert np.abs(outside - render.BACKGROUND).max() <= 3


def test_zones_units_and_team_colours(crossfire, start_image):
    _, level, _ = crossfire
    lava = pixel(start_image, level, level.zones.centre[0])
    assert lava[0] > lava[1] + 60 and lava[0] > lava[2] + 100, lava
    assert share_near(disc_pixels(start_image, level, MAMMOTH), render.TEAM_COLOURS[C.ALLY]) > 0.6
    assert share_near(disc_pixels(start_image, level, KING), render.TEAM_COLOURS[C.ENEMY]) > 0.4
    assert share_near(disc_pixels(start_image, level, KING), render.TEAM_COLOURS[C.ALLY]) == 0


def test_bush_and_swamp_colours(crossfire):
    config = crossfire[0]
    zones = [dict(type="lava", centre=(-30, 0), semi_axes=(6, 4), effect=10.0),
             dict(type="bush", centre=(0, 0), semi_axes=(6, 4)),
             dict(type="swamp", centre=(30, 0), semi_axes=(6, 4), effect=0.5)]
    units = [dict(unit="farmer", position=(0, -30))]
    level = make_level(config, units, units, zones)
    image = np.asarray(render_level(config, level))
    a = render.ZONE_ALPHA / 255
    for j, colour in enumerate(render.ZONE_COLOURS.values()):
        got = pixel(image, level, (-30 + 30 * j + 2.5, 1.5))  # off the grid lines
        expected = a * np.array(colour) + (1 - a) * np.array(render.ARENA_FILL)
        assert np.abs(got - expected).max() <= 20, (j, got, expected)
    empty = pixel(image, level, (2.5, 21.5))  # the fourth zone slot is empty: nothing drawn
    assert np.abs(empty - render.ARENA_FILL).max() <= 12


def test_dead_units_are_grey(crossfire):
    config, level, state = crossfire
    dead = state.replace(alive=state.alive.copy(), health=state.health.copy())
    dead.alive[MAMMOTH] = False
    dead.health[MAMMOTH] = 0.0
    image = np.asarray(render_frame(config, level, dead))
    pixels = disc_pixels(image, level, MAMMOTH)
    assert share_near(pixels, render.DEAD_COLOUR, tol=30) > 0.6
    assert share_near(pixels, render.TEAM_COLOURS[C.ALLY]) == 0
    # The header counts the living.
    alive = np.asarray(render_frame(config, level, state))
    assert not np.array_equal(image[:40], alive[:40])


def test_fov_and_hurtbox_change_the_picture(crossfire, start_image):
    config, level, state = crossfire
    with_fov = np.asarray(render_level(config, level, show_fov=True))
    ahead = np.asarray(level.units.position[ARCHER]) + [6.0, 0.0]  # inside its view wedge
    assert np.abs(pixel(with_fov, level, ahead) - pixel(start_image, level, ahead)).sum() > 15
    behind = np.asarray(level.units.position[ARCHER]) - [6.0, 0.0]
    assert np.array_equal(pixel(with_fov, level, behind), pixel(start_image, level, behind))

    attacking = np.zeros(config.num_units, bool)
    attacking[ARCHER] = True
    info = {"attacking": attacking, "hit": np.zeros(config.num_units, bool)}
    shot = np.asarray(render_frame(config, level, state, info=info))
    reach = np.asarray(level.units.position[ARCHER]) + [15.0, 0.0]  # archer range 27, +x
    assert np.abs(pixel(shot, level, reach) - pixel(start_image, level, reach)).sum() > 15
    hidden = np.asarray(render_frame(config, level, state, info=info, show_hurtbox=False))
    assert np.array_equal(hidden, start_image)


def test_jax_and_numpy_inputs_agree_and_batches_are_refused(crossfire, start_image):
    config, level, state = crossfire
    assert np.array_equal(np.asarray(render_frame(config, jax.device_get(level), state)),
                          start_image)
    batch = jax.tree.map(lambda x: np.stack([x, x]), jax.device_get(level))
    with pytest.raises(ValueError, match="batch"):
        render_level(config, batch)
    with pytest.raises(ValueError, match="scale"):
        render_level(config, level, scale=0.0)


def test_trajectory_stops_after_done_and_gif_loops(crossfire, tmp_path):
    config, level, state = crossfire
    T = 5
    states = jax.tree.map(lambda x: np.stack([x] * T), state)
    states = states.replace(step=np.arange(T, dtype=np.int32), done=np.arange(T) >= 2,
                            won=np.tile([False, True], (T, 1)))
    infos = {"attacking": np.zeros((T, config.num_units), bool)}
    frames = render_trajectory(config, level, states, infos, title="t")
    assert len(frames) == 3 and all(f.size == frames[0].size for f in frames)
    assert not np.array_equal(np.asarray(frames[0]), np.asarray(frames[1]))  # the step counter
    path = save_gif(frames, tmp_path / "episode.gif", fps=5)
    with Image.open(path) as gif:
        assert gif.format == "GIF" and gif.n_frames == 3
        assert gif.info["loop"] == 0 and gif.info["duration"] == 200
    with pytest.raises(ValueError):
        save_gif([], tmp_path / "empty.gif")


@pytest.mark.slow  # compiles the step (seconds)
def test_trajectory_of_a_scan(crossfire):
    config, level, _ = crossfire
    env = TabxEnv(config)

    @jax.jit
    def play(key):
        _, state = env.reset(key, level)

        def body(state, k):
            actions = jax.random.randint(k, (config.num_units,), 0, C.NUM_ACTIONS)
            _, state, _, _, info = env.step(k, state, actions, level)
            return state, (state, info)

        return jax.lax.scan(body, state, jax.random.split(key, 4))[1]

    states, infos = play(jax.random.key(0))
    frames = render_trajectory(config, level, states, infos, show_fov=True)
    assert len(frames) == 4


def test_files_are_written_atomically(crossfire, tmp_path, monkeypatch):
    config, level, _ = crossfire
    calls = []
    real = render.atomic_write_bytes
    monkeypatch.setattr(render, "atomic_write_bytes",
                        lambda path, data: calls.append(path) or real(path, data))
    image = render_level(config, level, scale=2.0)
    png = save_png(image, tmp_path / "level.png")
    gif = save_gif([image, image], tmp_path / "level.gif")
    assert calls == [png, gif]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["level.gif", "level.png"]
    with Image.open(png) as back:
        assert back.format == "PNG" and back.size == image.size
        assert np.array_equal(np.asarray(back.convert("RGB")), np.asarray(image))


def test_cli_scenarios_render(capsys, tmp_path):
    out = tmp_path / "crossfire.png"
    assert tabx_cli.main(["scenarios", "render", "crossfire", "--out", str(out), "--fov",
                          "--scale", "4"]) == 0
    assert "wrote" in capsys.readouterr().out
    with Image.open(out) as image:
        assert image.format == "PNG" and 121 * 4 <= image.width <= 121 * 4 + 60
    assert tabx_cli.main(["scenarios", "render", "no_such_level", "--out", str(out)]) == 2
    assert "no_such_level" in capsys.readouterr().err
    missing = tmp_path / "nowhere" / "x.png"
    assert tabx_cli.main(["scenarios", "render", "crossfire", "--out", str(missing)]) == 2
    assert "does not exist" in capsys.readouterr().err and not missing.parent.exists()
    assert tabx_cli.main(["scenarios", "render", "crossfire", "--out", str(out),
                          "--scale", "-1"]) == 2
    assert "--scale" in capsys.readouterr().err


def test_cli_buffer_render(capsys, tmp_path):
    level = jax.tree.map(np.asarray, load_named("crossfire").to_level())
    buf = LevelBuffer(level, capacity=4)
    level_id = int(np.asarray(buf.insert(level, 0.5).ids).reshape(-1)[0])
    path = buf.save(tmp_path / "tabx.msgpack")
    out = tmp_path / "level.png"
    argv = ["buffer", "render", str(path), "--id", str(level_id), "--out", str(out)]
    assert tabx_cli.main(argv) == 0
    assert f"wrote level {level_id}" in capsys.readouterr().out
    with Image.open(out) as image:
        assert image.format == "PNG" and image.width >= 121 * 8
    assert tabx_cli.main([*argv[:3], "--id", "99", "--out", str(out)]) == 2
    assert "no level with id 99" in capsys.readouterr().err

    other = LevelBuffer({"x": np.zeros(3, np.float32)}, capacity=4)
    other_id = int(np.asarray(other.insert({"x": np.ones(3, np.float32)}, 0.1).ids)
                   .reshape(-1)[0])
    other_path = other.save(tmp_path / "other.msgpack")
    argv = ["buffer", "render", str(other_path), "--id", str(other_id), "--out", str(out)]
    assert tabx_cli.main(argv) == 2
    assert "not a TABX level" in capsys.readouterr().err

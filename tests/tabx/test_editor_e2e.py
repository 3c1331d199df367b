"""The editor end to end in headless Chromium (Debian's package, driven by Playwright).

Open the editor, place two allies and an enemy, draw a bush, rotate a unit, edit the enemy's
health (an out-of-range value first: the error shows next to the field), take a screenshot of
the canvas and check it is not blank, save; then load the saved file with the simulator and
check the values. Skips only when /usr/bin/chromium or playwright is missing (`.ci/run`
installs both).
"""

from __future__ import annotations

import io
import json
import math
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "tools"))

from editor_screenshot import (  # noqa: E402 - tools/, beside the tests
    VIEWPORT,
    chromium_missing,
    launch_chromium,
    start_server,
)

_missing = chromium_missing()
pytestmark = pytest.mark.skipif(_missing is not None, reason=f"browser test: {_missing}")


@pytest.fixture(scope="module")
def browser():
    """One headless Chromium for the module (starting it is the slow part)."""
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        chromium = launch_chromium(p)
        yield chromium
        chromium.close()


@pytest.fixture()
def editor(browser, tmp_path: Path, monkeypatch: pytest.MonkeyPatch):
    """(page, user folder): a fresh editor server on a free port and a page showing it."""
    user = tmp_path / "user"
    monkeypatch.setenv("TABX_SCENARIO_DIR", str(user))
    server, _ = start_server()
    errors: list[str] = []
    page = browser.new_page(viewport=VIEWPORT, bypass_csp=True)  # CSP forbids eval
    try:
        page.set_default_timeout(10_000)
        page.on("pageerror", lambda err: errors.append(f"page error: {err}"))
        page.on("console", lambda m: errors.append(f"console: {m.text}")
                if m.type == "error" and "409 (Conflict)" not in m.text else None)
        page.goto(server.url)
        page.wait_for_function("window.editorDebug && window.editorDebug.ready")
        yield page, user
    finally:
        page.close()
        server.shutdown()
        server.server_close()
    assert not errors, errors


def _client(page, x: float, y: float) -> tuple[float, float]:
    pt = page.evaluate("([x, y]) => editorDebug.worldToClient(x, y)", [x, y])
    return pt["x"], pt["y"]


def _cell(page, i: int, j: int) -> tuple[float, float]:
    c = page.evaluate("([i, j]) => editorDebug.cellCentre(i, j)", [i, j])
    return c["x"], c["y"]


def _not_blank(png: bytes) -> dict[str, int]:
    from PIL import Image

    image = np.asarray(Image.open(io.BytesIO(png)).convert("RGB")).astype(int)
    r, g, b = image[..., 0], image[..., 1], image[..., 2]
    return {
        "colours": len(np.unique(image.reshape(-1, 3), axis=0)),
        "ally_px": int(((b > 150) & (r < 90) & (g > 60) & (g < 150)).sum()),  # #2f6fdc
        "enemy_px": int(((r > 170) & (g < 90) & (b < 90)).sum()),  # #d23a3a
        "bush_px": int(((g > r + 20) & (g > b + 20)).sum()),  # green over sand
    }


def test_place_draw_rotate_edit_save(editor):
    page, user = editor
    tid = page.get_by_test_id

    # Two allies (an archer and a farmer) and an enemy king, each by a click on a grid cell.
    ally1, ally2, enemy = _cell(page, 6, 5), _cell(page, 6, 12), _cell(page, 21, 9)
    tid("team-ally").click()
    tid("palette-unit-archer").click()
    page.mouse.click(*_client(page, *ally1))
    tid("palette-unit-farmer").click()
    page.mouse.click(*_client(page, *ally2))
    tid("team-enemy").click()
    tid("palette-unit-theking").click()
    page.mouse.click(*_client(page, *enemy))
    units = page.evaluate("editorDebug.scenario().units")
    assert [(u["unit"], u["team"]) for u in units] == [
        ("archer", "ally"), ("farmer", "ally"), ("theking", "enemy")]
    assert units[2]["heading"] == pytest.approx(math.pi)  # enemies face -x

    # A bush: drag a box from (-10, -6) to (4, 8) in Zones mode.
    tid("mode-zones").click()
    tid("palette-zone-bush").click()
    page.mouse.move(*_client(page, -10, -6))
    page.mouse.down()
    page.mouse.move(*_client(page, -3, 1), steps=4)
    page.mouse.move(*_client(page, 4, 8), steps=4)
    page.mouse.up()
    zones = page.evaluate("editorDebug.scenario().zones")
    assert len(zones) == 1 and zones[0]["type"] == "bush"
    assert zones[0]["centre"] == pytest.approx([-3, 1], abs=0.15)
    assert zones[0]["semi_axes"] == pytest.approx([7, 7], abs=0.15)

    # Rotate the archer: hover it, Q twice (+15 degrees each).
    tid("mode-units").click()
    page.mouse.move(*_client(page, *ally1))
    page.keyboard.press("q")
    page.keyboard.press("q")
    assert page.evaluate("editorDebug.scenario().units[0].heading") == pytest.approx(math.pi / 6)

    # Edit the king's health: an out-of-range value is refused with the error by the field.
    page.mouse.click(*_client(page, *enemy))
    assert page.evaluate("editorDebug.selection()") == {"kind": "unit", "index": 2}
    health = tid("prop-health")
    health.fill("-5")
    health.press("Enter")
    assert "(0, 1e5]" in tid("err-health").inner_text()
    assert "overrides" not in page.evaluate("editorDebug.scenario().units[2]")
    health.fill("250")
    health.press("Enter")
    assert not tid("err-health").is_visible()
    assert page.evaluate("editorDebug.scenario().units[2].overrides") == {"health": 250}
    page.wait_for_function("editorDebug.validation() && editorDebug.validation().ok")

    # The canvas shows the arena, both teams and the bush.
    page.mouse.move(5, 5)  # no hover ring over the shot
    stats = _not_blank(tid("canvas").screenshot())
    assert stats["colours"] > 50, stats
    assert stats["ally_px"] > 30 and stats["enemy_px"] > 30 and stats["bush_px"] > 500, stats

    # Save into the challenges folder of the user scenario folder.
    tid("btn-save").click()
    tid("save-name").fill("e2e_duel")
    tid("save-category").select_option("challenge")
    tid("save-ok").click()
    page.wait_for_function(
        "document.querySelector('[data-testid=status-msg]').textContent.startsWith('Saved')")
    path = user / "challenges" / "e2e_duel.json"
    assert path.is_file()

    # Load it with the simulator and check what the editor wrote.
    import jax

    from tabx.env import TabxEnv
    from tabx.scenarios import config_for, load_named

    scenario = load_named(str(path))
    assert scenario.name == "e2e_duel" and scenario.category == "challenge"
    archer, farmer, king = scenario.units
    assert archer.position == pytest.approx(ally1) and farmer.position == pytest.approx(ally2)
    assert king.position == pytest.approx(enemy)
    assert archer.heading == pytest.approx(math.pi / 6)
    assert king.overrides == {"health": 250.0} and king.stats()["max_health"] == 250.0
    (bush,) = scenario.zones
    assert bush.type == "bush" and bush.semi_axes == pytest.approx((7, 7), abs=0.15)
    config = config_for([scenario])
    level = scenario.to_level(config)
    _, state = jax.jit(TabxEnv(config).reset)(jax.random.key(0), level)  # eager is slow
    assert np.asarray(state.health)[np.asarray(level.units.active)].tolist() == [40, 60, 250]
    assert json.loads(path.read_text())["format"] == "tabx-scenario/1"

    # Saving again under the same name asks before replacing the file.
    tid("btn-save").click()
    tid("save-ok").click()
    tid("save-overwrite").wait_for(state="visible")
    assert "exists" in tid("save-error").inner_text()
    tid("save-overwrite").click()
    page.wait_for_function("!document.querySelector('#dlg-save').open")


def test_grid_drag_delete_undo_and_server_errors(editor):
    page, _ = editor
    tid = page.get_by_test_id
    units = lambda: page.evaluate("editorDebug.scenario().units")  # noqa: E731

    # A mammoth takes 2 x 2 cells around a grid corner: it cannot go where it would cover
    # the farmer's cell, and goes one corner further up-right.
    tid("palette-unit-farmer").click()
    page.mouse.click(*_client(page, *_cell(page, 9, 9)))
    tid("palette-unit-mammoth").click()
    centre = _cell(page, 10, 10)
    page.mouse.click(*_client(page, centre[0] - 1.0, centre[1] - 1.0))  # corner (10, 10)
    assert len(units()) == 1 and "taken" in tid("status-msg").inner_text()
    page.mouse.click(*_client(page, centre[0] + 1.0, centre[1] + 1.0))  # corner (11, 11)
    spacing = page.evaluate("editorDebug.grid().s")
    assert units()[1]["unit"] == "mammoth"
    assert units()[1]["position"] == pytest.approx([centre[0] + spacing / 2,
                                                    centre[1] + spacing / 2])
    page.mouse.click(*_client(page, *_cell(page, 9, 9)), button="right")  # delete the farmer
    tid("palette-unit-farmer").click()

    # Place a farmer, drag it three cells right (it snaps to the cell centre).
    start, end = _cell(page, 3, 3), _cell(page, 6, 3)
    page.mouse.click(*_client(page, *start))
    page.mouse.move(*_client(page, *start))
    page.mouse.down()
    page.mouse.move(*_client(page, end[0] + 0.7, end[1] - 0.4), steps=5)
    page.mouse.up()
    assert units()[1]["position"] == pytest.approx(list(end))

    # Undo the move, redo it; right-click deletes; Ctrl+Z brings the unit back.
    page.keyboard.press("Control+z")
    assert units()[1]["position"] == pytest.approx(list(start))
    page.keyboard.press("Control+y")
    assert units()[1]["position"] == pytest.approx(list(end))
    page.mouse.click(*_client(page, *end), button="right")
    assert [u["unit"] for u in units()] == ["mammoth"]
    tid("btn-undo").click()
    assert [u["unit"] for u in units()] == ["mammoth", "farmer"]

    # A radius that pushes the unit out of the arena passes the range check (0, 20] but not
    # the server's validator: its error shows next to the position field.
    tid("team-enemy").click()
    page.mouse.click(*_client(page, *_cell(page, 20, 12)))
    page.wait_for_function("editorDebug.validation() && editorDebug.validation().ok")
    page.mouse.click(*_client(page, *_cell(page, 0, 0)))
    assert page.evaluate("editorDebug.selection()") == {"kind": "unit", "index": 3}
    tid("prop-radius").fill("5")
    tid("prop-radius").press("Enter")
    page.wait_for_function("editorDebug.validation() && !editorDebug.validation().ok")
    assert page.evaluate("editorDebug.validation().error.path") == "units[3].position[0]"
    assert "outside" in tid("err-x").inner_text()
    assert "outside" in tid("status-valid").inner_text()

    # Load a bundled scenario from the Load dialog by searching for it.
    tid("btn-load").click()
    tid("load-row-crossfire").wait_for()
    tid("load-search").fill("crossf")
    tid("load-search").press("Enter")
    page.wait_for_function("editorDebug.scenario().name === 'crossfire'")
    assert len(units()) == 6
    page.wait_for_function("editorDebug.validation().ok")  # the old error is gone

"""The editor server's JSON API over real HTTP: units, listing, load, validate, save, preview,
and the plumbing (static files, Host check, content type); plus `tabx editor` argument errors.
"""

from __future__ import annotations

import copy
import json
import math
import threading
import time
import urllib.error
import urllib.request
from pathlib import Path

import numpy as np
import pytest

from tabx import constants as C
from tabx import params as P
from tabx.editor.server import make_server
from tabx.scenarios import (
    UNIT_STAT_RANGES,
    Scenario,
    dumps_scenario,
    list_scenarios,
    load_file,
    load_named,
)
from tabx_ued import cli

DUEL = {
    "format": "tabx-scenario/1",
    "name": "duel",
    "category": "user",
    # The enemy comes first in the file: the preview must still report units in file order.
    "units": [
        {"unit": "farmer", "team": "enemy", "position": [25.0, 0.0], "heading": math.pi},
        {"unit": "archer", "team": "ally", "position": [-10.0, 0.0], "heading": 0.0,
         "overrides": {"health": 30.0, "max_health": 50.0}},
    ],
    "zones": [{"type": "lava", "centre": [-10.0, 0.0], "semi_axes": [3.0, 3.0], "effect": 0.5}],
}


@pytest.fixture(scope="module")
def server():
    srv = make_server(0)
    thread = threading.Thread(target=srv.serve_forever, kwargs={"poll_interval": 0.05},
                              daemon=True)
    thread.start()
    yield srv
    srv.shutdown()
    srv.server_close()


@pytest.fixture(autouse=True)
def user_dir(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """Every test gets an empty user scenario folder."""
    folder = tmp_path / "user"
    monkeypatch.setenv("TABX_SCENARIO_DIR", str(folder))
    return folder


def request(server, method: str, path: str, body=None, headers=None, raw: bytes | None = None
            ) -> tuple[int, dict | bytes, dict]:
    data = raw if raw is not None else (None if body is None else json.dumps(body).encode())
    hdrs = {"Content-Type": "application/json"} if data is not None else {}
    hdrs.update(headers or {})
    req = urllib.request.Request(server.url.rstrip("/") + path, data=data, method=method,
                                 headers=hdrs)
    try:
        with urllib.request.urlopen(req, timeout=120) as resp:
            status, payload, rh = resp.status, resp.read(), dict(resp.headers)
    except urllib.error.HTTPError as err:
        status, payload, rh = err.code, err.read(), dict(err.headers)
    if rh.get("Content-Type", "").startswith("application/json"):
        return status, json.loads(payload), rh
    return status, payload, rh


def get(server, path):
    return request(server, "GET", path)[:2]


def post(server, path, body):
    return request(server, "POST", path, body)[:2]


# --- GET ---------------------------------------------------------------------------------------


def test_units_serves_the_validators_tables(server):
    status, body = get(server, "/api/units")
    assert status == 200
    assert [u["name"] for u in body["units"]] == list(C.UNIT_NAMES)
    assert {u["name"]: u["space"] for u in body["units"]}["mammoth"] == 2
    king = next(u for u in body["units"] if u["name"] == "theking")
    assert king["stats"]["health"] == 346.0 and king["stats"]["max_health"] == 346.0
    for key, rng in UNIT_STAT_RANGES.items():
        served = body["stat_ranges"][key]
        assert (served["lo"], served["hi"], served["lo_open"], served["hi_open"]) == (
            rng.lo, rng.hi, rng.lo_open, rng.hi_open)
    assert body["zone_effect_ranges"]["swamp"]["hi"] == 1.0
    assert body["grid_default"] == {"spacing": 4.25, "margin": 0.0}
    assert "medium" in body["tiers"]


def test_list_bundled_and_user_scenarios(server, user_dir):
    status, body = get(server, "/api/scenarios")
    assert status == 200
    names = {e["name"]: e for e in body["scenarios"]}
    assert set(names) == set(list_scenarios(include_user=False))
    assert sum(e["category"] == "challenge" for e in body["scenarios"]) == 13
    assert names["crossfire"]["units_text"] == "1M2A vs 3K" and names["crossfire"]["zones"] == 4
    assert names["1S-1"]["split"] == "eval" and names["1S-1"]["category"] == "zones"
    # A saved file and a broken one show up as user scenarios; the broken one with its error.
    (user_dir / "units").mkdir(parents=True)
    (user_dir / "units" / "mine.json").write_text(
        json.dumps({**DUEL, "name": "mine", "category": "units"}))
    (user_dir / "broken.json").write_text("{not json")
    body = get(server, "/api/scenarios")[1]
    names = {e["name"]: e for e in body["scenarios"]}
    assert names["mine"]["source"] == "user" and names["mine"]["category"] == "units"
    assert names["mine"]["file"] == "units/mine.json"
    assert "invalid JSON" in names["broken"]["error"]


def test_load_by_name(server, user_dir):
    status, body = get(server, "/api/scenario?name=crossfire")
    assert status == 200 and body["source"] == "bundled"
    assert body["scenario"] == load_named("crossfire").to_dict()
    status, body = get(server, "/api/scenario?name=2F1M2Avs2S1K_2L2B2S")
    assert status == 200 and body["source"] == "composed" and len(body["scenario"]["zones"]) == 6
    (user_dir / "zones").mkdir(parents=True)
    (user_dir / "zones" / "mine.json").write_text(json.dumps({**DUEL, "name": "mine"}))
    status, body = get(server, "/api/scenario?name=mine")
    assert status == 200 and body["source"] == "user" and len(body["scenario"]["units"]) == 2
    status, body = get(server, "/api/scenario?name=crosfire")
    assert status == 404 and "crossfire" in body["error"]["message"]
    for bad in ("/etc/passwd", "..%2Fsecret.json", "x.json", ""):
        status, body = get(server, f"/api/scenario?name={bad}")
        assert status == 400 and body["error"]["path"] == "name", bad


# --- validate ----------------------------------------------------------------------------------


def test_validate_reports_field_paths(server):
    status, body = post(server, "/api/validate", {"scenario": DUEL})
    assert status == 200 and body["ok"] and body["summary"]["allies"] == 1
    bad = copy.deepcopy(DUEL)
    bad["units"][1]["overrides"]["health"] = -5
    body = post(server, "/api/validate", {"scenario": bad})[1]
    assert not body["ok"]
    assert body["error"]["path"] == "units[1].overrides.health"
    assert "(0, 100000]" in body["error"]["message"]
    bad = copy.deepcopy(DUEL)
    bad["units"][0]["position"] = [60.0, 0.0]
    body = post(server, "/api/validate", {"scenario": bad})[1]
    assert body["error"]["path"] == "units[0].position[0]" and "59.5" in body["error"]["message"]
    bad = copy.deepcopy(DUEL)
    bad["zones"][0]["type"] = "lavva"
    body = post(server, "/api/validate", {"scenario": bad})[1]
    assert body["error"]["path"] == "zones[0].type" and "did you mean 'lava'" in body[
        "error"]["message"]
    body = post(server, "/api/validate", {"nothing": 1})[1]
    assert not body["ok"] and "scenario" in body["error"]["message"]


# --- save --------------------------------------------------------------------------------------


def test_save_validates_and_writes_atomically(server, user_dir):
    status, body = post(server, "/api/save", {"scenario": DUEL, "name": "my_duel",
                                              "category": "challenge"})
    assert status == 200 and body["ok"], body
    path = user_dir / "challenges" / "my_duel.json"
    assert body["path"] == str(path)
    saved = load_file(path)
    assert saved.name == "my_duel" and saved.category == "challenge"
    assert saved == Scenario.from_dict({**DUEL, "name": "my_duel", "category": "challenge"})
    assert path.read_text() == dumps_scenario(saved)  # the same writer as the library
    assert [p.name for p in path.parent.iterdir()] == ["my_duel.json"]  # no temp file left
    # The editor lists and loads it by name.
    assert get(server, "/api/scenario?name=my_duel")[1]["scenario"]["name"] == "my_duel"

    # Overwriting needs overwrite=true.
    changed = copy.deepcopy(DUEL)
    changed["units"][0]["position"] = [20.0, 5.0]
    request_body = {"scenario": changed, "name": "my_duel", "category": "challenge"}
    status, body = post(server, "/api/save", request_body)
    assert status == 409 and body["exists"] and body["can_overwrite"]
    assert load_file(path).units[0].position == (25.0, 0.0)
    status, body = post(server, "/api/save", {**request_body, "overwrite": True})
    assert status == 200 and load_file(path).units[0].position == (20.0, 5.0)
    # The same name in another category folder would make loading by name ambiguous.
    status, body = post(server, "/api/save", {**request_body, "category": "units",
                                              "overwrite": True})
    assert status == 409 and not body["can_overwrite"]
    assert not (user_dir / "units").exists()


@pytest.mark.parametrize("name", ["../evil", "a/b", "a\\b", ".hidden", "", "x" * 101, 7])
def test_save_refuses_bad_names(server, user_dir, name):
    status, body = post(server, "/api/save", {"scenario": DUEL, "name": name, "category": "user"})
    assert status == 400 and body["error"]["path"] == "name"
    assert not user_dir.exists() or not any(user_dir.rglob("*.json"))


def test_save_refuses_invalid_content_and_bundled_names(server, user_dir):
    bad = copy.deepcopy(DUEL)
    bad["units"][1]["overrides"]["health"] = 60.0  # above max_health 50
    status, body = post(server, "/api/save", {"scenario": bad, "name": "x", "category": "user"})
    assert status == 400 and body["error"]["path"] == "units[1].overrides.health"
    assert "exceeds max_health" in body["error"]["message"]
    status, body = post(server, "/api/save", {"scenario": DUEL, "name": "crossfire",
                                              "category": "challenge"})
    assert status == 400 and "bundled" in body["error"]["message"]
    status, body = post(server, "/api/save", {"scenario": DUEL, "name": "x", "category": "nope"})
    assert status == 400 and body["error"]["path"] == "category"
    assert not user_dir.exists()


# --- preview -----------------------------------------------------------------------------------


def test_preview_runs_the_simulator_and_caches_the_compiled_function(server):
    body = {"scenario": DUEL, "steps": 40, "ally": "idle", "enemy": "random", "seed": 3}
    status, first = post(server, "/api/preview", body)
    assert status == 200 and first["ok"], first
    assert first["controllers"] == ["idle", "random"]
    assert len(first["position"]) == len(first["health"]) == 41  # the start and 40 steps
    assert np.asarray(first["position"]).shape == (41, 2, 2)
    # File order: unit 0 is the enemy farmer (random), unit 1 the idle ally archer.
    pos = np.asarray(first["position"])
    assert pos[0].tolist() == [[25.0, 0.0], [-10.0, 0.0]]
    assert np.allclose(pos[:, 1], [-10.0, 0.0])  # idle: never moves
    assert not np.allclose(pos[:, 0], [25.0, 0.0])  # random: wanders
    # The archer stands in lava (0.5 health per second): exactly the simulator's health loss.
    dt = P.PHYSICS_PRESETS["default"]["dt"]
    health = np.asarray(first["health"])
    assert np.allclose(health[:, 1], 30.0 - 0.5 * dt * np.arange(41), atol=1e-3)
    assert first["max_health"] == [60.0, 50.0]
    assert all(first["alive"][-1])
    cooldown = np.asarray(first["cooldown"])
    assert cooldown.min() >= 0.0 and cooldown.max() <= 1.0
    assert first["done_at"] is None and first["winner"] is None

    # Another preview of the same size (other seed, steps in the same bucket, one more zone)
    # reuses the compiled function.
    scenario = copy.deepcopy(DUEL)
    scenario["zones"].append({"type": "bush", "centre": [0, 0], "semi_axes": [2, 2]})
    t0 = time.perf_counter()
    status, second = post(server, "/api/preview", {**body, "scenario": scenario, "steps": 60,
                                                   "seed": 4})
    elapsed = time.perf_counter() - t0
    assert status == 200 and not second["compiled"] and len(second["health"]) == 61
    assert elapsed < 2.0, elapsed
    assert np.allclose(np.asarray(second["position"])[:, 1], [-10.0, 0.0])

    # Hot lava kills the archer on the first step: the enemies win by elimination.
    scenario = copy.deepcopy(DUEL)
    scenario["zones"][0]["effect"] = 100.0
    third = post(server, "/api/preview", {**body, "scenario": scenario})[1]
    assert not third["compiled"]
    assert (third["done_at"], third["winner"], third["outcome"]) == (1, "enemy", "elimination")
    assert third["alive"][1] == [True, False] and third["health"][-1][1] == 0.0


@pytest.mark.parametrize("change, path", [
    ({"steps": 0}, "steps"),
    ({"steps": 100000}, "steps"),
    ({"ally": "external"}, "ally"),
    ({"enemy": "heuristic:godlike"}, "enemy"),
    ({"seed": -1}, "seed"),
    ({"scenario": {**DUEL, "units": DUEL["units"][:1]}}, "units"),
])
def test_preview_errors_name_the_field(server, change, path):
    status, body = post(server, "/api/preview", {"scenario": DUEL, "steps": 10, "ally": "random",
                                                 "enemy": "random", **change})
    assert status == 400 and body["error"]["path"] == path, body


@pytest.mark.slow
def test_preview_with_heuristic_tiers(server):
    """Heuristic against heuristic; a second tier pair reuses the compiled function."""
    crossfire = load_named("crossfire").to_dict()
    body = {"scenario": crossfire, "steps": 200, "ally": "heuristic:expert",
            "enemy": "heuristic:novice"}
    first = post(server, "/api/preview", body)[1]
    assert first["ok"] and len(first["health"]) == 201
    second = post(server, "/api/preview", {**body, "ally": "heuristic:novice",
                                           "enemy": "heuristic:expert"})[1]
    assert second["ok"] and not second["compiled"]
    assert first["health"] != second["health"]


# --- plumbing ----------------------------------------------------------------------------------


def test_static_files_and_request_guards(server):
    status, page, headers = request(server, "GET", "/")
    assert status == 200 and b"/static/editor.js" in page
    assert headers["Content-Type"].startswith("text/html")
    assert "default-src 'self'" in headers["Content-Security-Policy"]
    status, js, headers = request(server, "GET", "/static/editor.js")
    assert status == 200 and headers["Content-Type"].startswith("text/javascript")
    assert b"editorDebug" in js
    assert request(server, "GET", "/static/editor.css")[0] == 200
    for bad in ("/static/../server.py", "/static/server.py", "/nope", "/api/nope"):
        assert request(server, "GET", bad)[0] == 404, bad
    status, body, _ = request(server, "GET", "/api/units", headers={"Host": "evil.example:80"})
    assert status == 403
    status, body, _ = request(server, "POST", "/api/validate", raw=b"{}",
                              headers={"Content-Type": "text/plain"})
    assert status == 415
    status, body, _ = request(server, "POST", "/api/validate", raw=b"{nope")
    assert status == 400 and "invalid JSON" in body["error"]["message"]
    status, body, _ = request(server, "POST", "/api/validate", raw=b'{"scenario": NaN}')
    assert status == 400


def test_cli_editor_arguments(capsys):
    assert cli.main(["editor", "nosuchscenario", "--no-browser"]) == 2
    assert "unknown scenario" in capsys.readouterr().err
    assert cli.main(["editor", "--port", "70000", "--no-browser"]) == 2

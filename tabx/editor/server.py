"""The editor's HTTP server: static page files from the package and a small JSON API.

Stdlib only (`http.server.ThreadingHTTPServer`), bound to 127.0.0.1. Routes:

| route | what it does |
|---|---|
| `GET /` and `GET /static/FILE` | the page (`tabx/editor/static/`) |
| `GET /api/units` | unit types with default stats, every range table, zone types, tiers |
| `GET /api/session` | the scenario named on the command line (or null) and the user folder |
| `GET /api/scenarios` | bundled and user scenarios: name, category, split, source, counts |
| `GET /api/scenario?name=N` | one scenario (bundled, user or a `UNITS_ZONES` composition) |
| `POST /api/validate` | `{scenario}`: `{ok: true, summary}` or `{ok: false, error}` |
| `POST /api/save` | `{scenario, name, category, overwrite}`: validate, then write atomically |
| `POST /api/preview` | `{scenario, steps, ally, enemy, seed}`: play it in the simulator |

Errors are JSON `{ok: false, error: {message, path, text}}`; `path` is the field path of a
`ScenarioError` (`units[2].overrides.health`), which the page shows next to the field.

Saving goes through the same validator as `tabx scenarios validate` and writes
`<user_scenario_dir()>/<folder>/<name>.json` (folders `challenges`, `units`, `zones`, `user` by
category) with `tabx.files.atomic_write_text`; never into the installed package. Names are the
scenario-format names (no path separators); an existing file is replaced only with
`overwrite: true`, and a name used by a bundled scenario or by a user file in another folder is
refused (loading by name would find the other file).

The API only serves names, never paths: a page cannot make the server read an arbitrary file.
A request needs exactly one `Host` header (two: 400) naming the server's own loopback address
(another: 403, DNS rebinding); an absolute-form request URI (`POST http://host/api/save`) must
name it too (400). Every request but GET and HEAD with an `Origin` other than the server's own
page is refused (403) before anything else, and POST bodies must be `application/json` (a
cross-site form cannot post one without a preflight, which the server does not answer).
At most MAX_CONNECTIONS connections are served at once (one thread each); the next ones are
answered 503 and closed at once.

Request bodies are bounded before anything is read: a POST needs a `Content-Length` of plain
digits (missing: 411, chunked: 411, negative or not a number: 400, over MAX_BODY: 413). A
request refused before its body was read is answered with `Connection: close`, so the unread
bytes are never parsed as a next request. Bodies are parsed with the scenario files' strict JSON
reader (`tabx.scenarios.format.parse_json_bytes`: no NaN, no repeated keys, bounded nesting), and
the free-text fields are bounded by the validator (name 100, description MAX_DESCRIPTION
characters). Other methods (PUT, DELETE, PATCH) get 405. Every error is a JSON answer.
"""

from __future__ import annotations

import functools
import json
import math
import re
import threading
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from importlib import resources
from pathlib import Path
from typing import Any
from urllib.parse import parse_qs, urlsplit

from tabx import constants as C
from tabx.files import atomic_write_text
from tabx.scenarios import (
    ARENA_RANGE,
    CATEGORIES,
    FORMAT,
    HEURISTIC_RANGES,
    PHYSICS_RANGES,
    UNIT_STAT_RANGES,
    ZONE_EFFECT_RANGES,
    Range,
    Scenario,
    ScenarioError,
    dumps_scenario,
    list_scenarios,
    load_file,
    load_named,
    user_scenario_dir,
)
from tabx.scenarios.format import (
    HEADING_RANGE,
    MAX_DESCRIPTION,
    NAME_PATTERN,
    SEMI_AXIS_RANGE,
    ZONE_TYPES,
    parse_json_bytes,
)
from tabx.scenarios.registry import USER_FOLDERS, _user_files, bundled_category

HOST = "127.0.0.1"
STATIC_TYPES = {".html": "text/html; charset=utf-8", ".js": "text/javascript; charset=utf-8",
                ".css": "text/css; charset=utf-8", ".png": "image/png", ".svg": "image/svg+xml"}
STATIC_NAME = re.compile(r"^[a-z0-9_\-]+\.(html|js|css|png|svg)$")
MAX_BODY = 8 * 1024 * 1024
MAX_QUERY_NAME = 201  # a composition UNITS_ZONES of two 100-character names
CONTENT_LENGTH = re.compile(r"[0-9]{1,15}")
SOCKET_TIMEOUT_S = 120  # a client that stops sending mid-request is dropped after this
MAX_CONNECTIONS = 32  # a browser opens about 6 per host; the rest would be threads for nothing
READ_METHODS = ("GET", "HEAD")
GRID_DEFAULTS = {"spacing": 4.25, "margin": 0.0}  # the reference editor: 28 x 18 on 121 x 78
CSP = ("default-src 'self'; img-src 'self' data:; style-src 'self' 'unsafe-inline'; "
       "script-src 'self'; connect-src 'self'; object-src 'none'; base-uri 'none'; "
       "frame-ancestors 'none'")


class EditorError(Exception):
    """An API error: HTTP status, message and optional field path."""

    def __init__(self, status: int, message: str, path: str = "", **extra: Any) -> None:
        super().__init__(message)
        self.status, self.message, self.path, self.extra = status, message, path, extra

    def payload(self) -> dict[str, Any]:
        text = f"{self.path}: {self.message}" if self.path else self.message
        return {"ok": False, "error": {"message": self.message, "path": self.path, "text": text},
                **self.extra}


def _describe(value: Any) -> str:
    text = repr(value)
    return (text[:60] + "...") if len(text) > 60 else text


def _scenario_error(err: ScenarioError, status: int = 400, **extra: Any) -> EditorError:
    return EditorError(status, err.message, err.path, **extra)


def _range(r: Range) -> dict[str, Any]:
    return {"lo": r.lo, "hi": r.hi, "lo_open": r.lo_open, "hi_open": r.hi_open, "text": str(r)}


def _summary(s: Scenario) -> dict[str, Any]:
    from tabx.scenarios.summary import composition, zone_summary

    return {"name": s.name, "category": s.category, "split": s.split or "train",
            "allies": len(s.allies), "enemies": len(s.enemies), "zones": len(s.zones),
            "units_text": (f"{composition(s.allies)} vs {composition(s.enemies)}"
                           if s.units else "-"),
            "zones_text": zone_summary(s), "description": s.description or "",
            "arena": list(s.arena)}


@functools.lru_cache(maxsize=1)
def _bundled_entries() -> tuple[dict[str, Any], ...]:
    """Summaries of every bundled scenario (they never change while the server runs)."""
    entries = []
    for name in list_scenarios(include_user=False):
        entry = _summary(load_named(name))
        entry.update(source="bundled", category=bundled_category(name) or entry["category"])
        entries.append(entry)
    return tuple(entries)


def user_files() -> dict[str, Path]:
    """name -> file of every user scenario (the registry's view: folder, then category folders)."""
    return _user_files()


def units_info() -> dict[str, Any]:
    """Everything the palette and the property panel need; the one source of the ranges."""
    from tabx.params import HEURISTIC_TIERS, PHYSICS_PRESETS

    units = []
    for index, spec in enumerate(C.UNIT_SPECS):
        stats = {k: getattr(spec, k) for k in UNIT_STAT_RANGES if k != "max_health"}
        stats["max_health"] = spec.health
        stats["heals"] = spec.heals
        units.append({"name": spec.name, "char": spec.char, "index": index, "space": spec.space,
                      "stats": stats})
    return {
        "format": FORMAT,
        "units": units,
        "stat_ranges": {k: _range(r) for k, r in UNIT_STAT_RANGES.items()},
        "stat_order": [*UNIT_STAT_RANGES, "heals"],
        "zone_types": list(ZONE_TYPES),
        "zone_effect_ranges": {k: _range(r) for k, r in ZONE_EFFECT_RANGES.items()},
        "zone_effect_defaults": {"lava": 10.0, "bush": 0.0, "swamp": 0.5},
        "arena_range": _range(ARENA_RANGE),
        "semi_axis_range": _range(SEMI_AXIS_RANGE),
        "heading_range": _range(HEADING_RANGE),
        "physics_ranges": {k: _range(r) for k, r in PHYSICS_RANGES.items()},
        "heuristic_ranges": {k: _range(r) for k, r in HEURISTIC_RANGES.items()},
        "physics_presets": list(PHYSICS_PRESETS),
        "tiers": list(HEURISTIC_TIERS),
        "categories": list(CATEGORIES),
        "user_folders": USER_FOLDERS,
        "name_pattern": NAME_PATTERN.pattern,
        "max_description": MAX_DESCRIPTION,
        "arena_default": [C.ARENA_WIDTH, C.ARENA_HEIGHT],
        "grid_default": GRID_DEFAULTS,
        "max_preview_steps": _preview_module().MAX_PREVIEW_STEPS,
        "pi": math.pi,
    }


def _preview_module():
    from tabx.editor import preview

    return preview


class EditorApp:
    """The API's logic, independent of HTTP (the handler maps routes onto these methods)."""

    def __init__(self, initial: Scenario | None = None) -> None:
        self.initial = initial
        self._save_lock = threading.Lock()

    # --- GET -------------------------------------------------------------------------------

    def session(self) -> dict[str, Any]:
        return {"initial": self.initial.to_dict() if self.initial is not None else None,
                "user_dir": str(user_scenario_dir())}

    def units(self) -> dict[str, Any]:
        return units_info()

    def scenarios(self) -> dict[str, Any]:
        """Bundled and user scenarios; an unreadable user file is listed with its error."""
        items = [dict(e) for e in _bundled_entries()]
        bundled = {e["name"] for e in items}
        root = user_scenario_dir()
        for name, path in user_files().items():
            if name in bundled:
                continue  # the bundled one wins on load: never offer the shadowed file
            rel = str(path.relative_to(root)) if path.is_relative_to(root) else str(path)
            try:
                entry = _summary(load_file(path, name=name))
                entry["name"] = name
            except ScenarioError as err:
                entry = {"name": name, "category": "user", "split": "train", "allies": 0,
                         "enemies": 0, "zones": 0, "units_text": "", "zones_text": "",
                         "description": "", "error": str(err)}
            entry.update(source="user", file=rel)
            items.append(entry)
        order = {c: i for i, c in enumerate(CATEGORIES)}
        items.sort(key=lambda e: (order.get(e["category"], 9), e["name"].lower()))
        return {"scenarios": items, "user_dir": str(root)}

    def scenario(self, name: Any) -> dict[str, Any]:
        """One scenario by name. Paths are refused: the page only ever names scenarios."""
        if not isinstance(name, str) or not name:
            raise EditorError(400, "expected ?name=NAME", "name")
        if len(name) > MAX_QUERY_NAME:
            raise EditorError(400, f"expected a scenario name of at most {MAX_QUERY_NAME} "
                              f"characters, got {len(name)}", "name")
        if "/" in name or "\\" in name or name.endswith(".json") or "\0" in name:
            raise EditorError(400, "expected a scenario name, not a path", "name")
        try:
            source = "bundled"
            if bundled_category(name) is None:
                path = user_files().get(name)
                if path is not None:
                    return {"scenario": load_file(path, name=name).to_dict(), "source": "user",
                            "file": str(path)}
                source = "composed"
            return {"scenario": load_named(name).to_dict(), "source": source}
        except ScenarioError as err:
            raise _scenario_error(err, 404 if "unknown" in err.message else 400) from None

    # --- POST ------------------------------------------------------------------------------

    @staticmethod
    def parse_scenario(body: Any) -> Scenario:
        if not isinstance(body, dict) or "scenario" not in body:
            raise EditorError(400, "expected a JSON object with a 'scenario' key")
        try:
            return Scenario.from_dict(body["scenario"])
        except ScenarioError as err:
            raise _scenario_error(err) from None

    def validate(self, body: Any) -> dict[str, Any]:
        """200 either way: {ok: true, summary} or {ok: false, error}."""
        try:
            scenario = self.parse_scenario(body)
        except EditorError as err:
            return err.payload()
        summary = _summary(scenario)
        warnings = []
        if not scenario.units and not scenario.zones:
            warnings.append("empty")
        elif not scenario.units:
            warnings.append("zones only: compose it with a unit scenario to play")
        return {"ok": True, "summary": summary, "warnings": warnings}

    def save(self, body: Any) -> dict[str, Any]:
        if not isinstance(body, dict):
            raise EditorError(400, "expected a JSON object")
        name, category = body.get("name"), body.get("category")
        overwrite = body.get("overwrite", False)
        if not isinstance(name, str) or "/" in name or "\\" in name or not NAME_PATTERN.fullmatch(
                name):
            raise EditorError(400, "expected 1-100 characters from A-Z a-z 0-9 _ . -, starting "
                              "with a letter or digit (no path separators); got "
                              f"{_describe(name)}", "name")
        if not isinstance(category, str) or category not in USER_FOLDERS:
            raise EditorError(400, f"expected one of {', '.join(USER_FOLDERS)}; got "
                              f"{_describe(category)}", "category")
        if not isinstance(overwrite, bool):
            raise EditorError(400, "expected true or false", "overwrite")
        data = body.get("scenario")
        if isinstance(data, dict):
            data = {**data, "name": name, "category": category}
        scenario = self.parse_scenario({"scenario": data})
        if bundled_category(name) is not None:
            raise EditorError(400, f"{name!r} is a bundled scenario: a user file with this name "
                              "would never load by name; choose another name", "name")
        root = user_scenario_dir()
        path = root / USER_FOLDERS[category] / f"{name}.json"
        resolved_root = root.expanduser().resolve()
        if not path.resolve().is_relative_to(resolved_root):  # belt and braces
            raise EditorError(400, "the file would land outside the user scenario folder", "name")
        with self._save_lock:
            other = user_files().get(name)
            if other is not None and other.resolve() != path.resolve():
                raise EditorError(409, f"a user scenario {name!r} already exists in "
                                  f"{other.parent}; choose another name or save it in that "
                                  "category", "name", exists=True, file=str(other),
                                  can_overwrite=False)
            if path.exists() and not overwrite:
                raise EditorError(409, f"{path} exists; save again with overwrite to replace it",
                                  "name", exists=True, file=str(path), can_overwrite=True)
            atomic_write_text(path, dumps_scenario(scenario))
        return {"ok": True, "path": str(path), "name": name, "category": category,
                "summary": _summary(scenario)}

    def preview(self, body: Any) -> dict[str, Any]:
        scenario = self.parse_scenario(body)
        preview = _preview_module()
        try:
            return preview.run_preview(scenario, body.get("steps", 256),
                                       body.get("ally", "heuristic:medium"),
                                       body.get("enemy", "heuristic:medium"),
                                       body.get("seed", 0))
        except ScenarioError as err:
            raise _scenario_error(err) from None


class _Handler(BaseHTTPRequestHandler):
    server: EditorServer
    protocol_version = "HTTP/1.1"
    server_version = "tabx-editor"
    timeout = SOCKET_TIMEOUT_S
    # True while the request may have body bytes we have not read: the answer then closes the
    # connection, so that those bytes are never taken for the next request.
    _unread_body = False
    _extra_headers: tuple[tuple[str, str], ...] = ()

    # --- plumbing --------------------------------------------------------------------------

    def log_message(self, format: str, *args: Any) -> None:  # noqa: A002 (stdlib signature)
        if self.server.verbose:
            super().log_message(format, *args)

    def _send(self, status: int, body: bytes, content_type: str, cache: str = "no-store") -> None:
        self.send_response(status)
        self.send_header("Content-Type", content_type)
        self.send_header("Content-Length", str(len(body)))
        self.send_header("Cache-Control", cache)
        self.send_header("X-Content-Type-Options", "nosniff")
        self.send_header("Content-Security-Policy", CSP)
        for key, value in self._extra_headers:
            self.send_header(key, value)
        if self._unread_body:
            self.send_header("Connection", "close")  # also sets self.close_connection
        self.end_headers()
        if self.command != "HEAD":
            self.wfile.write(body)

    def _json(self, status: int, obj: Any) -> None:
        self._send(status, json.dumps(obj, allow_nan=False).encode("utf-8"),
                   "application/json; charset=utf-8")

    def _refusal(self) -> EditorError | None:
        """Why this request is not for this server, or None: Host, request URI, Origin."""
        own = self.server.authorities
        hosts = self.headers.get_all("Host") or []
        if len(hosts) != 1:
            return EditorError(400, f"expected exactly one Host header, got {len(hosts)}")
        if hosts[0].strip().lower() not in own:
            return EditorError(403, "unexpected Host header")
        url = urlsplit(self.path)
        if (url.scheme or url.netloc) and (url.scheme.lower() != "http"
                                           or url.netloc.lower() not in own):
            return EditorError(400, "the request URI names another host")
        if self.command not in READ_METHODS:
            origins = self.headers.get_all("Origin") or []
            if any(o.strip().lower() not in {f"http://{a}" for a in own} for o in origins):
                return EditorError(403, "requests from another origin may not change anything")
        return None

    def _guarded(self, action) -> None:
        refusal = self._refusal()
        if refusal is not None:
            self._json(refusal.status, refusal.payload())
            return
        try:
            action()
        except EditorError as err:
            self._json(err.status, err.payload())
        except Exception as err:  # a bug: report it to the page instead of hanging up
            self.log_error("internal error: %r", err)
            self._json(500, EditorError(500, f"internal error: {type(err).__name__}: {err}")
                       .payload())

    # --- routes ----------------------------------------------------------------------------

    def _start(self) -> None:
        """Per-request state (one handler serves every request of a keep-alive connection)."""
        self._extra_headers = ()
        length = self.headers.get("Content-Length")
        self._unread_body = (self.headers.get("Transfer-Encoding") is not None
                             or (length is not None and length.strip() != "0"))

    def do_HEAD(self) -> None:  # noqa: N802 (stdlib name)
        self.do_GET()

    def do_GET(self) -> None:  # noqa: N802 (stdlib name)
        self._start()
        self._guarded(self._get)

    def do_POST(self) -> None:  # noqa: N802 (stdlib name)
        self._start()
        self._guarded(self._post)

    def _not_allowed(self) -> None:
        self._start()
        self._extra_headers = (("Allow", "GET, HEAD, POST"),)
        self._guarded(self._refuse_method)

    def _refuse_method(self) -> None:
        raise EditorError(405, f"method {self.command} not allowed; the API takes GET and POST")

    do_PUT = do_DELETE = do_PATCH = _not_allowed  # noqa: N815 (stdlib names)

    def _get(self) -> None:
        url = urlsplit(self.path)
        app = self.server.app
        if url.path in ("/", "/index.html"):
            self._static("index.html")
        elif url.path.startswith("/static/"):
            self._static(url.path[len("/static/"):])
        elif url.path == "/api/units":
            self._json(200, app.units())
        elif url.path == "/api/session":
            self._json(200, app.session())
        elif url.path == "/api/scenarios":
            self._json(200, app.scenarios())
        elif url.path == "/api/scenario":
            name = parse_qs(url.query).get("name", [""])[0]
            self._json(200, app.scenario(name))
        else:
            raise EditorError(404, f"no such page: {url.path}")

    def _post(self) -> None:
        url = urlsplit(self.path)
        routes = {"/api/validate": "validate", "/api/save": "save", "/api/preview": "preview"}
        if url.path not in routes:
            raise EditorError(404, f"no such API: {url.path}")
        ctype = (self.headers.get("Content-Type") or "").split(";")[0].strip().lower()
        if ctype != "application/json":
            raise EditorError(415, "expected Content-Type: application/json")
        raw = self._read_body()
        try:
            body = parse_json_bytes(raw, what="request body")
        except ScenarioError as err:
            raise _scenario_error(err) from None
        self._json(200, getattr(self.server.app, routes[url.path])(body))

    def _read_body(self) -> bytes:
        """The request body, after checking its declared length (nothing is read before)."""
        if self.headers.get("Transfer-Encoding") is not None:
            raise EditorError(411, "chunked request bodies are not accepted; send a "
                              "Content-Length header")
        values = {v.strip() for v in self.headers.get_all("Content-Length") or []}
        if not values:
            raise EditorError(411, "a POST needs a Content-Length header")
        if len(values) > 1:
            raise EditorError(400, "conflicting Content-Length headers")
        value = values.pop()
        if not CONTENT_LENGTH.fullmatch(value):
            raise EditorError(400, "expected Content-Length to be a non-negative integer, got "
                              f"{_describe(value)}")
        length = int(value)
        if length > MAX_BODY:
            raise EditorError(413, f"request body of {length} bytes is over the limit of "
                              f"{MAX_BODY} bytes")
        if length == 0:
            raise EditorError(400, "empty request body: expected a JSON object")
        try:
            raw = self.rfile.read(length)
        except OSError:  # TimeoutError included: the client stopped sending
            raise EditorError(408, "the request body did not arrive in time") from None
        if len(raw) < length:
            raise EditorError(400, f"request body ended after {len(raw)} of {length} bytes")
        self._unread_body = False
        return raw

    def _static(self, name: str) -> None:
        suffix = name[name.rfind("."):] if "." in name else ""
        if not STATIC_NAME.fullmatch(name):
            raise EditorError(404, f"no such file: {name}")
        entry = resources.files("tabx.editor") / "static" / name
        if not entry.is_file():
            raise EditorError(404, f"no such file: {name}")
        self._send(200, entry.read_bytes(), STATIC_TYPES[suffix], cache="no-cache")


class EditorServer(ThreadingHTTPServer):
    """The editor's HTTP server; `url` is its address, `app` the API logic."""

    daemon_threads = True
    allow_reuse_address = True

    def __init__(self, port: int = 0, app: EditorApp | None = None, verbose: bool = False,
                 max_connections: int = MAX_CONNECTIONS) -> None:
        self.app = app if app is not None else EditorApp()
        self.verbose = verbose
        self._slots = threading.BoundedSemaphore(max_connections)
        super().__init__((HOST, port), _Handler)
        port = self.server_address[1]
        self.authorities = frozenset({f"127.0.0.1:{port}", f"localhost:{port}"})

    @property
    def url(self) -> str:
        return f"http://{HOST}:{self.server_address[1]}/"

    def process_request(self, request: Any, client_address: Any) -> None:
        """Serve the connection on a thread of its own if one of MAX_CONNECTIONS is free;
        otherwise answer 503 and close it, without waiting."""
        if not self._slots.acquire(blocking=False):
            self._busy(request)
            return
        try:
            super().process_request(request, client_address)
        except BaseException:
            self._slots.release()
            raise

    def process_request_thread(self, request: Any, client_address: Any) -> None:
        try:
            super().process_request_thread(request, client_address)
        finally:
            self._slots.release()

    def _busy(self, request: Any) -> None:
        body = json.dumps(EditorError(503, "too many connections; try again").payload()).encode()
        head = ("HTTP/1.1 503 Service Unavailable\r\nContent-Type: application/json; "
                f"charset=utf-8\r\nContent-Length: {len(body)}\r\nRetry-After: 1\r\n"
                "Connection: close\r\n\r\n").encode()
        try:
            request.settimeout(1.0)  # the accept loop never waits long on a slow client
            request.sendall(head + body)
        except OSError:
            pass
        finally:
            self.shutdown_request(request)


def make_server(port: int = 0, initial: Scenario | None = None, verbose: bool = False
                ) -> EditorServer:
    """An editor server on 127.0.0.1:`port` (0: a free port); call `serve_forever()`."""
    return EditorServer(port, EditorApp(initial), verbose)


__all__ = ["MAX_CONNECTIONS", "EditorApp", "EditorError", "EditorServer", "USER_FOLDERS",
           "make_server", "units_info", "user_files"]

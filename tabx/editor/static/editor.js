// TABX scenario editor: the page's logic. Plain ES module, canvas 2D, no dependencies.
//
// The scenario is edited in the shape of our JSON format (docs/scenarios.md): units with a type,
// team, position, heading (radians) and `overrides` (only stats that differ from the type's
// defaults); zones with a type, centre, semi-axes and effect. The server (tabx/editor/server.py)
// loads, validates, saves and previews; every range checked here comes from GET /api/units, the
// same tables the server validates against. World coordinates: origin at the arena centre, y up.

const TAU = Math.PI * 2;
const DEG = Math.PI / 180;
const ROTATE_STEP = 15; // degrees per Q / E press; headings snap to multiples of it
const HISTORY_LIMIT = 100;
const TEAM_FILL = { ally: "#2f6fdc", enemy: "#d23a3a" };
const TEAM_EDGE = { ally: "#133a86", enemy: "#7c1515" };
const DEAD_FILL = "#a3a6ab";
const ZONE_FILL = { lava: [232, 80, 20], bush: [50, 150, 55], swamp: [125, 110, 40] };
const ZONE_HELP = {
  lava: "Lava: health lost per second inside.",
  bush: "Bush: hides units inside from enemies outside. The effect is unused (normally 0).",
  swamp: "Swamp: slows units inside, speed × (1 − effect).",
};
const STAT_LABELS = {
  health: "Health", max_health: "Max health", speed: "Speed", damage: "Damage",
  attack_range: "Attack range", cooldown: "Cooldown (s)", radius: "Radius", mass: "Mass",
  sight_angle: "Sight angle (°)", heals: "Heals",
};
const $ = (id) => document.getElementById(id);

// --- state -----------------------------------------------------------------------------------

const S = {
  meta: null, // GET /api/units
  specs: {}, // unit name -> spec
  doc: null, // {name, category, description, arena: [w, h], extra: {split, physics, heuristic, start_noise, shuffle_positions}}
  units: [], // {unit, team, x, y, heading, overrides}
  zones: [], // {type, cx, cy, ax, ay, effect}
  grid: { spacing: 4.25, margin: 0 },
  mode: "units",
  team: "ally",
  paletteUnit: "farmer",
  paletteZone: "bush",
  zoneEffect: {},
  typeDefaults: {}, // unit name -> overrides applied to newly placed units
  showSight: false,
  selection: null, // {kind: "unit"|"zone", index}
  hover: { unit: -1, zone: -1, world: null },
  view: { scale: 8, ox: 0, oy: 0 },
  undo: [],
  redo: [],
  drag: null,
  keys: new Set(),
  dirty: false,
  validation: null, // {ok, error, summary}
  preview: null, // {data, units, frame, playing, speed}
  userDir: "",
};

const canvas = $("canvas");
const ctx = canvas.getContext("2d");
let cssW = 0, cssH = 0, dpr = 1;
let FONT = "sans-serif"; // the page's font family, read once at start

// --- helpers ---------------------------------------------------------------------------------

function clamp(v, lo, hi) { return Math.min(hi, Math.max(lo, v)); }
function round(v, d = 3) { const k = 10 ** d; return Math.round(v * k) / k; }
function fmt(v) {
  if (typeof v !== "number") return String(v);
  if (Number.isInteger(v)) return String(v);
  return String(round(v, 4));
}
function el(tag, attrs = {}, ...children) {
  const node = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs)) {
    if (v === undefined || v === null || v === false) continue;
    if (k === "class") node.className = v;
    else if (k === "text") node.textContent = v;
    else if (k.startsWith("on")) node.addEventListener(k.slice(2), v);
    else if (k === "dataset") Object.assign(node.dataset, v);
    else node.setAttribute(k, v === true ? "" : v);
  }
  for (const c of children.flat()) if (c !== null && c !== undefined) node.append(c);
  return node;
}
function inRange(v, r) {
  const above = r.lo_open ? v > r.lo : v >= r.lo;
  const below = r.hi_open ? v < r.hi : v <= r.hi;
  return above && below;
}
function compact(v) {
  // 100000 -> 1e5, 10000 -> 1e4: the range tables' round bounds, written short.
  const a = Math.abs(v);
  if (a >= 10000 && Number.isInteger(Math.log10(a))) return `${v < 0 ? "-" : ""}1e${Math.log10(a)}`;
  return fmt(round(v, 4));
}
function rangeText(r, scale = 1) {
  const left = r.lo_open ? "(" : "[", right = r.hi_open ? ")" : "]";
  return `${left}${compact(r.lo * scale)}, ${compact(r.hi * scale)}${right}`;
}
function parseNumber(text) {
  const t = String(text).trim();
  if (t === "" || !/^[-+]?(\d+\.?\d*|\.\d+)([eE][-+]?\d+)?$/.test(t)) return null;
  const v = Number(t);
  return Number.isFinite(v) ? v : null;
}
function sameF32(a, b) { return Math.fround(a) === Math.fround(b); }
function deepCopy(x) { return JSON.parse(JSON.stringify(x)); }

async function apiGet(path) {
  const r = await fetch(path, { headers: { Accept: "application/json" } });
  const body = await r.json();
  if (!r.ok) throw Object.assign(new Error(body.error ? body.error.text : r.statusText), { body });
  return body;
}
async function apiPost(path, payload) {
  const r = await fetch(path, {
    method: "POST",
    headers: { "Content-Type": "application/json", Accept: "application/json" },
    body: JSON.stringify(payload),
  });
  let body;
  try { body = await r.json(); } catch { body = { ok: false, error: { text: r.statusText } }; }
  return { status: r.status, body };
}

// --- unit stats ------------------------------------------------------------------------------

function spec(u) { return S.specs[typeof u === "string" ? u : u.unit]; }
function statOf(unit, overrides, key) {
  if (key in overrides) return overrides[key];
  if (key === "max_health") return statOf(unit, overrides, "health");
  if (key === "heals") return statOf(unit, overrides, "damage") < 0;
  return S.specs[unit].stats[key];
}
function stat(u, key) { return statOf(u.unit, u.overrides, key); }
function defaultOf(unit, overrides, key) {
  // The value this stat has without its own override (max_health follows health, heals damage).
  if (key === "max_health") return statOf(unit, overrides, "health");
  if (key === "heals") return statOf(unit, overrides, "damage") < 0;
  return S.specs[unit].stats[key];
}
function setOverride(unit, overrides, key, value) {
  if (key === "heals" ? value === defaultOf(unit, overrides, key)
    : sameF32(value, defaultOf(unit, overrides, key))) delete overrides[key];
  else overrides[key] = value;
  // Overrides that now equal their (changed) default are dropped, as the exporter does.
  if ("max_health" in overrides && sameF32(overrides.max_health, statOf(unit, overrides, "health"))) {
    delete overrides.max_health;
  }
  if ("heals" in overrides && overrides.heals === (statOf(unit, overrides, "damage") < 0)) {
    delete overrides.heals;
  }
}
function radius(u) { return stat(u, "radius"); }

// --- grid ------------------------------------------------------------------------------------

function gridGeom() {
  const [W, H] = S.doc.arena;
  const s = S.grid.spacing, m = S.grid.margin;
  const cols = Math.max(0, Math.floor((W - 2 * m) / s + 1e-9));
  const rows = Math.max(0, Math.floor((H - 2 * m) / s + 1e-9));
  return { s, cols, rows, x0: -cols * s / 2, y0: -rows * s / 2 };
}
// Where a unit of `space` cells per side snaps for the world point (x, y), or null.
function snap(space, x, y) {
  const g = gridGeom();
  const fx = (x - g.x0) / g.s, fy = (y - g.y0) / g.s;
  if (fx < 0 || fy < 0 || fx >= g.cols || fy >= g.rows) return null;
  if (space <= 1) {
    return { x: g.x0 + (Math.floor(fx) + 0.5) * g.s, y: g.y0 + (Math.floor(fy) + 0.5) * g.s };
  }
  if (g.cols < space || g.rows < space) return null;
  const i = clamp(Math.round(fx), 1, g.cols - 1), j = clamp(Math.round(fy), 1, g.rows - 1);
  return { x: g.x0 + i * g.s, y: g.y0 + j * g.s };
}
function cellsOf(space, x, y) {
  const g = gridGeom();
  const fx = (x - g.x0) / g.s, fy = (y - g.y0) / g.s;
  const cells = [];
  if (space <= 1) cells.push(`${Math.floor(fx)},${Math.floor(fy)}`);
  else {
    const i = Math.round(fx), j = Math.round(fy);
    for (const di of [-1, 0]) for (const dj of [-1, 0]) cells.push(`${i + di},${j + dj}`);
  }
  return cells;
}
function occupiedBy(cells, except = -1) {
  const want = new Set(cells);
  for (let k = 0; k < S.units.length; k++) {
    if (k === except) continue;
    const u = S.units[k];
    if (cellsOf(spec(u).space, u.x, u.y).some((c) => want.has(c))) return k;
  }
  return -1;
}
function clampIntoArena(u) {
  const [W, H] = S.doc.arena, r = radius(u);
  if (W / 2 - r >= 0) u.x = clamp(u.x, -(W / 2 - r), W / 2 - r);
  if (H / 2 - r >= 0) u.y = clamp(u.y, -(H / 2 - r), H / 2 - r);
}

// --- view ------------------------------------------------------------------------------------

function w2s(x, y) { return [cssW / 2 + (x - S.view.ox) * S.view.scale, cssH / 2 - (y - S.view.oy) * S.view.scale]; }
function s2w(px, py) { return [S.view.ox + (px - cssW / 2) / S.view.scale, S.view.oy - (py - cssH / 2) / S.view.scale]; }
function fitScale() {
  const [W, H] = S.doc.arena;
  return Math.max(0.05, Math.min((cssW - 48) / W, (cssH - 48) / H));
}
function fitView() {
  S.view = { scale: fitScale(), ox: 0, oy: 0 };
  requestDraw();
}
function zoomAt(px, py, factor) {
  const fit = fitScale();
  const [wx, wy] = s2w(px, py);
  S.view.scale = clamp(S.view.scale * factor, fit * 0.4, fit * 24);
  S.view.ox = wx - (px - cssW / 2) / S.view.scale;
  S.view.oy = wy + (py - cssH / 2) / S.view.scale;
  requestDraw();
}
function pan(dx, dy) { S.view.ox -= dx / S.view.scale; S.view.oy += dy / S.view.scale; requestDraw(); }
function resize() {
  const rect = canvas.getBoundingClientRect();
  const first = cssW === 0;
  cssW = Math.max(1, rect.width); cssH = Math.max(1, rect.height);
  dpr = window.devicePixelRatio || 1;
  canvas.width = Math.round(cssW * dpr); canvas.height = Math.round(cssH * dpr);
  if (first && S.doc) fitView(); else requestDraw();
}

// --- hit tests -------------------------------------------------------------------------------

function currentUnits() {
  // Units as drawn now: the editor's, or the preview frame's.
  if (!S.preview) return S.units.map((u) => ({ ...u, alive: true }));
  const p = S.preview, f = p.frame, d = p.data;
  return p.units.map((u, i) => ({
    ...u, x: d.position[f][i][0], y: d.position[f][i][1], heading: d.heading[f][i],
    alive: d.alive[f][i], health: d.health[f][i], maxHealth: d.max_health[i],
    cooldown: d.cooldown[f][i], attacking: d.attacking[f][i],
  }));
}
function unitAt(wx, wy) {
  const list = currentUnits();
  const slack = 3 / S.view.scale;
  for (let k = list.length - 1; k >= 0; k--) {
    const u = list[k];
    if (Math.hypot(u.x - wx, u.y - wy) <= radius(u) + slack) return k;
  }
  return -1;
}
function zoneAt(wx, wy) {
  for (let k = S.zones.length - 1; k >= 0; k--) {
    const z = S.zones[k];
    const dx = (wx - z.cx) / z.ax, dy = (wy - z.cy) / z.ay;
    if (dx * dx + dy * dy <= 1) return k;
  }
  return -1;
}

// --- history ---------------------------------------------------------------------------------

function snapshot() {
  return JSON.stringify({ doc: S.doc, units: S.units, zones: S.zones, grid: S.grid });
}
function restore(snap) {
  const s = JSON.parse(snap);
  const arenaChanged = String(s.doc.arena) !== String(S.doc.arena);
  S.doc = s.doc; S.units = s.units; S.zones = s.zones; S.grid = s.grid;
  if (S.selection) {
    const list = S.selection.kind === "unit" ? S.units : S.zones;
    if (S.selection.index >= list.length) S.selection = null;
  }
  if (arenaChanged) fitView();
  changed({ rebuild: true });
}
function pushHistory() {
  S.undo.push(snapshot());
  if (S.undo.length > HISTORY_LIMIT) S.undo.shift();
  S.redo = [];
}
function commit(fn, opts = {}) {
  pushHistory();
  fn();
  changed(opts);
}
function undo() {
  if (!S.undo.length || S.preview) return;
  S.redo.push(snapshot());
  restore(S.undo.pop());
  status("Undone");
}
function redo() {
  if (!S.redo.length || S.preview) return;
  S.undo.push(snapshot());
  restore(S.redo.pop());
  status("Redone");
}
function changed({ rebuild = false, dirty = true } = {}) {
  if (dirty) S.dirty = true;
  updateChrome();
  if (rebuild) renderProps(); else refreshPropValues();
  scheduleValidate();
  requestDraw();
}

// --- scenario <-> JSON -----------------------------------------------------------------------

function toScenario() {
  const d = S.doc;
  const out = { format: S.meta.format, name: d.name, category: d.category };
  if (d.extra.split) out.split = d.extra.split;
  if (d.description) out.description = d.description;
  out.arena = { width: d.arena[0], height: d.arena[1] };
  out.units = S.units.map((u) => {
    const rec = { unit: u.unit, team: u.team, position: [u.x, u.y], heading: u.heading };
    if (Object.keys(u.overrides).length) rec.overrides = { ...u.overrides };
    return rec;
  });
  out.zones = S.zones.map((z) => ({ type: z.type, centre: [z.cx, z.cy], semi_axes: [z.ax, z.ay], effect: z.effect }));
  if (d.extra.physics !== undefined) out.physics = d.extra.physics;
  if (d.extra.heuristic !== undefined) out.heuristic = d.extra.heuristic;
  // Randomised starts are kept as the file has them (not edited here).
  for (const k of ["start_noise", "shuffle_positions"]) if (d.extra[k] !== undefined) out[k] = d.extra[k];
  return out;
}
function fromScenario(data) {
  const extra = {};
  for (const k of ["split", "physics", "heuristic", "start_noise", "shuffle_positions"]) {
    if (data[k] !== undefined) extra[k] = data[k];
  }
  S.doc = {
    name: data.name, category: data.category, description: data.description || "",
    arena: data.arena ? [data.arena.width, data.arena.height] : [...S.meta.arena_default], extra,
  };
  S.units = data.units.map((u) => ({
    unit: u.unit, team: u.team, x: u.position[0], y: u.position[1],
    heading: u.heading !== undefined ? u.heading : (u.heading_deg || 0) * DEG,
    overrides: { ...(u.overrides || {}) },
  }));
  S.zones = data.zones.map((z) => ({
    type: z.type, cx: z.centre[0], cy: z.centre[1], ax: z.semi_axes[0], ay: z.semi_axes[1],
    effect: z.effect || 0,
  }));
}

// --- validation ------------------------------------------------------------------------------

let validateTimer = 0, validateSeq = 0;
function scheduleValidate() {
  clearTimeout(validateTimer);
  validateTimer = setTimeout(validateNow, 250);
}
async function validateNow() {
  const seq = ++validateSeq;
  const { body } = await apiPost("/api/validate", { scenario: toScenario() });
  if (seq !== validateSeq) return;
  S.validation = body;
  showValidation();
}
// Map a ScenarioError field path onto the element and the property field it names.
function parseErrorPath(path) {
  let m = /^units\[(\d+)\](?:\.(\w+))?(?:\.(\w+)|\[(\d)\])?/.exec(path || "");
  if (m) {
    let field = m[2] || null;
    if (field === "overrides") field = m[3] || null;
    else if (field === "position") field = m[4] === "1" ? "y" : "x";
    else if (field === "heading_deg") field = "heading";
    return { kind: "unit", index: Number(m[1]), field };
  }
  m = /^zones\[(\d+)\](?:\.(\w+))?(?:\[(\d)\])?/.exec(path || "");
  if (m) {
    let field = m[2] || null;
    if (field === "centre") field = m[3] === "1" ? "cy" : "cx";
    else if (field === "semi_axes") field = m[3] === "1" ? "ay" : "ax";
    return { kind: "zone", index: Number(m[1]), field };
  }
  if (path === "name") return { kind: "doc", field: "scn-name" };
  return null;
}
function showValidation() {
  const v = S.validation, node = $("status-valid");
  document.querySelectorAll(".field-error.server").forEach((e) => {
    e.textContent = ""; e.classList.remove("server");
  });
  if (!v) { node.textContent = ""; return; }
  if (v.ok) {
    node.className = "linkish ok";
    node.textContent = v.warnings && v.warnings.length ? `✓ valid (${v.warnings[0]})` : "✓ valid";
    node.title = "";
    return;
  }
  node.className = "linkish bad";
  node.textContent = `⚠ ${v.error.text}`;
  node.title = `${v.error.text}\n(click to select the element)`;
  const target = parseErrorPath(v.error.path);
  if (!target) return;
  let errNode = null;
  if (target.kind === "doc") errNode = $(`err-${target.field}`);
  else if (S.selection && S.selection.kind === target.kind && S.selection.index === target.index) {
    errNode = $(`err-${target.field}`) || $("err-selection");
  }
  if (errNode && !errNode.textContent) { errNode.textContent = v.error.message; errNode.classList.add("server"); }
}
function jumpToError() {
  const v = S.validation;
  if (!v || v.ok) return;
  const target = parseErrorPath(v.error.path);
  if (target && target.kind !== "doc") { select(target.kind, target.index); showValidation(); }
  else if (target) $(target.field).focus();
}

// --- status, toasts --------------------------------------------------------------------------

let toastTimer = 0;
function toast(text, isError = false) {
  const t = $("toast");
  t.textContent = text; t.className = `toast${isError ? " error" : ""}`; t.hidden = false;
  clearTimeout(toastTimer);
  toastTimer = setTimeout(() => { t.hidden = true; }, isError ? 5000 : 2600);
}
function status(text) { $("status-msg").textContent = text; }
function busy(text) {
  $("busy").hidden = !text;
  if (text) $("busy-text").textContent = text;
}

function updateChrome() {
  $("scenario-title").textContent = S.doc.name || "untitled";
  $("dirty-mark").hidden = !S.dirty;
  const allies = S.units.filter((u) => u.team === "ally").length;
  const enemies = S.units.length - allies;
  const g = gridGeom();
  $("status-counts").textContent =
    `${allies} ${allies === 1 ? "ally" : "allies"} · ${enemies} ${enemies === 1 ? "enemy" : "enemies"} · ` +
    `${S.zones.length} ${S.zones.length === 1 ? "zone" : "zones"} · arena ${fmt(S.doc.arena[0])} × ${fmt(S.doc.arena[1])} · grid ${g.cols} × ${g.rows}`;
  $("btn-undo").disabled = !S.undo.length || !!S.preview;
  $("btn-redo").disabled = !S.redo.length || !!S.preview;
  for (const b of document.querySelectorAll("[data-mode]")) b.classList.toggle("active", b.dataset.mode === S.mode);
  for (const b of document.querySelectorAll("[data-team]")) b.classList.toggle("active", b.dataset.team === S.team);
  $("palette-units").hidden = S.mode !== "units";
  $("palette-zones").hidden = S.mode !== "zones";
  $("btn-sight").setAttribute("aria-pressed", String(S.showSight));
  for (const b of document.querySelectorAll("[data-palette-unit]")) {
    b.classList.toggle("active", b.dataset.paletteUnit === S.paletteUnit);
    const custom = Object.keys(S.typeDefaults[b.dataset.paletteUnit] || {}).length > 0;
    b.querySelector(".custom").hidden = !custom;
    b.querySelector(".chip").style.background = TEAM_FILL[S.team];
  }
  for (const b of document.querySelectorAll("[data-palette-zone]")) {
    b.classList.toggle("active", b.dataset.paletteZone === S.paletteZone);
    b.querySelector(".meta").textContent = `effect ${fmt(S.zoneEffect[b.dataset.paletteZone])}`;
  }
  // Scenario panel.
  if (document.activeElement !== $("scn-name")) $("scn-name").value = S.doc.name;
  $("scn-category").value = S.doc.category;
  if (document.activeElement !== $("scn-description")) $("scn-description").value = S.doc.description;
  const facts = $("scn-facts");
  facts.replaceChildren(
    el("dt", { text: "Arena" }), el("dd", { text: `${fmt(S.doc.arena[0])} × ${fmt(S.doc.arena[1])} (New… to change)` }),
    el("dt", { text: "Grid" }), el("dd", { text: `${g.cols} × ${g.rows} cells of ${fmt(S.grid.spacing)}, margin ${fmt(S.grid.margin)}` }),
  );
  if (S.doc.extra.split) facts.append(el("dt", { text: "Split" }), el("dd", { text: S.doc.extra.split }));
  if (S.doc.extra.physics !== undefined) {
    facts.append(el("dt", { text: "Physics" }), el("dd", { text: typeof S.doc.extra.physics === "string" ? S.doc.extra.physics : JSON.stringify(S.doc.extra.physics) }));
  }
  if (S.doc.extra.heuristic !== undefined) {
    const h = S.doc.extra.heuristic;
    const txt = ["ally", "enemy"].filter((t) => t in h).map((t) => `${t} ${typeof h[t] === "string" ? h[t] : "custom"}`).join(", ");
    facts.append(el("dt", { text: "Opponent" }), el("dd", { text: txt }));
  }
}

// --- drawing ---------------------------------------------------------------------------------

let drawPending = false;
function requestDraw() {
  if (drawPending) return;
  drawPending = true;
  requestAnimationFrame(() => { drawPending = false; draw(); });
}

function draw() {
  if (!S.doc) return;
  ctx.setTransform(dpr, 0, 0, dpr, 0, 0);
  ctx.fillStyle = "#dfe3e8";
  ctx.fillRect(0, 0, cssW, cssH);
  const [W, H] = S.doc.arena;
  const k = S.view.scale;
  const [ax0, ay0] = w2s(-W / 2, H / 2);
  // Arena.
  ctx.save();
  ctx.shadowColor = "rgba(0,0,0,0.18)"; ctx.shadowBlur = 14; ctx.shadowOffsetY = 3;
  ctx.fillStyle = "#ece6d5";
  ctx.fillRect(ax0, ay0, W * k, H * k);
  ctx.restore();
  drawGrid();
  // Zones.
  S.zones.forEach((z, i) => drawZone(z, i));
  if (S.drag && S.drag.kind === "draw-zone" && S.drag.moved) drawZone(zoneFromDrag(S.drag), -1, true);
  ctx.strokeStyle = "#3c3c3c"; ctx.lineWidth = 1.5;
  ctx.strokeRect(ax0, ay0, W * k, H * k);
  // Units.
  const units = currentUnits();
  units.forEach((u, i) => {
    const hovered = i === S.hover.unit;
    if ((S.showSight || hovered || (S.selection && S.selection.kind === "unit" && S.selection.index === i && !S.preview)) && u.alive) drawSight(u, hovered ? 1 : 0.6);
  });
  if (S.preview) units.forEach((u) => { if (u.attacking && u.alive) drawAttack(u); });
  units.forEach((u, i) => drawUnit(u, i));
  if (!S.preview) drawGhost();
  if (S.preview) drawHud();
}

function drawGrid() {
  const g = gridGeom(), k = S.view.scale;
  if (g.cols < 1 || g.rows < 1) return;
  const [gx0, gy0] = w2s(g.x0, g.y0 + g.rows * g.s);
  const gw = g.cols * g.s * k, gh = g.rows * g.s * k;
  ctx.save();
  if (g.s * k >= 6) {
    ctx.strokeStyle = "rgba(120, 100, 60, 0.16)"; ctx.lineWidth = 1;
    ctx.beginPath();
    for (let i = 0; i <= g.cols; i++) { const x = Math.round(gx0 + i * g.s * k) + 0.5; ctx.moveTo(x, gy0); ctx.lineTo(x, gy0 + gh); }
    for (let j = 0; j <= g.rows; j++) { const y = Math.round(gy0 + j * g.s * k) + 0.5; ctx.moveTo(gx0, y); ctx.lineTo(gx0 + gw, y); }
    ctx.stroke();
  }
  // The axes through the origin, faintly.
  ctx.strokeStyle = "rgba(120, 100, 60, 0.22)"; ctx.setLineDash([4, 4]);
  const [ox, oy] = w2s(0, 0), [W, H] = S.doc.arena;
  ctx.beginPath();
  ctx.moveTo(ox, oy - H / 2 * k); ctx.lineTo(ox, oy + H / 2 * k);
  ctx.moveTo(ox - W / 2 * k, oy); ctx.lineTo(ox + W / 2 * k, oy);
  ctx.stroke();
  ctx.restore();
}

function drawZone(z, i, ghost = false) {
  const [x, y] = w2s(z.cx, z.cy), k = S.view.scale;
  const [r, g, b] = ZONE_FILL[z.type];
  const selected = S.selection && S.selection.kind === "zone" && S.selection.index === i;
  const hovered = S.mode === "zones" && i === S.hover.zone;
  ctx.save();
  ctx.beginPath();
  ctx.ellipse(x, y, Math.max(0.5, z.ax * k), Math.max(0.5, z.ay * k), 0, 0, TAU);
  ctx.fillStyle = `rgba(${r},${g},${b},${ghost ? 0.35 : 0.55})`;
  ctx.fill();
  ctx.lineWidth = selected ? 2.5 : 1.2;
  ctx.strokeStyle = selected ? "#ffb400" : `rgba(${r * 0.6},${g * 0.6},${b * 0.6},${hovered ? 1 : 0.8})`;
  if (ghost) ctx.setLineDash([5, 4]);
  ctx.stroke();
  if (selected) {
    ctx.setLineDash([]); ctx.fillStyle = "#fff"; ctx.strokeStyle = "#b37e00"; ctx.lineWidth = 1.2;
    for (const [hx, hy] of [[x + z.ax * k, y], [x - z.ax * k, y], [x, y + z.ay * k], [x, y - z.ay * k]]) {
      ctx.beginPath(); ctx.rect(hx - 3, hy - 3, 6, 6); ctx.fill(); ctx.stroke();
    }
  }
  if (Math.min(z.ax, z.ay) * k > 16 && !ghost) {
    ctx.fillStyle = "rgba(255,255,255,0.92)";
    ctx.font = `600 ${clamp(Math.min(z.ax, z.ay) * k * 0.3, 9, 13)}px ${FONT}`;
    ctx.textAlign = "center"; ctx.textBaseline = "middle";
    ctx.fillText(z.type === "bush" ? "bush" : `${z.type} ${fmt(z.effect)}`, x, y);
  }
  ctx.restore();
}

function drawSight(u, strength) {
  const [x, y] = w2s(u.x, u.y), k = S.view.scale;
  const half = stat(u, "sight_angle") / 2;
  const range = stat(u, "attack_range");
  const length = Math.max(range, 14) * k;
  // Canvas y points down: a world angle a is -a on screen.
  const a0 = -u.heading - half, a1 = -u.heading + half;
  ctx.save();
  const grad = ctx.createRadialGradient(x, y, radius(u) * k, x, y, length);
  const col = u.team === "ally" ? "47,111,220" : "210,58,58";
  grad.addColorStop(0, `rgba(${col},${0.32 * strength})`);
  grad.addColorStop(1, `rgba(${col},0)`);
  ctx.beginPath(); ctx.moveTo(x, y); ctx.arc(x, y, length, a0, a1); ctx.closePath();
  ctx.fillStyle = grad; ctx.fill();
  ctx.strokeStyle = `rgba(${col},${0.55 * strength})`; ctx.lineWidth = 1; ctx.setLineDash([3, 3]);
  ctx.beginPath(); ctx.moveTo(x, y); ctx.lineTo(x + Math.cos(a0) * length, y + Math.sin(a0) * length);
  ctx.moveTo(x, y); ctx.lineTo(x + Math.cos(a1) * length, y + Math.sin(a1) * length); ctx.stroke();
  if (range > 0) {
    ctx.setLineDash([]); ctx.lineWidth = 1.5; ctx.strokeStyle = `rgba(${col},${0.7 * strength})`;
    ctx.beginPath(); ctx.arc(x, y, (range + radius(u)) * k, a0, a1); ctx.stroke();
  }
  ctx.restore();
}

function drawAttack(u) {
  const [x, y] = w2s(u.x, u.y), k = S.view.scale;
  const half = stat(u, "sight_angle") / 2, reach = (stat(u, "attack_range") + radius(u)) * k;
  ctx.save();
  ctx.beginPath(); ctx.moveTo(x, y); ctx.arc(x, y, reach, -u.heading - half, -u.heading + half); ctx.closePath();
  ctx.fillStyle = stat(u, "heals") ? "rgba(40,180,80,0.25)" : "rgba(255,170,0,0.3)";
  ctx.fill();
  ctx.restore();
}

function drawUnit(u, i) {
  const [x, y] = w2s(u.x, u.y), k = S.view.scale;
  const r = Math.max(3, radius(u) * k);
  const selected = !S.preview && S.selection && S.selection.kind === "unit" && S.selection.index === i;
  const hovered = i === S.hover.unit;
  ctx.save();
  if (selected || hovered) {
    ctx.beginPath(); ctx.arc(x, y, r + 4, 0, TAU);
    ctx.strokeStyle = selected ? "#ffb400" : "rgba(255,255,255,0.9)"; ctx.lineWidth = selected ? 3 : 2;
    ctx.stroke();
  }
  ctx.beginPath(); ctx.arc(x, y, r, 0, TAU);
  ctx.fillStyle = u.alive ? TEAM_FILL[u.team] : DEAD_FILL; ctx.fill();
  ctx.lineWidth = Math.max(1.2, r * 0.12); ctx.strokeStyle = u.alive ? TEAM_EDGE[u.team] : "#6d7075"; ctx.stroke();
  // Heading: a pointer just outside the rim (a line from the centre for tiny units).
  const hx = Math.cos(-u.heading), hy = Math.sin(-u.heading);
  ctx.fillStyle = u.alive ? TEAM_EDGE[u.team] : "#6d7075";
  if (r >= 5) {
    const tip = r + Math.max(5, r * 0.35), base = r - 1, w = Math.max(3.5, r * 0.3);
    ctx.beginPath();
    ctx.moveTo(x + hx * tip, y + hy * tip);
    ctx.lineTo(x + hx * base - hy * w, y + hy * base + hx * w);
    ctx.lineTo(x + hx * base + hy * w, y + hy * base - hx * w);
    ctx.closePath(); ctx.fill();
  } else {
    ctx.beginPath(); ctx.moveTo(x, y); ctx.lineTo(x + hx * (r + 4), y + hy * (r + 4));
    ctx.strokeStyle = ctx.fillStyle; ctx.lineWidth = 1.5; ctx.stroke();
  }
  if (r >= 6) {
    ctx.fillStyle = "#fff";
    ctx.font = `700 ${Math.round(clamp(r * 0.95, 8, 22))}px ${FONT}`;
    ctx.textAlign = "center"; ctx.textBaseline = "middle";
    ctx.fillText(spec(u).char, x, y + 0.5);
  }
  if (!S.preview && Object.keys(u.overrides).length && r >= 5) {
    ctx.beginPath(); ctx.arc(x + r * 0.72, y - r * 0.72, Math.max(2.5, r * 0.22), 0, TAU);
    ctx.fillStyle = "#ffc21a"; ctx.fill(); ctx.strokeStyle = "#7a5a00"; ctx.lineWidth = 1; ctx.stroke();
  }
  if (S.preview && u.alive) {
    const bw = Math.max(18, r * 2.2), bh = Math.max(3, Math.min(5, r * 0.22));
    const bx = x - bw / 2, by = y - r - 6 - 2 * bh;
    ctx.fillStyle = "#464646"; ctx.fillRect(bx, by, bw, bh); ctx.fillRect(bx, by + bh + 1, bw, bh);
    ctx.fillStyle = "#2db441"; ctx.fillRect(bx, by, bw * clamp(u.health / u.maxHealth, 0, 1), bh);
    ctx.fillStyle = "#f0af14"; ctx.fillRect(bx, by + bh + 1, bw * clamp(u.cooldown, 0, 1), bh);
  }
  ctx.restore();
}

function drawGhost() {
  // Where a click would place the palette unit.
  if (S.mode !== "units" || !S.hover.world || S.hover.unit >= 0 || S.drag) return;
  const sp = spec(S.paletteUnit);
  const pos = snap(sp.space, S.hover.world[0], S.hover.world[1]);
  if (!pos) return;
  const free = occupiedBy(cellsOf(sp.space, pos.x, pos.y)) < 0;
  const [x, y] = w2s(pos.x, pos.y);
  const r = Math.max(3, statOf(S.paletteUnit, S.typeDefaults[S.paletteUnit] || {}, "radius") * S.view.scale);
  ctx.save();
  ctx.globalAlpha = free ? 0.45 : 0.3;
  ctx.beginPath(); ctx.arc(x, y, r, 0, TAU);
  ctx.fillStyle = free ? TEAM_FILL[S.team] : "#888"; ctx.fill();
  ctx.setLineDash([3, 3]); ctx.strokeStyle = free ? TEAM_EDGE[S.team] : "#c62828"; ctx.lineWidth = 1.5; ctx.stroke();
  ctx.restore();
}

function drawHud() {
  const p = S.preview, d = p.data, f = p.frame;
  const alive = { ally: 0, enemy: 0 }, total = { ally: 0, enemy: 0 };
  p.units.forEach((u, i) => { total[u.team]++; if (d.alive[f][i]) alive[u.team]++; });
  const lines = [
    `step ${f} / ${d.steps}   ·   ${d.controllers[0]} vs ${d.controllers[1]}`,
    `allies ${alive.ally}/${total.ally}  health ${(d.hp_ratio[f][0] * 100).toFixed(0)}%   ·   enemies ${alive.enemy}/${total.enemy}  health ${(d.hp_ratio[f][1] * 100).toFixed(0)}%`,
  ];
  if (d.done_at !== null && f >= d.done_at) lines.push(`${d.winner === "ally" ? "allies" : "enemies"} win by ${d.outcome} at step ${d.done_at}`);
  ctx.save();
  ctx.font = `12px ${FONT}`;
  const w = Math.max(...lines.map((l) => ctx.measureText(l).width)) + 20;
  ctx.fillStyle = "rgba(255,255,255,0.93)"; ctx.strokeStyle = "#c7ccd4";
  ctx.beginPath(); ctx.roundRect(12, 12, w, lines.length * 18 + 12, 8); ctx.fill(); ctx.stroke();
  ctx.fillStyle = "#1f2328"; ctx.textBaseline = "top";
  lines.forEach((l, i) => { ctx.font = `${i === 2 ? "600 " : ""}12px ${FONT}`; ctx.fillText(l, 22, 19 + i * 18); });
  ctx.restore();
}

// --- editing operations ----------------------------------------------------------------------

function select(kind, index) {
  S.selection = kind ? { kind, index } : null;
  renderProps();
  showValidation();
  requestDraw();
}

function placeUnit(wx, wy) {
  const sp = spec(S.paletteUnit);
  const pos = snap(sp.space, wx, wy);
  if (!pos) { status("Outside the placement grid"); return; }
  const other = occupiedBy(cellsOf(sp.space, pos.x, pos.y));
  if (other >= 0) { status(`That cell is taken by unit #${other}`); return; }
  const u = {
    unit: S.paletteUnit, team: S.team, x: pos.x, y: pos.y,
    heading: S.team === "ally" ? 0 : Math.PI, overrides: { ...(S.typeDefaults[S.paletteUnit] || {}) },
  };
  clampIntoArena(u);
  commit(() => { S.units.push(u); S.selection = { kind: "unit", index: S.units.length - 1 }; }, { rebuild: true });
  status(`Placed ${S.team} ${u.unit} at (${fmt(round(u.x))}, ${fmt(round(u.y))})`);
}

function deleteUnit(i) {
  const u = S.units[i];
  commit(() => {
    S.units.splice(i, 1);
    if (S.selection && S.selection.kind === "unit") {
      if (S.selection.index === i) S.selection = null;
      else if (S.selection.index > i) S.selection.index--;
    }
  }, { rebuild: true });
  S.hover.unit = -1;
  status(`Deleted ${u.team} ${u.unit}`);
}
function deleteZone(i) {
  const z = S.zones[i];
  commit(() => {
    S.zones.splice(i, 1);
    if (S.selection && S.selection.kind === "zone") {
      if (S.selection.index === i) S.selection = null;
      else if (S.selection.index > i) S.selection.index--;
    }
  }, { rebuild: true });
  S.hover.zone = -1;
  status(`Deleted ${z.type} zone`);
}
function deleteSelection() {
  if (!S.selection || S.preview) return;
  if (S.selection.kind === "unit") deleteUnit(S.selection.index); else deleteZone(S.selection.index);
}

function rotateUnit(i, dir) {
  const u = S.units[i];
  let deg = Math.round(u.heading / DEG / ROTATE_STEP) * ROTATE_STEP + dir * ROTATE_STEP;
  deg = ((deg % 360) + 360) % 360;
  if (deg > 180) deg -= 360;
  commit(() => { u.heading = deg * DEG; });
  status(`Unit #${i} heading ${deg}°`);
}

function zoneFromDrag(d) {
  const [W, H] = S.doc.arena;
  const cx = clamp((d.start[0] + d.cur[0]) / 2, -W / 2, W / 2), cy = clamp((d.start[1] + d.cur[1]) / 2, -H / 2, H / 2);
  return {
    type: S.paletteZone, cx: round(cx, 2), cy: round(cy, 2),
    ax: Math.max(0.25, round(Math.abs(d.cur[0] - d.start[0]) / 2, 2)),
    ay: Math.max(0.25, round(Math.abs(d.cur[1] - d.start[1]) / 2, 2)),
    effect: S.zoneEffect[S.paletteZone],
  };
}

// --- mouse and keyboard ----------------------------------------------------------------------

function eventPos(e) {
  const rect = canvas.getBoundingClientRect();
  return [e.clientX - rect.left, e.clientY - rect.top];
}

canvas.addEventListener("contextmenu", (e) => e.preventDefault());
canvas.addEventListener("mousedown", (e) => {
  canvas.focus();
  const [px, py] = eventPos(e);
  const [wx, wy] = s2w(px, py);
  if (e.button === 1 || (e.button === 0 && (S.keys.has(" ") || e.altKey))) {
    S.drag = { kind: "pan", last: [px, py] };
    canvas.classList.add("panning");
    e.preventDefault();
    return;
  }
  if (S.preview) {
    if (e.button === 0) { S.drag = { kind: "pan", last: [px, py] }; canvas.classList.add("panning"); }
    return;
  }
  if (e.button === 2) {
    if (S.mode === "units") { const i = unitAt(wx, wy); if (i >= 0) deleteUnit(i); }
    else { const z = zoneAt(wx, wy); if (z >= 0) deleteZone(z); }
    return;
  }
  if (e.button !== 0) return;
  if (S.mode === "units") {
    const i = unitAt(wx, wy);
    if (i >= 0) {
      select("unit", i);
      const u = S.units[i];
      S.drag = { kind: "move-unit", index: i, start: [px, py], grab: [u.x - wx, u.y - wy], moved: false };
    } else {
      placeUnit(wx, wy);
    }
  } else {
    const z = zoneAt(wx, wy);
    if (z >= 0 && S.selection && S.selection.kind === "zone" && S.selection.index === z) {
      S.drag = { kind: "move-zone", index: z, start: [px, py], grab: [S.zones[z].cx - wx, S.zones[z].cy - wy], moved: false };
    } else {
      S.drag = { kind: "draw-zone", start: [wx, wy], cur: [wx, wy], startPx: [px, py], hit: z, moved: false };
    }
  }
});

window.addEventListener("mousemove", (e) => {
  const [px, py] = eventPos(e);
  const [wx, wy] = s2w(px, py);
  const inside = px >= 0 && py >= 0 && px < cssW && py < cssH;
  const d = S.drag;
  if (d && d.kind === "pan") {
    pan(px - d.last[0], py - d.last[1]);
    d.last = [px, py];
    return;
  }
  if (d && d.kind === "move-unit") {
    if (!d.moved && Math.hypot(px - d.start[0], py - d.start[1]) < 3) return;
    const u = S.units[d.index];
    let target;
    if (e.shiftKey) target = { x: round(wx + d.grab[0], 3), y: round(wy + d.grab[1], 3) };
    else {
      target = snap(spec(u).space, wx, wy);
      if (!target || occupiedBy(cellsOf(spec(u).space, target.x, target.y), d.index) >= 0) return;
    }
    if (!d.moved) { pushHistory(); d.moved = true; }
    u.x = target.x; u.y = target.y;
    clampIntoArena(u);
    changed();
    return;
  }
  if (d && d.kind === "move-zone") {
    if (!d.moved && Math.hypot(px - d.start[0], py - d.start[1]) < 3) return;
    if (!d.moved) { pushHistory(); d.moved = true; }
    const z = S.zones[d.index], [W, H] = S.doc.arena;
    z.cx = round(clamp(wx + d.grab[0], -W / 2, W / 2), 2);
    z.cy = round(clamp(wy + d.grab[1], -H / 2, H / 2), 2);
    changed();
    return;
  }
  if (d && d.kind === "draw-zone") {
    d.cur = [wx, wy];
    if (Math.hypot(px - d.startPx[0], py - d.startPx[1]) >= 4) d.moved = true;
    requestDraw();
    return;
  }
  if (!inside) {
    if (S.hover.world) { S.hover = { unit: -1, zone: -1, world: null }; $("status-cursor").textContent = ""; requestDraw(); }
    return;
  }
  const hu = unitAt(wx, wy), hz = S.preview ? -1 : zoneAt(wx, wy);
  S.hover = { unit: hu, zone: hz, world: [wx, wy] };
  canvas.classList.toggle("over-unit", hu >= 0 && S.mode === "units" && !S.preview);
  $("status-cursor").textContent = `x ${wx.toFixed(2)}  y ${wy.toFixed(2)}`;
  requestDraw();
});

window.addEventListener("mouseup", (e) => {
  const d = S.drag;
  if (!d) return;
  S.drag = null;
  canvas.classList.remove("panning");
  if (d.kind === "move-unit" && d.moved) {
    const u = S.units[d.index];
    status(`Moved unit #${d.index} to (${fmt(round(u.x))}, ${fmt(round(u.y))})`);
  } else if (d.kind === "draw-zone") {
    if (d.moved) {
      const z = zoneFromDrag(d);
      commit(() => { S.zones.push(z); S.selection = { kind: "zone", index: S.zones.length - 1 }; }, { rebuild: true });
      status(`Drew a ${z.type} zone at (${fmt(z.cx)}, ${fmt(z.cy)}), semi-axes ${fmt(z.ax)} × ${fmt(z.ay)}`);
    } else {
      select(d.hit >= 0 ? "zone" : null, d.hit);
    }
  }
  requestDraw();
  e.preventDefault();
});

canvas.addEventListener("wheel", (e) => {
  e.preventDefault();
  const [px, py] = eventPos(e);
  zoomAt(px, py, Math.exp(-e.deltaY * (e.deltaMode === 1 ? 0.05 : 0.0015)));
}, { passive: false });

canvas.addEventListener("dblclick", (e) => {
  if (S.preview) return;
  const [wx, wy] = s2w(...eventPos(e));
  const i = unitAt(wx, wy);
  if (i >= 0) { select("unit", i); focusFirstProp(); return; }
  const z = zoneAt(wx, wy);
  if (z >= 0) { select("zone", z); focusFirstProp(); }
});

function typing(e) {
  const t = e.target;
  return t instanceof HTMLInputElement || t instanceof HTMLTextAreaElement || t instanceof HTMLSelectElement
    || document.querySelector("dialog[open]");
}

window.addEventListener("keydown", (e) => {
  const key = e.key.toLowerCase();
  if ((e.ctrlKey || e.metaKey) && key === "s") { e.preventDefault(); openSave(); return; }
  if (typing(e)) return;
  if (e.ctrlKey || e.metaKey) {
    if (key === "z" && !e.shiftKey) { e.preventDefault(); undo(); }
    else if (key === "y" || (key === "z" && e.shiftKey)) { e.preventDefault(); redo(); }
    return;
  }
  S.keys.add(e.key);
  const step = 40;
  switch (key) {
    case "q": case "e": {
      if (S.preview) break;
      let i = S.hover.unit;
      if (i < 0 && S.selection && S.selection.kind === "unit") i = S.selection.index;
      if (i >= 0) rotateUnit(i, key === "q" ? 1 : -1);
      break;
    }
    case "delete": case "backspace": deleteSelection(); break;
    case "escape":
      if (S.preview) closePreview(); else if (S.drag) { S.drag = null; requestDraw(); } else select(null);
      break;
    case "w": case "arrowup": pan(0, step); break;
    case "s": case "arrowdown": pan(0, -step); break;
    case "a": case "arrowleft": pan(step, 0); break;
    case "d": case "arrowright": pan(-step, 0); break;
    case "r": fitView(); break;
    case "1": setMode("units"); break;
    case "2": setMode("zones"); break;
    case " ":
      e.preventDefault();
      if (S.preview) togglePlay();
      break;
    default: return;
  }
});
window.addEventListener("keyup", (e) => S.keys.delete(e.key));
window.addEventListener("blur", () => S.keys.clear());

function setMode(mode) {
  if (S.mode === mode) return;
  S.mode = mode;
  if (S.selection && S.selection.kind !== (mode === "units" ? "unit" : "zone")) S.selection = null;
  updateChrome();
  renderProps();
  requestDraw();
}

// --- property panel --------------------------------------------------------------------------

// A labelled text field with a range hint, live checks and an error line.
function numberRow({ id, label, value, range, scale = 1, overridden = false, onApply, extraCheck, resetTitle, onReset }) {
  const input = el("input", { id, "data-testid": id, inputmode: "decimal", autocomplete: "off", spellcheck: "false" });
  input.value = fmt(round(value * scale, 6));
  if (overridden) input.classList.add("overridden");
  const err = el("div", { class: "field-error", id: `err-${id.replace(/^prop-/, "")}`, "data-testid": `err-${id.replace(/^prop-/, "")}` });
  const check = () => {
    const v = parseNumber(input.value);
    if (v === null) return { error: "expected a number" };
    const raw = v / scale;
    if (range && !inRange(raw, range)) return { error: `expected a value in ${rangeText(range, scale)}` };
    if (extraCheck) { const msg = extraCheck(raw); if (msg) return { error: msg }; }
    return { value: raw };
  };
  const showCheck = () => {
    const r = check();
    err.textContent = r.error || ""; err.classList.remove("server");
    input.classList.toggle("invalid", !!r.error);
    return r;
  };
  const apply = () => {
    const r = showCheck();
    if (r.error) return;
    onApply(r.value);
  };
  input.addEventListener("input", showCheck);
  input.addEventListener("change", apply);
  input.addEventListener("keydown", (e) => { if (e.key === "Enter") { e.preventDefault(); apply(); } });
  const row = el("div", { class: "stat-row" },
    el("label", { for: id, text: label }), input,
    onReset ? el("button", { class: "reset", type: "button", hidden: !overridden, title: resetTitle || "Back to the default", text: "↺", onclick: onReset }) : el("span"),
    range ? el("span", { class: "range", text: rangeText(range, scale) }) : null, err);
  return row;
}

function statRows(unitName, overrides, apply, idPrefix) {
  // One row per stat of UNIT_STAT_RANGES (+ heals) for a unit type and its overrides.
  const rows = [];
  for (const key of S.meta.stat_order) {
    const id = `${idPrefix}-${key}`;
    const overridden = key in overrides;
    if (key === "heals") {
      const box = el("input", { type: "checkbox", id, "data-testid": id });
      box.checked = statOf(unitName, overrides, "heals");
      box.addEventListener("change", () => apply(key, box.checked));
      rows.push(el("div", { class: "stat-row checkbox" }, el("label", { for: id, text: STAT_LABELS.heals }),
        el("span", { class: "check" }, box, el("span", { class: "range", text: overridden ? "overridden" : "default: damage < 0" })),
        el("button", { class: "reset", type: "button", hidden: !overridden, title: "Back to the default (damage < 0)", text: "↺", onclick: () => apply(key, null) })));
      continue;
    }
    const scale = key === "sight_angle" ? 1 / DEG : 1;
    rows.push(numberRow({
      id, label: STAT_LABELS[key], value: statOf(unitName, overrides, key), range: S.meta.stat_ranges[key], scale, overridden,
      onApply: (v) => apply(key, v),
      onReset: () => apply(key, null),
      extraCheck: (v) => {
        if (key === "health" && v > statOf(unitName, overrides, "max_health") && "max_health" in overrides) {
          return `health ${fmt(v)} exceeds max_health ${fmt(statOf(unitName, overrides, "max_health"))}`;
        }
        if (key === "max_health" && statOf(unitName, overrides, "health") > v) {
          return `max_health ${fmt(v)} is below health ${fmt(statOf(unitName, overrides, "health"))}`;
        }
        return null;
      },
    }));
  }
  return rows;
}

function applyOverride(unitName, overrides, key, value) {
  if (value === null) {
    delete overrides[key];
    if (key === "health" && "max_health" in overrides && sameF32(overrides.max_health, statOf(unitName, overrides, "health"))) delete overrides.max_health;
  } else setOverride(unitName, overrides, key, value);
}

function renderProps() {
  const box = $("selection-props");
  box.replaceChildren();
  const sel = S.selection;
  if (S.preview) {
    box.append(el("h2", { text: "Preview" }),
      el("p", { class: "empty-note", text: "Editing is paused while a preview plays. Press Edit (or Esc) to go back." }),
      el("div", { class: "preview-units", id: "preview-units", "data-testid": "preview-units" }));
    renderPreviewUnits();
    return;
  }
  if (!sel) {
    box.append(el("h2", { text: "Selection" }), el("p", { class: "empty-note", text:
      S.mode === "units" ? "Click a unit to edit its stats, or click an empty cell to place the palette unit."
        : "Draw a zone by dragging on the arena, or click a zone to edit it." }));
    return;
  }
  if (sel.kind === "unit") {
    const u = S.units[sel.index];
    box.append(el("h2", {}, `Unit #${sel.index}`, el("span", { class: `badge ${u.team}`, text: `${u.team} ${u.unit}` })));
    const typeSel = el("select", { id: "prop-unit", "data-testid": "prop-unit" },
      S.meta.units.map((t) => el("option", { value: t.name, text: `${t.char} · ${t.name}` })));
    typeSel.value = u.unit;
    typeSel.addEventListener("change", () => commit(() => { u.unit = typeSel.value; u.overrides = {}; clampIntoArena(u); }, { rebuild: true }));
    const teamSel = el("select", { id: "prop-team", "data-testid": "prop-team" }, ["ally", "enemy"].map((t) => el("option", { value: t, text: t })));
    teamSel.value = u.team;
    teamSel.addEventListener("change", () => commit(() => { u.team = teamSel.value; }, { rebuild: true }));
    const [W, H] = S.doc.arena;
    box.append(
      el("div", { class: "prop-grid" },
        el("div", { class: "stat-row" }, el("label", { for: "prop-unit", text: "Type" }), typeSel),
        el("div", { class: "stat-row" }, el("label", { for: "prop-team", text: "Team" }), teamSel),
        numberRow({ id: "prop-x", label: "x", value: u.x, onApply: (v) => commit(() => { u.x = v; }),
          extraCheck: (v) => Math.abs(v) > W / 2 - radius(u) + 1e-6 ? `expected |x| <= width/2 - radius = ${fmt(round(W / 2 - radius(u), 4))}` : null }),
        numberRow({ id: "prop-y", label: "y", value: u.y, onApply: (v) => commit(() => { u.y = v; }),
          extraCheck: (v) => Math.abs(v) > H / 2 - radius(u) + 1e-6 ? `expected |y| <= height/2 - radius = ${fmt(round(H / 2 - radius(u), 4))}` : null }),
        numberRow({ id: "prop-heading", label: "Heading (°)", value: u.heading, scale: 1 / DEG, range: S.meta.heading_range,
          onApply: (v) => commit(() => { u.heading = v; }) }),
      ),
      el("div", { class: "subhead" }, "Stats", el("span", { class: "note", text: "yellow: differs from the type · ↺ resets" })),
      el("div", { class: "stat-fields" }, statRows(u.unit, u.overrides, (key, value) => commit(() => applyOverride(u.unit, u.overrides, key, value)), "prop")),
      el("div", { class: "field-error", id: "err-selection", "data-testid": "err-selection" }),
      el("div", { class: "sel-actions" },
        el("button", { type: "button", text: "Rotate ⟲", title: "Q", onclick: () => rotateUnit(sel.index, 1) }),
        el("button", { type: "button", text: "Rotate ⟳", title: "E", onclick: () => rotateUnit(sel.index, -1) }),
        el("button", { type: "button", class: "danger", "data-testid": "prop-delete", text: "Delete", onclick: () => deleteUnit(sel.index) })),
    );
  } else {
    const z = S.zones[sel.index];
    const [W, H] = S.doc.arena;
    box.append(el("h2", {}, `Zone #${sel.index}`, el("span", { class: "badge", text: z.type })));
    const typeSel = el("select", { id: "prop-zone-type", "data-testid": "prop-zone-type" }, S.meta.zone_types.map((t) => el("option", { value: t, text: t })));
    typeSel.value = z.type;
    typeSel.addEventListener("change", () => commit(() => {
      z.type = typeSel.value;
      if (!inRange(z.effect, S.meta.zone_effect_ranges[z.type])) z.effect = S.meta.zone_effect_defaults[z.type];
    }, { rebuild: true }));
    const axisRange = S.meta.semi_axis_range;
    box.append(
      el("div", { class: "prop-grid" },
        el("div", { class: "stat-row" }, el("label", { for: "prop-zone-type", text: "Type" }), typeSel),
        numberRow({ id: "prop-cx", label: "Centre x", value: z.cx, onApply: (v) => commit(() => { z.cx = v; }),
          extraCheck: (v) => Math.abs(v) > W / 2 ? `expected |x| <= ${fmt(W / 2)} (inside the arena)` : null }),
        numberRow({ id: "prop-cy", label: "Centre y", value: z.cy, onApply: (v) => commit(() => { z.cy = v; }),
          extraCheck: (v) => Math.abs(v) > H / 2 ? `expected |y| <= ${fmt(H / 2)} (inside the arena)` : null }),
        numberRow({ id: "prop-ax", label: "Semi-axis x", value: z.ax, range: axisRange, onApply: (v) => commit(() => { z.ax = v; }) }),
        numberRow({ id: "prop-ay", label: "Semi-axis y", value: z.ay, range: axisRange, onApply: (v) => commit(() => { z.ay = v; }) }),
        numberRow({ id: "prop-effect", label: "Effect", value: z.effect, range: S.meta.zone_effect_ranges[z.type], onApply: (v) => commit(() => { z.effect = v; }) }),
      ),
      el("p", { class: "hint", text: ZONE_HELP[z.type] }),
      el("div", { class: "field-error", id: "err-selection", "data-testid": "err-selection" }),
      el("div", { class: "sel-actions" },
        el("button", { type: "button", class: "danger", "data-testid": "prop-delete", text: "Delete", onclick: () => deleteZone(sel.index) })),
    );
  }
}

function refreshPropValues() {
  // Keep the panel in step with canvas edits (drag, rotate) without rebuilding it.
  const sel = S.selection;
  if (!sel || S.preview) return;
  const set = (id, v) => {
    const node = $(id);
    if (node && document.activeElement !== node) { node.value = fmt(round(v, 6)); node.classList.remove("invalid"); const e = $(`err-${id.slice(5)}`); if (e) e.textContent = ""; }
  };
  if (sel.kind === "unit") {
    const u = S.units[sel.index];
    if (!u) return;
    set("prop-x", u.x); set("prop-y", u.y); set("prop-heading", u.heading / DEG);
    refreshStatRows($("selection-props"), u.unit, u.overrides, "prop");
  } else {
    const z = S.zones[sel.index];
    if (!z) return;
    set("prop-cx", z.cx); set("prop-cy", z.cy); set("prop-ax", z.ax); set("prop-ay", z.ay); set("prop-effect", z.effect);
  }
}
// Update stat fields in place (values, override marks, reset buttons): rebuilding them would
// take the focus away from the field the user just clicked.
function refreshStatRows(container, unitName, overrides, prefix) {
  if (!container) return;
  for (const key of S.meta.stat_order) {
    const input = container.querySelector(`#${prefix}-${key}`);
    if (!input) continue;
    const row = input.closest(".stat-row"), overridden = key in overrides;
    const reset = row.querySelector(".reset");
    if (reset) reset.hidden = !overridden;
    if (key === "heals") {
      input.checked = statOf(unitName, overrides, "heals");
      row.querySelector(".check .range").textContent = overridden ? "overridden" : "default: damage < 0";
      continue;
    }
    input.classList.toggle("overridden", overridden);
    if (document.activeElement !== input) {
      input.value = fmt(round(statOf(unitName, overrides, key) * (key === "sight_angle" ? 1 / DEG : 1), 6));
      input.classList.remove("invalid");
      const err = row.querySelector(".field-error");
      if (err) err.textContent = "";
    }
  }
}
function focusFirstProp() {
  const first = $("selection-props").querySelector("input");
  if (first) first.focus();
}

// --- palette ---------------------------------------------------------------------------------

function buildPalette() {
  const list = $("unit-list");
  list.replaceChildren(...S.meta.units.map((t) => el("button", {
    class: "palette-item", type: "button", "data-testid": `palette-unit-${t.name}`, dataset: { paletteUnit: t.name },
    title: `${t.name}: click to pick, double-click to edit default stats`,
    onclick: () => { S.paletteUnit = t.name; updateChrome(); requestDraw(); },
    ondblclick: () => openDefaults(t.name),
  }, el("span", { class: "chip", text: t.char }),
  el("span", { class: "name" }, t.name, el("span", { class: "custom", text: "*", title: "custom default stats" })),
  el("span", { class: "meta", text: `${fmt(t.stats.health)} hp · ${fmt(t.stats.damage)}` }))));
  const zones = $("zone-list");
  zones.replaceChildren(...S.meta.zone_types.map((t) => {
    const [r, g, b] = ZONE_FILL[t];
    return el("button", {
      class: "palette-item", type: "button", "data-testid": `palette-zone-${t}`, dataset: { paletteZone: t },
      onclick: () => { S.paletteZone = t; syncZoneEffect(); updateChrome(); },
    }, el("span", { class: "chip zone", style: `background: rgb(${r},${g},${b})` }), el("span", { class: "name", text: t }), el("span", { class: "meta" }));
  }));
  const effect = $("zone-effect");
  const check = () => {
    const v = parseNumber(effect.value), r = S.meta.zone_effect_ranges[S.paletteZone];
    const msg = v === null ? "expected a number" : inRange(v, r) ? "" : `expected a value in ${rangeText(r)}`;
    $("err-zone-effect").textContent = msg;
    effect.classList.toggle("invalid", !!msg);
    return msg ? null : v;
  };
  effect.addEventListener("input", () => { const v = check(); if (v !== null) { S.zoneEffect[S.paletteZone] = v; updateChrome(); } });
  syncZoneEffect();
}
function syncZoneEffect() {
  const t = S.paletteZone;
  $("zone-effect").value = fmt(S.zoneEffect[t]);
  $("zone-effect").classList.remove("invalid");
  $("err-zone-effect").textContent = "";
  $("zone-effect-range").textContent = rangeText(S.meta.zone_effect_ranges[t]);
  $("zone-effect-hint").textContent = ZONE_HELP[t];
}

let defaultsDraft = null;
function openDefaults(name) {
  defaultsDraft = { name, overrides: { ...(S.typeDefaults[name] || {}) } };
  renderDefaults();
  $("dlg-defaults").showModal();
}
function renderDefaults() {
  const { name, overrides } = defaultsDraft;
  $("defaults-title").textContent = `Default stats: ${name}`;
  $("defaults-fields").replaceChildren(...statRows(name, overrides, (key, value) => {
    applyOverride(name, overrides, key, value);
    refreshStatRows($("defaults-fields"), name, overrides, "def");
  }, "def"));
}
$("defaults-reset").addEventListener("click", () => { defaultsDraft.overrides = {}; renderDefaults(); });
$("form-defaults").addEventListener("submit", (e) => {
  // Apply values typed but not yet confirmed with Enter.
  for (const input of $("defaults-fields").querySelectorAll("input:not([type=checkbox])")) input.dispatchEvent(new Event("change"));
  if ($("defaults-fields").querySelector("input.invalid")) { e.preventDefault(); return; }
  S.typeDefaults[defaultsDraft.name] = { ...defaultsDraft.overrides };
  status(`Default stats of ${defaultsDraft.name}: ${Object.keys(defaultsDraft.overrides).length ? JSON.stringify(defaultsDraft.overrides) : "the type's own"}`);
  updateChrome();
});

// --- New / Load / Save / Clear ---------------------------------------------------------------

function openNew() {
  $("new-width").value = fmt(S.doc.arena[0]);
  $("new-height").value = fmt(S.doc.arena[1]);
  $("new-margin").value = fmt(S.grid.margin);
  $("new-spacing").value = fmt(S.grid.spacing);
  checkNew();
  $("dlg-new").showModal();
}
function checkNew() {
  const ar = S.meta.arena_range;
  const vals = {}, errs = {};
  for (const k of ["width", "height", "margin", "spacing"]) {
    const v = parseNumber($(`new-${k}`).value);
    if (v === null) errs[k] = "expected a number";
    else if ((k === "width" || k === "height") && !inRange(v, ar)) errs[k] = `expected a value in ${rangeText(ar)}`;
    else if (k === "margin" && v < 0) errs[k] = "expected a value >= 0";
    else if (k === "spacing" && !(v > 0)) errs[k] = "expected a value > 0";
    vals[k] = v;
  }
  if (!errs.margin && !errs.width && !errs.height && vals.margin * 2 >= Math.min(vals.width, vals.height)) errs.margin = "the margins leave no room";
  let note = "";
  if (!Object.keys(errs).length) {
    const cols = Math.floor((vals.width - 2 * vals.margin) / vals.spacing + 1e-9);
    const rows = Math.floor((vals.height - 2 * vals.margin) / vals.spacing + 1e-9);
    if (cols < 1 || rows < 1) errs.spacing = "the spacing leaves no grid cell";
    else note = `Grid: ${cols} × ${rows} cells (${cols * rows} places for units).`;
  }
  for (const k of ["width", "height", "margin", "spacing"]) {
    $(`err-new-${k}`).textContent = errs[k] || "";
    $(`new-${k}`).classList.toggle("invalid", !!errs[k]);
  }
  $("new-grid-note").textContent = note;
  return Object.keys(errs).length ? null : vals;
}
for (const k of ["width", "height", "margin", "spacing"]) $(`new-${k}`).addEventListener("input", checkNew);
$("form-new").addEventListener("submit", (e) => {
  const v = checkNew();
  if (!v) { e.preventDefault(); return; }
  closePreview();
  commit(() => {
    S.doc = { name: "untitled", category: "user", description: "", arena: [v.width, v.height], extra: {} };
    S.units = []; S.zones = []; S.grid = { spacing: v.spacing, margin: v.margin }; S.selection = null;
  }, { rebuild: true });
  S.dirty = false;
  updateChrome();
  fitView();
  status(`New ${fmt(v.width)} × ${fmt(v.height)} scenario`);
});

let loadItems = [], loadTab = "all", loadSelected = null;
const LOAD_TABS = [["all", "All"], ["challenge", "Challenges"], ["units", "Units"], ["zones", "Zones"], ["user", "Mine"]];
async function openLoad() {
  $("dlg-load").showModal();
  $("load-search").value = "";
  loadSelected = null;
  $("load-list").replaceChildren(el("div", { class: "load-empty", text: "Loading…" }));
  $("load-search").focus();
  try {
    const r = await apiGet("/api/scenarios");
    loadItems = r.scenarios;
    $("load-note").textContent = `User scenarios: ${r.user_dir}`;
  } catch (err) {
    loadItems = [];
    $("load-note").textContent = String(err.message);
  }
  renderLoadList();
}
function renderLoadList() {
  $("load-tabs").replaceChildren(...LOAD_TABS.map(([key, label]) => el("button", {
    type: "button", class: key === loadTab ? "active" : "", "data-testid": `load-tab-${key}`, text: label,
    onclick: () => { loadTab = key; renderLoadList(); },
  })));
  const q = $("load-search").value.trim().toLowerCase();
  const rows = loadItems.filter((s) => (loadTab === "all" || (loadTab === "user" ? s.source === "user" : s.category === loadTab))
    && (!q || s.name.toLowerCase().includes(q) || (s.description || "").toLowerCase().includes(q)));
  const nodes = rows.map((s) => el("div", {
    class: `load-row${loadSelected === s.name ? " selected" : ""}${s.error ? " bad" : ""}`, "data-testid": `load-row-${s.name}`, dataset: { name: s.name },
    title: s.error || s.description || s.name,
    onclick: () => { loadSelected = s.name; renderLoadList(); },
    ondblclick: () => { loadSelected = s.name; $("dlg-load").close(); loadByName(s.name); },
  }, el("span", { class: "n", text: s.name }),
  el("span", {}, el("span", { class: `badge${s.source === "user" ? " user" : ""}`, text: s.category }), s.split === "eval" ? el("span", { class: "badge eval", text: "eval" }) : null),
  el("span", { class: "u", text: s.error ? "invalid: " + s.error : s.units_text !== "-" ? `${s.allies} v ${s.enemies} · ${s.units_text}` : "no units" }),
  el("span", { class: "z", text: s.zones ? `${s.zones} · ${s.zones_text}` : "no zones" })));
  const raw = $("load-search").value.trim();
  if (raw && !rows.some((s) => s.name === raw)) {
    nodes.unshift(el("div", {
      class: `load-row by-name${loadSelected === raw ? " selected" : ""}`, "data-testid": "load-row-by-name",
      onclick: () => { loadSelected = raw; renderLoadList(); },
      ondblclick: () => { $("dlg-load").close(); loadByName(raw); },
    }, el("span", { class: "n", text: `Open “${raw}” by name` }), el("span"), el("span", { class: "u", text: "e.g. a composition UNITS_ZONES" }), el("span")));
  }
  if (!nodes.length) nodes.push(el("div", { class: "load-empty", text: "No scenario matches." }));
  $("load-list").replaceChildren(...nodes);
}
$("load-search").addEventListener("input", () => { loadSelected = null; renderLoadList(); });
$("load-search").addEventListener("keydown", (e) => {
  if (e.key === "Escape") { e.preventDefault(); $("dlg-load").close("cancel"); return; }
  if (e.key === "Enter") {
    e.preventDefault();
    // The selected row, else the first listed scenario, else the text as a name.
    const first = $("load-list").querySelector(".load-row:not(.by-name)");
    const name = loadSelected || (first ? first.dataset.name : $("load-search").value.trim());
    if (name) { $("dlg-load").close(); loadByName(name); }
  }
});
$("form-load").addEventListener("submit", (e) => {
  const name = loadSelected || $("load-search").value.trim();
  if (!name) { e.preventDefault(); return; }
  loadByName(name);
});
async function loadByName(name) {
  try {
    const r = await apiGet(`/api/scenario?name=${encodeURIComponent(name)}`);
    closePreview();
    commit(() => { fromScenario(r.scenario); S.selection = null; }, { rebuild: true });
    S.dirty = false;
    updateChrome();
    fitView();
    status(`Loaded ${r.scenario.name} (${r.source})`);
    toast(`Loaded ${r.scenario.name}`);
  } catch (err) {
    toast(`Cannot load ${name}: ${err.message}`, true);
    status(`Cannot load ${name}: ${err.message}`);
  }
}

function defaultCategory() {
  if (S.doc.category && S.doc.category !== "user") return S.doc.category;
  if (S.units.length && !S.zones.length) return "units";
  if (!S.units.length && S.zones.length) return "zones";
  return "challenge";
}
function openSave() {
  if (S.preview) closePreview();
  if (document.querySelector("dialog[open]")) return;
  $("save-name").value = S.doc.name === "untitled" ? "" : S.doc.name;
  $("save-category").value = defaultCategory();
  $("save-error").textContent = "";
  $("err-save-name").textContent = "";
  $("save-overwrite").hidden = true;
  updateSavePath();
  $("dlg-save").showModal();
  $("save-name").focus();
}
function updateSavePath() {
  const name = $("save-name").value.trim() || "NAME";
  $("save-path").textContent = `${S.userDir}/${S.meta.user_folders[$("save-category").value]}/${name}.json`;
  const ok = new RegExp(S.meta.name_pattern).test($("save-name").value.trim());
  $("err-save-name").textContent = ok || !$("save-name").value ? "" : "1-100 characters A-Z a-z 0-9 _ . -, starting with a letter or digit";
  $("save-overwrite").hidden = true;
}
$("save-name").addEventListener("input", updateSavePath);
$("save-category").addEventListener("change", updateSavePath);
$("form-save").addEventListener("submit", (e) => {
  e.preventDefault();
  doSave(!!e.submitter && e.submitter.value === "overwrite");
});
async function doSave(overwrite) {
  const name = $("save-name").value.trim(), category = $("save-category").value;
  $("save-error").textContent = "";
  const { status: code, body } = await apiPost("/api/save", { scenario: toScenario(), name, category, overwrite });
  if (body.ok) {
    $("dlg-save").close();
    commit(() => { S.doc.name = name; S.doc.category = category; }, { dirty: false });
    S.dirty = false;
    updateChrome();
    status(`Saved ${body.path}`);
    toast(`Saved ${name}`);
    return;
  }
  const err = body.error || { text: `error ${code}`, path: "" };
  if (code === 409) {
    $("save-error").textContent = err.message;
    $("save-overwrite").hidden = !body.can_overwrite;
    return;
  }
  if (err.path === "name") { $("err-save-name").textContent = err.message; return; }
  // A validation error in the content: show it here and next to the field in the panel.
  $("save-error").textContent = `Not saved: ${err.text}`;
  S.validation = body;
  const target = parseErrorPath(err.path);
  if (target && target.kind !== "doc") select(target.kind, target.index);
  showValidation();
}

function clearAll() {
  if (!S.units.length && !S.zones.length) return;
  closePreview();
  commit(() => { S.units = []; S.zones = []; S.selection = null; }, { rebuild: true });
  status("Cleared (Undo brings it back)");
}

// --- preview ---------------------------------------------------------------------------------

let playTimer = 0, playLast = 0;
async function runPreview() {
  $("preview-error").textContent = "";
  const steps = parseNumber($("preview-steps").value), seed = parseNumber($("preview-seed").value);
  if (steps === null || !Number.isInteger(steps) || steps < 1 || steps > S.meta.max_preview_steps) {
    $("preview-error").textContent = `Steps: expected an integer in [1, ${S.meta.max_preview_steps}]`; return;
  }
  if (seed === null || !Number.isInteger(seed) || seed < 0) { $("preview-error").textContent = "Seed: expected an integer >= 0"; return; }
  const payload = { scenario: toScenario(), steps, seed, ally: $("preview-ally").value, enemy: $("preview-enemy").value };
  const units = S.units.map((u) => deepCopy(u));
  $("preview-run").disabled = true;
  busy("Running the simulator… (the first preview of a size compiles; this can take a while)");
  const t0 = performance.now();
  try {
    const { body } = await apiPost("/api/preview", payload);
    if (!body.ok) {
      $("preview-error").textContent = body.error.text;
      const target = parseErrorPath(body.error.path);
      if (target && target.kind !== "doc") { S.validation = body; select(target.kind, target.index); showValidation(); }
      return;
    }
    S.preview = { data: body, units, frame: 0, playing: true, speed: Number($("play-speed").value) };
    S.selection = null;
    $("play-slider").max = String(body.steps);
    $("playback").hidden = false;
    renderProps();
    updateChrome();
    const secs = ((performance.now() - t0) / 1000).toFixed(1);
    status(`Preview: ${body.steps} steps in ${secs} s${body.compiled ? ` (compiled in ${body.compile_s.toFixed(1)} s)` : ""}` +
      (body.done_at !== null ? `; ${body.winner === "ally" ? "allies" : "enemies"} win by ${body.outcome} at step ${body.done_at}` : "; no winner yet"));
    startPlay();
  } catch (err) {
    $("preview-error").textContent = String(err.message || err);
  } finally {
    $("preview-run").disabled = false;
    busy(null);
  }
}
function setFrame(f) {
  const p = S.preview;
  if (!p) return;
  p.frame = clamp(Math.round(f), 0, p.data.steps);
  $("play-slider").value = String(p.frame);
  $("play-step").textContent = `${p.frame} / ${p.data.steps}`;
  renderPreviewUnits();
  requestDraw();
}
function renderPreviewUnits() {
  // Every unit's health at the current frame, in file order.
  const box = $("preview-units"), p = S.preview;
  if (!box || !p) return;
  const d = p.data, f = p.frame;
  box.replaceChildren(...p.units.map((u, i) => {
    const ratio = clamp(d.health[f][i] / d.max_health[i], 0, 1);
    return el("div", { class: `pu${d.alive[f][i] ? "" : " dead"}` },
      el("span", { class: "chip", style: `background: ${d.alive[f][i] ? TEAM_FILL[u.team] : DEAD_FILL}`, text: spec(u).char }),
      el("span", { class: "pu-name", text: `#${i} ${u.unit}` }),
      el("span", { class: "bar" }, el("span", { style: `width: ${(ratio * 100).toFixed(1)}%` })),
      el("span", { class: "pu-hp", text: `${fmt(round(d.health[f][i], 1))}` }));
  }));
}
function startPlay() {
  const p = S.preview;
  if (!p) return;
  p.playing = true;
  if (p.frame >= p.data.steps) setFrame(0);
  $("play-toggle").textContent = "❚❚";
  playLast = performance.now();
  cancelAnimationFrame(playTimer);
  const tick = (now) => {
    if (!S.preview || !S.preview.playing) return;
    const stepsPerSecond = 12 * S.preview.speed;
    const adv = Math.floor((now - playLast) * stepsPerSecond / 1000);
    if (adv > 0) {
      playLast += adv * 1000 / stepsPerSecond;
      setFrame(S.preview.frame + adv);
      if (S.preview.frame >= S.preview.data.steps) { pausePlay(); return; }
    }
    playTimer = requestAnimationFrame(tick);
  };
  playTimer = requestAnimationFrame(tick);
}
function pausePlay() {
  if (S.preview) S.preview.playing = false;
  $("play-toggle").textContent = "▶";
}
function togglePlay() { if (S.preview && S.preview.playing) pausePlay(); else startPlay(); }
function closePreview() {
  if (!S.preview) return;
  cancelAnimationFrame(playTimer);
  S.preview = null;
  $("playback").hidden = true;
  renderProps();
  updateChrome();
  requestDraw();
}

// --- start -----------------------------------------------------------------------------------

function wire() {
  for (const b of document.querySelectorAll("dialog button[value=cancel]")) {
    b.addEventListener("click", () => b.closest("dialog").close("cancel"));
  }
  $("btn-new").addEventListener("click", openNew);
  $("btn-load").addEventListener("click", openLoad);
  $("btn-save").addEventListener("click", openSave);
  $("btn-clear").addEventListener("click", clearAll);
  $("btn-undo").addEventListener("click", undo);
  $("btn-redo").addEventListener("click", redo);
  $("btn-fit").addEventListener("click", fitView);
  $("btn-help").addEventListener("click", () => $("dlg-help").showModal());
  $("btn-sight").addEventListener("click", () => { S.showSight = !S.showSight; updateChrome(); requestDraw(); });
  for (const b of document.querySelectorAll("[data-mode]")) b.addEventListener("click", () => setMode(b.dataset.mode));
  for (const b of document.querySelectorAll("[data-team]")) b.addEventListener("click", () => { S.team = b.dataset.team; updateChrome(); requestDraw(); });
  $("status-valid").addEventListener("click", jumpToError);
  $("scn-name").addEventListener("input", () => {
    const v = $("scn-name").value.trim();
    const ok = new RegExp(S.meta.name_pattern).test(v);
    $("err-scn-name").textContent = ok ? "" : "1-100 characters A-Z a-z 0-9 _ . -, starting with a letter or digit";
    $("scn-name").classList.toggle("invalid", !ok);
  });
  $("scn-name").addEventListener("change", () => {
    const v = $("scn-name").value.trim();
    if (new RegExp(S.meta.name_pattern).test(v) && v !== S.doc.name) commit(() => { S.doc.name = v; });
  });
  $("scn-category").addEventListener("change", () => commit(() => { S.doc.category = $("scn-category").value; }));
  $("scn-description").addEventListener("change", () => commit(() => { S.doc.description = $("scn-description").value; }));
  $("preview-run").addEventListener("click", runPreview);
  $("play-toggle").addEventListener("click", togglePlay);
  $("play-close").addEventListener("click", closePreview);
  $("play-slider").addEventListener("input", () => { pausePlay(); setFrame(Number($("play-slider").value)); });
  $("play-speed").addEventListener("change", () => { if (S.preview) { S.preview.speed = Number($("play-speed").value); playLast = performance.now(); } });
  new ResizeObserver(resize).observe(canvas);
  window.addEventListener("beforeunload", (e) => {
    if (S.dirty && (S.units.length || S.zones.length)) { e.preventDefault(); e.returnValue = ""; }
  });
}

async function main() {
  const [meta, session] = await Promise.all([apiGet("/api/units"), apiGet("/api/session")]);
  S.meta = meta;
  FONT = getComputedStyle(document.body).fontFamily;
  S.userDir = session.user_dir;
  for (const t of meta.units) S.specs[t.name] = t;
  S.zoneEffect = { ...meta.zone_effect_defaults };
  S.grid = { ...meta.grid_default };
  for (const c of meta.categories) $("scn-category").append(el("option", { value: c, text: c }));
  for (const c of Object.keys(meta.user_folders)) $("save-category").append(el("option", { value: c, text: `${c}  →  ${meta.user_folders[c]}/` }));
  for (const id of ["preview-ally", "preview-enemy"]) {
    $(id).append(
      el("optgroup", { label: "Scripted heuristic" },
        meta.tiers.map((t) => el("option", { value: `heuristic:${t}`, text: `heuristic ${t}` })),
        el("option", { value: "heuristic", text: "heuristic (scenario's)" })),
      el("optgroup", { label: "Other" },
        el("option", { value: "random", text: "random actions" }), el("option", { value: "idle", text: "idle" })));
    $(id).value = "heuristic:medium";
  }
  S.doc = { name: "untitled", category: "user", description: "", arena: [...meta.arena_default], extra: {} };
  if (session.initial) fromScenario(session.initial);
  buildPalette();
  wire();
  resize();
  fitView();
  updateChrome();
  renderProps();
  scheduleValidate();
  status(session.initial ? `Opened ${session.initial.name}` : "Ready: pick a unit and click the arena");
  window.editorDebug.ready = true;
}

// A small hook for tests and scripts: coordinates and the current scenario.
window.editorDebug = {
  ready: false,
  worldToClient(x, y) {
    const rect = canvas.getBoundingClientRect();
    const [px, py] = w2s(x, y);
    return { x: rect.left + px, y: rect.top + py };
  },
  clientToWorld(cx, cy) {
    const rect = canvas.getBoundingClientRect();
    const [x, y] = s2w(cx - rect.left, cy - rect.top);
    return { x, y };
  },
  cellCentre(i, j) { const g = gridGeom(); return { x: g.x0 + (i + 0.5) * g.s, y: g.y0 + (j + 0.5) * g.s }; },
  grid: () => gridGeom(),
  scenario: () => toScenario(),
  validation: () => S.validation,
  selection: () => S.selection && { ...S.selection },
  preview: () => S.preview && { frame: S.preview.frame, steps: S.preview.data.steps },
  setFrame: (f) => { pausePlay(); setFrame(f); },
  setSight: (on) => { S.showSight = !!on; updateChrome(); requestDraw(); },
  select: (kind, index) => select(kind, index),
  load: (name) => loadByName(name),
};

main().catch((err) => {
  document.body.append(el("div", { class: "toast error", text: `The editor failed to start: ${err.message}` }));
  console.error(err);
});

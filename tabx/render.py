"""Pictures of TABX battles: one level or state as a PIL image, a trajectory as frames, PNG/GIF.

    from tabx.render import render_level, render_trajectory, save_gif, save_png
    save_png(render_level(config, level, show_fov=True), "level.png")
    save_gif(render_trajectory(config, level, states, infos), "episode.gif", fps=10)

Drawn with Pillow's `ImageDraw` (no window, no matplotlib), at twice the size and scaled down,
which smooths the edges. World coordinates have their origin at the arena centre and y up; the
image flips y. What a frame shows:

- the arena (sand, with a faint 10-unit grid) and the zones as semi-transparent ellipses: lava
  orange-red, bush green, swamp olive-brown;
- every active unit as a circle of its radius in its team colour (allies blue, enemies red; dead
  units grey), its letter (`constants.UNIT_SPECS[type].char`), a heading mark from the centre
  through the rim, and above it a health bar (green, health / max health) and a cooldown bar
  (amber, full = ready to attack);
- optionally each living unit's field of view (a faint wedge of its sight angle, drawn to
  `FOV_LENGTH` world units) and the hurtbox of every unit that attacked this step (pass the
  step's `info`; a landed attack is drawn stronger than a miss);
- a status header (title, step, living units and health ratio per team, the outcome once done)
  and a legend below the arena.

All functions take single (unbatched) levels and states, as jax or numpy arrays.
"""

from __future__ import annotations

import dataclasses
import functools
import io
import math
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import jax
import numpy as np
from PIL import Image, ImageDraw, ImageFont

from tabx import constants as C
from tabx.errors import UserError
from tabx.files import atomic_write_bytes
from tabx.params import EnvConfig, EnvParams
from tabx.state import EnvState

RGB = tuple[int, int, int]

# --- colours (the legend of docs/rendering.md) -------------------------------------------------
BACKGROUND: RGB = (250, 250, 248)
ARENA_FILL: RGB = (236, 230, 213)
ARENA_GRID: RGB = (226, 219, 199)
ARENA_EDGE: RGB = (60, 60, 60)
TEXT: RGB = (35, 35, 35)
TEXT_DIM: RGB = (110, 110, 110)
ZONE_COLOURS: dict[int, RGB] = {
    C.ZONE_LAVA: (232, 80, 20),
    C.ZONE_BUSH: (50, 150, 55),
    C.ZONE_SWAMP: (125, 110, 40),
}
ZONE_ALPHA = 165
TEAM_COLOURS: dict[int, RGB] = {C.ALLY: (40, 100, 215), C.ENEMY: (210, 40, 40)}
TEAM_OUTLINES: dict[int, RGB] = {C.ALLY: (15, 40, 115), C.ENEMY: (110, 15, 15)}
DEAD_COLOUR: RGB = (155, 155, 155)
DEAD_OUTLINE: RGB = (100, 100, 100)
HEALTH_COLOUR: RGB = (45, 180, 65)
COOLDOWN_COLOUR: RGB = (240, 175, 20)
BAR_BACKGROUND: RGB = (70, 70, 70)
FOV_ALPHA = 38
HURTBOX_ALPHA = (45, 110)  # fill alpha of a missed and of a landed attack

FOV_LENGTH = 12.0  # world units: how far the (infinitely long) view wedges are drawn
GRID_STEP = 10.0  # world units between grid lines
_SUPERSAMPLE = 2  # drawn at this multiple of the output size, then scaled down (anti-aliasing)


# --- layout --------------------------------------------------------------------------------------


@dataclass(frozen=True)
class _Layout:
    """Pixel geometry of a frame at `k` pixels per world unit (output pixels times `ss`)."""

    arena: tuple[float, float]
    scale: float
    ss: int = 1
    legend_rows: int = 1

    @property
    def k(self) -> float:
        return self.scale * self.ss

    @property
    def font_size(self) -> int:  # header and legend text, output pixels
        return int(np.clip(round(1.3 * self.scale + 3), 11, 24))

    @property
    def margin(self) -> int:
        return max(12, round(1.5 * self.scale)) * self.ss

    @property
    def header(self) -> int:
        return round(2 * 1.35 * self.font_size + 10) * self.ss

    @property
    def footer(self) -> int:
        return round(1.4 * _legend_font_size(self.scale) * self.legend_rows + 8) * self.ss

    @property
    def arena_px(self) -> tuple[int, int]:
        return round(self.arena[0] * self.k), round(self.arena[1] * self.k)

    @property
    def size(self) -> tuple[int, int]:
        w, h = self.arena_px
        return w + 2 * self.margin, self.header + h + 2 * self.margin + self.footer

    @property
    def arena_box(self) -> tuple[int, int, int, int]:
        w, h = self.arena_px
        x0, y0 = self.margin, self.header + self.margin
        return x0, y0, x0 + w, y0 + h

    def px(self, xy: np.ndarray) -> np.ndarray:
        """World (..., 2) -> pixel (..., 2) float (x right, y down)."""
        xy = np.asarray(xy, np.float64)
        x0, y0, _, _ = self.arena_box
        w, h = self.arena
        return np.stack([x0 + (xy[..., 0] + w / 2) * self.k,
                         y0 + (h / 2 - xy[..., 1]) * self.k], -1)


def _layout(level: Any, scale: float, ss: int = 1) -> _Layout:
    try:
        value = float(scale)
    except (TypeError, ValueError):
        value = math.nan
    if not (math.isfinite(value) and value > 0):
        raise ValueError(f"scale must be a positive number of pixels per world unit, got {scale!r}")
    arena = np.asarray(level.physics.arena_size, np.float64)
    return _Layout((float(arena[0]), float(arena[1])), value, ss)


def world_to_pixel(level: EnvParams, xy: Any, *, scale: float = 8.0) -> np.ndarray:
    """Pixel coordinates (x right, y down; float) in a `render_frame` image of world points
    `xy` (..., 2), for a level's arena at the given scale."""
    return _layout(level, scale).px(xy)


@functools.lru_cache(maxsize=64)
def _font(size: int) -> ImageFont.FreeTypeFont | ImageFont.ImageFont:
    try:
        return ImageFont.load_default(size=size)
    except (TypeError, ImportError, OSError, AttributeError):  # old Pillow or no FreeType
        return ImageFont.load_default()


def _centred_text(draw: ImageDraw.ImageDraw, xy: tuple[float, float], text: str, font: Any,
                  fill: RGB, stroke: int = 0, stroke_fill: RGB | None = None) -> None:
    left, top, right, bottom = draw.textbbox((0, 0), text, font=font, stroke_width=stroke)
    x = xy[0] - (left + right) / 2
    y = xy[1] - (top + bottom) / 2
    draw.text((x, y), text, font=font, fill=fill, stroke_width=stroke, stroke_fill=stroke_fill)


# --- input handling ------------------------------------------------------------------------------


def _check_single(config: EnvConfig, level: Any, state: Any) -> None:
    team = np.asarray(level.units.team)
    if team.ndim != 1:
        raise ValueError(f"render needs one level, got a batch (units.team has shape {team.shape})")
    if team.shape[0] != config.num_units or np.shape(level.zones.zone_type) != (config.max_zones,):
        raise ValueError(
            f"the level has {team.shape[0]} unit and {np.shape(level.zones.zone_type)[0]} zone "
            f"slots, the config {config.num_units} and {config.max_zones}")
    if state is not None and np.ndim(state.step) != 0:
        raise ValueError(f"render_frame needs one state, got a batch (step has shape "
                         f"{np.shape(state.step)}); use render_trajectory for a time axis")


@functools.lru_cache(maxsize=16)
def _start_state_fn(config: EnvConfig) -> Any:
    from tabx.env import TabxEnv  # late: keeps `import tabx.render` light
    from tabx.jit_options import simulator_jit

    # Jitted: op-by-op dispatch of the start state's geometry takes seconds, the compile ~1 s.
    return simulator_jit(TabxEnv(config).initial_state)


def _start_state(config: EnvConfig, level: EnvParams) -> EnvState:
    return _start_state_fn(config)(level)


# --- drawing -------------------------------------------------------------------------------------


def _draw(config: EnvConfig, level: Any, state: Any, lay: _Layout, *, show_fov: bool,
          show_hurtbox: bool, title: str | None, info: dict | None) -> Image.Image:
    """One frame from numpy level/state, at the layout's (supersampled) size."""
    u, z = level.units, level.zones
    ss, k = lay.ss, lay.k
    attacking = _info_flags(info, "attacking", np.shape(u.active)[0])
    rows = _legend_rows(_legend_items(show_fov, show_hurtbox and attacking is not None), lay)
    lay = dataclasses.replace(lay, legend_rows=len(rows))
    canvas = Image.new("RGB", lay.size, BACKGROUND)
    draw = ImageDraw.Draw(canvas, "RGBA")  # RGBA inks blend onto the RGB canvas
    ax0, ay0, ax1, ay1 = lay.arena_box
    draw.rectangle((ax0, ay0, ax1, ay1), fill=ARENA_FILL)
    w, h = lay.arena
    for x in np.arange(-(w / 2 // GRID_STEP) * GRID_STEP, w / 2, GRID_STEP):
        px = lay.px(np.array([x, 0.0]))[0]
        draw.line((px, ay0, px, ay1), fill=ARENA_GRID, width=ss)
    for y in np.arange(-(h / 2 // GRID_STEP) * GRID_STEP, h / 2, GRID_STEP):
        py = lay.px(np.array([0.0, y]))[1]
        draw.line((ax0, py, ax1, py), fill=ARENA_GRID, width=ss)

    # Zones, field of view and hurtboxes: translucent, clipped to the arena afterwards.
    for j in range(int(np.shape(z.zone_type)[0])):
        ztype = int(z.zone_type[j])
        if ztype not in ZONE_COLOURS or np.any(np.asarray(z.semi_axes[j]) <= 0):
            continue
        c = lay.px(z.centre[j])
        a = np.asarray(z.semi_axes[j], np.float64) * k
        colour = ZONE_COLOURS[ztype]
        draw.ellipse((c[0] - a[0], c[1] - a[1], c[0] + a[0], c[1] + a[1]),
                     fill=colour + (ZONE_ALPHA,), outline=colour + (230,), width=ss)

    # Units with a non-finite position or heading (never produced by the step) are left out.
    finite = np.isfinite(state.position).all(-1) & np.isfinite(state.heading)
    active = np.asarray(u.active, bool) & finite
    alive = np.asarray(state.alive, bool) & active
    team = np.asarray(u.team)
    centre = lay.px(state.position)
    heading = np.asarray(state.heading, np.float64)
    radius_px = np.asarray(u.radius, np.float64) * k
    if show_fov:
        reach = FOV_LENGTH * k
        for i in np.flatnonzero(alive):
            half = math.degrees(float(u.sight_angle[i])) / 2
            mid = -math.degrees(heading[i])  # Pillow's angles run clockwise in image space
            cx, cy = centre[i]
            colour = TEAM_COLOURS[int(team[i])]
            draw.pieslice((cx - reach, cy - reach, cx + reach, cy + reach), mid - half,
                          mid + half, fill=colour + (FOV_ALPHA,), outline=colour + (80,),
                          width=ss)
    if show_hurtbox and attacking is not None:
        hit = _info_flags(info, "hit", active.shape[0])
        for i in np.flatnonzero(attacking & active):
            corners = _hurtbox_corners(np.asarray(state.position[i], np.float64), heading[i],
                                       float(u.radius[i]), float(u.sight_angle[i]),
                                       float(u.attack_range[i]))
            landed = hit is not None and bool(hit[i])
            draw.polygon([tuple(p) for p in lay.px(corners)],
                         fill=TEAM_COLOURS[int(team[i])] + (HURTBOX_ALPHA[landed],),
                         outline=TEAM_OUTLINES[int(team[i])] + (220,), width=ss)
    width, height = lay.size
    for box in ((0, 0, width, ay0), (0, ay1, width, height), (0, ay0, ax0, ay1),
                (ax1, ay0, width, ay1)):
        draw.rectangle(box, fill=BACKGROUND)

    # Units: the dead first (underneath), then the living.
    order = [i for i in np.flatnonzero(active) if not alive[i]]
    order += [i for i in np.flatnonzero(alive)]
    for i in order:
        cx, cy = centre[i]
        r = radius_px[i]
        living = bool(alive[i])
        fill = TEAM_COLOURS[int(team[i])] if living else DEAD_COLOUR
        outline = TEAM_OUTLINES[int(team[i])] if living else DEAD_OUTLINE
        line_w = max(ss, round(0.12 * k))
        draw.ellipse((cx - r, cy - r, cx + r, cy + r), fill=fill, outline=outline, width=line_w)
        dx, dy = math.cos(heading[i]), -math.sin(heading[i])
        tip = r + max(0.6 * k, 3 * ss)
        draw.line((cx + 0.6 * r * dx, cy + 0.6 * r * dy, cx + tip * dx, cy + tip * dy),
                  fill=outline, width=max(ss, round(0.22 * k)))
        if r >= 5 * ss:
            unit_type = int(u.unit_type[i])
            char = C.UNIT_SPECS[unit_type].char if 0 <= unit_type < C.NUM_UNIT_TYPES else "?"
            size = int(np.clip(1.35 * r, 6 * ss, 30 * ss))
            _centred_text(draw, (cx, cy), char, _font(size),
                          fill=(255, 255, 255) if living else (225, 225, 225),
                          stroke=max(1, ss // 2), stroke_fill=outline)
    for i in np.flatnonzero(alive):
        _bars(draw, centre[i], radius_px[i], lay,
              float(state.health[i]) / max(float(u.max_health[i]), 1e-6),
              float(state.cooldown[i]) / max(float(u.cooldown[i]), 1e-6))
    draw.rectangle((ax0, ay0, ax1, ay1), outline=ARENA_EDGE, width=2 * ss)

    _header(draw, config, level, state, lay, title)
    _legend(draw, lay, rows)
    return canvas


def _info_flags(info: dict | None, key: str, n: int) -> np.ndarray | None:
    if info is None or key not in info:
        return None
    flags = np.asarray(info[key]).astype(bool)
    if flags.shape != (n,):
        raise ValueError(f"info[{key!r}] must have shape ({n},) for one step, got {flags.shape}")
    return flags


def _hurtbox_corners(position: np.ndarray, heading: float, radius: float, sight_angle: float,
                     attack_range: float) -> np.ndarray:
    """World corners of a unit's hurtbox (tabx.geometry.hurtbox_overlap): in the unit's frame,
    x in [r cos(s/2), r cos(s/2) + range] and |y| <= r sin(s/2)."""
    x0 = radius * math.cos(sight_angle / 2)
    x1 = x0 + attack_range
    hw = radius * math.sin(sight_angle / 2)
    local = np.array([[x0, -hw], [x1, -hw], [x1, hw], [x0, hw]])
    c, s = math.cos(heading), math.sin(heading)
    rot = np.array([[c, -s], [s, c]])
    return position + local @ rot.T


def _bars(draw: ImageDraw.ImageDraw, centre: np.ndarray, r: float, lay: _Layout,
          health: float, cooldown: float) -> None:
    """Health bar and cooldown bar above a unit."""
    ss = lay.ss
    width = max(2 * r, 1.8 * lay.k, 14 * ss)
    height, gap = max(3, round(0.3 * lay.scale)) * ss, ss
    x0 = centre[0] - width / 2
    bottom = centre[1] - r - 2 * ss
    rows = ((HEALTH_COLOUR, health), (COOLDOWN_COLOUR, cooldown))
    top = bottom - 2 * height - gap
    for n, (colour, value) in enumerate(rows):
        y0 = top + n * (height + gap)
        draw.rectangle((x0, y0, x0 + width, y0 + height), fill=BAR_BACKGROUND)
        value = float(np.clip(value, 0.0, 1.0))
        if value > 0:
            draw.rectangle((x0, y0, x0 + width * value, y0 + height), fill=colour)


def _header(draw: ImageDraw.ImageDraw, config: EnvConfig, level: Any, state: Any,
            lay: _Layout, title: str | None) -> None:
    u = level.units
    font = _font(lay.font_size * lay.ss)
    x = float(lay.margin)
    line = 1.35 * lay.font_size * lay.ss
    y = 5.0 * lay.ss
    step = int(state.step)
    parts = [(title, TEXT)] if title else []
    parts.append((f"step {step} / {config.max_steps}", TEXT_DIM if title else TEXT))
    if bool(state.done):
        won = np.asarray(state.won, bool)
        outcome = ("allies won" if won[C.ALLY] else "enemies won" if won[C.ENEMY]
                   else "ended")
        colour = (TEAM_COLOURS[C.ALLY] if won[C.ALLY] else TEAM_COLOURS[C.ENEMY] if won[C.ENEMY]
                  else TEXT)
        parts.append((f"done: {outcome}", colour))
    _text_row(draw, x, y, parts, font)
    active = np.asarray(u.active, bool)
    alive = np.asarray(state.alive, bool) & active
    team = np.asarray(u.team)
    hp = np.asarray(state.hp_ratio, np.float64)
    row = []
    for t, name in ((C.ALLY, "allies"), (C.ENEMY, "enemies")):
        member = active & (team == t)
        row.append((f"{name} {int((alive & member).sum())}/{int(member.sum())} alive, "
                    f"hp {hp[t]:.2f}", TEAM_COLOURS[t]))
    _text_row(draw, x, y + line, row, font)


def _text_row(draw: ImageDraw.ImageDraw, x: float, y: float, parts: Sequence[tuple[str, RGB]],
              font: Any, sep: str = "   |   ") -> float:
    for n, (text, colour) in enumerate(parts):
        if n:
            draw.text((x, y), sep, font=font, fill=TEXT_DIM)
            x += draw.textlength(sep, font=font)
        draw.text((x, y), text, font=font, fill=colour)
        x += draw.textlength(text, font=font)
    return x


def _legend_items(show_fov: bool, hurtbox: bool) -> list[tuple[str, RGB, RGB, str]]:
    """(swatch shape, fill, outline, label) of the legend below the arena."""
    items = [("dot", TEAM_COLOURS[C.ALLY], TEAM_OUTLINES[C.ALLY], "ally"),
             ("dot", TEAM_COLOURS[C.ENEMY], TEAM_OUTLINES[C.ENEMY], "enemy"),
             ("dot", DEAD_COLOUR, DEAD_OUTLINE, "dead")]
    for ztype, colour in ZONE_COLOURS.items():
        tint = tuple(round(c * ZONE_ALPHA / 255 + a * (1 - ZONE_ALPHA / 255))
                     for c, a in zip(colour, ARENA_FILL, strict=True))
        items.append(("zone", tint, colour, C.ZONE_NAMES[ztype]))
    items.append(("bar", HEALTH_COLOUR, HEALTH_COLOUR, "health"))
    items.append(("bar", COOLDOWN_COLOUR, COOLDOWN_COLOUR, "cooldown (full = ready)"))
    if show_fov:
        items.append(("fan", (200, 200, 215), TEXT_DIM, "field of view"))
    if hurtbox:
        items.append(("box", (205, 190, 190), TEXT_DIM, "attack"))
    return items


def _legend_font_size(scale: float) -> int:
    return max(11, _Layout((1.0, 1.0), scale).font_size - 1)


def _legend_rows(items: list[tuple[str, RGB, RGB, str]], lay: _Layout
                 ) -> list[list[tuple[tuple[str, RGB, RGB, str], float]]]:
    """Items with their widths (canvas pixels), wrapped into rows that fit the frame width."""
    size = _legend_font_size(lay.scale) * lay.ss
    font = _font(size)
    limit = lay.size[0] - 2 * lay.margin
    rows: list[list] = [[]]
    used = 0.0
    for item in items:
        swatch = (0.9 if item[0] == "dot" else 1.45) * size
        width = swatch + 0.35 * size + font.getlength(item[3]) + 1.2 * size
        if rows[-1] and used + width - 1.2 * size > limit:
            rows.append([])
            used = 0.0
        rows[-1].append((item, width))
        used += width
    return rows


def _legend(draw: ImageDraw.ImageDraw, lay: _Layout, rows: list) -> None:
    ss = lay.ss
    size = _legend_font_size(lay.scale) * ss
    font = _font(size)
    _, _, _, ay1 = lay.arena_box
    sw = 0.9 * size  # swatch height
    for n, row in enumerate(rows):
        y = ay1 + lay.margin / 2 + 2 * ss + n * 1.4 * size
        cy = y + size * 0.55
        x = float(lay.margin)
        for (shape, fill, outline, text), width in row:
            if shape == "dot":
                draw.ellipse((x, cy - sw / 2, x + sw, cy + sw / 2), fill=fill, outline=outline,
                             width=ss)
                sx = sw
            elif shape == "zone":
                sx = 1.45 * size
                draw.ellipse((x, cy - sw / 2.6, x + sx, cy + sw / 2.6), fill=fill,
                             outline=outline, width=ss)
            elif shape == "bar":
                sx = 1.45 * size
                draw.rectangle((x, cy - 1.5 * ss, x + sx, cy + 1.5 * ss), fill=fill)
            elif shape == "fan":
                sx = 1.45 * size
                draw.pieslice((x - sx, cy - sx, x + sx, cy + sx), -22, 22, fill=fill,
                              outline=outline, width=ss)
            else:
                sx = 1.45 * size
                draw.rectangle((x, cy - sw / 3, x + sx, cy + sw / 3), fill=fill, outline=outline,
                               width=ss)
            draw.text((x + sx + 0.35 * size, y), text, font=font, fill=TEXT)
            x += width


def _finish(canvas: Image.Image, lay: _Layout) -> Image.Image:
    return canvas.reduce(lay.ss) if lay.ss > 1 else canvas


# --- public API ----------------------------------------------------------------------------------


def render_frame(config: EnvConfig, level: EnvParams, state: EnvState | None = None, *,
                 scale: float = 8.0, show_fov: bool = False, show_hurtbox: bool = True,
                 title: str | None = None, info: dict | None = None) -> Image.Image:
    """One frame: `level` in `state` (None: the level's start state) as an RGB image of about
    arena * scale pixels plus margins, header and legend.

    `info` is one step's info dict from `TabxEnv.step`; with `show_hurtbox`, the hurtboxes of
    the units in `info["attacking"]` are drawn (stronger where `info["hit"]`).
    """
    _check_single(config, level, state)
    lay = _layout(level, scale, _SUPERSAMPLE)
    if state is None:
        state = _start_state(config, level)
    level, state = jax.device_get((level, state))
    info = None if info is None else {key: np.asarray(v) for key, v in info.items()}
    canvas = _draw(config, level, state, lay, show_fov=show_fov, show_hurtbox=show_hurtbox,
                   title=title, info=info)
    return _finish(canvas, lay)


def render_level(config: EnvConfig, level: EnvParams, **kw: Any) -> Image.Image:
    """The level's start state (`render_frame` with state None; same keyword options)."""
    return render_frame(config, level, None, **kw)


def render_trajectory(config: EnvConfig, level: EnvParams, states: EnvState,
                      infos: dict | None = None, **kw: Any) -> list[Image.Image]:
    """One frame per time step of `states` (an EnvState with a leading time axis T, e.g. the
    stacked states of a `lax.scan`), stopping after the first frame whose state is done.
    `infos`: the matching info dicts, stacked the same way (T, ...), or None. Keyword options
    as `render_frame`."""
    steps = np.asarray(jax.device_get(states.step))
    if steps.ndim != 1:
        raise ValueError(f"render_trajectory needs states with one leading time axis; step has "
                         f"shape {steps.shape}")
    _check_single(config, level, None)
    level, states = jax.device_get((level, states))
    infos = None if infos is None else {key: np.asarray(v) for key, v in infos.items()}
    for key, value in (infos or {}).items():
        if value.shape[:1] != steps.shape:
            raise ValueError(f"infos[{key!r}] has {value.shape[:1]} time steps, states "
                             f"{steps.shape}")
    frames = []
    for t in range(steps.shape[0]):
        state = jax.tree.map(lambda x, t=t: x[t], states)
        info = None if infos is None else {key: v[t] for key, v in infos.items()}
        frames.append(render_frame(config, level, state, info=info, **kw))
        if bool(state.done):
            break
    return frames


def save_png(image: Image.Image, path: str | os.PathLike) -> Path:
    """Write `image` as a PNG file, atomically."""
    out = io.BytesIO()
    image.save(out, format="PNG", optimize=True)
    return atomic_write_bytes(path, out.getvalue())


def save_gif(frames: Sequence[Image.Image], path: str | os.PathLike, fps: float = 10.0) -> Path:
    """Write `frames` as an animated GIF that loops forever, atomically. GIF timing has a
    resolution of 10 ms, so fps above 50 play at most at 50."""
    if not frames:
        raise ValueError("save_gif needs at least one frame")
    if not (math.isfinite(fps) and fps > 0):
        raise ValueError(f"fps must be positive, got {fps!r}")
    duration = max(20, round(1000 / fps / 10) * 10)
    rgb = [f.convert("RGB") for f in frames]
    # One palette for the whole animation, from the first, a middle and the last frame: much
    # faster than a palette per frame, and colours do not flicker between frames.
    sample = [rgb[i] for i in sorted({0, len(rgb) // 2, len(rgb) - 1})]
    montage = Image.new("RGB", (max(f.width for f in sample), sum(f.height for f in sample)))
    y = 0
    for f in sample:
        montage.paste(f, (0, y))
        y += f.height
    palette = montage.quantize(256, method=Image.Quantize.MEDIANCUT, dither=Image.Dither.NONE)
    first, *rest = [f.quantize(palette=palette, dither=Image.Dither.NONE) for f in rgb]
    out = io.BytesIO()
    first.save(out, format="GIF", save_all=True, append_images=rest, duration=duration, loop=0)
    return atomic_write_bytes(path, out.getvalue())


def check_png_path(path: str | os.PathLike) -> Path:
    """An output path for a PNG that can be written: ends in .png, is not a folder, and its
    folder exists. Raises ValueError with a message naming the problem."""
    path = Path(path)
    if path.suffix.lower() != ".png":
        raise ValueError(f"{path}: the output must be a .png file")
    if path.is_dir():
        raise ValueError(f"{path} is a folder; give a file name ending in .png")
    if not path.parent.is_dir():
        raise ValueError(f"{path}: the folder {path.parent} does not exist")
    return path


MAX_SCALE = 40.0  # pixels per world unit: about 5000 x 3600 pixels for the default arena


def check_render_options(out: str, scale: float) -> None:
    """UserError unless `out` is a writable .png path and `scale` is sensible: the `--out` and
    `--scale` of the commands that draw a level (`tabx scenarios render`, `tabx buffer render`,
    `tabx levels sample`)."""
    if not (0 < scale <= MAX_SCALE):  # also rejects nan
        raise UserError(f"--scale must be in (0, {MAX_SCALE:g}] pixels per world unit, "
                        f"got {scale:g}")
    try:
        check_png_path(out)
    except ValueError as err:
        raise UserError(f"--out {err}") from None

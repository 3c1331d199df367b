"""`tabx scenarios list|show|validate|render`: browse the bundled and user scenarios, check a
file, draw a scenario's start as a PNG."""

from __future__ import annotations

import argparse
import math

from tabx.errors import UserError
from tabx.render import check_render_options, render_level, save_png
from tabx.scenarios import (
    CATEGORIES,
    Scenario,
    ScenarioError,
    config_for,
    list_scenarios,
    load_file,
    load_named,
)
from tabx.scenarios.summary import composition, summary, zone_summary


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    """Add `tabx scenarios` and its actions."""
    parser = subparsers.add_parser("scenarios", help="list, show and validate scenarios",
                                   description=__doc__)
    sub = parser.add_subparsers(dest="scenarios_command", metavar="ACTION")
    sub.required = True
    p = sub.add_parser("list", help="bundled and user scenarios as a table")
    p.add_argument("--category", choices=CATEGORIES, help="only this category")
    p.set_defaults(func=cmd_list)
    p = sub.add_parser("show", help="units with stats and zones of one scenario")
    p.add_argument("name", help="a name (crossfire, 2F1M2Avs2S1K_2L2B2S) or a JSON file path")
    p.set_defaults(func=cmd_show)
    p = sub.add_parser("validate", help="check a scenario file (ours or the reference format)")
    p.add_argument("file")
    p.set_defaults(func=cmd_validate)
    p = sub.add_parser("render", help="draw a scenario's start state as a PNG image")
    p.add_argument("name", help="a name (crossfire, 2F1M2Avs2S1K_2L2B2S) or a JSON file path")
    p.add_argument("--out", required=True, help="output PNG path (its folder must exist)")
    p.add_argument("--fov", action="store_true", help="draw each unit's field of view")
    p.add_argument("--scale", type=float, default=8.0,
                   help="pixels per world unit (default 8: about 1000 x 720 pixels)")
    p.set_defaults(func=cmd_render)


def _user_error(err: ScenarioError) -> Exception:
    return UserError(str(err))


def cmd_list(args: argparse.Namespace) -> int:
    try:
        names = list_scenarios(args.category)
    except ScenarioError as err:
        raise _user_error(err) from None
    loaded: list[tuple[str, Scenario | None]] = []
    for name in names:
        try:
            loaded.append((name, load_named(name)))
        except ScenarioError:
            loaded.append((name, None))
    order = {c: i for i, c in enumerate(CATEGORIES)}
    loaded.sort(key=lambda item: (order.get(item[1].category, 9) if item[1] else 9, item[0]))
    rows = [("NAME", "CATEGORY", "SPLIT", "ALLIES v ENEMIES", "ZONES")]
    for name, s in loaded:
        if s is None:
            rows.append((name, "?", "", "INVALID (run tabx scenarios validate FILE)", ""))
            continue
        units = (f"{len(s.allies)} v {len(s.enemies)}  {composition(s.allies)} vs "
                 f"{composition(s.enemies)}") if s.units else "-"
        rows.append((name, s.category, s.split or "", units, zone_summary(s)))
    widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
    for r in rows:
        print("  ".join(c.ljust(w) for c, w in zip(r, widths, strict=True)).rstrip())
    print(f"{len(names)} scenarios; compose units and zones as UNITS_ZONES, "
          "e.g. 2F1M2Avs2S1K_2L2B2S")
    return 0


def cmd_show(args: argparse.Namespace) -> int:
    try:
        s = load_named(args.name)
    except ScenarioError as err:
        raise _user_error(err) from None
    print(summary(s))
    if s.description:
        print(f"  {s.description}")
    if s.physics is not None:
        print(f"physics: {s.physics}")
    if s.heuristic is not None:
        print(f"heuristic: {s.heuristic}")
    if s.units:
        print("units (* = differs from the unit type's default):")
        head = ("#", "team", "unit", "x", "y", "head°", "health", "max_hp", "damage", "range",
                "cooldown", "speed", "radius", "mass", "sight°", "heals")
        rows = [head]
        for i, u in enumerate(s.units):
            st = u.stats()

            def cell(key: str, value: str, unit=u) -> str:
                return value + ("*" if key in unit.overrides else "")

            rows.append((
                str(i), u.team, u.unit, f"{u.position[0]:.2f}", f"{u.position[1]:.2f}",
                f"{math.degrees(u.heading) + 0.0:.0f}",
                cell("health", f"{st['health']:g}"), cell("max_health", f"{st['max_health']:g}"),
                cell("damage", f"{st['damage']:g}"),
                cell("attack_range", f"{st['attack_range']:g}"),
                cell("cooldown", f"{st['cooldown']:g}"), cell("speed", f"{st['speed']:g}"),
                cell("radius", f"{st['radius']:g}"), cell("mass", f"{st['mass']:g}"),
                cell("sight_angle", f"{math.degrees(st['sight_angle']):.0f}"),
                cell("heals", "yes" if st["heals"] else "no")))
        widths = [max(len(r[i]) for r in rows) for i in range(len(head))]
        for r in rows:
            print("  " + "  ".join(c.rjust(w) for c, w in zip(r, widths, strict=True)))
    else:
        print("units: none (a zone-only scenario; compose it as UNITS_" + s.name + ")")
    if s.zones:
        print("zones:")
        for j, z in enumerate(s.zones):
            print(f"  {j}  {z.type:<5}  centre ({z.centre[0]:g}, {z.centre[1]:g})  "
                  f"semi-axes ({z.semi_axes[0]:g}, {z.semi_axes[1]:g})  effect {z.effect:g}")
    else:
        print("zones: none")
    return 0


def cmd_validate(args: argparse.Namespace) -> int:
    try:
        s = load_file(args.file)
    except ScenarioError as err:
        raise _user_error(err) from None
    note = "" if s.units else " (zone-only: compose it with a unit scenario to play)"
    print(f"OK: {summary(s)}{note}")
    return 0


def cmd_render(args: argparse.Namespace) -> int:
    """Draw a scenario's start state as a PNG."""
    check_render_options(args.out, args.scale)
    try:
        s = load_named(args.name)
        config = config_for([s])
        level = s.to_level(config)
    except ScenarioError as err:
        raise _user_error(err) from None
    image = render_level(config, level, scale=args.scale, show_fov=args.fov,
                         title=s.name)
    save_png(image, args.out)
    print(f"wrote {args.out} ({image.width} x {image.height}): {summary(s)}")
    return 0


__all__ = ["add_parser", "cmd_list", "cmd_render", "cmd_show", "cmd_validate"]

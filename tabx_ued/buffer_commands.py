"""`tabx buffer ...`: inspect level-buffer files from the command line.

    tabx buffer inspect FILE            size, score / staleness quantiles, sources, lineage, ...
    tabx buffer top FILE -k 10          the best-scoring levels
    tabx buffer show FILE ID            one level's slot data and fields, as JSON by key path
    tabx buffer export FILE ID --out level.json
    tabx buffer hist FILE FIELD [--bins 20] [--png out.png]
    tabx buffer diff FILE ID1 ID2       the level fields that differ
    tabx buffer render FILE --id ID --out level.png   a TABX level's start state as a PNG

Files are read without a template, so any buffer file can be inspected. Registered by
`tabx_ued.commands` through `add_parser(subparsers)`.
"""

from __future__ import annotations

import argparse
import io
import json
import math
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np

from level_buffer.buffer import LevelBuffer
from level_buffer.config import Source
from level_buffer.fileformat import FORMAT_VERSION, BufferFileError
from level_buffer.prioritization import PRIORITIZATIONS
from level_buffer.tree import named_leaves
from tabx.errors import UserError

QUANTILES = (("min", 0.0), ("p10", 0.1), ("p25", 0.25), ("median", 0.5), ("p75", 0.75),
             ("p90", 0.9), ("max", 1.0))



def _load(path: str) -> LevelBuffer:
    try:
        return LevelBuffer.load(path)
    except BufferFileError as err:
        raise UserError(str(err)) from err


def _check_id(buf: LevelBuffer, level_id: int, path: str) -> None:
    if level_id not in buf:
        ids = buf.ids
        have = f"{buf.size} levels, ids {ids.min()}..{ids.max()}" if buf.size else "it is empty"
        raise UserError(f"{path}: no level with id {level_id} ({have})")


def _jsonable(x: Any) -> Any:
    """Lists and scalars for JSON; non-finite floats as strings ("inf", "-inf", "nan")."""
    if isinstance(x, np.ndarray):
        return _jsonable(x.tolist())
    if isinstance(x, np.generic):
        return _jsonable(x.item())
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, dict):
        return {k: _jsonable(v) for k, v in x.items()}
    if isinstance(x, float) and not math.isfinite(x):
        return str(x)
    return x


def _leaf_json(arr: np.ndarray) -> Any:
    """A leaf as JSON data; float32 values by their shortest float32 repr (1.1, not
    1.100000023841858), which reads back to the identical float32."""
    if arr.dtype.kind == "f" and arr.dtype.itemsize < 8:
        flat = [float(str(v)) for v in arr.ravel()]  # str(np.float32) is the shortest repr
        return _jsonable(np.array(flat, np.float64).reshape(arr.shape))
    return _jsonable(arr)


def _num(v: float) -> str:
    return f"{v:>10.4g}"


def _quantile_row(name: str, values: np.ndarray) -> str:
    finite = values[np.isfinite(values)]
    if finite.size == 0:
        cells = ["-".rjust(10)] * (len(QUANTILES) + 1)
    else:
        cells = [_num(float(np.quantile(finite, q))) for _, q in QUANTILES]
        cells.append(_num(float(finite.mean())))
    note = f"  ({values.size - finite.size} non-finite)" if finite.size < values.size else ""
    return f"{name:<12}" + "".join(cells) + note


def dumps_level(data: dict[str, Any]) -> str:
    """JSON of `level_json` output with one line per level field (valid JSON, easy to read)."""
    level = data["level"]
    head = {k: v for k, v in data.items() if k != "level"}
    lines = ["{"] + [f"  {json.dumps(k)}: {json.dumps(v)}," for k, v in head.items()]
    lines.append('  "level": {')
    items = [f"    {json.dumps(k)}: {json.dumps(v)}" for k, v in level.items()]
    lines.append(",\n".join(items))
    lines += ["  }", "}"]
    return "\n".join(lines) + "\n"


def level_json(buf: LevelBuffer, level_id: int) -> dict[str, Any]:
    """One level as JSON-ready data: its slot record and its leaves keyed by key path."""
    level = buf.get_level(level_id)
    return {"id": int(level_id), "record": _jsonable(buf.record(level_id)),
            "level": {k: _leaf_json(np.asarray(v)) for k, v in level.items()}}


# --- sub-commands ----------------------------------------------------------------------------


def cmd_inspect(args: argparse.Namespace) -> int:
    buf = _load(args.file)
    print(summary(buf, args.file, Path(args.file).stat().st_size))
    return 0


def summary(buf: LevelBuffer, name: str, size_bytes: int) -> str:
    """What `tabx buffer inspect` prints of a buffer (`name`: where it came from)."""
    cfg = buf.config
    prio = PRIORITIZATIONS[cfg.prioritization].describe(cfg)
    dup = ("off" if not cfg.duplicate_check else
           f"near (atol {cfg.near_duplicate_atol:g})" if cfg.near_duplicates else "exact")
    lines = [
        f"{name}: {buf.size} / {buf.capacity} levels ({100 * buf.size / buf.capacity:.1f}% "
        f"full), format {FORMAT_VERSION}, {size_bytes / 2**20:.2f} MiB",
        f"clock {buf.clock}, next id {buf.next_id}, {len(buf.spec.paths)} level fields",
        f"config: {prio}, staleness coeff {cfg.staleness_coeff:g}, replay prob "
        f"{cfg.replay_prob:g}, minimum fill {cfg.minimum_fill_ratio:g}, duplicate check {dup}",
        "counters: " + ", ".join(f"{k.replace('_', ' ')} {v}" for k, v in buf.stats.items()),
    ]
    if buf.size == 0:
        return "\n".join(lines + ["(empty buffer)"])
    lines.append("")
    lines.append(" " * 12 + "".join(name.rjust(10) for name, _ in QUANTILES) + "mean".rjust(10))
    for name, values in (("score", buf.column("score")),
                         ("staleness", buf.staleness().astype(float)),
                         ("max return", buf.column("max_return")),
                         ("replays", buf.column("replay_count").astype(float)),
                         ("weight", buf.weights() * buf.size)):
        lines.append(_quantile_row(name, values))
    lines.append("(weight is relative to uniform: 1 = an average level)")
    lines.append("")
    sources = Counter(buf.column("source").tolist())
    lines.append("sources: " + ", ".join(
        f"{Source(s).name.lower()} {c} ({100 * c / buf.size:.1f}%)"
        for s, c in sorted(sources.items())))
    depths = Counter(buf.column("depth").tolist())
    shown = sorted(depths.items())
    text = ", ".join(f"{d}: {c}" for d, c in shown[:8])
    if len(shown) > 8:
        text += f", deeper: {sum(c for _, c in shown[8:])} (max {shown[-1][0]})"
    lines.append(f"lineage depth: {text}")
    parents = buf.column("parent_id")
    has_parent = parents >= 0
    lines.append(f"parents: {int(has_parent.sum())} levels have one, "
                 f"{int(np.isin(parents[has_parent], buf.ids).sum())} of those parents are "
                 "still in the buffer")
    versions = buf.column("policy_version")
    known = versions[versions >= 0]
    if known.size:
        common = Counter(known.tolist()).most_common(3)
        lines.append(f"policy versions: {np.unique(known).size} distinct, {known.min()}.."
                     f"{known.max()}; most levels: "
                     + ", ".join(f"v{v} ({c})" for v, c in common)
                     + (f"; {versions.size - known.size} unknown" if known.size < versions.size
                        else "")
                     + " (the policy's gradient updates when it scored the level, not the "
                       "run's update count: steps that only score new levels add none)")
    else:
        lines.append("policy versions: none recorded")
    return "\n".join(lines)


def cmd_top(args: argparse.Namespace) -> int:
    buf = _load(args.file)
    if args.k < 1:
        raise UserError(f"-k must be >= 1, got {args.k}")
    header = (f"{'rank':>4} {'id':>8} {'score':>10} {'stale':>7} {'max ret':>10} "
              f"{'replays':>7} {'source':>8} {'parent':>8} {'depth':>5} {'policy':>6}")
    print(header)
    for rank, level_id in enumerate(buf.top(args.k).tolist(), 1):
        r = buf.record(level_id)
        print(f"{rank:>4} {level_id:>8} {r['score']:>10.4g} {r['staleness']:>7} "
              f"{r['max_return']:>10.4g} {r['replay_count']:>7} {r['source']:>8} "
              f"{r['parent_id']:>8} {r['depth']:>5} {r['policy_version']:>6}")
    return 0


def as_env_params(leaves: dict[str, Any]) -> Any | None:
    """The level as `tabx.params.EnvParams` if its key paths are exactly EnvParams', else None
    (the buffer is generic: other level pytrees are shown as their leaves)."""
    import jax

    from tabx.params import EnvConfig, make_level

    template = make_level(EnvConfig(max_allies=1, max_enemies=1, max_zones=1), [], [])
    names = list(named_leaves(template))
    if set(names) != set(leaves):
        return None
    treedef = jax.tree_util.tree_structure(template)
    return jax.tree_util.tree_unflatten(treedef, [np.asarray(leaves[n]) for n in names])


def scenario_text(buf: LevelBuffer, level_id: int) -> str | None:
    """The level as scenario JSON (the format `tabx rollout` and the editor open), or None when
    the level is not a TABX level."""
    from tabx.scenarios import dumps_scenario, level_to_scenario

    params = as_env_params(buf.get_level(level_id))
    if params is None:
        return None
    scenario = level_to_scenario(params, name=f"buffer_level_{level_id}",
                                 description=f"level {level_id} exported from a level buffer")
    return dumps_scenario(scenario)


def cmd_show(args: argparse.Namespace) -> int:
    buf = _load(args.file)
    _check_id(buf, args.id, args.file)
    text = None if args.leaves else scenario_text(buf, args.id)
    print(text if text is not None else dumps_level(level_json(buf, args.id)), end="")
    return 0


def cmd_export(args: argparse.Namespace) -> int:
    from tabx.files import atomic_write_text

    buf = _load(args.file)
    _check_id(buf, args.id, args.file)
    text = None if args.leaves else scenario_text(buf, args.id)
    kind = "scenario" if text is not None else "level leaves"
    atomic_write_text(args.out, text if text is not None else dumps_level(level_json(buf, args.id)))
    print(f"wrote level {args.id} ({kind}) to {args.out}")
    return 0


def cmd_render(args: argparse.Namespace) -> int:
    from tabx.params import level_config
    from tabx.render import check_render_options, render_level, save_png

    check_render_options(args.out, args.scale)
    buf = _load(args.file)
    _check_id(buf, args.id, args.file)
    params = as_env_params(buf.get_level(args.id))
    if params is None:
        raise UserError(f"{args.file}: level {args.id} is not a TABX level (its fields are not "
                          "tabx.params.EnvParams'); render draws buffers of TABX levels only")
    record = buf.record(args.id)
    title = f"buffer level {args.id} (score {record['score']:.4g}, {record['source']})"
    image = render_level(level_config(params), params, scale=args.scale, show_fov=args.fov,
                         title=title)
    save_png(image, args.out)
    print(f"wrote level {args.id} to {args.out} ({image.width} x {image.height})")
    return 0


def _histogram_counts(values: np.ndarray, bins: int) -> list[tuple[str, int]]:
    distinct = np.unique(values)
    if distinct.size <= bins and np.all(distinct == np.round(distinct)):
        # Integer-valued fields (types, flags): one row per value reads better than ranges.
        return [(f"{v:g}", int((values == v).sum())) for v in distinct]
    counts, edges = np.histogram(values, bins=bins)
    return [(f"[{lo:.4g}, {hi:.4g}{']' if i == bins - 1 else ')'}", int(c))
            for i, (c, lo, hi) in enumerate(zip(counts, edges[:-1], edges[1:], strict=True))]


def cmd_hist(args: argparse.Namespace) -> int:
    buf = _load(args.file)
    if args.field not in buf.spec.paths:
        raise UserError(f"{args.file}: no level field {args.field!r}; fields: "
                          f"{', '.join(buf.spec.paths)}")
    if args.bins < 1:
        raise UserError(f"--bins must be >= 1, got {args.bins}")
    values = buf.leaf(args.field).astype(np.float64).ravel()
    finite = values[np.isfinite(values)]
    shape = buf.spec.shapes[buf.spec.paths.index(args.field)]
    print(f"{args.field}: {finite.size} values from {buf.size} levels (shape {shape} each)"
          + (f", {values.size - finite.size} non-finite left out" if finite.size < values.size
             else ""))
    if finite.size == 0:
        return 0
    print(f"min {finite.min():.4g}  mean {finite.mean():.4g}  max {finite.max():.4g}")
    rows = _histogram_counts(finite, args.bins)
    width = max(len(label) for label, _ in rows)
    top = max(c for _, c in rows) or 1
    for label, count in rows:
        print(f"{label:>{width}} {count:>8} {'#' * round(args.width * count / top)}")
    if args.png:
        _write_png(args.png, finite, args.field, args.bins)
        print(f"wrote {args.png}")
    return 0


def _write_png(path: str, values: np.ndarray, field: str, bins: int) -> None:
    try:
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure
    except ImportError as err:
        raise UserError("--png needs matplotlib, which is not installed "
                          "(pip install matplotlib)") from err
    from tabx.files import atomic_write_bytes

    fig = Figure(figsize=(6, 4))  # no pyplot: no global backend or figure state is touched
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    ax.hist(values, bins=bins)
    ax.set_xlabel(field)
    ax.set_ylabel("count")
    out = io.BytesIO()
    fig.savefig(out, format="png", dpi=100)
    atomic_write_bytes(path, out.getvalue())


def cmd_diff(args: argparse.Namespace) -> int:
    buf = _load(args.file)
    for level_id in (args.id1, args.id2):
        _check_id(buf, level_id, args.file)
    a, b = buf.get_level(args.id1), buf.get_level(args.id2)
    ra, rb = buf.record(args.id1), buf.record(args.id2)
    print(f"level {args.id1} (score {ra['score']:.4g}, {ra['source']}) vs level {args.id2} "
          f"(score {rb['score']:.4g}, {rb['source']})")
    differing = 0
    for path in buf.spec.paths:
        x, y = np.asarray(a[path]), np.asarray(b[path])
        neq = np.abs(x.astype(np.float64) - y.astype(np.float64)) > args.atol
        neq |= np.isnan(x.astype(np.float64)) != np.isnan(y.astype(np.float64))
        if not neq.any():
            continue
        differing += 1
        if x.ndim == 0:
            print(f"  {path}: {x.item()} -> {y.item()}")
            continue
        where = np.argwhere(neq)
        items = ", ".join(f"[{','.join(map(str, idx))}] {x[tuple(idx)].item()} -> "
                          f"{y[tuple(idx)].item()}" for idx in where[:args.max_items])
        more = f", ... ({len(where) - args.max_items} more)" if len(where) > args.max_items \
            else ""
        print(f"  {path} ({len(where)} of {x.size} differ): {items}{more}")
    if not differing:
        print("  the levels are identical" + (f" within {args.atol:g}" if args.atol else ""))
    else:
        print(f"{differing} of {len(buf.spec.paths)} fields differ")
    return 0


def add_parser(subparsers: Any) -> None:
    """Register `tabx buffer` and its actions on the `tabx` sub-command parser."""
    parser = subparsers.add_parser(
        "buffer", help="inspect level-buffer files",
        description="Inspect PLR level-buffer files (any level structure, no template needed).")
    sub = parser.add_subparsers(dest="buffer_command", metavar="ACTION")
    sub.required = True

    p = sub.add_parser("inspect", help="summary: size, score and staleness quantiles, sources, "
                       "lineage, policy versions")
    p.add_argument("file")
    p.set_defaults(func=cmd_inspect)

    p = sub.add_parser("top", help="the best-scoring levels")
    p.add_argument("file")
    p.add_argument("-k", type=int, default=10, help="how many (default 10)")
    p.set_defaults(func=cmd_top)

    leaves_help = "print the raw fields by key path instead of scenario JSON"
    p = sub.add_parser("show", help="one level as scenario JSON (TABX levels) or its fields")
    p.add_argument("file")
    p.add_argument("id", type=int, help="the level id")
    p.add_argument("--leaves", action="store_true", help=leaves_help)
    p.set_defaults(func=cmd_show)

    p = sub.add_parser("export", help="write one level as a scenario file (tabx rollout FILE)")
    p.add_argument("file")
    p.add_argument("id", type=int, help="the level id")
    p.add_argument("--out", required=True, help="output JSON path")
    p.add_argument("--leaves", action="store_true", help=leaves_help)
    p.set_defaults(func=cmd_export)

    p = sub.add_parser("hist", help="text histogram of a level field over the buffer")
    p.add_argument("file")
    p.add_argument("field", help="key path of a level field, e.g. units.health")
    p.add_argument("--bins", type=int, default=20)
    p.add_argument("--width", type=int, default=50, help="longest bar, in characters")
    p.add_argument("--png", help="also save a PNG plot here (needs matplotlib)")
    p.set_defaults(func=cmd_hist)

    p = sub.add_parser("render", help="draw a TABX level's start state as a PNG image")
    p.add_argument("file")
    p.add_argument("--id", type=int, required=True, help="the level id")
    p.add_argument("--out", required=True, help="output PNG path (its folder must exist)")
    p.add_argument("--fov", action="store_true", help="draw each unit's field of view")
    p.add_argument("--scale", type=float, default=8.0, help="pixels per world unit (default 8)")
    p.set_defaults(func=cmd_render)

    p = sub.add_parser("diff", help="the level fields in which two levels differ")
    p.add_argument("file")
    p.add_argument("id1", type=int)
    p.add_argument("id2", type=int)
    p.add_argument("--atol", type=float, default=0.0, help="ignore float differences up to this")
    p.add_argument("--max-items", type=int, default=6, help="elements listed per field")
    p.set_defaults(func=cmd_diff)

"""`tabx levels sample CONFIG`: a picture of what a UED config's level generator produces.

    tabx levels sample configs/ued/robust_plr_zone.yaml --n 9 --out levels.png
    tabx levels sample configs/ued/accel_unit.yaml --mutate --out children.png

Renders a grid of generated levels (the config's base scenarios with its free parameters
resampled), or with `--mutate` one generated level followed by ACCEL children of it, each one
`levels.num_edits` edits further than the previous. `KEY=VALUE` overrides work as for
`tabx train` (`levels.free=[health]`).
"""

from __future__ import annotations

import argparse
import math

import jax
import jax.numpy as jnp
from PIL import Image

from tabx.errors import UserError
from tabx.params import index_level, stack_levels


def sample_levels(config, n: int, seed: int, mutate: bool):
    """(env_config, the n levels as one batch, a title per level)."""
    from ued.experiment import learner_for, scenario_levels
    from ued.levels import LevelGenerator

    env_config, base = scenario_levels(config)
    learner = learner_for(config, env_config)
    base = learner.prepare_levels(jax.tree.map(jnp.asarray, stack_levels(base)))
    generator = LevelGenerator(env_config, base, config.levels)
    key = jax.random.key(seed)
    k_sample, k_mutate = jax.random.split(key)
    if not mutate:
        levels = generator.sample(k_sample, n)
        return env_config, levels, [f"level {i}" for i in range(n)]
    chain = [index_level(generator.sample(k_sample, 1), 0)]
    for i in range(1, n):
        chain.append(index_level(generator.mutate(jax.random.fold_in(k_mutate, i),
                                                  stack_levels([chain[-1]])), 0))
    edits = config.levels.num_edits
    titles = ["generated"] + [f"+{i * edits} edits" for i in range(1, n)]
    return env_config, stack_levels(chain), titles


def grid_image(images: list[Image.Image], columns: int) -> Image.Image:
    """The images in rows of `columns`, on a white canvas."""
    width = max(im.width for im in images)
    height = max(im.height for im in images)
    rows = math.ceil(len(images) / columns)
    canvas = Image.new("RGB", (columns * width, rows * height), "white")
    for i, im in enumerate(images):
        canvas.paste(im, ((i % columns) * width, (i // columns) * height))
    return canvas


def cmd_sample(args: argparse.Namespace) -> int:
    from tabx.render import check_render_options, render_level, save_png
    from ued.config import ConfigError, load_config

    check_render_options(args.out, args.scale)
    if args.n < 1 or args.n > 64:
        raise UserError(f"--n: expected 1 to 64 levels, got {args.n}")
    try:
        config = load_config(args.config, args.overrides)
    except ConfigError as err:
        raise UserError(str(err)) from None
    env_config, levels, titles = sample_levels(config, args.n, args.seed, args.mutate)
    images = [render_level(env_config, index_level(levels, i), scale=args.scale, title=title)
              for i, title in enumerate(titles)]
    columns = args.columns or math.ceil(math.sqrt(len(images)))
    image = grid_image(images, columns)
    save_png(image, args.out)
    what = "a level and its ACCEL children" if args.mutate else "generated levels"
    print(f"wrote {len(images)} {what} (free: {', '.join(config.levels.free)}) to {args.out} "
          f"({image.width} x {image.height})")
    return 0


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser("levels", help="what a UED config's level generator makes")
    sub = parser.add_subparsers(dest="levels_command", metavar="SUBCOMMAND")
    sub.required = True
    p = sub.add_parser("sample", help="render a grid of generated (or mutated) levels")
    p.add_argument("config", help="a training config with a levels: section (a file, or a "
                                  "shipped name such as ued/accel_unit)")
    p.add_argument("overrides", nargs="*", metavar="KEY=VALUE", help="config overrides")
    p.add_argument("--n", type=int, default=9, help="number of levels (default 9)")
    p.add_argument("--mutate", action="store_true",
                   help="one generated level and a chain of ACCEL mutations of it")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--columns", type=int, default=0, help="grid columns (default: square)")
    p.add_argument("--scale", type=float, default=4.0, help="pixels per world unit")
    p.add_argument("--out", required=True, help="PNG file to write")
    p.set_defaults(func=cmd_sample)


__all__ = ["add_parser", "grid_image", "sample_levels"]

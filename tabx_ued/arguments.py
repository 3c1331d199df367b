"""Arguments that several `tabx` commands share."""

from __future__ import annotations

import argparse

from tabx.profiles import DEFAULT_PROFILE, PROFILE_NAMES


def add_profile_argument(parser: argparse.ArgumentParser, default: str = DEFAULT_PROFILE
                         ) -> None:
    """`--profile NAME` on a command; `default` is what the help says happens without it."""
    parser.add_argument("--profile", choices=PROFILE_NAMES, default=None,
                        help=f"behaviour profile: tabx-ued (our fixes and choices) or reference "
                             f"(the reference implementation's choices, to reproduce the "
                             f"paper's numbers; docs/differences.md); default {default}")


__all__ = ["add_profile_argument"]

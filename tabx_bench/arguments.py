"""Argument types of the `tabx bench` commands: comma-separated integer lists, bounded
integers, team sizes and controller lists, each an `argparse` type that says what it expected."""

from __future__ import annotations

import argparse
from collections.abc import Callable


def non_negative_ints(text: str) -> list[int]:
    try:
        values = [int(v) for v in text.split(",") if v]
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected comma-separated integers, got {text!r}") from None
    if not values or any(v < 0 for v in values):
        raise argparse.ArgumentTypeError(f"expected non-negative integers, got {text!r}")
    return values


def int_list(minimum: int, maximum: int | None = None) -> Callable[[str], list[int]]:
    def parse(text: str) -> list[int]:
        parts = [p.strip() for p in text.split(",")]
        if not text.strip() or any(not p for p in parts):
            raise argparse.ArgumentTypeError(
                f"expected a comma-separated list of integers such as 1,16,256, got {text!r}")
        try:
            values = [int(p) for p in parts]
        except ValueError:
            raise argparse.ArgumentTypeError(
                f"expected a comma-separated list of integers, got {text!r}") from None
        bad = [v for v in values if v < minimum]
        if bad:
            raise argparse.ArgumentTypeError(
                f"every value must be >= {minimum}, got {', '.join(map(str, bad))}")
        bad = [v for v in values if maximum is not None and v > maximum]
        if bad:
            raise argparse.ArgumentTypeError(
                f"every value must be <= {maximum}, got {', '.join(map(str, bad))}")
        return values

    return parse


def seconds_up_to(maximum: float) -> Callable[[str], float]:
    """A duration in seconds: a finite number in (0, `maximum`]."""
    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a number of seconds, got {text!r}"
                                             ) from None
        if not 0 < value <= maximum:  # NaN fails too
            raise argparse.ArgumentTypeError(f"expected seconds in (0, {maximum:g}], got {text}")
        return value

    return parse


def int_at_least(minimum: int) -> Callable[[str], int]:
    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
        if value < minimum:
            raise argparse.ArgumentTypeError(f"expected an integer >= {minimum}, got {value}")
        return value

    return parse


def team_sizes(text: str) -> list[int]:
    values = int_list(1)(text)
    too_big = [v for v in values if v > 100]
    if too_big:
        raise argparse.ArgumentTypeError(f"at most 100 units a side, got {too_big[0]}")
    return values


def controllers(text: str) -> list[str]:
    parts = [p.strip() for p in text.split(",")]
    if not text.strip() or any(not p for p in parts):
        raise argparse.ArgumentTypeError(
            f"expected comma-separated controllers such as random,heuristic:medium, got {text!r}")
    return parts


__all__ = ["controllers", "int_at_least", "int_list", "non_negative_ints", "seconds_up_to",
           "team_sizes"]

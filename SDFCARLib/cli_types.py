"""Small helpers shared by the command lines (``SDFCARLib.cli`` and ``SDFCARLib.benchmark.cli``):
argparse type functions and one-line error texts. Standard library only, so both can import it
without importing each other."""

from __future__ import annotations

import argparse
import math


def _whole_number(text: str, least: int, wording: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be {wording}, got {text!r}") from None
    if value < least:
        raise argparse.ArgumentTypeError(f"must be {wording}, got {text}")
    return value


def positive_int(text: str) -> int:
    """argparse type: an integer ≥ 1."""
    return _whole_number(text, 1, "a positive integer")


def non_negative_int(text: str) -> int:
    """argparse type: an integer ≥ 0 (a seed: numpy's generators take no negative one)."""
    return _whole_number(text, 0, "a whole number, 0 or more")


def positive_float(text: str) -> float:
    """argparse type: a finite number > 0."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a positive number, got {text!r}") from None
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"must be a positive number, got {text}")
    return value


def one_line(exc: BaseException, with_type: bool = False) -> str:
    """The exception's message on one line (its type's name when it has none).

    ``with_type`` prefixes the type's name ("RuntimeError: …"): for recorded failures, where the
    type is part of the diagnosis; the CLI's own errors carry messages that stand alone.
    """
    message = " ".join(str(exc).split())
    if not message:
        return type(exc).__name__
    return f"{type(exc).__name__}: {message}" if with_type else message

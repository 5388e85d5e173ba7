"""argparse value types shared by the ``coreg`` subcommands (a bad value: one line, exit 1)."""

from __future__ import annotations

import argparse
import math


def _float(text: str) -> float:
    try:
        return float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f'{text!r} is not a number') from None


def positive(text: str) -> float:
    """Parse a finite number > 0."""
    value = _float(text)
    if not (value > 0 and math.isfinite(value)):
        raise argparse.ArgumentTypeError(f'must be a positive number, got {text}')
    return value


def positive_or_inf(text: str) -> float:
    """Parse a number > 0, ``inf`` allowed (e.g. ``--rate inf``: as fast as possible)."""
    value = _float(text)
    if not value > 0:  # also refuses NaN
        raise argparse.ArgumentTypeError(f'must be > 0, got {text}')
    return value


def positive_int(text: str) -> int:
    """Parse an integer >= 1 (a count: cases, workers)."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f'{text!r} is not an integer') from None
    if value < 1:
        raise argparse.ArgumentTypeError(f'must be at least 1, got {value}')
    return value


def finite(text: str) -> float:
    """Parse a finite number."""
    value = _float(text)
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f'must be finite, got {text}')
    return value

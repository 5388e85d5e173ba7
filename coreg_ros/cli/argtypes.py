"""argparse value types shared by the ``coreg`` subcommands (a bad value: one line, exit 1)."""

from __future__ import annotations

import argparse
import math
from typing import Optional


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


def add_sigma_arguments(parser, defaults: Optional[tuple] = None) -> None:
    """
    Add ``--sigma-a POS_M ROT_RAD`` and ``--sigma-b POS_M ROT_RAD`` (each device's noise).

    ``defaults``: ((pos, rot) of A, (pos, rot) of B) named in the help, if the command has them.
    """
    for k, device in enumerate('ab'):
        default = '' if defaults is None else (
            f' (default {defaults[k][0]:g} {defaults[k][1]:g})')
        parser.add_argument(f'--sigma-{device}', nargs=2, type=positive,
                            metavar=('POS_M', 'ROT_RAD'),
                            help=f"device {device.upper()}'s noise, 1 sigma per axis: position m, "
                                 f'rotation rad{default}')


def add_storage_option(parser) -> None:
    """Add ``--storage sqlite3|mcap`` (the rosbag2 format of a bag the command writes)."""
    parser.add_argument('--storage', choices=('sqlite3', 'mcap'), default='sqlite3',
                        help='rosbag2 storage format of the bag written (default sqlite3)')


def add_parallel_arguments(parser) -> None:
    """
    Add ``--workers N`` and ``--scheduler ADDRESS`` to an argparse parser.

    Every many-case command and evidence script takes the same two options, with the same
    meaning: ``args.workers`` (int, default the machine's cores) and ``args.scheduler``
    (str or None), passed on to ``coreg_ros.parallel.run_cases``.
    """
    from coreg_ros.parallel import default_workers

    parser.add_argument('--workers', type=positive_int, default=default_workers(),
                        metavar='N', help='local processes to run the cases in (default: '
                                          f'every core, {default_workers()} here)')
    parser.add_argument('--scheduler', metavar='ADDRESS',
                        help='run the cases on an existing Dask distributed cluster instead, '
                             "e.g. tcp://host:8786 (needs pip install 'coreg_ros[dask]')")


def points_from_flat(values, report_dir=None):
    """
    Turn ``--points X Y Z [X Y Z ...]`` into an (M, 3) array (None stays None).

    Parameters
    ----------
    values : sequence of float, optional
        The flat numbers, metres.
    report_dir : str, optional
        ``--report``; points without a report are refused rather than ignored.

    Returns
    -------
    points : ndarray, shape (M, 3), or None

    Raises
    ------
    ConfigError
        If the number of values is not a positive multiple of three, or no report is asked.

    """
    if values is None:
        return None
    from coreg_ros.core.errors import ConfigError
    import numpy as np

    if not report_dir:
        raise ConfigError('--points are shown in the report: add --report DIR')
    flat = np.asarray(values, dtype=float).ravel()
    if flat.size == 0 or flat.size % 3:
        raise ConfigError(f'--points takes X Y Z triples (metres), got {flat.size} number(s)')
    return flat.reshape(-1, 3)

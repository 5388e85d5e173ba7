"""
``coreg convert``: two CSV pose exports to a rosbag2 recording, and the direction check.

A CSV export has one row per sample, ``t, x, y, z`` and a quaternion (``qx, qy, qz, qw`` by
default, as in the ETH hand-eye data sets), t in seconds (e.g. unix time), comma and/or
whitespace separated, with an optional header line. Four-column rows (``t, x, y, z``) are a
position-only tracker (identity orientation). The stream can be converted from millimetres,
inverted (``T → T⁻¹``) when the export gives the base in the tracked frame, and is written as
``geometry_msgs/PoseStamped`` on ``/device_a/pose`` and ``/device_b/pose``.

``direction_guard`` is the check ``coreg calibrate`` runs when a fit is bad: whether the data
would fit far better with a stream inverted (``coreg_ros.core.directions``).
"""

from __future__ import annotations

from dataclasses import dataclass
from decimal import ROUND_HALF_EVEN, Decimal, InvalidOperation
from pathlib import Path
import re
import sys
from typing import Optional

import numpy as np

from coreg_ros.core import quaternion as quat
from coreg_ros.core.directions import DirectionReport, check_directions, invert_poses
from coreg_ros.core.errors import ConfigError, InputError
from coreg_ros.core.settings import DEFAULT_TOPIC_A, DEFAULT_TOPIC_B
from coreg_ros.core.types import PoseStream

#: Quaternion column orders accepted by ``--quaternion-order``.
QUATERNION_ORDERS = ('xyzw', 'wxyz')
#: Position units accepted by ``--units`` and their size in metres.
UNITS = {'m': 1.0, 'mm': 1e-3}
#: Largest deviation of a quaternion's norm from 1 accepted (then it is normalised).
NORM_TOLERANCE = 1e-2
#: p-value below which ``coreg calibrate`` checks the stream directions.
DIRECTION_CHECK_P = 1e-3
#: ``header.frame_id`` of the converted streams.
FRAME_A = 'device_a_base'
FRAME_B = 'device_b_base'

_SPLIT = re.compile(r'\s*,\s*|\s+')
_NS = Decimal(10) ** 9


@dataclass(frozen=True)
class CsvStream:
    """
    A pose stream read from a CSV export, and what was done to it.

    Attributes
    ----------
    stream : PoseStream
        Stamps int64 ns, positions m, quaternions (w, x, y, z) unit with w >= 0.
    has_orientation : bool
        False for a four-column (position-only) export.
    header : bool
        Whether a header line was skipped.
    n_dropped : int
        Rows dropped by ``sort`` because their time repeated an earlier row's.
    n_reordered : int
        Rows that were out of time order (``sort`` only).

    """

    stream: PoseStream
    has_orientation: bool
    header: bool = False
    n_dropped: int = 0
    n_reordered: int = 0


def _seconds_to_ns(text: str) -> int:
    """Convert decimal seconds to int64 ns exactly (no float rounding), half to even."""
    value = Decimal(text)
    if not value.is_finite():
        raise ValueError('not finite')
    return int((value * _NS).to_integral_value(rounding=ROUND_HALF_EVEN))


def _format_ns(ns) -> str:
    """Format int ns as exact decimal seconds."""
    ns = int(ns)
    sign, ns = ('-', -ns) if ns < 0 else ('', ns)
    return f'{sign}{ns // 10 ** 9}.{ns % 10 ** 9:09d}'


def _fields(line: str) -> list:
    line = line.strip()
    return [f for f in _SPLIT.split(line)] if line else []


def _is_number(token: str) -> bool:
    try:
        float(token)
    except ValueError:
        return False
    return True


def read_pose_csv(path, *, quaternion_order: str = 'xyzw', units: str = 'm',
                  invert: bool = False, sort: bool = False, frame_id: str = '',
                  name: str = 'CSV') -> CsvStream:
    """
    Read one device's CSV export into a pose stream.

    Parameters
    ----------
    path : str or path-like
        The CSV file: one row per sample, ``t, x, y, z[, q, q, q, q]``; t in seconds (any
        number of decimals, converted to int64 ns exactly), separators commas and/or
        whitespace; an optional header line first; blank lines and ``#`` comments skipped.
    quaternion_order : {'xyzw', 'wxyz'}
        Order of the four quaternion columns.
    units : {'m', 'mm'}
        Unit of the positions.
    invert : bool
        Invert every pose (``T → T⁻¹``): for an export of the base frame in the tracked frame.
    sort : bool
        Sort the rows by time and drop rows whose time repeats an earlier row's (keeping the
        first); without it, a repeated or decreasing time is an error.
    frame_id : str
        ``frame_id`` of the stream.
    name : str
        What the file is in error messages (e.g. ``'CSV_A'``).

    Returns
    -------
    CsvStream

    Raises
    ------
    InputError
        One line with the file and line number: missing or empty file, a wrong number of
        columns, a non-numeric or NaN/inf value, a non-unit quaternion, a repeated or
        decreasing time (the fix: ``--sort``).
    ConfigError
        For an unknown ``quaternion_order`` or ``units``, or ``invert`` of a position-only file.

    """
    if quaternion_order not in QUATERNION_ORDERS:
        raise ConfigError(f'quaternion order {quaternion_order!r} is unknown; use one of '
                          f'{", ".join(QUATERNION_ORDERS)}')
    if units not in UNITS:
        raise ConfigError(f'units {units!r} are unknown; use one of {", ".join(UNITS)}')
    path = Path(path)
    where = f'{name} {path}'
    try:
        text = path.read_text(encoding='utf-8-sig')
    except FileNotFoundError:
        raise InputError(f'{where}: no such file; give the path of the CSV export') from None
    except IsADirectoryError:
        raise InputError(f'{where}: is a directory; give the path of the CSV file') from None
    except (OSError, UnicodeDecodeError) as e:
        raise InputError(f'{where}: cannot be read as text ({e})') from e

    stamps, values, lines = [], [], []
    header = False
    ncol = None
    for lineno, raw in enumerate(text.splitlines(), start=1):
        line = raw.split('#', 1)[0]
        tokens = _fields(line)
        if not tokens:
            continue
        if ncol is None and not stamps and not header and not all(map(_is_number, tokens)):
            header = True                                  # first non-blank line: a header
            continue
        if '' in tokens:
            raise InputError(f'{where}: line {lineno}: empty field; every row needs t, x, y, '
                             f'z and four quaternion components')
        if ncol is None:
            ncol = len(tokens)
            if ncol not in (4, 8):
                raise InputError(
                    f'{where}: line {lineno}: {ncol} columns; expected 8 (t, x, y, z and a '
                    f'quaternion in {quaternion_order} order) or 4 (t, x, y, z)')
        elif len(tokens) != ncol:
            raise InputError(f'{where}: line {lineno}: {len(tokens)} columns where the rows '
                             f'before have {ncol}; fix or drop that line')
        bad = next((v for v in tokens if not _is_number(v)), None)
        if bad is not None:
            raise InputError(f'{where}: line {lineno}: {bad!r} is not a number')
        row = [float(v) for v in tokens]
        if not np.isfinite(row).all():
            raise InputError(f'{where}: line {lineno}: NaN or inf value; drop samples where '
                             f'tracking was lost')
        try:
            t = _seconds_to_ns(tokens[0])
        except (ValueError, InvalidOperation):
            raise InputError(f'{where}: line {lineno}: time {tokens[0]!r} is not a number of '
                             f'seconds') from None
        row = row[1:]
        stamps.append(t)
        values.append(row)
        lines.append(lineno)
    if not stamps:
        raise InputError(f'{where}: no samples (empty file, or a header only)')

    stamps = np.array(stamps, dtype=np.int64)
    values = np.array(values, dtype=float)
    lines = np.array(lines)
    position = values[:, :3] * UNITS[units]
    has_orientation = values.shape[1] == 7
    if has_orientation:
        q = values[:, 3:7]
        q = q[:, [3, 0, 1, 2]] if quaternion_order == 'xyzw' else q
        norm = np.linalg.norm(q, axis=1)
        bad = np.flatnonzero(np.abs(norm - 1.0) > NORM_TOLERANCE)
        if bad.size:
            i = int(bad[0])
            raise InputError(
                f'{where}: line {lines[i]}: quaternion norm {norm[i]:.4g} is not 1 '
                f'({bad.size} row(s) in all); check the columns (t, x, y, z, then the '
                f'quaternion) and --quaternion-order (now {quaternion_order})')
        q = quat.canonical(q / norm[:, None])
    else:
        if invert:
            raise ConfigError(f'{where}: a position-only export (4 columns) cannot be '
                              f'inverted: it has no orientation')
        q = np.tile([1.0, 0.0, 0.0, 0.0], (len(stamps), 1))

    n_dropped = n_reordered = 0
    step = np.diff(stamps)
    if sort:
        order = np.argsort(stamps, kind='stable')
        n_reordered = int(np.count_nonzero(order != np.arange(order.size)))
        stamps, position, q = stamps[order], position[order], q[order]
        keep = np.ones(len(stamps), dtype=bool)
        keep[1:] = np.diff(stamps) > 0
        n_dropped = int((~keep).sum())
        stamps, position, q = stamps[keep], position[keep], q[keep]
    elif (step <= 0).any():
        i = int(np.flatnonzero(step <= 0)[0]) + 1
        what = 'repeats' if step[i - 1] == 0 else 'goes back from'
        raise InputError(
            f"{where}: line {lines[i]}: time {_format_ns(stamps[i])} s {what} the previous row's "
            f'(line {lines[i - 1]}; {int((step == 0).sum())} repeated and '
            f'{int((step < 0).sum())} decreasing time(s) in all); pass --sort to sort by time '
            f'and drop repeated times')
    if invert:
        position, q = invert_poses(position, q)
    stream = PoseStream(stamps=stamps, position=np.ascontiguousarray(position),
                        quat_wxyz=np.ascontiguousarray(q), frame_id=frame_id)
    return CsvStream(stream=stream, has_orientation=has_orientation, header=header,
                     n_dropped=n_dropped, n_reordered=n_reordered)


def _describe(label: str, csv: CsvStream) -> str:
    s = csv.stream
    span = (s.stamps[-1] - s.stamps[0]) * 1e-9
    rate = (len(s) - 1) / span if span > 0 else float('nan')
    extra = []
    if csv.header:
        extra.append('header skipped')
    if csv.n_reordered:
        extra.append(f'{csv.n_reordered} rows reordered')
    if csv.n_dropped:
        extra.append(f'{csv.n_dropped} repeated times dropped')
    if not csv.has_orientation:
        extra.append('position only')
    note = f'; {", ".join(extra)}' if extra else ''
    return f'{label}: {len(s)} samples over {span:.3f} s (~{rate:.1f} Hz){note}'


def cmd_convert(args) -> int:
    """Convert two CSV exports to a rosbag2 recording."""
    from coreg_ros.bag.posebag import write_pose_bag

    common = {'quaternion_order': args.quaternion_order, 'units': args.units,
              'sort': args.sort}
    a = read_pose_csv(args.csv_a, invert=args.invert_a, frame_id=FRAME_A, name='CSV_A',
                      **common)
    b = read_pose_csv(args.csv_b, invert=args.invert_b, frame_id=FRAME_B, name='CSV_B',
                      **common)
    topic_a, topic_b = args.topic_a, args.topic_b
    if topic_a == topic_b:
        raise ConfigError(f'--topic-a and --topic-b are both {topic_a}; give two topics')
    sa, sb = a.stream.stamps, b.stream.stamps
    overlap = (min(sa[-1], sb[-1]) - max(sa[0], sb[0])) * 1e-9
    write_pose_bag(args.out_bag, {topic_a: a.stream, topic_b: b.stream}, storage=args.storage)
    print(f'coreg convert: wrote {args.out_bag} ({args.storage})')
    print('  ' + _describe(f'{topic_a} (A{", inverted" if args.invert_a else ""})', a))
    print('  ' + _describe(f'{topic_b} (B{", inverted" if args.invert_b else ""})', b))
    if overlap <= 0:
        print(f'  warning: the two streams do not overlap in time (gap {-overlap:.3f} s); '
              f'they cannot be paired', file=sys.stderr)
    else:
        print(f'  overlap {overlap:.3f} s')
    return 0


def register(subparsers) -> None:
    """Add the ``convert`` subcommand to the ``coreg`` parser's subparsers."""
    p = subparsers.add_parser(
        'convert', help='convert two CSV pose exports (t, x, y, z, quaternion) to a rosbag2',
        description='Convert two CSV exports, one row per sample "t, x, y, z, q, q, q, q" '
                    '(t in seconds; comma and/or whitespace separated; optional header), to '
                    'a rosbag2 with PoseStamped on two topics.')
    p.add_argument('csv_a', help='device A export (tool pose in A base)')
    p.add_argument('csv_b', help='device B export (marker pose in B base)')
    p.add_argument('out_bag', help='rosbag2 directory to create')
    p.add_argument('--quaternion-order', choices=QUATERNION_ORDERS, default='xyzw',
                   help='order of the quaternion columns (default xyzw)')
    p.add_argument('--units', choices=tuple(UNITS), default='m',
                   help='unit of the positions (default m)')
    p.add_argument('--invert-a', action='store_true',
                   help='invert device A poses (T -> T^-1): the export is base-in-tool')
    p.add_argument('--invert-b', action='store_true',
                   help='invert device B poses (T -> T^-1): the export is base-in-marker')
    p.add_argument('--sort', action='store_true',
                   help='sort rows by time and drop repeated times instead of refusing them')
    p.add_argument('--storage', choices=('sqlite3', 'mcap'), default='sqlite3')
    p.add_argument('--topic-a', default=DEFAULT_TOPIC_A, help=f'default {DEFAULT_TOPIC_A}')
    p.add_argument('--topic-b', default=DEFAULT_TOPIC_B[0], help=f'default {DEFAULT_TOPIC_B[0]}')
    p.set_defaults(func=cmd_convert)


def direction_guard(args, stream_a: PoseStream, streams_b, settings,
                    result) -> Optional[DirectionReport]:
    """
    Check the stream directions after a bad fit, for ``coreg calibrate``.

    Runs ``check_directions`` only when the fit's p-value is below ``DIRECTION_CHECK_P`` (or
    not a number) and ``--no-direction-check`` was not given; good data pay nothing.

    Returns
    -------
    DirectionReport or None
        None when the check did not run. ``report.flagged`` means the data fit more than 10×
        better with a stream inverted: the caller should refuse the fit (``report.message``
        names the ``coreg convert`` flag).

    """
    if getattr(args, 'no_direction_check', False):
        return None
    p = float(result.p_value)
    if np.isfinite(p) and p >= DIRECTION_CHECK_P:
        return None
    return check_directions(stream_a, streams_b, settings)

"""
CSV pose exports: read into ``PoseStream`` arrays, and two compared for convention mistakes.

A CSV export has one row per sample, ``t, x, y, z`` and a quaternion (``qx, qy, qz, qw`` by
default, as in the ETH hand-eye data sets), t in seconds (e.g. unix time), comma and/or
whitespace separated, with an optional header line. Four-column rows (``t, x, y, z``) are a
position-only tracker (identity orientation). A stream can be converted from millimetres and
inverted (``T → T⁻¹``) when the export gives the base in the tracked frame.
``check_conventions`` compares two exports for a unit factor, a time unit, a quaternion order
or a direction that disagree.
"""

from __future__ import annotations

from dataclasses import dataclass
from decimal import Decimal, InvalidOperation, ROUND_HALF_EVEN
from pathlib import Path
import re

from coreg_ros.core import quaternion as quat
from coreg_ros.core.errors import ConfigError, InputError
from coreg_ros.core.so3 import invert_poses
from coreg_ros.core.types import PoseStream
import numpy as np

#: Quaternion column orders accepted by ``--quaternion-order``.
QUATERNION_ORDERS = ('xyzw', 'wxyz')
#: Position units accepted by ``--units`` and their size in metres.
UNITS = {'m': 1.0, 'cm': 1e-2, 'mm': 1e-3}
#: Time units accepted by ``--time-unit`` and their size in nanoseconds.
TIME_UNITS = {'s': 10**9, 'ms': 10**6, 'us': 10**3, 'ns': 1}
#: A header stamp (builtin_interfaces/Time, int32 seconds) holds times below this, ns.
MAX_STAMP_NS = 2**31 * 10**9
#: Largest deviation of a quaternion's norm from 1 accepted (then it is normalised).
NORM_TOLERANCE = 1e-2
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
    nonnegative_columns : tuple of bool
        For each quaternion column of the file, whether it is never negative (an exporter
        that keeps w >= 0 shows which column is w).

    """

    stream: PoseStream
    has_orientation: bool
    header: bool = False
    n_dropped: int = 0
    n_reordered: int = 0
    nonnegative_columns: tuple = ()


def _seconds_to_ns(text: str, ns_per_unit: int = 10**9) -> int:
    """Convert a decimal time to int ns exactly (no float rounding), half to even."""
    value = Decimal(text)
    if not value.is_finite():
        raise ValueError('not finite')
    unit = _NS if ns_per_unit == 10**9 else Decimal(ns_per_unit)
    return int((value * unit).to_integral_value(rounding=ROUND_HALF_EVEN))


def _time_unit_hint(ns: int, time_unit: str, option: str = '') -> str:
    """Name the time unit that would bring ``ns`` (read in ``time_unit``) below 2038."""
    factor = TIME_UNITS[time_unit]
    for unit, size in TIME_UNITS.items():
        if size < factor and 0 <= ns * size // factor < MAX_STAMP_NS:
            return f'the times look like {unit}: pass --time-unit{option} {unit}'
    return 'check that the first column is the time'


def _format_ns(ns) -> str:
    """Format int ns as exact decimal seconds."""
    ns = int(ns)
    sign, ns = ('-', -ns) if ns < 0 else ('', ns)
    return f'{sign}{ns // 10 ** 9}.{ns % 10 ** 9:09d}'


def _fields(line: str) -> list:
    line = line.strip()
    return list(_SPLIT.split(line)) if line else []


def _is_number(token: str) -> bool:
    try:
        float(token)
    except ValueError:
        return False
    return True


def read_pose_csv(path, *, quaternion_order: str = 'xyzw', units: str = 'm',
                  invert: bool = False, sort: bool = False, frame_id: str = '',
                  name: str = 'CSV', time_unit: str = 's', option: str = '') -> CsvStream:
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
    units : {'m', 'cm', 'mm'}
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
    time_unit : {'s', 'ms', 'us', 'ns'}
        Unit of the time column.
    option : str
        Suffix of this file's ``coreg convert`` options named in error messages (``'-a'``:
        ``--time-unit-a``); empty: the options for both files.

    Returns
    -------
    CsvStream

    Raises
    ------
    InputError
        One line with the file and line number: missing or empty file, a wrong number of
        columns, a non-numeric or NaN/inf value, a non-unit quaternion, a repeated or
        decreasing time (the fix: ``--sort``), a time at or past 2**31 s (2038, beyond a
        header stamp: the message names the time unit that fits, e.g. ``--time-unit ms``).
    ConfigError
        For an unknown ``quaternion_order`` or ``units``, or ``invert`` of a position-only file.

    """
    if quaternion_order not in QUATERNION_ORDERS:
        raise ConfigError(f'quaternion order {quaternion_order!r} is unknown; use one of '
                          f'{", ".join(QUATERNION_ORDERS)}')
    if units not in UNITS:
        raise ConfigError(f'units {units!r} are unknown; use one of {", ".join(UNITS)}')
    if time_unit not in TIME_UNITS:
        raise ConfigError(f'time unit {time_unit!r} is unknown; use one of '
                          f'{", ".join(TIME_UNITS)}')
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
            t = _seconds_to_ns(tokens[0], TIME_UNITS[time_unit])
        except (ValueError, InvalidOperation):
            raise InputError(f'{where}: line {lineno}: time {tokens[0]!r} is not a number of '
                             f'seconds') from None
        if not -MAX_STAMP_NS < t < MAX_STAMP_NS:
            raise InputError(
                f'{where}: line {lineno}: time {tokens[0]} {time_unit} is past the year 2038, '
                f'more than a header stamp holds (2**31 s); '
                f'{_time_unit_hint(t, time_unit, option)}')
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
    nonnegative = ()
    if has_orientation:
        q = values[:, 3:7]
        nonnegative = tuple(bool(v) for v in (q >= 0).all(axis=0))
        q = q[:, [3, 0, 1, 2]] if quaternion_order == 'xyzw' else q
        norm = np.linalg.norm(q, axis=1)
        bad = np.flatnonzero(np.abs(norm - 1.0) > NORM_TOLERANCE)
        if bad.size:
            i = int(bad[0])
            raise InputError(
                f'{where}: line {lines[i]}: quaternion norm {norm[i]:.4g} is not 1 '
                f'({bad.size} row(s) in all); check the columns (t, x, y, z, then the '
                f'quaternion) and --quaternion-order{option} (now {quaternion_order})')
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
                     n_dropped=n_dropped, n_reordered=n_reordered,
                     nonnegative_columns=nonnegative)


#: Ratio of two streams' time spans taken as a time unit factor of 1000.
FACTOR_1000 = (300.0, 3000.0)
#: Relative residual below which A's and B's relative rotations agree (``rotation_agreement``).
ROTATION_AGREE = 0.05


def _span(stream: PoseStream) -> float:
    return float(stream.stamps[-1] - stream.stamps[0]) * 1e-9 if len(stream) > 1 else 0.0


def _reorder(q: np.ndarray, given: str, inverted: bool) -> np.ndarray:
    """Return the (w, x, y, z) quaternions read with the other column order than ``given``."""
    q = quat.conjugate(q) if inverted else q
    raw = q[:, [1, 2, 3, 0]] if given == 'xyzw' else q      # the columns as in the file
    other = raw[:, [3, 0, 1, 2]] if given == 'wxyz' else raw  # read in the other order
    other = quat.canonical(other)
    return quat.conjugate(other) if inverted else other


def _relative_rotations(stream_q: np.ndarray, stamps: np.ndarray, times: np.ndarray):
    """Body- and space-frame rotation vectors between successive samples nearest ``times``."""
    i = np.clip(np.searchsorted(stamps, times), 0, len(stamps) - 1)
    prev = np.clip(i - 1, 0, len(stamps) - 1)
    i = np.where(np.abs(stamps[prev] - times) < np.abs(stamps[i] - times), prev, i)
    q = stream_q[i]
    body = quat.log(quat.multiply(quat.conjugate(q[:-1]), q[1:]))
    space = quat.log(quat.multiply(q[1:], quat.conjugate(q[:-1])))
    return body, space


def _kabsch_residual(u: np.ndarray, v: np.ndarray) -> float:
    """Relative residual of the best rotation R with v ≈ R u (0: a rotation maps u onto v)."""
    h = u.T @ v
    uu, _, vt = np.linalg.svd(h)
    d = np.sign(np.linalg.det(vt.T @ uu.T)) or 1.0
    r = vt.T @ np.diag([1.0, 1.0, d]) @ uu.T
    scale = 0.5 * (np.sum(u * u) + np.sum(v * v))
    return float(np.sum((v - u @ r.T) ** 2) / scale) if scale > 0 else float('nan')


def rotation_agreement(stamps_a, q_a, stamps_b, q_b, n: int = 200) -> float:
    """
    How well A's and B's relative rotations agree, for the quaternion-order check.

    For rigidly linked devices ``R_B = R0 R_A R1``, so the rotation between two instants seen
    in A's tool frame is the one seen in B's marker frame turned by R1 (and in the base frames
    by R0). Successive rotations between ``n`` instants of the common span are compared by the
    best rotation mapping A's onto B's, tool or base frame for each. Reading one file in the
    other column order breaks this (reading both in the other order does not: only a mismatch
    shows). The cyclic column shift is ``R -> C Rᵀ D`` for constant C, D, so an export that
    needs inverting breaks it alike: the check cannot tell the two apart.

    Returns
    -------
    residual : float
        Relative residual of the best pairing (0: exact; about 1: unrelated); NaN when the
        streams do not overlap or barely rotate.

    """
    lo, hi = max(stamps_a[0], stamps_b[0]), min(stamps_a[-1], stamps_b[-1])
    if hi <= lo:
        return float('nan')
    times = np.linspace(lo, hi, n + 1).astype(np.int64)
    rot_a = _relative_rotations(q_a, stamps_a, times)
    rot_b = _relative_rotations(q_b, stamps_b, times)
    if np.median(np.linalg.norm(rot_a[0], axis=1)) < 1e-3:
        return float('nan')  # too little rotation to tell
    return min(_kabsch_residual(u, v) for u in rot_a for v in rot_b)


def check_conventions(a: CsvStream, b: CsvStream, *, units=('m', 'm'), time_units=('s', 's'),
                      orders=('xyzw', 'xyzw'), inverted=(False, False)) -> list:
    """
    Test the cheap explanations of a recording that will fit badly; return what they find.

    Checks, without a fit: a unit factor (mm or cm against m) between the streams
    (``verdict.unit_mismatch``: the spread of their positions, which for one rigidly linked
    body differs by far less, told which units the files were read in), a time unit (their time
    spans), and the quaternion column order (``rotation_agreement`` under the given and the
    other orders, for each file).

    Parameters
    ----------
    a, b : CsvStream
        The two converted streams.
    units, time_units, orders, inverted : tuple
        The options they were converted with, (A, B).

    Returns
    -------
    findings : list of str
        One line each, naming the option that fixes it; empty when nothing is suspicious.

    """
    # imported here: the verdict's statistics (SciPy, 0.15 s) would otherwise load with the
    # option choices of every coreg command (coreg_ros.cli.main registers them all)
    from coreg_ros.core.calibration.verdict import unit_mismatch

    sa, sb = a.stream, b.stream
    # the same check as a calibration's verdict, told which units each file was read in
    findings = [f for f in (unit_mismatch(sa, sb, units),) if f]
    span_a, span_b = _span(sa), _span(sb)
    if span_a > 0 and span_b > 0:
        ratio = span_a / span_b
        for big, r, k in (('A', ratio, 0), ('B', 1.0 / ratio, 1)):
            if FACTOR_1000[0] <= r <= FACTOR_1000[1]:
                faster = {'s': 'ms', 'ms': 'us', 'us': 'ns'}.get(time_units[k])
                if faster:
                    findings.append(
                        f"{big}'s times span {r:.0f}x longer than the other's "
                        f'({max(span_a, span_b):.4g} s vs {min(span_a, span_b):.4g} s): a time '
                        f'unit; pass --time-unit-{big.lower()} {faster}')
    if a.has_orientation and b.has_orientation and len(sa) > 2 and len(sb) > 2:
        given = rotation_agreement(sa.stamps, sa.quat_wxyz, sb.stamps, sb.quat_wxyz)
        swapped = rotation_agreement(sa.stamps, sa.quat_wxyz, sb.stamps,
                                     _reorder(sb.quat_wxyz, orders[1], inverted[1]))
        if swapped < ROTATION_AGREE and not given < 10 * swapped:
            findings.append(
                f"A's and B's rotations agree only if one file's quaternion columns are read "
                f'in the other order (residual {swapped:.2g} against {given:.2g} as given) or '
                f'one export is inverted; {_order_fix((a, b), orders, inverted)}')
    return findings


def _order_fix(csvs, orders, inverted) -> str:
    """Name the fixes; the file whose order is wrong when its w column shows (never < 0)."""
    other = {'xyzw': 'wxyz', 'wxyz': 'xyzw'}
    w_col = {'xyzw': 3, 'wxyz': 0}
    suspects = []
    for side, csv, order in zip('ab', csvs, orders, strict=True):
        cols = csv.nonnegative_columns
        # an exporter that keeps w >= 0: the column read as w has negatives, the other never
        if len(cols) == 4 and not cols[w_col[order]] and cols[w_col[other[order]]]:
            suspects.append(f'--quaternion-order-{side} {other[order]}')
    if len(suspects) == 1:
        return f'pass {suspects[0]} (its w column is the one never negative)'
    flips = ' or '.join(f'{"drop " if inv else ""}--invert-{side}'
                        for side, inv in zip('ab', inverted, strict=True))
    return (f'pass --quaternion-order-a {other[orders[0]]} or --quaternion-order-b '
            f'{other[orders[1]]}, whichever export puts w first, else {flips}')

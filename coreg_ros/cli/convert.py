"""
``coreg convert`` and ``coreg fix-bag``: CSV pose exports to a rosbag2 recording; bag repairs.

The exports are read and checked by ``coreg_ros.files.csv_poses`` and written as
``geometry_msgs/PoseStamped`` on ``/device_a/pose`` and ``/device_b/pose``.
"""

from __future__ import annotations

import sys

from coreg_ros.cli.argtypes import add_storage_option
from coreg_ros.core.errors import ConfigError, InputError
from coreg_ros.core.settings import DEFAULT_TOPIC_A, DEFAULT_TOPIC_B
from coreg_ros.files.csv_poses import (
    check_conventions,
    CsvStream,
    FRAME_A,
    FRAME_B,
    QUATERNION_ORDERS,
    read_pose_csv,
    TIME_UNITS,
    UNITS,
)


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
    from coreg_ros.files.bag.posebag import write_pose_bag
    from coreg_ros.files.output_paths import check_new_bag

    check_new_bag(args.out_bag, 'OUT_BAG')  # before reading the CSVs

    def per_file(name: str, side: str, default: str) -> str:
        value = getattr(args, f'{name}_{side}', None)
        return value or getattr(args, name, None) or default

    options = {side: {'quaternion_order': per_file('quaternion_order', side, 'xyzw'),
                      'units': per_file('units', side, 'm'),
                      'time_unit': per_file('time_unit', side, 's')} for side in 'ab'}
    a = read_pose_csv(args.csv_a, invert=args.invert_a, frame_id=FRAME_A, name='CSV_A',
                      sort=args.sort, option='-a', **options['a'])
    b = read_pose_csv(args.csv_b, invert=args.invert_b, frame_id=FRAME_B, name='CSV_B',
                      sort=args.sort, option='-b', **options['b'])
    if not a.has_orientation:
        raise InputError(f'{args.csv_a} (device A) has no orientation columns (t, x, y, z): '
                         f"every model needs the orientation of A's tool; export its "
                         f'quaternion, or give the position-only tracker as B')
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
    findings = check_conventions(
        a, b, units=(options['a']['units'], options['b']['units']),
        time_units=(options['a']['time_unit'], options['b']['time_unit']),
        orders=(options['a']['quaternion_order'], options['b']['quaternion_order']),
        inverted=(args.invert_a, args.invert_b))
    for finding in findings:
        print(f'  warning: {finding}; the calibration would fit badly', file=sys.stderr)
    return 0


def register(subparsers) -> None:
    """Add the ``convert`` subcommand to the ``coreg`` parser's subparsers."""
    p = subparsers.add_parser(
        'convert', help='convert two CSV pose exports (t, x, y, z, quaternion) to a rosbag2',
        description='Convert two CSV exports, one row per sample "t, x, y, z, q, q, q, q" '
                    '(t in seconds; comma and/or whitespace separated; optional header), to '
                    'a rosbag2 with PoseStamped on two topics. After converting it checks the '
                    'cheap explanations of a bad fit (a unit factor, mm or cm against m, between '
                    'the files, a time unit, the quaternion column order) and names the option '
                    'that fixes one.')
    p.add_argument('csv_a', help='device A export (tool pose in A base)')
    p.add_argument('csv_b', help='device B export (marker pose in B base)')
    p.add_argument('out_bag', help='rosbag2 directory to create')
    for name, choices, default, what in (
            ('quaternion-order', QUATERNION_ORDERS, 'xyzw', 'order of the quaternion columns'),
            ('units', tuple(UNITS), 'm', 'unit of the positions'),
            ('time-unit', tuple(TIME_UNITS), 's', 'unit of the time column')):
        p.add_argument(f'--{name}', choices=choices,
                       help=f'{what} of both files (default {default})')
        for side in 'ab':
            p.add_argument(f'--{name}-{side}', choices=choices,
                           help=f'{what} of CSV_{side.upper()} (default: --{name})')
    p.add_argument('--invert-a', action='store_true',
                   help='invert device A poses (T -> T^-1): the export is base-in-tool')
    p.add_argument('--invert-b', action='store_true',
                   help='invert device B poses (T -> T^-1): the export is base-in-marker')
    p.add_argument('--sort', action='store_true',
                   help='sort rows by time and drop repeated times instead of refusing them')
    add_storage_option(p)
    p.add_argument('--topic-a', default=DEFAULT_TOPIC_A, help=f'default {DEFAULT_TOPIC_A}')
    p.add_argument('--topic-b', default=DEFAULT_TOPIC_B[0], help=f'default {DEFAULT_TOPIC_B[0]}')
    p.set_defaults(func=cmd_convert)
    register_fix_bag(subparsers)


def cmd_fix_bag(args) -> int:
    """Write a repaired copy of a recording: sorted, without repeated stamps, or split."""
    from coreg_ros.files.bag.fixbag import fix_bag
    from coreg_ros.files.output_paths import check_new_bag

    check_new_bag(args.out_bag, 'OUT_BAG')  # split parts are checked by fix_bag
    report = fix_bag(args.bag, args.out_bag, sort=args.sort,
                     drop_duplicates=args.drop_duplicates, split_at_jump=args.split_at_jump,
                     storage=args.storage, salvage=args.salvage)
    for line in report.salvage_stopped:
        print(f'  salvage: {line}')
    for topic, n in report.reordered.items():
        print(f'  {topic}: {n} messages were out of stamp order, now sorted')
    for topic, n in report.dropped.items():
        print(f'  {topic}: {n} messages with a repeated stamp dropped')
    for topic, before, after in report.jumps:
        print(f'  {topic}: clock jump of {(after - before) * 1e-9:+.3f} s (stamp {before} -> '
              f'{after} ns): split there')
    if report.skipped_topics:
        print(f'  not copied (not PoseStamped): {", ".join(report.skipped_topics)}')
    for path, counts in report.outputs:
        print(f'coreg fix-bag: wrote {path} ('
              + ', '.join(f'{t} {n}' for t, n in counts.items()) + ')')
    return 0


def register_fix_bag(subparsers) -> None:
    """Add the ``fix-bag`` subcommand (``coreg_ros.files.bag.fixbag``)."""
    from coreg_ros.cli.argtypes import positive

    p = subparsers.add_parser(
        'fix-bag', help='salvage a damaged bag, sort it by stamp, drop repeated stamps or split '
                        'it at a clock jump',
        description='Write a repaired copy of the PoseStamped topics of a rosbag2: what a '
                    'damaged recording still holds (--salvage), sorted by '
                    'header stamp (--sort), without messages whose stamp repeats '
                    '(--drop-duplicates), or split where a stamp jumps by more than S seconds '
                    '(--split-at-jump S: OUT_BAG_1, OUT_BAG_2, ...).')
    p.add_argument('bag', help='rosbag2 directory to repair (left unchanged)')
    p.add_argument('out_bag', help='rosbag2 directory to create')
    p.add_argument('--salvage', action='store_true',
                   help='read the storage file(s) directly: a recording cut short (no '
                        'metadata.yaml, a truncated .mcap or .db3) gives what it still holds')
    p.add_argument('--sort', action='store_true', help='sort each topic by header stamp')
    p.add_argument('--drop-duplicates', action='store_true',
                   help='drop messages whose header stamp repeats an earlier one (keep first)')
    p.add_argument('--split-at-jump', type=positive, metavar='S',
                   help='split where a header stamp jumps by more than S seconds')
    add_storage_option(p)
    p.set_defaults(func=cmd_fix_bag)

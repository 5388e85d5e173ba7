"""
``coreg noise RECORDING``: each device's noise measured where it stands still; a noise file.

The still segments of each device are found from the samples (or ``--window T0 T1``), and
each device's position and rotation noise is measured there as 3×3 covariances in its base
frame, with principal axes, the Allan deviation, the growth with distance and the sampling
(``coreg_ros.core.noise``). The noise file written (``--out``, by default beside the
recording) is what ``--noise FILE`` and the node's ``noise_file`` read.
"""

from __future__ import annotations

import json
import sys

from coreg_ros.cli.argtypes import finite, positive
from coreg_ros.cli.policy import PROG


def noise_file_document(report, settings, recording: str) -> dict:
    """
    Return the noise file of a measurement (``files.noise_file`` layout).

    A channel not measured (B's orientation of a position-only or three-marker tracker)
    keeps the stated σ and is marked so.
    """
    from coreg_ros.core.noise_model import DeviceNoise
    from coreg_ros.files.noise_file import device_block, noise_document

    blocks = {}
    for m, topic in ((report.device_a, settings.topic_a),
                     (report.device_b, tuple(settings.topic_b))):
        stated = settings.device_noise(m.device)
        fallback = stated if isinstance(stated, DeviceNoise) else DeviceNoise.isotropic(stated)
        extra = {'measured': list(m.channels),
                 'still_seconds': round(m.sampling.duration_s, 3)}
        for name, ch in m.channels.items():
            extra[f'{name}_sigma_se'] = [float(v) for v in ch.principal_sigma_se]
        blocks[f'device_{m.device}'] = device_block(m.device_noise(fallback), topic,
                                                    m.frame_id, extra)
    return noise_document(blocks, 'measured (still parts)', recording)


def cmd_noise(args) -> int:
    """Measure both devices' noise in the still parts of a recording."""
    from coreg_ros.cli.options import settings_from_args
    from coreg_ros.core.noise.recording import measure_recording
    from coreg_ros.core.noise.text import format_noise_report, noise_report_dict
    from coreg_ros.files.atomic import write_json
    from coreg_ros.files.bag.posebag import read_pose_bag
    from coreg_ros.files.noise_file import write_noise_file

    out = sys.stderr if args.json == '-' else sys.stdout
    settings = settings_from_args(args)
    streams = read_pose_bag(args.bag, [settings.topic_a, *settings.topic_b])
    report = measure_recording(streams[settings.topic_a],
                               [streams[t] for t in settings.topic_b], settings.model,
                               (settings.topic_a, ' '.join(settings.topic_b)),
                               tuple(args.window) if args.window else None, args.precision)
    print(f'{PROG} noise: {args.bag}', file=out)
    print(format_noise_report(report), file=out)
    path = args.out or f'{str(args.bag).rstrip("/")}.noise.yaml'
    document = noise_file_document(report, settings, str(args.bag))
    write_noise_file(path, document)
    print(f'noise file written to {path} (use it with --noise {path})', file=out)
    data = dict(noise_report_dict(report), recording=str(args.bag), noise_file=str(path))
    if args.json == '-':
        print(json.dumps(data, indent=2))
    elif args.json:
        write_json(args.json, data)
        print(f'measurement written to {args.json}', file=out)
    if args.plot:
        from coreg_ros.report.noise_figure import write_noise_plot
        write_noise_plot(report, args.plot)
        print(f'plot written to {args.plot}', file=out)
    return 0


def register(sub) -> None:
    """Add the ``noise`` subcommand to the ``coreg`` subparsers."""
    from coreg_ros.core.noise.measure import DEFAULT_PRECISION
    from coreg_ros.core.types import MODELS

    p = sub.add_parser('noise', help="measure each device's noise where it stands still "
                                     '(3x3 covariances, Allan deviation) and write a noise file')
    p.add_argument('bag', help='rosbag2 directory (sqlite3 or mcap) with still parts')
    p.add_argument('--config', help='ROS parameter YAML (topics, model); flags win')
    p.add_argument('--topic-a', help='device A PoseStamped topic (default /device_a/pose)')
    p.add_argument('--topic-b', nargs='+', metavar='T',
                   help='device B topic(s); three for three_marker (default /device_b/pose)')
    p.add_argument('--model', choices=MODELS,
                   help="measurement model: B's orientation is measured for full_pose only")
    p.add_argument('--window', nargs=2, type=finite, metavar=('T0', 'T1'),
                   help="measure in this still part (s from the recording's first stamp) "
                        'instead of the still segments found')
    p.add_argument('--precision', type=positive, default=DEFAULT_PRECISION, metavar='P',
                   help='relative precision of σ to ask for when a recording is too short '
                        f'(default {DEFAULT_PRECISION:g})')
    p.add_argument('--out', metavar='FILE',
                   help='the noise file to write (default RECORDING.noise.yaml)')
    p.add_argument('--json', metavar='OUT', help='also write the measurement as JSON (-: stdout)')
    p.add_argument('--plot', metavar='PNG',
                   help='write the Allan deviation and per-axis σ of both devices as a PNG')
    # the calibration options settings_from_args reads, absent here
    p.set_defaults(func=cmd_noise, method=None, sigma_a=None, sigma_b=None, max_gap=None,
                   min_pairs=None)

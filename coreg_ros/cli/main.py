"""
The ``coreg`` command: offline calibration, simulation, and the ROS stand-in tools.

Every subcommand returns an exit code; a failure is one line on stderr saying what is wrong and
what to do (exit 1), never a traceback.
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
import sys
from typing import Any, Optional

from coreg_ros.cli.argtypes import finite, positive
from coreg_ros.core.errors import CoregError
from coreg_ros.core.types import METHODS, MODELS

PROG = 'coreg'
#: Exit code of ``coreg calibrate`` when the estimator converged but the fit does not match
#: the stated noise (or the prior disagrees): the result is printed and written, flagged.
EXIT_INCONSISTENT = 3


class OneLineParser(argparse.ArgumentParser):
    """ArgumentParser whose usage errors are one line and exit code 1."""

    def error(self, message: str):  # noqa: D102 - argparse API
        self.exit(1, f'{self.prog}: error: {message}; see {self.prog} --help\n')


def add_calibration_options(p: argparse.ArgumentParser, bag: bool = True) -> None:
    """Options shared by ``calibrate``, ``diagnose`` and ``batch``: topics, model, noise."""
    if bag:
        p.add_argument('bag', help='rosbag2 directory (sqlite3 or mcap)')
    p.add_argument('--config', help='ROS parameter YAML (e.g. config/coreg.yaml); flags win')
    p.add_argument('--topic-a', help='device A PoseStamped topic (default /device_a/pose)')
    p.add_argument('--topic-b', nargs='+', metavar='T',
                   help='device B PoseStamped topic(s); three for three_marker '
                        '(default /device_b/pose)')
    p.add_argument('--model', choices=MODELS, help='measurement model (default full_pose)')
    p.add_argument('--method', choices=METHODS, help='estimator (default tls)')
    p.add_argument('--sigma-a', nargs=2, type=positive, metavar=('POS_M', 'ROT_RAD'),
                   help='device A noise std: position m, rotation rad')
    p.add_argument('--sigma-b', nargs=2, type=positive, metavar=('POS_M', 'ROT_RAD'),
                   help='device B noise std: position m, rotation rad')
    p.add_argument('--max-gap', type=positive, metavar='S',
                   help='largest time from a B stamp to the A samples it is paired with, s')
    p.add_argument('--time-offset', type=offset_or_auto, metavar='auto|S',
                   help="B's clock minus A's clock: auto (default) estimates it jointly with "
                        "the transforms (starting from the config's time_offset); a number "
                        '(s) fixes it')
    p.add_argument('--clock-drift', choices=('auto', 'off'),
                   help='auto also estimates a linear clock drift (ppm); default off')
    p.add_argument('--robust', choices=('on', 'off'),
                   help='on (default) rejects pairs far outside the stated noise before the '
                        'final fit; off is plain least squares')
    p.add_argument('--min-pairs', type=int, help='fewest pairs accepted (default 30)')


def offset_or_auto(text: str):
    """``auto`` or a finite number of seconds (argparse type of --time-offset)."""
    if text.strip().lower() == 'auto':
        return 'auto'
    return finite(text)


def settings_from_args(args):
    """Build Settings from --config (if any), overridden by the flags given."""
    from coreg_ros.cli.files import load_parameters
    from coreg_ros.core.settings import Settings, settings_from_mapping

    settings = Settings()
    if args.config:
        settings = settings_from_mapping(load_parameters(args.config), settings)
    topic_b = tuple(args.topic_b) if args.topic_b else None
    if topic_b is None and args.model and args.model != settings.model:
        # the default B topic(s) follow the model unless given
        from coreg_ros.core.settings import DEFAULT_TOPIC_B, DEFAULT_TOPICS_B_THREE_MARKER
        topic_b = DEFAULT_TOPICS_B_THREE_MARKER if args.model == 'three_marker' \
            else DEFAULT_TOPIC_B
    offset = getattr(args, 'time_offset', None)
    drift = getattr(args, 'clock_drift', None)
    robust = getattr(args, 'robust', None)
    return settings.updated(
        topic_a=args.topic_a, topic_b=topic_b, model=args.model, method=args.method,
        sigma_a=tuple(args.sigma_a) if args.sigma_a else None,
        sigma_b=tuple(args.sigma_b) if args.sigma_b else None,
        max_gap=args.max_gap, min_pairs=args.min_pairs,
        time_offset=None if offset in (None, 'auto') else offset,
        estimate_time_offset=None if offset is None else offset == 'auto',
        estimate_clock_drift=None if drift is None else drift == 'auto',
        robust=None if robust is None else robust == 'on')


@dataclass
class CalibrationRun:
    """
    What ``coreg calibrate`` computes for one bag (``calibrate_bag``), before any printing.

    Attributes
    ----------
    result : CalibrationResult
    report : PairingReport
    check : DirectionReport or None
        The direction check after a bad fit (None when it did not run).
    data : dict
        The ``--json`` document: the result, pairing counts, settings, direction check.
    exit_code : int
        0 consistent, EXIT_INCONSISTENT fit not matching the noise, 1 refused (a stream the
        wrong way round, or the estimator failed).

    """

    result: Any
    report: Any
    check: Any
    data: dict
    exit_code: int

    @property
    def wrong_way(self) -> bool:
        """A stream fits far better inverted: the fit is refused."""
        return self.check is not None and self.check.flagged


def calibrate_bag(bag, settings, prior=None, frames=None,
                  direction_check: bool = True) -> CalibrationRun:
    """
    Read, pair and calibrate one recording as ``coreg calibrate --json`` does.

    Parameters
    ----------
    bag : str or Path
        rosbag2 directory.
    settings : Settings
    prior : optional
        A loaded prior (``load_prior``).
    frames : tuple, optional
        (frame_base_a, frame_base_b) for the swap check (``config_frames``).
    direction_check : bool
        Check the stream directions after a bad fit (``--no-direction-check`` turns it off).

    Raises
    ------
    CoregError
        The bag cannot be read, too few pairs, data refused as a whole (naming a stream given
        the wrong way round when that explains it).

    """
    from types import SimpleNamespace

    from coreg_ros.bag.posebag import read_pose_bag
    from coreg_ros.cli.convert import direction_guard
    from coreg_ros.core.directions import check_directions
    from coreg_ros.core.errors import InconsistentDataError
    from coreg_ros.core.pipeline import calibrate_streams
    from coreg_ros.core.result_io import result_to_dict

    streams = read_pose_bag(bag, [settings.topic_a, *settings.topic_b])
    stream_a, streams_b = streams[settings.topic_a], [streams[t] for t in settings.topic_b]
    try:
        result, report = calibrate_streams(stream_a, streams_b, settings, prior, frames=frames)
    except InconsistentDataError as e:
        # data refused as a whole: a stream given the wrong way round is a cheap explanation
        check = check_directions(stream_a, streams_b, settings) if direction_check else None
        if check is not None and check.flagged:
            raise InconsistentDataError(f'{check.message} ({e})') from e
        raise
    check = direction_guard(SimpleNamespace(no_direction_check=not direction_check), stream_a,
                            streams_b, settings, result)
    data = result_to_dict(result)
    data['pairing'] = {'n_a': report.n_a, 'n_b': report.n_b, 'n_paired': report.n_paired,
                       'unpaired': dict(report.unpaired)}
    data['settings'] = settings.as_dict()
    if check is not None:
        data['direction_check'] = check.as_dict()
    run = CalibrationRun(result, report, check, data, 0)
    if run.wrong_way or not (result.success or result.fit_consistent is False):
        run.exit_code = 1
    else:
        run.exit_code = 0 if result.success else EXIT_INCONSISTENT
    return run


def cmd_calibrate(args) -> int:
    """Calibrate a recording offline and print (and optionally write) the result."""
    import json

    from coreg_ros.cli.files import write_json
    from coreg_ros.core.result_io import load_prior
    from coreg_ros.core.result_text import format_result
    from coreg_ros.report.calibration_report import points_from_flat

    # `--json -` puts the JSON on stdout; the text for a person then goes to stderr
    out = sys.stderr if args.json == '-' else sys.stdout
    settings = settings_from_args(args)
    points = points_from_flat(args.points, args.report)  # checked before the long fit
    prior = load_prior(args.prior) if args.prior else None
    run = calibrate_bag(args.bag, settings, prior, frames=config_frames(args),
                        direction_check=not args.no_direction_check)
    result, report, check = run.result, run.report, run.check
    print(f'{PROG} calibrate: {args.bag}', file=out)
    if run.wrong_way:
        print(f'{PROG} calibrate: error: {check.message} (or --no-direction-check to fit the '
              f'data as given)', file=sys.stderr)
    else:
        print(format_result(result, report), file=out)
        if check is not None:
            print(f'direction check: {check.message}', file=out)
    if args.json:
        if args.json == '-':
            print(json.dumps(run.data, indent=2))
        else:
            write_json(args.json, run.data)
            print(f'result written to {args.json}', file=out)
    if args.report:
        from coreg_ros.report.calibration_report import write_calibration_report
        page = write_calibration_report(
            result, args.report, report=report, points=points,
            points_frame=args.points_frame, title=f'{PROG} calibrate {args.bag}')
        print(f'report written to {page}', file=out)
    return run.exit_code


def config_frames(args) -> tuple:
    """(frame_base_a, frame_base_b): from --config, else the node's defaults (swap check)."""
    from coreg_ros.core.config_schema import NODE_DEFAULTS
    values = {}
    if getattr(args, 'config', None):
        from coreg_ros.cli.files import load_parameters
        values = load_parameters(args.config)
    frames = tuple(values.get(k, NODE_DEFAULTS[k]) for k in ('frame_base_a', 'frame_base_b'))
    return frames if all(isinstance(f, str) and f for f in frames) else None


def cmd_simulate(args) -> int:
    """Write a simulated two-device recording and its ground truth beside it."""
    from coreg_ros.bag.posebag import write_pose_bag
    from coreg_ros.cli.files import write_json
    from coreg_ros.sim import simulate_recording

    kwargs = {}
    if args.sigma_a:
        kwargs['sigma_a'] = tuple(args.sigma_a)
    if args.sigma_b:
        kwargs['sigma_b'] = tuple(args.sigma_b)
    from coreg_ros.sim.changes import apply_changes, parse_change
    from coreg_ros.sim.effect_library import parse_effect
    effects = [parse_effect(text) for text in args.effect or ()]
    changes = [parse_change(text) for text in args.change or ()]
    rec = simulate_recording(args.seed, args.duration, args.model, rate_a=args.rate_a,
                             rate_b=args.rate_b, motion=args.motion, effects=effects, **kwargs)
    rec = apply_changes(rec, changes, seed=args.seed)
    write_pose_bag(args.out_bag, rec.streams, storage=args.storage)
    truth_path = truth_path_for(args.out_bag)
    truth = rec.truth.as_dict()
    truth.update({'seed': args.seed, 'duration': args.duration, 'motion': args.motion,
                  'rate_a': args.rate_a, 'rate_b': args.rate_b, 'topic_a': rec.topics_a,
                  'topic_b': list(rec.topics_b), 'storage': args.storage})
    write_json(truth_path, truth)
    counts = ', '.join(f'{t}: {len(s)}' for t, s in rec.streams.items())
    print(f'{PROG} simulate: wrote {args.out_bag} ({args.storage}; {counts}) and the ground '
          f'truth {truth_path}')
    return 0


def truth_path_for(bag) -> Path:
    """Where ``coreg simulate`` puts the ground truth: ``<bag>.truth.json`` beside the bag."""
    bag = Path(bag)
    return bag.with_name(bag.name + '.truth.json')


def build_parser() -> argparse.ArgumentParser:
    """Build the ``coreg`` argument parser with every subcommand."""
    parser = OneLineParser(prog=PROG, description=__doc__.strip().splitlines()[0])
    sub = parser.add_subparsers(dest='command', required=True, parser_class=OneLineParser)

    p = sub.add_parser('calibrate', help='calibrate a recording offline (Ikits OLS/TLS)')
    add_calibration_options(p)
    p.add_argument('--json', metavar='OUT',
                   help='also write the result as JSON (atomically); - for stdout')
    p.add_argument('--prior', metavar='FILE',
                   help="a previous result (--json output or the node's result.yaml) or a "
                        'partial prior (base_to_base / tool_to_marker with sigma per axis) '
                        'that this recording refines (Ikits B.3)')
    p.add_argument('--no-direction-check', action='store_true',
                   help='do not check, after a bad fit, whether a stream should be inverted')
    p.add_argument('--report', metavar='DIR',
                   help='also write an HTML report (ellipsoids, axis cones, residuals) to DIR')
    p.add_argument('--points', nargs='+', type=finite, metavar='X Y Z',
                   help="points (m) in A's base frame (or see --points-frame) at which the "
                        'report gives the registration error to expect')
    p.add_argument('--points-frame', choices=('a_base', 'a_tool'), default='a_base',
                   help="frame of --points: A's base (mapped into B's base by T0; default) or "
                        "A's tool (located in B's marker frame by T1⁻¹, e.g. a stylus tip)")
    p.set_defaults(func=cmd_calibrate)

    p = sub.add_parser('simulate', help='write a simulated two-device recording')
    p.add_argument('out_bag', help='rosbag2 directory to create')
    p.add_argument('--seed', type=int, required=True)
    p.add_argument('--duration', type=positive, required=True, metavar='SECONDS')
    p.add_argument('--storage', choices=('sqlite3', 'mcap'), default='sqlite3')
    p.add_argument('--model', choices=MODELS, default='full_pose')
    p.add_argument('--motion', default='diverse',
                   choices=('diverse', 'single_axis', 'no_rotation', 'static'))
    p.add_argument('--rate-a', type=positive, default=100.0, help='Hz (default 100)')
    p.add_argument('--rate-b', type=positive, default=50.0, help='Hz (default 50)')
    p.add_argument('--sigma-a', nargs=2, type=positive, metavar=('POS_M', 'ROT_RAD'))
    p.add_argument('--sigma-b', nargs=2, type=positive, metavar=('POS_M', 'ROT_RAD'))
    p.add_argument('--effect', action='append', metavar='NAME=VALUE',
                   help='inject an unmodelled effect (repeatable), e.g. time_offset=0.012 (s), '
                        'clock_drift=100 (ppm), timestamp_jitter=0.005 (s), '
                        'field_distortion=5 (mm), distance_noise=4 (exponent), scale=0.005, '
                        'link_flex=1 (mm), outliers=0.02, backlash=0.3 (mm), noise_scale=2')
    p.add_argument('--change', action='append', metavar='SPEC',
                   help='a change mid-recording (repeatable; TIME in s from the start): '
                        "t0_step=2mm@30 (A's base moves in B's base), t1_step=0.5deg@30 (the "
                        'marker slips on the tool), t0_step=1mm+0.2deg:z@45 (sizes add; axis '
                        "optional, else random), clock_step=0.01@30 (B's clock jumps, s or ms), "
                        "noise_step=2@30 (B's noise × 2)")
    p.set_defaults(func=cmd_simulate)

    # the other front ends add their own subcommands (each imports its heavy parts lazily)
    from coreg_ros.cli import batch, convert, diagnose, plan, ros_commands, watch
    for module in (diagnose, batch, convert, plan, ros_commands, watch):
        module.register(sub)
    return parser


def main(argv: Optional[Sequence[str]] = None) -> int:
    """Entry point of the ``coreg`` console script."""
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except CoregError as e:
        print(f'{PROG} {args.command}: error: {e}', file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f'{PROG} {args.command}: interrupted', file=sys.stderr)
        return 130
    except BrokenPipeError:
        # the reader (e.g. `| head`) went away: not an error of ours
        sys.stderr.close()
        return 0


if __name__ == '__main__':
    sys.exit(main())

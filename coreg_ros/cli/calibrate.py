"""
``coreg calibrate BAG``: read, pair and calibrate a recording offline; print and write the result.

``calibrate_bag`` is the whole job without printing (``coreg batch calibrate`` runs it per bag).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
import importlib
import sys
import threading
from typing import Any

from coreg_ros.cli.argtypes import finite, points_from_flat
from coreg_ros.cli.options import (
    add_calibration_options,
    add_check_options,
    add_prior_options,
    config_frames,
    EXIT_INCONSISTENT,
    prior_from_args,
    roles_confirmed,
    settings_and_devices,
)
from coreg_ros.cli.policy import exit_codes, PROG, with_flags


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
        0 consistent, EXIT_INCONSISTENT converged but flagged (the fit not matching the
        noise, a disagreeing prior, devices swapped without ``--roles-confirmed``), 1 refused
        (a stream the wrong way round, or the estimator failed).

    """

    result: Any
    report: Any
    check: Any
    data: dict
    exit_code: int

    @property
    def wrong_way(self) -> bool:
        """Tell whether a stream fits far better inverted (then the fit is refused)."""
        return self.check is not None and self.check.flagged


def calibrate_bag(bag, settings, prior=None, frames=None, direction_check: bool = True,
                  roles_confirmed: bool = False) -> CalibrationRun:
    """
    Read, pair and calibrate one recording as ``coreg calibrate --json`` does.

    Parameters
    ----------
    bag : str or Path
        rosbag2 directory.
    settings : Settings
        Topics, model, method, noise and the rest of the configuration.
    prior : optional
        A loaded prior (``load_prior``).
    frames : tuple, optional
        (frame_base_a, frame_base_b) for the swap check (``config_frames``).
    direction_check : bool
        Check the stream directions after a bad fit (``--no-direction-check`` turns it off;
        the check itself is the pipeline's, ``calibrate_streams``).
    roles_confirmed : bool
        ``--roles-confirmed``: frame ids that say the devices are swapped refuse nothing.

    Raises
    ------
    CoregError
        The bag cannot be read, too few pairs, data refused as a whole (naming a stream given
        the wrong way round when that explains it).

    """
    from coreg_ros.files.bag.posebag import read_pose_bag

    # the calibration's modules (SciPy among them: 0.2 s) are imported while SQLite reads the
    # bag outside Python's lock; a failed import fails again, with its error, below. Joined
    # in any case: no import outlives this call (a process forked later would inherit its lock)
    importer = threading.Thread(target=importlib.import_module, daemon=True,
                                args=('coreg_ros.core.calibration.pipeline',))
    importer.start()
    try:
        # the log times are the diagnosis's (coreg diagnose), not the calibration's: let go
        streams = {topic: replace(s, receive_stamps=None) for topic, s in
                   read_pose_bag(bag, [settings.topic_a, *settings.topic_b]).items()}
    finally:
        importer.join()
    from coreg_ros.core.calibration.pairing import validated_streams
    from coreg_ros.core.calibration.pipeline import calibrate_streams
    from coreg_ros.core.provenance import data_sketch
    from coreg_ros.files.results import result_to_dict
    from coreg_ros.threads import one_blas_thread

    sketch = data_sketch([streams[t] for t in settings.topic_b])  # --prior refuses the same
    # checked and normalised once here, and the samples as read let go: the pipeline takes
    # the validated streams as they are (a 4M-message recording's quaternions: 122 MiB)
    stream_a, streams_b = validated_streams(streams[settings.topic_a],
                                            [streams[t] for t in settings.topic_b],
                                            settings.model == 'full_pose')
    del streams
    # small products over many pairs: BLAS threads only spin (coreg_ros.threads); at 2M pairs
    # they took 2.5x the CPU time, and one thread gives the numbers bench/fingerprint.py checks;
    # this also covers the noise estimation's small products (noise: auto)
    with one_blas_thread():
        result, report = calibrate_streams(stream_a, streams_b, settings, prior, frames=frames,
                                           direction_check=direction_check,
                                           roles_confirmed=roles_confirmed)
    check = result.direction_check
    data = result_to_dict(result)
    data['data_sketch'] = sketch
    data['pairing'] = {'n_a': report.n_a, 'n_b': report.n_b, 'n_paired': report.n_paired,
                       'unpaired': dict(report.unpaired)}
    data['settings'] = settings.as_dict()
    if 'noise' not in data:  # the noise the fit was judged against, stated
        from coreg_ros.core.calibration.auto_noise import stated_noise
        from coreg_ros.core.calibration.noise_verdict import stated_noise_dict
        data['noise'] = stated_noise_dict(*stated_noise(settings))
    if check is not None:
        data['direction_check'] = check.as_dict()
    run = CalibrationRun(result, report, check, data, 0)
    if run.wrong_way or not (result.success or result.flagged):
        run.exit_code = 1
    else:
        run.exit_code = 0 if result.success else EXIT_INCONSISTENT
    return run


def cmd_calibrate(args) -> int:
    """Calibrate a recording offline and print (and optionally write) the result."""
    import json

    from coreg_ros.allocator import keep_memory_for_reuse
    from coreg_ros.core.result_text import format_result
    from coreg_ros.files.atomic import write_json
    from coreg_ros.files.output_paths import check_output_dir, check_output_file

    settings, devices = settings_and_devices(args)
    check_output_file(args.json, '--json')  # before the work, not after it
    keep_memory_for_reuse()  # a long recording's arrays: reused, not asked of the kernel again
    if devices:  # a rig: several devices B
        from coreg_ros.cli.rig_calibrate import run_rig
        return run_rig(args, settings, devices, config_frames(args))
    # `--json -` puts the JSON on stdout; the text for a person then goes to stderr
    out = sys.stderr if args.json == '-' else sys.stdout
    check_output_dir(args.report, '--report')
    points = points_from_flat(args.points, args.report)  # checked before the long fit
    prior = prior_from_args(args)
    run = calibrate_bag(args.bag, settings, prior, frames=config_frames(args),
                        direction_check=not args.no_direction_check,
                        roles_confirmed=roles_confirmed(args))
    result, report, check = run.result, run.report, run.check
    print(f'{PROG} calibrate: {args.bag}', file=out)
    if run.wrong_way:
        print(f'{PROG} calibrate: error: {check.message} (or --no-direction-check to fit the '
              f'data as given)', file=sys.stderr)
    else:
        print(with_flags(format_result(result, report)), file=out)  # `name` (--flag)
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


def register(sub) -> None:
    """Add ``calibrate`` to the ``coreg`` subparsers."""
    p = sub.add_parser('calibrate', help='calibrate a recording offline (Ikits OLS/TLS)',
                       epilog=exit_codes('calibrate'))
    add_calibration_options(p)
    p.add_argument('--json', metavar='OUT',
                   help='also write the result as JSON (atomically); - for stdout')
    add_prior_options(p, "a previous result (--json output or the node's result.yaml) or a "
                         'partial prior (base_to_base / tool_to_marker with sigma per axis) '
                         'that this recording refines (Ikits B.3)')
    p.add_argument('--shared-base', action='store_true',
                   help='the B topics are sensors of one device: one base (T0) and one clock '
                        'for all of them')
    p.add_argument('--loops', action='store_true',
                   help='a rig: also calibrate every two devices directly and check that the '
                        "rig's loops close, naming the device that is off")
    add_check_options(p)
    p.add_argument('--report', metavar='DIR',
                   help='also write an HTML report (ellipsoids, axis cones, residuals) to DIR')
    p.add_argument('--points', nargs='+', type=finite, metavar='X Y Z',
                   help="points (m) in A's base frame (or see --points-frame) at which the "
                        'report gives the registration error to expect')
    p.add_argument('--points-frame', choices=('a_base', 'a_tool'), default='a_base',
                   help="frame of --points: A's base (mapped into B's base by T0; default) or "
                        "A's tool (located in B's marker frame by T1⁻¹, e.g. a stylus tip)")
    p.set_defaults(func=cmd_calibrate)

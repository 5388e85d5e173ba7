"""
``coreg diagnose`` and ``coreg validate-diagnosis``: the sim-to-real gap diagnosis (issue 4).

``coreg diagnose BAG`` pairs and calibrates a recording as ``coreg calibrate`` does, then
detects, locates and explains the gap between it and the model with the stated noise
(``coreg_ros.core.diagnosis``), prints a summary, and optionally writes the JSON document and
an HTML report.

``coreg validate-diagnosis`` checks the diagnosis the way a user would trust it: it simulates
recordings with one random effect (or none) of a random size drawn from the realistic ranges
of docs/design.md §5, hides the truth, diagnoses them and scores the answers (confusion matrix,
false alarms on clean recordings, the size from which each effect is found).
"""

from __future__ import annotations

import argparse
import json
import sys
from typing import Optional

from coreg_ros.cli.argtypes import positive_int
from coreg_ros.cli.policy import PROG


class Progress:
    """A simple progress bar on stderr (only when stderr is a terminal, or forced)."""

    def __init__(self, label: str, enabled: Optional[bool] = None, width: int = 30):
        self.label = label
        self.enabled = sys.stderr.isatty() if enabled is None else enabled
        self.width = width
        self.last = -1.0

    def __call__(self, fraction: float, text: str = '') -> None:
        """Draw the bar at ``fraction`` (0..1) with a short text."""
        if not self.enabled:
            return
        fraction = min(max(float(fraction), 0.0), 1.0)
        filled = int(round(fraction * self.width))
        bar = '#' * filled + '.' * (self.width - filled)
        sys.stderr.write(f'\r{self.label} [{bar}] {fraction * 100:3.0f}% {text[:40]:<40}')
        if fraction >= 1.0:
            sys.stderr.write('\n')
        sys.stderr.flush()


# ----------------------------------------------------------------------------------- diagnose

def diagnose_bag(bag, settings, progress=None):
    """
    Read one recording and diagnose it as ``coreg diagnose --json`` does.

    Parameters
    ----------
    bag : str or Path
        rosbag2 directory.
    settings : Settings
        Topics, model and stated noise (``coreg diagnose``'s options).
    progress : callable, optional
        ``progress(fraction, text)`` of the diagnosis.

    Returns
    -------
    (Diagnosis, dict)
        The diagnosis (for the text and the HTML report) and its JSON document
        (``report.as_dict()`` with the settings and the bag path added).

    """
    from coreg_ros.core.diagnosis import diagnose_streams
    from coreg_ros.files.bag.posebag import read_pose_bag
    from coreg_ros.threads import one_blas_thread

    streams = read_pose_bag(bag, [settings.topic_a, *settings.topic_b])
    with one_blas_thread():  # small products: BLAS threads only spin (coreg_ros.threads)
        diag = diagnose_streams(streams[settings.topic_a],
                                [streams[t] for t in settings.topic_b], settings,
                                progress=progress)
    document = diag.report.as_dict()
    document['settings'] = settings.as_dict()
    document['bag'] = str(bag)
    return diag, document


def cmd_diagnose(args) -> int:
    """Diagnose the gap between a recording and the model with the stated noise."""
    from coreg_ros.cli.options import settings_from_args
    from coreg_ros.core.diagnosis.text import format_diagnosis
    from coreg_ros.files.atomic import write_json
    from coreg_ros.files.output_paths import check_output_dir, check_output_file

    check_output_file(args.json, '--json')  # before the work, not after it
    check_output_dir(args.report, '--report')
    settings = settings_from_args(args)
    progress = Progress(f'{PROG} diagnose', enabled=None if not args.quiet else False)
    diag, document = diagnose_bag(args.bag, settings, progress)
    report = diag.report
    print(f'{PROG} diagnose: {args.bag} ({report.n_pairs} pairs, '
          f'{report.duration_s:.1f} s, model {report.model})')
    print(format_diagnosis(report))
    if report.noise is not None:  # noise: auto, the floor the gap was measured against
        print('noise floor: estimated with the calibration (the stated noise beside it):')
        for s in report.noise['statements']:
            print(f"  {s['text']}")
    if args.json:
        write_json(args.json, document)
        print(f'diagnosis written to {args.json}')
    if args.report:
        from coreg_ros.report.html import write_report
        path = write_report(diag, args.report, title=f'coreg diagnose: {args.bag}')
        print(f'report written to {path}')
    return 0


class PlainProgress:
    """``progress(fraction, text)`` for a log: one line on stderr per tenth of the cases."""

    def __init__(self, label: str):
        self.label = label
        self.next = 0.1

    def __call__(self, fraction: float, text: str = '') -> None:
        """Print a line when ``fraction`` passes the next tenth."""
        if fraction + 1e-12 >= self.next:
            print(f'{self.label}: {text}', file=sys.stderr, flush=True)
            while self.next <= fraction + 1e-12:
                self.next += 0.1


def case_progress(label: str, quiet: bool):
    """
    Choose the progress of a many-case command: None, a no-op, or :class:`PlainProgress`.

    None lets ``coreg_ros.parallel.run_cases`` draw its rich bar (stderr is a terminal);
    ``--quiet`` is a no-op callback (no bar, no lines); a log gets a line per tenth.
    """
    if quiet:
        return lambda fraction, text='': None
    return None if sys.stderr.isatty() else PlainProgress(label)


def report_failures(command: str, failed: list) -> None:
    """One line per failed case on stderr (seed or bag, and the error)."""
    if failed:
        print(f'{PROG} {command}: {len(failed)} case(s) failed:', file=sys.stderr)
        for f in failed:
            print(f'  {f}', file=sys.stderr)


def cmd_validate(args) -> int:
    """Score the diagnosis on simulated recordings with hidden effects."""
    from coreg_ros.files.atomic import write_json
    from coreg_ros.files.output_paths import check_output_file
    from coreg_ros.parallel import CaseFailure, failures
    from coreg_ros.sim.validation import _jsonable, format_validation, validate

    check_output_file(args.json, '--json')
    progress = case_progress(f'{PROG} validate-diagnosis', args.quiet)
    noise = None
    if args.noise:
        from coreg_ros.files.noise_file import load_noise_file
        got = load_noise_file(args.noise)
        noise = {d: getattr(got, f'device_{d}') for d in 'ab'
                 if getattr(got, f'device_{d}') is not None}
    out = validate(args.cases, args.seed, progress, workers=args.workers,
                   scheduler=args.scheduler, noise=noise)
    failed = failures(out['results'])
    print(f'{PROG} validate-diagnosis: {args.cases} cases, seed {args.seed}'
          + (f', {len(failed)} failed' if failed else ''))
    print(format_validation(out['summary']))
    if args.json:
        doc = dict(out, results=[r.as_dict() if isinstance(r, CaseFailure) else r
                                 for r in out['results']])
        write_json(args.json, json.loads(json.dumps(doc, default=_jsonable)))
        print(f'validation written to {args.json}')
    report_failures('validate-diagnosis', failed)
    return 1 if failed else 0


def register(sub) -> None:
    """Add ``diagnose`` and ``validate-diagnosis`` to the ``coreg`` subparsers."""
    from coreg_ros.cli.argtypes import add_parallel_arguments
    from coreg_ros.cli.options import add_calibration_options
    from coreg_ros.cli.policy import exit_codes

    p = sub.add_parser('diagnose', help='detect, locate and explain the gap between a '
                                        'recording and the model (sim-to-real)',
                       epilog=exit_codes('diagnose'))
    add_calibration_options(p)
    p.add_argument('--json', metavar='OUT', help='also write the diagnosis as JSON')
    p.add_argument('--report', metavar='DIR', help='write an HTML report (index.html + PNGs)')
    p.add_argument('--quiet', action='store_true', help='no progress bar')
    p.set_defaults(func=cmd_diagnose)

    p = sub.add_parser('validate-diagnosis',
                       help='score the diagnosis on simulated recordings with hidden effects',
                       epilog=exit_codes('validate-diagnosis'))
    p.add_argument('--cases', type=positive_int, default=40, help='recordings (default 40)')
    p.add_argument('--seed', type=int, default=0, help='seed of the draws (default 0)')
    add_parallel_arguments(p)
    p.add_argument('--jobs', type=positive_int, dest='workers', default=argparse.SUPPRESS,
                   help=argparse.SUPPRESS)  # the old name of --workers
    p.add_argument('--json', metavar='OUT', help='also write every case and the summary')
    p.add_argument('--noise', metavar='FILE',
                   help='a noise file (coreg noise RECORDING): every case simulated and stated '
                        "with its devices' noise instead of the drawn one")
    p.add_argument('--quiet', action='store_true', help='no progress bar')
    p.set_defaults(func=cmd_validate)

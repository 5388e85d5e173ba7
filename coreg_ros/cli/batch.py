"""
``coreg batch calibrate|diagnose FOLDER --out DIR``: one command over a folder of recordings.

Finds every rosbag2 recording under FOLDER (a directory holding ``metadata.yaml``), runs on each
what ``coreg calibrate --json`` / ``coreg diagnose --json`` runs (``calibrate_bag`` /
``diagnose_bag``, the same functions), in local processes or on a Dask cluster
(``coreg_ros.parallel``), writes one JSON per bag into DIR plus ``summary.json``, and prints a
summary table. A bag that fails is a row with its one-line error; the others go on.

Exit code: 1 if any bag failed or was refused, else 3 if any calibration does not match the
stated noise (as ``coreg calibrate``), else 0.
"""

from __future__ import annotations

from pathlib import Path
import sys
import time

from coreg_ros.cli.policy import PROG
from coreg_ros.core.errors import ConfigError


def find_bags(folder) -> list[Path]:
    """
    Find every rosbag2 recording under ``folder`` (itself included), sorted by path.

    A recording is a directory with a ``metadata.yaml``; its own subfolders are not searched.

    Raises
    ------
    ConfigError
        ``folder`` is not a directory, or holds no recording.

    """
    root = Path(folder)
    if not root.is_dir():
        raise ConfigError(f'{folder} is not a directory; give the folder that holds the '
                          'recordings')
    bags = sorted({p.parent for p in root.rglob('metadata.yaml')})
    bags = [b for b in bags if not any(o in b.parents for o in bags)]
    if not bags:
        raise ConfigError(f'no rosbag2 recording (a folder with metadata.yaml) under {folder}; '
                          'record one with `ros2 bag record` or `coreg simulate`')
    return bags


def json_name(bag: Path, root: Path) -> str:
    """Name the file of a bag's JSON in the output folder: its path under ``root``, '/' -> '__'."""
    rel = bag.relative_to(root)
    name = '__'.join(rel.parts) if rel.parts else bag.resolve().name
    return name + '.json'


def calibrate_one(bag: str, settings, prior, frames, direction_check: bool,
                  roles_confirmed: bool = False) -> dict:
    """Run ``coreg calibrate --json`` on one bag; its document and a summary row."""
    from coreg_ros.cli.calibrate import calibrate_bag
    from coreg_ros.cli.options import EXIT_INCONSISTENT

    t0 = time.perf_counter()
    run = calibrate_bag(bag, settings, prior, frames=frames, direction_check=direction_check,
                        roles_confirmed=roles_confirmed)
    r = run.result
    if run.wrong_way:
        verdict = f'refused: {run.check.message}'
    elif run.exit_code == 0:
        verdict = 'consistent'
    elif run.exit_code == EXIT_INCONSISTENT and r.refusals:
        verdict = 'refused: ' + ', '.join(r.refusals).replace('_', ' ')
    elif run.exit_code == EXIT_INCONSISTENT:
        verdict = 'inconsistent with the stated noise'
    else:
        verdict = f'failed: {r.message}'
    return {'doc': run.data, 'pairs': int(run.report.n_paired),
            'chi2_dof': float(r.reduced_chi2), 'verdict': verdict,
            'exit_code': run.exit_code, 'seconds': time.perf_counter() - t0}


def diagnose_one(bag: str, settings) -> dict:
    """Run ``coreg diagnose --json`` on one bag; its document and a summary row."""
    from coreg_ros.cli.diagnose import diagnose_bag

    t0 = time.perf_counter()
    _, report = diagnose_bag(bag, settings)
    names = [e['name'] for e in report['effects']]
    verdict = ', '.join(names) or ('gap, not explained' if report['gap_detected'] else 'no gap')
    return {'doc': report, 'pairs': int(report['n_pairs']),
            'chi2_dof': float(report['gap_before'].get('chi2_per_dof', float('nan'))),
            'verdict': verdict, 'exit_code': 0, 'seconds': time.perf_counter() - t0}


def format_table(rows: list) -> str:
    """Format the summary as a text table: bag, pairs, chi2/dof, verdict, seconds, error."""
    head = ('bag', 'pairs', 'chi2/dof', 'verdict / effects', 'seconds', 'error')
    cells = [head]
    for r in rows:
        cells.append((r['bag'], '' if r['pairs'] is None else str(r['pairs']),
                      '' if r['chi2_dof'] is None else f'{r["chi2_dof"]:.3g}',
                      r['verdict'] or '', '' if r['seconds'] is None else f'{r["seconds"]:.1f}',
                      r['error'] or ''))
    widths = [max(len(c[i]) for c in cells) for i in range(len(head) - 1)]
    return '\n'.join('  '.join(c[i].ljust(widths[i]) for i in range(len(head) - 1))
                     + '  ' + c[-1] for c in cells).rstrip()


def _jsonable(o):
    import numpy as np

    if isinstance(o, (np.floating, np.integer, np.bool_)):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    return str(o)


def cmd_batch(args) -> int:
    """Calibrate or diagnose every recording under a folder, in parallel."""
    import json

    from coreg_ros.cli.diagnose import case_progress
    from coreg_ros.cli.options import config_frames, settings_from_args
    from coreg_ros.files.atomic import write_json
    from coreg_ros.files.output_paths import check_output_dir
    from coreg_ros.parallel import CaseFailure, run_cases

    root = Path(args.folder)
    bags = find_bags(root)
    check_output_dir(args.out, '--out')
    settings = settings_from_args(args)
    if args.what == 'calibrate':
        from coreg_ros.cli.options import prior_from_args, roles_confirmed
        prior = prior_from_args(args)
        fn, extra = calibrate_one, (settings, prior, config_frames(args),
                                    not args.no_direction_check, roles_confirmed(args))
    else:
        fn, extra = diagnose_one, (settings,)
    out_dir = Path(args.out)
    out_dir.mkdir(parents=True, exist_ok=True)
    label = f'{PROG} batch {args.what}'
    results = run_cases(fn, [str(b) for b in bags], args=extra, workers=args.workers,
                        scheduler=args.scheduler, progress=case_progress(label, args.quiet),
                        label=str, title=label)
    rows = []
    for bag, res in zip(bags, results, strict=True):
        path = out_dir / json_name(bag, root)
        row = {'bag': str(bag.relative_to(root)) if bag != root else str(bag),
               'json': str(path), 'pairs': None, 'chi2_dof': None, 'verdict': None,
               'seconds': None, 'error': None, 'exit_code': 1}
        if isinstance(res, CaseFailure):
            row.update(error=res.error, verdict='error')
            doc = {'bag': str(bag), 'error': res.error}
        else:
            doc = res.pop('doc')
            row.update(res)
        write_json(path, json.loads(json.dumps(doc, default=_jsonable)))
        rows.append(row)
    write_json(out_dir / 'summary.json', json.loads(json.dumps(
        {'command': args.what, 'folder': str(root), 'bags': rows}, default=_jsonable)))
    print(f'{label}: {len(bags)} recording(s) under {root}, JSON in {out_dir}')
    print(format_table(rows))
    failed = [r for r in rows if r['exit_code'] == 1]
    if failed:
        print(f'{label}: {len(failed)} of {len(rows)} recording(s) failed', file=sys.stderr)
        return 1
    return 3 if any(r['exit_code'] == 3 for r in rows) else 0


def register(sub) -> None:
    """Add ``batch calibrate`` and ``batch diagnose`` to the ``coreg`` subparsers."""
    from coreg_ros.cli.argtypes import add_parallel_arguments
    from coreg_ros.cli.options import add_calibration_options
    from coreg_ros.cli.policy import exit_codes

    p = sub.add_parser('batch', help='calibrate or diagnose every recording under a folder, '
                                     'in parallel (a JSON per bag and a summary table)',
                       epilog=exit_codes('batch'))
    what = p.add_subparsers(dest='what', required=True, parser_class=type(p))
    for name, text in (('calibrate', 'run `coreg calibrate --json` on every recording'),
                       ('diagnose', 'run `coreg diagnose --json` on every recording')):
        q = what.add_parser(name, help=text, description=text, epilog=exit_codes('batch'))
        q.add_argument('folder', help='folder searched for rosbag2 recordings (metadata.yaml)')
        q.add_argument('--out', required=True, metavar='DIR',
                       help='folder for one JSON per recording and summary.json')
        add_parallel_arguments(q)
        q.add_argument('--quiet', action='store_true', help='no progress bar')
        add_calibration_options(q, bag=False)
        if name == 'calibrate':
            from coreg_ros.cli.options import add_prior_options
            add_prior_options(q, 'a previous result or partial prior, the same for every bag')
            from coreg_ros.cli.options import add_check_options
            add_check_options(q)
        q.set_defaults(func=cmd_batch)

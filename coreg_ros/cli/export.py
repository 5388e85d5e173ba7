"""
``coreg export``: a calibration as a ROS system reads it.

From a ``coreg calibrate --json`` result or a node's ``result_*.yaml`` (or a file this command
wrote): the ``ros2 run tf2_ros static_transform_publisher`` lines (``static-tf``, the
default), a ``launch.py`` starting them (``launch``), URDF links and joints (``urdf``), or the
calibration with its covariance, verdict, clock offset, date and configuration as YAML or
JSON (``yaml``, ``json``), which ``--prior`` and the node's ``prior_file`` read back.
"""

from __future__ import annotations

import sys

FORMATS = ('static-tf', 'launch', 'urdf', 'yaml', 'json')


def render(doc: dict, fmt: str, base_parent: str = 'b') -> str:
    """
    Return the export document in one of ``FORMATS`` as text.

    Parameters
    ----------
    doc : dict
        The export document (``coreg_ros.files.export``).
    fmt : str
        One of ``FORMATS``.
    base_parent : str
        T0's parent base in the tf2 formats: ``'b'`` (the node's /tf_static) or ``'a'``.

    """
    import json

    from coreg_ros.files import tf_snippets

    if fmt == 'json':
        return json.dumps(doc, indent=2) + '\n'
    if fmt == 'yaml':
        import yaml

        head = ''.join(f'# {note}\n' for note in tf_snippets.notes(doc))
        return (head + "# T0 base_to_base: pose of A's base in B's base; T1 tool_to_marker: pose "
                "of B's marker in A's tool\n# read back by: coreg calibrate BAG --prior FILE, "
                "the node's prior_file, coreg export FILE\n"
                + yaml.safe_dump(doc, sort_keys=False))
    return {'static-tf': tf_snippets.static_tf, 'launch': tf_snippets.launch,
            'urdf': tf_snippets.urdf}[fmt](doc, base_parent)


def cmd_export(args) -> int:
    """Run ``coreg export`` (see the module docstring)."""
    from coreg_ros.core.errors import InputError
    from coreg_ros.files.atomic import write_atomic
    from coreg_ros.files.export import load_export

    frames = {'base_a': args.frame_base_a, 'base_b': args.frame_base_b,
              'tool': args.frame_tool, 'marker': args.frame_marker}
    doc = load_export(args.result, frames)
    fit = doc['fit']
    if not fit.get('success') and not args.force:
        raise InputError(
            f'{args.result} is no successful calibration ('
            f'{fit.get("verdict") or fit.get("message") or "the fit failed"}); its transforms '
            f'are not to be trusted: recalibrate, or add --force to export them all the same')
    text = render(doc, args.format, args.base_parent)
    if args.out in (None, '-'):
        sys.stdout.write(text)
    else:
        path = write_atomic(args.out, text)
        print(f'{args.format} written to {path}', file=sys.stderr)
    return 0


def register(sub) -> None:
    """Add ``export`` to the ``coreg`` subparsers."""
    p = sub.add_parser('export', help='a calibration as tf2 static publishers, a launch file, '
                                      'URDF, YAML or JSON',
                       description='A calibration as a ROS system reads it, from a coreg '
                                   "calibrate --json result or a node's result_*.yaml: tf2 "
                                   'static transform publishers (their command lines or a '
                                   'launch file), URDF, or YAML/JSON that --prior reads back. '
                                   'Directions and formats: docs/tf.md.')
    p.add_argument('result', metavar='RESULT',
                   help="a `coreg calibrate --json` result or a node's result_*.yaml")
    p.add_argument('--format', choices=FORMATS, default='static-tf',
                   help='static-tf: ros2 run tf2_ros static_transform_publisher lines '
                        '(default); launch: a launch.py starting them; urdf: links and fixed '
                        'joints; yaml, json: the calibration, readable by --prior')
    p.add_argument('--out', metavar='FILE',
                   help='write to FILE (atomically) instead of stdout')
    for key, what in (('base_a', "A's base"), ('base_b', "B's base"), ('tool', "A's tool"),
                      ('marker', "B's marker")):
        p.add_argument(f'--frame-{key.replace("_", "-")}', metavar='ID',
                       help=f"frame id of {what} (default: the result's, a node's "
                            f"frame_{key}; for a --json result the node's default)")
    p.add_argument('--base-parent', choices=('b', 'a'), default='b',
                   help="T0's parent frame in static-tf, launch and urdf: b: B's base -> A's "
                        "base, as the node's /tf_static (default); a: A's base -> B's base "
                        "(the inverse, e.g. for a robot description rooted at A's base)")
    p.add_argument('--force', action='store_true',
                   help='export a calibration that was not a success (marked so in the output)')
    p.set_defaults(func=cmd_export)

"""
``coreg calibrate`` of a rig: device A and several devices B_k from one recording, jointly.

``calibrate_rig_bag`` is the whole job without printing; ``run_rig`` prints the rig's text (every
device, the relative poses of their bases, the loop report) and writes ``--json``.
"""

from __future__ import annotations

import sys

from coreg_ros.cli.options import EXIT_INCONSISTENT
from coreg_ros.cli.policy import PROG


def calibrate_rig_bag(bag, settings, specs, frames=None, loops: bool = False):
    """
    Read the rig's topics from ``bag`` and calibrate it (``core.rig.pipeline``).

    Returns
    -------
    rig : RigResult
    data : dict
        The ``--json`` document (``files.rig_results.rig_to_dict`` and the settings).
    exit_code : int
        0 consistent, ``EXIT_INCONSISTENT`` a fit that does not match its stated noise.

    """
    from coreg_ros.core.rig.pipeline import calibrate_rig
    from coreg_ros.files.bag.posebag import read_pose_bag
    from coreg_ros.files.rig_results import rig_to_dict

    topics = [settings.topic_a] + [t for s in specs for t in s.topics]
    streams = read_pose_bag(bag, topics)
    devices = [s.with_streams([streams[t] for t in s.topics]) for s in specs]
    rig = calibrate_rig(streams[settings.topic_a], devices, settings, frames=frames,
                        loops=loops)
    data = rig_to_dict(rig)
    data['settings'] = {**settings.as_dict(), 'devices': [
        {'name': s.name, 'topics': list(s.topics), 'model': s.model,
         'sigma': None if s.sigma is None else list(s.sigma), 'base': s.base or s.name}
        for s in specs]}
    code = 0 if rig.success else (EXIT_INCONSISTENT if rig.status > 0 else 1)
    return rig, data, code


def run_rig(args, settings, specs, frames) -> int:
    """Calibrate the rig of ``coreg calibrate``, print it and write ``--json``."""
    import json

    from coreg_ros.core.errors import ConfigError
    from coreg_ros.files.atomic import write_json

    for flag in ('prior', 'report', 'points'):
        if getattr(args, flag, None):
            raise ConfigError(f'--{flag} applies to one device B; calibrate that device alone '
                              f'(--topic-b with one topic) for it')
    if getattr(args, 'gravity_aligned', None) is not None:
        raise ConfigError('--gravity-aligned applies to one device B; calibrate that device '
                          'alone (--topic-b with one topic) for it')
    if settings.noise != 'stated' or settings.noise_a is not None or settings.noise_b is not None:
        raise ConfigError("--noise (and a noise_file) applies to one device B; give a rig's "
                          "noise as each device's sigma (device.<name>.sigma) and --sigma-a, "
                          'or calibrate a device alone (--topic-b with one topic) with --noise')
    out = sys.stderr if args.json == '-' else sys.stdout
    rig, data, code = calibrate_rig_bag(args.bag, settings, specs, frames,
                                        loops=getattr(args, 'loops', False))
    print(f'{PROG} calibrate: {args.bag}', file=out)
    print(rig.summary(), file=out)
    if args.json:
        if args.json == '-':
            print(json.dumps(data, indent=2))
        else:
            write_json(args.json, data)
            print(f'result written to {args.json}', file=out)
    return code

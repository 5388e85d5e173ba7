"""``coreg simulate OUT_BAG``: a seeded two-device recording with its ground truth beside it."""

from __future__ import annotations

from pathlib import Path

from coreg_ros.cli.argtypes import add_sigma_arguments, add_storage_option, positive
from coreg_ros.cli.policy import PROG
from coreg_ros.core.types import MODELS


def cmd_simulate(args) -> int:
    """Write a simulated two-device recording and its ground truth beside it."""
    from coreg_ros.files.atomic import write_json
    from coreg_ros.files.bag.posebag import write_pose_bag
    from coreg_ros.files.output_paths import check_new_bag, check_output_file
    from coreg_ros.sim import simulate_recording

    check_new_bag(args.out_bag, 'OUT_BAG')  # before simulating, not after it
    check_output_file(truth_path_for(args.out_bag), 'the ground truth')
    kwargs = {}
    if args.sigma_a:
        kwargs['sigma_a'] = tuple(args.sigma_a)
    if args.sigma_b:
        kwargs['sigma_b'] = tuple(args.sigma_b)
    from coreg_ros.sim.changes import apply_changes, parse_change
    from coreg_ros.sim.injected import parse_effect
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


def register(sub) -> None:
    """Add ``simulate`` to the ``coreg`` subparsers."""
    from coreg_ros.sim.devices import DEFAULT_SIGMA_A, DEFAULT_SIGMA_B

    p = sub.add_parser('simulate', help='write a simulated two-device recording')
    p.add_argument('out_bag', help='rosbag2 directory to create')
    p.add_argument('--seed', type=int, required=True,
                   help='seed of every random draw: the same seed, the same recording')
    p.add_argument('--duration', type=positive, required=True, metavar='SECONDS',
                   help='length of the recording, s')
    add_storage_option(p)
    p.add_argument('--model', choices=MODELS, default='full_pose',
                   help='what device B measures (default full_pose)')
    from coreg_ros.sim.motion import MOTION_PRESETS
    p.add_argument('--motion', default='diverse', choices=MOTION_PRESETS,
                   help='what device A can do (default diverse); scara, planar, gantry and '
                        'turntable are rigs that cannot move in every direction')
    p.add_argument('--rate-a', type=positive, default=100.0, help='Hz (default 100)')
    p.add_argument('--rate-b', type=positive, default=50.0, help='Hz (default 50)')
    add_sigma_arguments(p, (DEFAULT_SIGMA_A, DEFAULT_SIGMA_B))
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

"""
``coreg plan``: predict a calibration's accuracy before recording, and what motion would help.

Without data (``--duration S --motion PRESET``) the preset motion is simulated with a random
truth; with a recording (``--bag BAG``) device A's recorded motion is used, at B's pair instants
when B is in the bag, and the bound is evaluated at a calibration of the bag when one succeeds
(else at a random truth). The prediction is the Cramér-Rao bound of the errors-in-variables
model (``coreg_ros.core.planning.plan``).
"""

from __future__ import annotations

from coreg_ros.cli.argtypes import add_sigma_arguments, positive
from coreg_ros.cli.options import add_noise_option
from coreg_ros.core.types import MODELS
import numpy as np


def register(subparsers) -> None:
    """Add the ``plan`` subcommand to the ``coreg`` subparsers."""
    p = subparsers.add_parser(
        'plan', help='predict the calibration accuracy (Cramér-Rao bound) and the best '
                     'motion to add')
    add_sigma_arguments(p)
    add_noise_option(p, auto=False)
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument('--bag', help='a recording whose device A motion is used')
    src.add_argument('--duration', type=positive, metavar='S',
                     help='simulate a recording of this length (with --motion)')
    from coreg_ros.sim.motion import MOTION_PRESETS
    p.add_argument('--motion', choices=MOTION_PRESETS, default='diverse',
                   help='motion preset simulated with --duration (default diverse)')
    p.add_argument('--model', choices=MODELS, default='full_pose',
                   help='what device B will measure (default full_pose)')
    p.add_argument('--rate-b', type=positive, metavar='HZ',
                   help="pairs per second, device B's rate (default 50; with --bag and B "
                        'in it, the recorded pairs)')
    p.add_argument('--topic-a', default=None, help='device A topic in the bag')
    p.add_argument('--topic-b', nargs='+', metavar='T', help='device B topic(s) in the bag')
    p.add_argument('--extra', type=positive, default=0.5,
                   help='recording time each candidate adds, as a fraction (default 0.5)')
    p.add_argument('--seed', type=int, default=0,
                   help='seed of the random truth and simulated motion (default 0)')
    p.add_argument('--json', metavar='OUT', help='also write the prediction as JSON')
    p.set_defaults(func=cmd_plan)


def _motion_from_bag(args, settings, cov_a, cov_b):
    """A's poses at the pair instants, the pair rate, and a calibration estimate if possible."""
    from coreg_ros.core.calibration.calibrate import calibrate
    from coreg_ros.core.calibration.pairing import pair_for
    from coreg_ros.core.errors import CoregError, InputError
    from coreg_ros.files.bag.posebag import list_topics, read_pose_bag

    topics = list_topics(args.bag)
    if settings.topic_a not in topics:
        raise InputError(f'bag {args.bag} has no topic {settings.topic_a}; pass --topic-a '
                         f'(topics: {", ".join(sorted(topics))})')
    have_b = all(t in topics for t in settings.topic_b)
    streams = read_pose_bag(args.bag, [settings.topic_a] + (list(settings.topic_b)
                                                            if have_b else []))
    a = streams[settings.topic_a]
    if len(a) < 2:
        raise InputError(f'topic {settings.topic_a} has {len(a)} sample(s); record longer')
    span = float(a.stamps[-1] - a.stamps[0]) * 1e-9
    estimate, note = None, ''
    if have_b:
        pairs, _ = pair_for(a, [streams[t] for t in settings.topic_b], settings)
        pos, q = np.asarray(pairs.pos_a), np.asarray(pairs.quat_a)
        rate = args.rate_b or (len(pos) / span if span > 0 else 50.0)
        try:
            estimate = calibrate(pairs, settings, cov_a=cov_a, cov_b=cov_b)
            note = 'bound at the calibration of the bag'
        except CoregError as e:
            note = f'the bag does not calibrate ({e}); bound at a random truth'
        source = f'{args.bag}: device A at the {len(pos)} paired instants of B'
    else:
        rate = args.rate_b or 50.0
        step = max(1, int(round(len(a) / max(span, 1e-9) / rate)))
        pos, q = a.position[::step], a.quat_wxyz[::step]
        source = (f'{args.bag}: device A resampled to {rate:g} Hz ({len(pos)} instants; B not '
                  'in the bag)')
        note = 'bound at a random truth'
    return pos, q, rate, estimate, source, note


def cmd_plan(args) -> int:
    """Predict the calibration accuracy and rank candidate additions to the motion."""
    from coreg_ros.cli.options import noise_from_args
    from coreg_ros.core.errors import ConfigError
    from coreg_ros.core.planning.plan import check_plan_memory, plan_recording
    from coreg_ros.core.settings import Settings
    from coreg_ros.files.atomic import write_json
    from coreg_ros.files.output_paths import check_output_file
    from coreg_ros.sim import make_motion, random_truth

    check_output_file(args.json, '--json')
    settings = Settings(model=args.model)
    if args.topic_a or args.topic_b:
        settings = settings.updated(topic_a=args.topic_a,
                                    topic_b=tuple(args.topic_b) if args.topic_b else None)
    settings = noise_from_args(args, settings.updated(
        sigma_a=tuple(args.sigma_a) if args.sigma_a else None,
        sigma_b=tuple(args.sigma_b) if args.sigma_b else None))
    for d in 'ab':
        if getattr(args, f'sigma_{d}') is None and getattr(settings, f'noise_{d}') is None:
            raise ConfigError(f"device {d.upper()}'s noise is needed: give --sigma-{d} POS_M "
                              f'ROT_RAD, or --noise FILE (coreg noise RECORDING writes one)')
    if settings.noise == 'auto':
        raise ConfigError('coreg plan takes the noise as stated: give --noise FILE or '
                          "--sigma-a/--sigma-b (a recording's noise: coreg noise RECORDING)")
    cov_a, cov_b = settings.cov_a, settings.cov_b
    rng = np.random.default_rng(args.seed)
    truth = random_truth(rng, args.model)
    if args.bag:
        pos, q, rate, estimate, source, note = _motion_from_bag(args, settings, cov_a, cov_b)
    else:
        rate = args.rate_b or 50.0
        check_plan_memory(args.duration * rate, args.extra,
                          f'a plan of {args.duration:g} s at {rate:g} Hz',
                          '--duration, --rate-b or --extra')
        motion = make_motion(rng, args.motion)
        n = max(2, int(round(args.duration * rate)))
        pos, q = motion.pose(np.arange(n) / rate)
        estimate = None
        source = f"motion preset '{args.motion}' simulated for {args.duration:g} s at " \
                 f'{rate:g} Hz ({n} pairs)'
        note = f'bound at a random truth (seed {args.seed})'
    if estimate is not None:
        p0, q0 = estimate.base_to_base.position, estimate.base_to_base.quat_wxyz
        markers = estimate.markers
    else:
        p0, q0, markers = truth.p0, truth.q0, truth.markers
    plan = plan_recording(args.model, p0, q0, markers, pos, q, cov_a, cov_b, rate, args.extra)
    print(format_plan(plan, source, note, args.model))
    if args.json:
        write_json(args.json, plan_to_dict(plan, source, note))
        print(f'plan written to {args.json}')
    return 0


def _sd_text(pred, name: str) -> str:
    s = pred.sigma[name]
    if name.startswith('theta'):
        return f'[{", ".join(f"{np.degrees(v):.4f}" for v in s)}] °'
    return f'[{", ".join(f"{v * 1e3:.3f}" for v in s)}] mm'


MEANING = {'p0': "T0 position (A's base in B's base)", 'theta0': 'T0 rotation',
           'p1': "T1 position (B's marker in A's tool)", 'theta1': 'T1 rotation',
           'p2': 'marker 2 position', 'p3': 'marker 3 position'}


def _reg_text(pred) -> str:
    pos, rot = pred.registration_rms
    out = f'{pos * 1e3:.3f} mm'
    if np.isfinite(rot):
        out += f', {np.degrees(rot):.4f} °'
    return out


def format_plan(plan, source: str, note: str, model: str) -> str:
    """Render a plan for a person."""
    out = [f'motion: {source}', f'model {model}; {note}',
           'predicted 1σ accuracy (Cramér-Rao bound of the errors-in-variables model):']
    base = plan.baseline.prediction
    if base is None:
        out.append('  UNOBSERVABLE: this motion determines nothing (the tool does not move)')
    else:
        for name in base.sigma:
            out.append(f'  {MEANING[name]:<38} σ {_sd_text(base, name)}')
        out.append(f"  registration of B's marker from A (RMS over the workspace): "
                   f'{_reg_text(base)}')
        name, axis, sd = base.worst()
        out.append(f'  weakest: {MEANING[name]}, {"xyz"[axis]} axis, σ {sd * 1e3:.3f} mm')
        for _, words, determine in base.unobservable:
            out.append(f'  unobservable with this motion (the calibration holds it; σ above are '
                       f'of the rest): {words}; to determine it: {determine}')
    rms = plan.rotation_spread
    out.append(f'rotation excited about the tool axes: RMS {np.degrees(rms[0]):.1f}°, '
               f'{np.degrees(rms[1]):.1f}°, {np.degrees(rms[2]):.1f}° (least about '
               f'[{", ".join(f"{v:+.2f}" for v in plan.weakest_axis)}])')
    out.append('what would improve it most (each candidate adds the same time; registration '
               'RMS over the recorded workspace):')
    for i, c in enumerate(plan.candidates):
        pred = c.prediction
        if pred is None:
            out.append(f'  {i + 1}. {c.description}: still unobservable')
            continue
        gain = 'makes it observable' if not np.isfinite(c.gain) else f'×{c.gain:.2f} better'
        if base is not None and len(pred.unobservable) < len(base.unobservable):
            gain += ('; determines what this motion leaves unobservable, if the rig can make '
                     'it')
        worst = max((k for k in pred.sigma if k.startswith('p')),
                    key=lambda k: float(np.max(pred.sigma[k])))
        out.append(f'  {i + 1}. {c.description}: registration {_reg_text(pred)} ({gain}); '
                   f'worst σ {MEANING[worst]} {float(np.max(pred.sigma[worst])) * 1e3:.3f} mm')
    return '\n'.join(out)


def plan_to_dict(plan, source: str, note: str) -> dict:
    """JSON-friendly plan: σ in m and rad, registration RMS [m, rad]."""
    def pred_dict(pred):
        if pred is None:
            return None
        return {'n_pairs': pred.n_pairs, 'duration': pred.duration,
                'sigma': {k: v.tolist() for k, v in pred.sigma.items()},
                'registration_rms': [float(v) for v in pred.registration_rms],
                'unobservable': [{'direction': [float(v) for v in u], 'description': words,
                                  'determine': determine}
                                 for u, words, determine in pred.unobservable]}

    return {'source': source, 'note': note,
            'baseline': pred_dict(plan.baseline.prediction),
            'weakest_axis': plan.weakest_axis.tolist(),
            'rotation_spread': plan.rotation_spread.tolist(),
            'candidates': [{'name': c.name, 'description': c.description,
                            'gain': c.gain if np.isfinite(c.gain) else None,
                            'prediction': pred_dict(c.prediction)} for c in plan.candidates]}

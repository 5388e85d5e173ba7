"""
What the ``coreg`` subcommands share: the parser class, the calibration options and the settings.

Every subcommand module has ``register(subparsers)``; the options a user types the same way
everywhere are defined once here.
"""

from __future__ import annotations

import argparse

from coreg_ros.cli.argtypes import add_sigma_arguments, finite, positive
from coreg_ros.core.settings import Settings
from coreg_ros.core.types import METHODS, MODELS

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
                        '(default /device_b/pose); several with full_pose or position_only: '
                        'a rig, one device per topic, calibrated jointly')
    p.add_argument('--model', choices=MODELS, help='measurement model (default full_pose)')
    p.add_argument('--method', choices=METHODS, help='estimator (default tls)')
    default = Settings()
    add_sigma_arguments(p, (default.sigma_a, default.sigma_b))
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
    add_noise_option(p)


def add_noise_option(p: argparse.ArgumentParser, auto: bool = True) -> None:
    """Add ``--noise FILE|auto`` (``noise_from_args``)."""
    p.add_argument('--noise', metavar='FILE|auto' if auto else 'FILE',
                   help='a noise file (coreg noise RECORDING): 3x3 covariances per device '
                        'in its base frame, instead of --sigma-a/--sigma-b'
                        + ("; auto estimates each device's noise with the calibration (what "
                           'the motion cannot separate held at the stated noise) and says '
                           'which device was noisier than stated' if auto else ''))


def offset_or_auto(text: str):
    """``auto`` or a finite number of seconds (argparse type of --time-offset)."""
    if text.strip().lower() == 'auto':
        return 'auto'
    return finite(text)


def settings_from_args(args):
    """Build Settings from --config (if any), overridden by the flags given."""
    from coreg_ros.core.settings import Settings, settings_from_mapping
    from coreg_ros.files.parameters import load_parameters

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
    settings = settings.updated(
        topic_a=args.topic_a, topic_b=topic_b, model=args.model, method=args.method,
        sigma_a=tuple(args.sigma_a) if args.sigma_a else None,
        sigma_b=tuple(args.sigma_b) if args.sigma_b else None,
        max_gap=args.max_gap, min_pairs=args.min_pairs,
        time_offset=None if offset in (None, 'auto') else offset,
        estimate_time_offset=None if offset is None else offset == 'auto',
        estimate_clock_drift=None if drift is None else drift == 'auto',
        robust=None if robust is None else robust == 'on')
    return noise_from_args(args, settings)


def noise_from_args(args, settings):
    """
    Return the settings with ``--noise`` applied (and the ``--config`` file's ``noise_file``).

    ``auto`` (or ``stated``) sets ``Settings.noise``; a file gives the devices' full noise
    (``files.noise_file.with_noise_file``: units, topics and covariances checked). A device
    whose noise both the file and ``--sigma-a``/``--sigma-b`` give is refused: say it once.
    """
    from coreg_ros.core.errors import ConfigError
    from coreg_ros.core.settings import NOISE_MODES

    given = getattr(args, 'noise', None)
    path = None
    if given is not None and given.strip().lower() in NOISE_MODES:
        settings = settings.updated(noise=given.strip().lower())
    elif given:
        path = given
    if path is None and getattr(args, 'config', None):
        from coreg_ros.files.parameters import load_parameters
        path = load_parameters(args.config).get('noise_file') or None
    if path is None:
        return settings
    from coreg_ros.files.noise_file import load_noise_file, with_noise_file
    noise = load_noise_file(path)
    for d in 'ab':
        if getattr(args, f'sigma_{d}', None) and getattr(noise, f'device_{d}') is not None:
            raise ConfigError(f'--sigma-{d} and the noise file {path} both give device '
                              f"{d.upper()}'s noise: give it once (drop --sigma-{d}, or "
                              f'the file)')
    return with_noise_file(settings, noise)


def _config_values(args) -> dict:
    """Return the checked parameters of --config ({} without one)."""
    if not getattr(args, 'config', None):
        return {}
    from coreg_ros.files.parameters import load_parameters
    return load_parameters(args.config)


def config_frames(args) -> tuple:
    """(frame_base_a, frame_base_b): from --config, else the node's defaults (swap check)."""
    from coreg_ros.core.config_schema import NODE_DEFAULTS
    values = _config_values(args)
    frames = tuple(values.get(k, NODE_DEFAULTS[k]) for k in ('frame_base_a', 'frame_base_b'))
    return frames if all(isinstance(f, str) and f for f in frames) else None


def add_check_options(p: argparse.ArgumentParser) -> None:
    """Add the options that turn the checks of a fit off: the stream directions, the swap."""
    p.add_argument('--no-direction-check', action='store_true',
                   help='do not check, after a bad fit, whether a stream should be inverted')
    p.add_argument('--roles-confirmed', action='store_true',
                   help="the topics are device A and device B as given, whatever the messages' "
                        'frame ids say: frame ids that name the other base frame (devices '
                        'swapped) refuse nothing (default: such a calibration exits 3)')


def roles_confirmed(args) -> bool:
    """--roles-confirmed, or ``roles_confirmed: true`` in --config (the node's parameter)."""
    return bool(getattr(args, 'roles_confirmed', False)
                or _config_values(args).get('roles_confirmed', False))


#: σ (rad) of ``--gravity-aligned`` given without a value: about half a degree of tilt.
GRAVITY_SIGMA = 0.01


def add_prior_options(p: argparse.ArgumentParser, prior_help: str) -> None:
    """Add ``--prior FILE`` and ``--gravity-aligned [SIGMA_RAD]`` (``prior_from_args``)."""
    p.add_argument('--prior', metavar='FILE', help=prior_help)
    p.add_argument('--gravity-aligned', nargs='?', type=positive, const=GRAVITY_SIGMA,
                   metavar='SIGMA_RAD',
                   help='both devices report z up (a VIO against motion capture): T0 keeps '
                        "A's base z on B's, within SIGMA_RAD of tilt (default "
                        f'{GRAVITY_SIGMA:g}); a yaw-only alignment (4 DOF)')


def prior_from_args(args):
    """Return the prior of ``--prior`` and ``--gravity-aligned`` (None when neither)."""
    from dataclasses import replace

    from coreg_ros.core.estimator.priors import Prior
    from coreg_ros.files.results import load_prior

    prior = load_prior(args.prior) if args.prior else None
    if args.gravity_aligned is not None:
        prior = replace(prior or Prior(), gravity_sigma=float(args.gravity_aligned))
    return prior


def settings_and_devices(args) -> tuple:
    """
    Return (Settings, the rig's devices) from --config and the flags.

    Several ``--topic-b`` with a model other than three_marker are a rig, one device per topic
    (named by it, with ``--sigma-b``); without ``--topic-b``, the config's ``devices``. A rig
    of one device is the two-device calibration (its topic, model and noise in the settings).
    ``--shared-base`` makes the devices sensors of one device (one base, one clock).
    """
    from argparse import Namespace

    from coreg_ros.core.errors import ConfigError
    from coreg_ros.core.rig.devices import device_specs, DeviceSpec
    from coreg_ros.files.parameters import load_parameters

    values = load_parameters(args.config) if args.config else {}
    topics = list(args.topic_b or [])
    model = args.model or values.get('model') or Settings().model
    shared = bool(getattr(args, 'shared_base', False))
    sigma = tuple(args.sigma_b) if args.sigma_b else None
    specs, flags = [], args
    if len(topics) > 1 and model != 'three_marker':
        specs = [DeviceSpec(t, (t,), model, sigma) for t in topics]
        flags = Namespace(**{**vars(args), 'topic_b': topics[:1]})
    elif not topics and values.get('devices'):
        specs = [s if sigma is None else DeviceSpec(s.name, s.topics, s.model, sigma, s.base)
                 for s in device_specs(values, model)]
        flags = Namespace(**{**vars(args), 'topic_b': list(specs[0].topics),
                             'model': specs[0].model})
    if shared:
        if len(specs) < 2:
            raise ConfigError('--shared-base makes several B topics sensors of one device; give '
                              'two or more with --topic-b T1 T2 (or a devices list)')
        specs = [DeviceSpec(s.name, s.topics, s.model, s.sigma, 'shared') for s in specs]
    settings = settings_from_args(flags)
    every = [settings.topic_a] + [t for spec in specs for t in spec.topics]
    same = [t for t in every if every.count(t) > 1]
    if specs and same:
        whose = 'device A and a device B' if same[0] == settings.topic_a else 'two devices B'
        raise ConfigError(f'topic {same[0]} is given for {whose}: each device needs its own '
                          f"topic (a B topic that is A's would calibrate A against itself)")
    if len(specs) == 1:
        one = specs[0]
        return settings.updated(topic_b=one.topics, model=one.model, sigma_b=one.sigma), []
    return settings, specs

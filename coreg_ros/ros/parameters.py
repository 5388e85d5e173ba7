"""
The parameters of ``coreg_node``: one table, declared once, read into typed settings.

The keys are those of ``config/coreg.yaml`` (ROS parameter file form). The calibration keys
are shared with ``coreg calibrate`` and become a ``coreg_ros.core.settings.Settings``; the
others belong to the node only.
"""

from __future__ import annotations

from dataclasses import dataclass
import os
import sys

from coreg_ros.core.config_schema import (
    check_parameters,
    check_value,
    CHOICES,
    DEFAULTS,
    example,
    RANGES,
)
from coreg_ros.core.errors import ConfigError, CoregError
from coreg_ros.core.settings import Settings, settings_from_mapping
from rcl_interfaces.msg import (
    FloatingPointRange,
    IntegerRange,
    ParameterDescriptor,
    SetParametersResult,
)
from rclpy.exceptions import ParameterException
from rclpy.node import Node
from rclpy.parameter import Parameter


def _float_range(lo: float, hi: float) -> list:
    return [FloatingPointRange(from_value=lo, to_value=hi, step=0.0)]


def _int_range(lo: int, hi: int) -> list:
    return [IntegerRange(from_value=lo, to_value=hi, step=1)]


def _desc(description: str, *, read_only: bool = False, constraints: str = '',
          floats: list | None = None, ints: list | None = None) -> ParameterDescriptor:
    return ParameterDescriptor(description=description, read_only=read_only,
                               additional_constraints=constraints,
                               floating_point_range=floats or [], integer_range=ints or [])


#: (name, default, descriptor). Read-only where a change would need new subscriptions or
#: buffers; the calibration keys may be changed at run time and apply to the next ~/calibrate.
PARAMETERS = (
    ('topic_a', DEFAULTS['topic_a'],
     _desc('PoseStamped topic of device A: tool pose in A base frame', read_only=True)),
    ('topic_b', DEFAULTS['topic_b'],
     _desc('PoseStamped topic(s) of device B: marker pose in B base frame (3 for three_marker)',
           read_only=True)),
    ('model', DEFAULTS['model'],
     _desc('measurement model', read_only=True,
           constraints='full_pose | position_only | three_marker')),
    ('method', DEFAULTS['method'], _desc('estimator', constraints='ols | tls')),
    ('sigma_a', DEFAULTS['sigma_a'],
     _desc('device A noise std: [position m, rotation rad]', constraints='two numbers > 0')),
    ('sigma_b', DEFAULTS['sigma_b'],
     _desc('device B noise std: [position m, rotation rad]', constraints='two numbers > 0')),
    ('max_gap', DEFAULTS['max_gap'],
     _desc('largest distance (s) from a B stamp to each A sample it is interpolated between',
           floats=_float_range(*RANGES['max_gap']))),
    ('time_offset', DEFAULTS['time_offset'],
     _desc("B's clock minus A's clock, s", floats=_float_range(*RANGES['time_offset']))),
    ('estimate_time_offset', DEFAULTS['estimate_time_offset'],
     _desc('estimate the clock offset jointly with the transforms (time_offset is the start); '
           'false: use time_offset as given')),
    ('estimate_clock_drift', DEFAULTS['estimate_clock_drift'],
     _desc('also estimate a linear clock drift (ppm) with the offset')),
    ('robust', DEFAULTS['robust'],
     _desc('reject pairs far outside the stated noise (outliers) before the final fit')),
    ('min_pairs', DEFAULTS['min_pairs'],
     _desc('fewest pairs a calibration accepts', ints=_int_range(*RANGES['min_pairs']))),
    ('max_iterations', DEFAULTS['max_iterations'],
     _desc('iteration limit of the estimator', ints=_int_range(*RANGES['max_iterations']))),
    ('noise', DEFAULTS['noise'],
     _desc('stated: the noise is as given (sigma_a/sigma_b or noise_file) and the fit is judged '
           'against it; auto: each device noise is estimated with the calibration (variance '
           'components), what the motion cannot separate held at the noise measured while a '
           'device stood still, else at the given noise', constraints='stated | auto')),
    ('prior_file', DEFAULTS['prior_file'],
     _desc('a previous result (result.yaml or coreg calibrate --json) or a partial prior that '
           'calibrations refine (Ikits B.3); empty: none')),
    ('noise_file', DEFAULTS['noise_file'],
     _desc('a noise file (coreg noise RECORDING --out FILE): 3x3 position and rotation '
           'covariances per device in its base frame, used instead of sigma_a/sigma_b; empty: '
           'none', read_only=True)),
    ('use_last_result_as_prior', DEFAULTS['use_last_result_as_prior'],
     _desc("refine the node's own stored result (its result_<node>_<hash>.yaml in "
           'storage_dir) when no prior_file is given')),
    ('gravity_aligned_sigma', DEFAULTS['gravity_aligned_sigma'],
     _desc('both devices report z up (a VIO against motion capture): T0 keeps A base z on B '
           'base z within this tilt sigma (rad), a yaw-only alignment; 0.0 = off',
           floats=_float_range(*RANGES['gravity_aligned_sigma']))),
    ('publish_inconsistent', DEFAULTS['publish_inconsistent'],
     _desc('publish a calibration whose fit contradicts the stated noise (it is refused by '
           'default: ~/calibrate answers success=false with the reason)')),
    ('roles_confirmed', DEFAULTS['roles_confirmed'],
     _desc('topic_a and topic_b are devices A and B as configured, whatever the frame ids of '
           'their messages say (frame ids that name the other base frame, swapped devices, '
           'refuse a calibration by default: ~/calibrate answers success=false)')),
    ('buffer_capacity', DEFAULTS['buffer_capacity'],
     _desc('samples kept per topic; the oldest are dropped when full', read_only=True,
           ints=_int_range(*RANGES['buffer_capacity']))),
    ('qos_reliable', DEFAULTS['qos_reliable'],
     _desc('false: sensor-data QoS (best effort), true: reliable', read_only=True)),
    ('frame_base_a', DEFAULTS['frame_base_a'], _desc("device A's base frame", read_only=True)),
    ('frame_base_b', DEFAULTS['frame_base_b'], _desc("device B's base frame", read_only=True)),
    ('frame_tool', DEFAULTS['frame_tool'], _desc("device A's tool frame", read_only=True)),
    ('frame_marker', DEFAULTS['frame_marker'], _desc("device B's marker frame", read_only=True)),
    ('publish_tf', DEFAULTS['publish_tf'],
     _desc('broadcast the calibration on /tf_static (tf2): frame_base_b -> frame_base_a (T0) '
           'and frame_tool -> frame_marker (T1), latched', read_only=True)),
    ('storage_dir', DEFAULTS['storage_dir'],
     _desc('directory of the stored results (one file per node and configuration), the '
           'sample journal and saved sample bags', read_only=True)),
    ('resume_samples', DEFAULTS['resume_samples'],
     _desc('at start-up, load the samples of an interrupted session (the journal a killed '
           'node left in storage_dir) instead of saving them to a bag and starting afresh',
           read_only=True)),
    # Uncertainty outputs (coreg_ros.ros.uncertainty_outputs), changeable at run time.
    ('publish_fused_pose', DEFAULTS['publish_fused_pose'],
     _desc('publish ~/fused_pose: A through the calibration fused with B, in frame_base_b, '
           'once a calibration exists')),
    ('publish_markers', DEFAULTS['publish_markers'],
     _desc('publish ~/uncertainty_markers: 3-sigma ellipsoids and axis cones of T0, T1 and '
           'the latest fused pose (transient local)')),
    ('fused_rate_limit', DEFAULTS['fused_rate_limit'],
     _desc('largest rate (Hz) of ~/fused_pose and of the fused markers (the newest pair '
           'each time); 0.0 = every pair', floats=_float_range(*RANGES['fused_rate_limit']))),
    ('marker_magnification', DEFAULTS['marker_magnification'],
     _desc('display gain on the ellipsoid semi-axes and on tan of the cone half-angles '
           '(1 = true size)', floats=_float_range(*RANGES['marker_magnification']))),
    ('fuse_when_stale', DEFAULTS['fuse_when_stale'],
     _desc('keep publishing ~/fused_pose when the watchdog finds the calibration stale '
           '(flagged on ~/calibration_stale); false: stop it until a new calibration')),
    # Live checks (coreg_ros.ros.live_checks), changeable at run time.
    ('guidance', DEFAULTS['guidance'],
     _desc('publish guidance while collecting on /diagnostics: the sigma a calibration would '
           'have now against the targets, and the motion that helps most')),
    ('motion_limits', DEFAULTS['motion_limits'],
     _desc('what the rig can move: free (guidance may ask for any motion), restricted (a SCARA '
           'arm, mobile robot, gantry or turntable: never ask for a motion that would determine '
           'what the recording leaves undetermined), auto (free until a direction stays '
           'undetermined for a minute of recording)', constraints='free | auto | restricted')),
    ('target_sigma_position', DEFAULTS['target_sigma_position'],
     _desc('guidance target: sigma of every position component, m',
           floats=_float_range(*RANGES['target_sigma_position']))),
    ('target_sigma_rotation', DEFAULTS['target_sigma_rotation'],
     _desc('guidance target: sigma of every rotation component, rad',
           floats=_float_range(*RANGES['target_sigma_rotation']))),
    ('target_sigma_time', DEFAULTS['target_sigma_time'],
     _desc('guidance target: sigma of the clock offset, s; 0.0 = no target',
           floats=_float_range(*RANGES['target_sigma_time']))),
    ('auto_calibrate', DEFAULTS['auto_calibrate'],
     _desc('calibrate (as ~/calibrate) once guidance says ready and no calibration exists')),
    ('watchdog', DEFAULTS['watchdog'],
     _desc('check every new pair against the published calibration; /diagnostics goes WARN '
           'then ERROR naming the change (T0, T1, clock, noise) when it no longer fits')),
    ('auto_recalibrate', DEFAULTS['auto_recalibrate'],
     _desc('after a change of T0, T1 or the clock, recalibrate on the samples since the '
           'change with what still holds as a prior; published only if the fit passes')),
)

if [name for name, _, _ in PARAMETERS] != list(DEFAULTS):  # one table of keys, one of types
    raise AssertionError('ros.parameters.PARAMETERS and core.config_schema.DEFAULTS differ')

#: Names of the calibration keys (those of Settings).
CALIBRATION_KEYS = ('topic_a', 'topic_b', 'model', 'method', 'sigma_a', 'sigma_b', 'max_gap',
                    'time_offset', 'estimate_time_offset', 'estimate_clock_drift', 'robust',
                    'min_pairs', 'max_iterations', 'noise')


@dataclass(frozen=True)
class NodeConfig:
    """
    Everything the node reads from its parameters.

    Attributes
    ----------
    settings : Settings
        Calibration settings (shared with ``coreg calibrate``).
    buffer_capacity : int
        Samples kept per topic.
    qos_reliable : bool
        Reliable subscriptions instead of the sensor-data (best effort) profile.
    frame_base_a, frame_base_b, frame_tool, frame_marker : str
        Frame ids of the published poses.
    publish_tf : bool
        Broadcast T0 and T1 on /tf_static (``ros.static_tf``).
    storage_dir : str
        Directory of the stored results, the journal and sample bags, user (~) expanded.
    resume_samples : bool
        Load the journal of an interrupted session at start-up.
    noise_file : files.noise_file.NoiseFile or None
        The ``noise_file`` read (and checked against the topics) at start-up; ``settings``
        carry its noise.

    """

    settings: Settings
    buffer_capacity: int
    qos_reliable: bool
    frame_base_a: str
    frame_base_b: str
    frame_tool: str
    frame_marker: str
    storage_dir: str
    resume_samples: bool = False
    noise_file: object = None
    publish_tf: bool = True

    @property
    def frames(self) -> dict:
        """Frame ids as a plain dict (stored beside the result)."""
        return {'base_a': self.frame_base_a, 'base_b': self.frame_base_b,
                'tool': self.frame_tool, 'marker': self.frame_marker}


def declare_parameters(node: Node) -> list[str]:
    """
    Declare every parameter of the table on ``node`` (once, at construction).

    The node's parameter overrides (``--params-file``, ``-p``) are checked first by
    ``core.config_schema.check_parameters``, the check ``coreg --config`` applies to the same
    file: an integer where a double is expected is converted (ROS itself would refuse
    ``max_gap: 1``), a wrong type is one line naming the key.

    Returns
    -------
    warnings : list of str
        One line per unknown key of the overrides, naming the nearest valid key.

    Raises
    ------
    ConfigError
        If an override has the wrong type or is outside the parameter's range.

    """
    # rclpy keeps the overrides it read from the arguments here (no public accessor); if a
    # later rclpy moves them, the declare-time exceptions below still give one line.
    overrides = getattr(node, '_parameter_overrides', None)
    warnings: list[str] = []
    if isinstance(overrides, dict):
        values = {name: p.value for name, p in overrides.items()}
        checked, warnings = check_parameters(values, where='parameters: ')
        for name, value in checked.items():
            if values[name] != value or type(values[name]) is not type(value):
                overrides[name] = Parameter(name, value=value)
    try:
        node.declare_parameters('', [(name, default, desc)
                                     for name, default, desc in PARAMETERS])
    except ParameterException as e:
        raise ConfigError(_one_line(e)) from None
    return warnings


def _one_line(error: ParameterException) -> str:
    """Turn rclpy's declare-time exception into one line naming the key and an example."""
    text = str(error)
    name = text.rsplit(': ', 1)[-1].strip("[]' ")
    reason = text.rsplit(': ', 1)[0]
    if 'Reason: ' in reason:
        reason = reason.split('Reason: ', 1)[1]
    if name in DEFAULTS:
        return f'parameter {name}: {reason}; e.g. {example(name)}'
    return f'parameters: {text}'


def params_files(args: list[str]) -> list[str]:
    """Return the ``--params-file`` paths of a command line's ``--ros-args`` sections."""
    files, in_ros = [], False
    for k, arg in enumerate(args):
        if arg == '--ros-args':
            in_ros = True
        elif arg == '--':
            in_ros = False
        elif in_ros and arg == '--params-file' and k + 1 < len(args):
            files.append(args[k + 1])
    return files


def node_name_of(args: list[str], default: str) -> str:
    """Return the node's name after the ``--ros-args`` remaps (``-r __node:=NAME``, ``__ns``)."""
    name, namespace, in_ros = default, '', False
    for k, arg in enumerate(args):
        if arg == '--ros-args':
            in_ros = True
        elif arg == '--':
            in_ros = False
        elif in_ros and arg in ('-r', '--remap') and k + 1 < len(args):
            key, _, value = args[k + 1].partition(':=')
            if key in ('__node', '__name') and value:
                name = value
            elif key == '__ns' and value:
                namespace = value.strip('/')
    return f'{namespace}/{name}' if namespace else name


def check_params_files(args: list[str], node_name: str, warn=None) -> None:
    """
    Check the parameter files of a command line before ROS parses them.

    ROS refuses an unparseable file, or a value of the wrong type, with a long traceback; this
    runs the check of ``coreg --config`` (``files.parameters.load_parameters``) on each file with a
    section for the node (``node_name``, or the name a ``__node`` remap gives it) first. A file
    that is empty or has no section of the node, which ROS ignores silently, is said through
    ``warn`` (default: one line on stderr). Unknown keys are not reported here (the node reports
    them from its overrides).

    Raises
    ------
    ConfigError
        One line naming the file, the key, the expected type and an example.

    """
    from coreg_ros.files.parameters import load_parameters

    if warn is None:
        def warn(line: str) -> None:
            print(f'coreg_node: warning: {line}', file=sys.stderr)
    name = node_name_of(args, node_name)
    for path in params_files(args):
        load_parameters(path, name, warn=lambda line: None, warn_section=warn)


def _plain(value):
    """Parameter value as plain Python (arrays come back as array.array or lists)."""
    if isinstance(value, (list, tuple)) or hasattr(value, 'tolist'):
        return tuple(value)
    return value


def settings_from_values(values: dict) -> Settings:
    """Build Settings from parameter values; raises ConfigError naming the bad key."""
    return settings_from_mapping({k: _plain(v) for k, v in values.items()
                                  if k in CALIBRATION_KEYS})


class ParameterView:
    """
    The current values of a node's parameters, for the collaborators that follow run-time changes.

    Parameters
    ----------
    node : rclpy.node.Node
        The node the parameters are declared on (``declare_parameters``).

    """

    def __init__(self, node: Node, noise=None):
        self._node = node
        #: ``live_noise.NoiseSources``: the noise in use (file, measured, estimated)
        self.noise = noise

    def __call__(self, name: str):
        """Return the current value of parameter ``name``."""
        return self._node.get_parameter(name).value

    def settings(self) -> Settings:
        """Calibration settings from the current parameter values, with the noise in use."""
        settings = settings_from_values({k: self(k) for k in CALIBRATION_KEYS})
        return settings if self.noise is None else self.noise.apply(settings)

    def check_change(self, params) -> SetParametersResult:
        """
        Refuse a run-time change that would make invalid Settings (on-set-parameters callback).

        Parameters
        ----------
        params : list of rclpy.parameter.Parameter
            The parameters about to be set.

        """
        for p in params:  # a choice (motion_limits) no descriptor can state
            if p.name in CHOICES:
                try:
                    check_value(p.name, p.value)
                except CoregError as e:
                    return SetParametersResult(successful=False, reason=str(e))
        changed = {p.name: p.value for p in params if p.name in CALIBRATION_KEYS}
        if not changed:
            return SetParametersResult(successful=True)
        values = {k: self(k) for k in CALIBRATION_KEYS if self._node.has_parameter(k)}
        values.update(changed)
        try:
            settings_from_values(values)
        except CoregError as e:
            return SetParametersResult(successful=False, reason=str(e))
        return SetParametersResult(successful=True)


def read_config(node: Node) -> NodeConfig:
    """
    Read the declared parameters into a NodeConfig.

    Raises
    ------
    ConfigError
        If a value is invalid (e.g. an unknown model, a wrong number of topics).

    """
    values = {name: node.get_parameter(name).value for name, _, _ in PARAMETERS}
    settings = settings_from_values(values)
    noise = None
    if str(values['noise_file']).strip():
        from coreg_ros.files.noise_file import load_noise_file, with_noise_file
        noise = load_noise_file(os.path.expanduser(str(values['noise_file']).strip()))
        settings = with_noise_file(settings, noise)  # refused here: other topics, units
    storage = str(values['storage_dir']).strip()
    if not storage:
        raise ConfigError('storage_dir is empty; set it to a writable directory')
    return NodeConfig(
        settings=settings,
        buffer_capacity=int(values['buffer_capacity']),
        qos_reliable=bool(values['qos_reliable']),
        frame_base_a=str(values['frame_base_a']),
        frame_base_b=str(values['frame_base_b']),
        frame_tool=str(values['frame_tool']),
        frame_marker=str(values['frame_marker']),
        storage_dir=os.path.expanduser(storage),
        resume_samples=bool(values['resume_samples']),
        noise_file=noise,
        publish_tf=bool(values['publish_tf']),
    )

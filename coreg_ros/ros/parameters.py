"""
The parameters of ``coreg_node``: one table, declared once, read into typed settings.

The keys are those of ``config/coreg.yaml`` (ROS parameter file form). The calibration keys
are shared with ``coreg calibrate`` and become a ``coreg_ros.core.settings.Settings``; the
others belong to the node only.
"""

from __future__ import annotations

from dataclasses import dataclass
import os

from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor
from rclpy.node import Node

from coreg_ros.core.errors import ConfigError
from coreg_ros.core.settings import Settings, settings_from_mapping

_DEFAULTS = Settings()


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
    ('topic_a', _DEFAULTS.topic_a,
     _desc('PoseStamped topic of device A: tool pose in A base frame', read_only=True)),
    ('topic_b', list(_DEFAULTS.topic_b),
     _desc('PoseStamped topic(s) of device B: marker pose in B base frame (3 for three_marker)',
           read_only=True)),
    ('model', _DEFAULTS.model,
     _desc('measurement model', read_only=True,
           constraints='full_pose | position_only | three_marker')),
    ('method', _DEFAULTS.method, _desc('estimator', constraints='ols | tls')),
    ('sigma_a', list(_DEFAULTS.sigma_a),
     _desc('device A noise std: [position m, rotation rad]', constraints='two numbers > 0')),
    ('sigma_b', list(_DEFAULTS.sigma_b),
     _desc('device B noise std: [position m, rotation rad]', constraints='two numbers > 0')),
    ('max_gap', _DEFAULTS.max_gap,
     _desc('largest distance (s) from a B stamp to each A sample it is interpolated between',
           floats=_float_range(1e-6, 10.0))),
    ('time_offset', _DEFAULTS.time_offset,
     _desc("B's clock minus A's clock, s", floats=_float_range(-10.0, 10.0))),
    ('estimate_time_offset', _DEFAULTS.estimate_time_offset,
     _desc('estimate the clock offset jointly with the transforms (time_offset is the start); '
           'false: use time_offset as given')),
    ('estimate_clock_drift', _DEFAULTS.estimate_clock_drift,
     _desc('also estimate a linear clock drift (ppm) with the offset')),
    ('robust', _DEFAULTS.robust,
     _desc('reject pairs far outside the stated noise (outliers) before the final fit')),
    ('min_pairs', _DEFAULTS.min_pairs,
     _desc('fewest pairs a calibration accepts', ints=_int_range(3, 1_000_000_000))),
    ('max_iterations', _DEFAULTS.max_iterations,
     _desc('iteration limit of the estimator', ints=_int_range(1, 100_000))),
    ('prior_file', '',
     _desc('a previous result (result.yaml or coreg calibrate --json) or a partial prior that '
           'calibrations refine (Ikits B.3); empty: none')),
    ('use_last_result_as_prior', False,
     _desc("refine the node's own stored result (result.yaml in storage_dir) when no "
           'prior_file is given')),
    ('publish_inconsistent', False,
     _desc('publish a calibration whose fit contradicts the stated noise (it is refused by '
           'default: ~/calibrate answers success=false with the reason)')),
    ('buffer_capacity', 200_000,
     _desc('samples kept per topic; the oldest are dropped when full', read_only=True,
           ints=_int_range(10, 100_000_000))),
    ('qos_reliable', False,
     _desc('false: sensor-data QoS (best effort), true: reliable', read_only=True)),
    ('frame_base_a', 'device_a_base', _desc("device A's base frame", read_only=True)),
    ('frame_base_b', 'device_b_base', _desc("device B's base frame", read_only=True)),
    ('frame_tool', 'device_a_tool', _desc("device A's tool frame", read_only=True)),
    ('frame_marker', 'device_b_marker', _desc("device B's marker frame", read_only=True)),
    ('storage_dir', '~/.ros/coreg',
     _desc('directory of the stored result (result.yaml) and saved sample bags',
           read_only=True)),
    # Uncertainty outputs (coreg_ros.ros.uncertainty_outputs), changeable at run time.
    ('publish_fused_pose', True,
     _desc('publish ~/fused_pose: A through the calibration fused with B, in frame_base_b, '
           'once a calibration exists')),
    ('publish_markers', True,
     _desc('publish ~/uncertainty_markers: 3-sigma ellipsoids and axis cones of T0, T1 and '
           'the latest fused pose (transient local)')),
    ('fused_rate_limit', 50.0,
     _desc('largest rate (Hz) of ~/fused_pose and of the fused markers (the newest pair '
           'each time); 0.0 = every pair', floats=_float_range(0.0, 1000.0))),
    ('marker_magnification', 1.0,
     _desc('display gain on the ellipsoid semi-axes and on tan of the cone half-angles '
           '(1 = true size)', floats=_float_range(1e-3, 1e6))),
)

#: Names of the calibration keys (those of Settings).
CALIBRATION_KEYS = ('topic_a', 'topic_b', 'model', 'method', 'sigma_a', 'sigma_b', 'max_gap',
                    'time_offset', 'estimate_time_offset', 'estimate_clock_drift', 'robust',
                    'min_pairs', 'max_iterations')


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
    storage_dir : str
        Directory of result.yaml and sample bags, user (~) expanded.

    """

    settings: Settings
    buffer_capacity: int
    qos_reliable: bool
    frame_base_a: str
    frame_base_b: str
    frame_tool: str
    frame_marker: str
    storage_dir: str

    @property
    def frames(self) -> dict:
        """Frame ids as a plain dict (stored beside the result)."""
        return {'base_a': self.frame_base_a, 'base_b': self.frame_base_b,
                'tool': self.frame_tool, 'marker': self.frame_marker}


def declare_parameters(node: Node) -> None:
    """Declare every parameter of the table on ``node`` (once, at construction)."""
    node.declare_parameters('', [(name, default, desc) for name, default, desc in PARAMETERS])


def _plain(value):
    """Parameter value as plain Python (arrays come back as array.array or lists)."""
    if isinstance(value, (list, tuple)) or hasattr(value, 'tolist'):
        return tuple(value)
    return value


def settings_from_values(values: dict) -> Settings:
    """Build Settings from parameter values; raises ConfigError naming the bad key."""
    return settings_from_mapping({k: _plain(v) for k, v in values.items()
                                  if k in CALIBRATION_KEYS})


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
    )

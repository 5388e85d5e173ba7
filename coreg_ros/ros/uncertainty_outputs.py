"""
The node's uncertainty outputs: ``~/fused_pose`` and ``~/uncertainty_markers``.

Once a calibration exists (fresh from ``~/calibrate`` or stored and loaded at start-up):

``~/fused_pose`` (geometry_msgs/PoseWithCovarianceStamped, frame ``frame_base_b``, stamp = B's
    header stamp of the pair)
    Device A's pose carried into B's base frame through the calibration (``T0 · T_A · T1``,
    with the calibration's joint covariance and A's noise ``sigma_a``), fused with device B's
    measurement (noise ``sigma_b``); see ``coreg_ros.core.live.fusion``. ``full_pose``: the
    whole pose is fused. ``position_only`` / ``three_marker``: the positions only (B's marker
    1); the orientation is A's prediction and its covariance rows are marked unknown (-1 on
    the diagonal). QoS: reliable, volatile, depth 100 (every-pair mode publishes in batches).
``~/uncertainty_markers`` (visualization_msgs/MarkerArray, transient-local)
    Hoff & Vincent's Fig. 1 for T0 (namespace ``base_to_base``, frame ``frame_base_b``), T1
    (``tool_to_marker``, frame ``frame_tool``) and the latest fused pose (``fused``, frame
    ``frame_base_b``): id 0 the 3σ position ellipsoid (SPHERE centred on the frame origin,
    ``scale`` = the diameters 2·k·√λ, orientation = the eigenvectors), ids 1-3 the cones of
    the frame's x, y, z axes (TRIANGLE_LIST, apex at the origin, 3σ ellipse of the axis tip
    at ``AXIS_LENGTH``). Components not estimated (T1's rotation for position-only models)
    are not drawn. Every message holds all the markers, so a late subscriber gets the whole
    picture; switching ``publish_markers`` off publishes one DELETEALL.

Parameters (``coreg_ros.ros.parameters``; changeable at run time)
    ``publish_fused_pose``, ``publish_markers`` (bool), ``fused_rate_limit`` (Hz; 0 = every
    pair), ``marker_magnification`` (display gain on the ellipsoid semi-axes and on tan of
    the cone half-angles; 1 = true size), ``fuse_when_stale`` (keep fusing when the watchdog
    of ``ros.live_checks`` finds the calibration stale; by default ``~/fused_pose`` stops).

Threads: the work runs in a timer of the services thread, never in the subscription callbacks.
Each tick copies the newest samples of each buffer (``A_WINDOW``, ``B_WINDOW``), pairs the B
samples that arrived since the last tick by the one pairing rule (``pending_pairs``), fuses them
vectorised and publishes: with a rate limit the newest pair only, at most ``fused_rate_limit``
times per second; with 0 every pair, in batches every ``DRAIN_PERIOD`` s. The fused markers
follow at most ``MARKER_MAX_RATE`` (10 Hz). A backlog larger than the windows (the services
thread was busy, e.g. with an automatic calibration) is skipped, not published late.
"""

from __future__ import annotations

import time
import traceback
from typing import Optional

from coreg_ros.core import uncertainty as unc
from coreg_ros.core.errors import CoregError
from coreg_ros.core.live.fusion import fused_stream, FusionCalibration, pending_pairs
from coreg_ros.core.types import CalibrationResult, Pairs, TimeOffset, UncertainPose
from coreg_ros.files.results import result_to_dict
from coreg_ros.ros.interface import LATCHED_QOS
from coreg_ros.ros.messages import ns_to_stamp, uncertain_pose_to_msg
from coreg_ros.ros.parameters import NodeConfig, ParameterView
from coreg_ros.ros.throttle import Throttle
from geometry_msgs.msg import Point
import numpy as np
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import ColorRGBA
from visualization_msgs.msg import Marker, MarkerArray

#: Samples of A and of each B topic looked at per tick (the newest ones).
A_WINDOW = 2048
B_WINDOW = 512
#: Timer period (s) when ``fused_rate_limit`` is 0: every pair, published in batches (fusing
#: twenty pairs costs about what one does, ~1.7 ms).
DRAIN_PERIOD = 0.02
#: The fused markers follow ``fused_rate_limit`` up to this rate, Hz: one MarkerArray (three
#: ellipsoids, nine cones of 72 vertices) costs ~4 ms to build and serialise.
MARKER_MAX_RATE = 10.0
#: Drawn length of the axis cones, m.
AXIS_LENGTH = 0.1
#: n_sigma of the ellipsoids and cones (Hoff: 3σ, 97 % in 3-D, 98.9 % at an axis tip).
N_SIGMA = 3.0
#: Segments of a cone's rim.
CONE_SEGMENTS = 24

OUTPUT_KEYS = ('publish_fused_pose', 'publish_markers', 'fused_rate_limit',
               'marker_magnification', 'fuse_when_stale')

#: Ellipsoid colour per namespace; cones are red, green, blue for the x, y, z axes.
ELLIPSOID_RGBA = {'base_to_base': (1.0, 0.8, 0.1, 0.5), 'tool_to_marker': (0.1, 0.8, 1.0, 0.5),
                  'fused': (0.9, 0.2, 0.9, 0.5)}
AXIS_RGBA = ((0.9, 0.15, 0.15, 0.7), (0.15, 0.8, 0.15, 0.7), (0.2, 0.35, 1.0, 0.7))

FUSED_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=100,
                       reliability=ReliabilityPolicy.RELIABLE,
                       durability=DurabilityPolicy.VOLATILE)
#: QoS of the markers: the result topics' (a late RViz gets the calibration's markers).
MARKER_QOS = LATCHED_QOS


# --------------------------------------------------------------------------- markers

def _colour(rgba) -> ColorRGBA:
    r, g, b, a = rgba
    return ColorRGBA(r=float(r), g=float(g), b=float(b), a=float(a))


def pose_markers(pose: UncertainPose, frame_id: str, stamp, ns: str, *,
                 magnification: float = 1.0, cone_magnification: Optional[float] = None,
                 axis_length: float = AXIS_LENGTH, n_sigma: float = N_SIGMA) -> list:
    """
    Build Hoff's Fig. 1 for one uncertain pose: the position ellipsoid and the three axis cones.

    Parameters
    ----------
    pose : UncertainPose
        Pose of a frame in ``frame_id`` with its ROS-layout covariance (None: nothing drawn).
    frame_id : str
        Frame the pose is expressed in (``header.frame_id`` of the markers).
    stamp : builtin_interfaces.msg.Time
        ``header.stamp`` of the markers.
    ns : str
        Marker namespace (ids 0 ellipsoid, 1-3 the x, y, z cones).
    magnification : float
        Display gain on the semi-axes and on tan of the cone half-angles (1 = true size).
    cone_magnification : float, optional
        A different gain for the cones (default: ``magnification``).
    axis_length : float
        Drawn axis length, m.
    n_sigma : float
        Size of the ellipsoid and of the ellipses at the axis tips.

    Returns
    -------
    list of visualization_msgs.msg.Marker
        The ellipsoid if the position covariance is known, the cones if the rotation is.

    """
    if pose.covariance is None:
        return []
    cov = np.asarray(pose.covariance, dtype=float).reshape(6, 6)
    diag = np.diag(cov)
    origin = np.asarray(pose.position, dtype=float)
    gain = float(magnification)
    markers = []

    def base(marker_id: int, kind: int) -> Marker:
        m = Marker()
        m.header.frame_id = frame_id
        m.header.stamp = stamp
        m.ns, m.id, m.type, m.action = ns, marker_id, kind, Marker.ADD
        m.pose.orientation.w = 1.0
        return m

    if (diag[0:3] >= 0).all():
        ell = unc.ellipsoid_axes(cov[0:3, 0:3], n_sigma)
        m = base(0, Marker.SPHERE)
        m.pose.position.x, m.pose.position.y, m.pose.position.z = (float(v) for v in origin)
        w, x, y, z = (float(v) for v in unc.ellipsoid_orientation(ell))
        o = m.pose.orientation
        o.w, o.x, o.y, o.z = w, x, y, z
        m.scale.x, m.scale.y, m.scale.z = (float(v) for v in 2.0 * gain * ell.semi_axes)
        m.color = _colour(ELLIPSOID_RGBA.get(ns, (0.8, 0.8, 0.8, 0.5)))
        markers.append(m)
    if (diag[3:6] >= 0).all():
        for cone in unc.axis_cones(UncertainPose(origin, pose.quat_wxyz, cov), n_sigma):
            tri = unc.cone_mesh(cone, length=axis_length, n=CONE_SEGMENTS,
                                gain=gain if cone_magnification is None else cone_magnification,
                                origin=origin)
            m = base(1 + cone.index, Marker.TRIANGLE_LIST)
            m.scale.x = m.scale.y = m.scale.z = 1.0
            m.color = _colour(AXIS_RGBA[cone.index])
            m.points = [Point(x=x, y=y, z=z) for x, y, z in tri.reshape(-1, 3).tolist()]
            markers.append(m)
    return markers


def delete_all_markers() -> MarkerArray:
    """Return a MarkerArray that clears every marker of the topic (RViz DELETEALL)."""
    m = Marker()
    m.action = Marker.DELETEALL
    return MarkerArray(markers=[m])


# --------------------------------------------------------------------------- buffers

def _last_pair(pairs: Pairs) -> Pairs:
    def last(v):
        return None if v is None else v[-1:]
    return Pairs(stamps=pairs.stamps[-1:], pos_a=pairs.pos_a[-1:], quat_a=pairs.quat_a[-1:],
                 pos_b=pairs.pos_b[-1:], quat_b=last(pairs.quat_b),
                 a_var_scale=last(pairs.a_var_scale))


def stored_result_dict(result: CalibrationResult) -> dict:
    """
    Return what the node stores: ``result_to_dict(result)``, the 12×12 ``cov_joint`` included.

    A node restarted on the stored result then fuses with the cross terms of T0 and T1 too,
    exactly as right after the calibration (and the result serves as a prior with them).
    """
    return result_to_dict(result)


# --------------------------------------------------------------------------- the outputs

class UncertaintyOutputs:
    """
    Publish ``~/fused_pose`` and ``~/uncertainty_markers`` once a calibration exists.

    Parameters
    ----------
    config : NodeConfig
        The frames of the poses and markers, B's first topic.
    params : ParameterView
        The current settings and the parameters of ``OUTPUT_KEYS``.
    buffers : dict of str to StreamBuffer
        The held samples, per topic (``SampleStore.buffers``).
    pub_fused, pub_markers : rclpy.publisher.Publisher
        Publishers of ``~/fused_pose`` (``FUSED_QOS``) and ``~/uncertainty_markers``
        (``MARKER_QOS``).
    timer : rclpy.timer.Timer
        A cancelled timer of the services thread whose callback calls ``tick``; its period and
        state follow the parameters and the calibration.
    clock : rclpy.clock.Clock
        Stamps the calibration's markers.
    logger : rclpy.impl.rcutils_logger.RcutilsLogger
        The node's logger.

    """

    def __init__(self, config: NodeConfig, params: ParameterView, buffers: dict, pub_fused,
                 pub_markers, timer, clock, logger):
        self.config = config
        self.params = params
        self.buffers = buffers
        self.pub_fused = pub_fused
        self.pub_markers = pub_markers
        self.clock = clock
        self.logger = logger
        self.calibration: Optional[FusionCalibration] = None
        #: the clock offset of the calibration: fusion pairs A and B as the calibration did
        self.timing: Optional[TimeOffset] = None
        self._calibration_markers: list = []
        self._cursor: Optional[int] = None
        self._log_throttle = Throttle()  # one line per WARN_PERIOD of a failing tick
        self._marker_time = -1.0  # monotonic time of the last fused MarkerArray
        self.published = 0  # fused poses published since start-up
        #: the watchdog found the calibration stale (``ros.live_checks``): no fused poses
        #: unless ``fuse_when_stale``
        self.stale = False
        values = {k: params(k) for k in OUTPUT_KEYS}
        self.fused_on = bool(values['publish_fused_pose'])
        self.markers_on = bool(values['publish_markers'])
        self.rate = float(values['fused_rate_limit'])
        self.magnification = float(values['marker_magnification'])
        self.fuse_when_stale = bool(values['fuse_when_stale'])
        self.timer = timer
        self._update_timer()

    # --- calibration -----------------------------------------------------------------------

    def set_result(self, result: CalibrationResult) -> None:
        """Use a fresh calibration (joint covariance with its cross terms) and its clock offset."""
        self.timing = result.time_offset
        self.set_calibration(FusionCalibration.from_result(result))

    def set_stored(self, doc: dict, base_to_base: UncertainPose,
                   tool_to_marker: UncertainPose) -> None:
        """Use a stored calibration (``persistence.load_result``); cov_joint if it was stored."""
        r = doc.get('result', {})
        self.timing = TimeOffset.from_dict(r.get('time_offset'), r.get('clock_drift'))
        # held directions (a restricted rig) change no pose: their unknown variance stays out
        joint = r.get('cov_determined', r.get('cov_joint'))
        self.set_calibration(FusionCalibration.from_poses(
            base_to_base, tool_to_marker, r.get('model', 'full_pose'),
            None if joint is None else np.asarray(joint, dtype=float).reshape(12, 12)))

    def set_calibration(self, calibration: FusionCalibration) -> None:
        """Start fusing with ``calibration`` from the newest samples on; publish its markers."""
        self.calibration = calibration
        b = self.buffers[self.config.settings.topic_b[0]]
        newest = b.tail(1).stamps
        self._cursor = int(newest[0]) if len(newest) else None
        self._build_calibration_markers()
        if self.markers_on:
            self.pub_markers.publish(MarkerArray(markers=list(self._calibration_markers)))
        self._update_timer()

    def _build_calibration_markers(self) -> None:
        cal, config = self.calibration, self.config
        if cal is None:
            self._calibration_markers = []
            return
        stamp = self.clock.now().to_msg()
        self._calibration_markers = (
            pose_markers(cal.base_to_base, config.frame_base_b, stamp, 'base_to_base',
                         magnification=self.magnification)
            + pose_markers(cal.tool_to_marker, config.frame_tool, stamp, 'tool_to_marker',
                           magnification=self.magnification))

    # --- parameters ------------------------------------------------------------------------

    def _period(self) -> float:
        return 1.0 / self.rate if self.rate > 0 else DRAIN_PERIOD

    def _update_timer(self) -> None:
        active = self.calibration is not None and (self.fused_on or self.markers_on)
        period_ns = int(round(self._period() * 1e9))
        if self.timer.timer_period_ns != period_ns:
            self.timer.timer_period_ns = period_ns
        if active and self.timer.is_canceled():
            self.timer.reset()
        elif not active and not self.timer.is_canceled():
            self.timer.cancel()

    def on_parameters(self, params) -> None:
        """Follow a change of the ``OUTPUT_KEYS`` parameters (post-set-parameters callback)."""
        changed = {p.name: p.value for p in params if p.name in OUTPUT_KEYS}
        if not changed:
            return
        was_markers = self.markers_on
        self.fused_on = bool(changed.get('publish_fused_pose', self.fused_on))
        self.markers_on = bool(changed.get('publish_markers', self.markers_on))
        self.rate = float(changed.get('fused_rate_limit', self.rate))
        self.fuse_when_stale = bool(changed.get('fuse_when_stale', self.fuse_when_stale))
        if 'marker_magnification' in changed:
            self.magnification = float(changed['marker_magnification'])
            self._build_calibration_markers()
        if was_markers and not self.markers_on:
            self.pub_markers.publish(delete_all_markers())
        elif self.markers_on and self.calibration is not None and (
                not was_markers or 'marker_magnification' in changed):
            self.pub_markers.publish(MarkerArray(markers=list(self._calibration_markers)))
        self._update_timer()

    # --- the tick --------------------------------------------------------------------------

    def set_stale(self, stale: bool) -> None:
        """Say whether the watchdog finds the calibration stale (no fused poses unless asked)."""
        self.stale = stale

    def tick(self) -> None:
        """Fuse and publish what is new (the timer); a failure is logged, throttled."""
        try:
            self.fuse_and_publish()
        except Exception as e:  # never let a bug stop the services thread's executor
            if self._log_throttle.ready():
                detail = str(e) if isinstance(e, CoregError) else traceback.format_exc()
                self.logger.error(f'fused pose: {detail}')

    def fuse_and_publish(self) -> int:
        """
        Fuse the pairs that became available since the last call and publish them.

        Returns
        -------
        n : int
            Fused poses published.

        """
        cal = self.calibration
        if cal is None or not (self.fused_on or self.markers_on):
            return 0
        settings = self.params.settings()  # sigmas, gap and offset may change live
        buffers = self.buffers
        stream_a = buffers[settings.topic_a].tail(A_WINDOW)
        streams_b = [buffers[t].tail(B_WINDOW) for t in settings.topic_b]
        newest = streams_b[0].stamps
        offset_ns = settings.time_offset_ns if self.timing is None or not len(newest) else \
            self.timing.offset_ns_at(int(newest[-1]))
        pairs, self._cursor = pending_pairs(
            stream_a, streams_b if len(streams_b) == 3 else streams_b[0], self._cursor,
            max_gap_ns=settings.max_gap_ns, offset_ns=offset_ns,
            with_orientation_b=settings.model == 'full_pose')
        if len(pairs) == 0:
            return 0
        if self.rate > 0:
            pairs = _last_pair(pairs)
        fused = fused_stream(cal, pairs, settings.device_noise('a'),
                             settings.device_noise('b'))
        frame = self.config.frame_base_b
        n = 0
        if self.fused_on and not (self.stale and not self.fuse_when_stale):
            publish = self.pub_fused.publish
            for i in range(len(fused)):
                publish(uncertain_pose_to_msg(fused.pose(i), frame,
                                              ns_to_stamp(fused.stamps[i])))
            n = len(fused)
            self.published += n
        now = time.monotonic()
        if self.markers_on and now - self._marker_time >= 0.8 / MARKER_MAX_RATE:
            self._marker_time = now
            latest = pose_markers(fused.pose(-1), frame, ns_to_stamp(fused.stamps[-1]),
                                  'fused', magnification=self.magnification)
            self.pub_markers.publish(MarkerArray(markers=self._calibration_markers + latest))
        return n

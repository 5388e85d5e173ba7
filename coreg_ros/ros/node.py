"""
``coreg_node``: accumulate two pose streams live, calibrate on request, publish the result.

Subscriptions
    ``topic_a`` and each ``topic_b`` (geometry_msgs/PoseStamped; sensor-data QoS, or reliable
    with ``qos_reliable``). The messages are taken raw, every waiting one at each wake, decoded
    and validated in bulk (``coreg_ros.ros.raw_intake``) and stored in a bounded, preallocated
    buffer (``coreg_ros.ros.buffer``); rejections are counted by reason. ``COREG_NODE_PLAIN=1``
    in the environment takes one deserialised message per callback instead (the older path,
    the benchmark's baseline; same samples and counts).
Services (std_srvs/Trigger)
    ``~/calibrate`` runs ``coreg_ros.core.pipeline.calibrate_streams`` on a snapshot of the
    raw samples, the very function ``coreg calibrate BAG`` runs, so live and offline results
    agree; ``~/reset`` forgets the samples; ``~/save_samples`` writes them to a rosbag2 in
    ``storage_dir``.
    A service never dies: any failure is answered with success=false and the reason.
Publications
    ``~/base_to_base`` (pose of ``frame_base_a`` in ``frame_base_b``) and ``~/tool_to_marker``
    (pose of ``frame_marker`` in ``frame_tool``), PoseWithCovarianceStamped, transient-local
    so late subscribers get the last result; ``/diagnostics`` at 1 Hz (with messages lost in
    the middleware or missing from the stamps, swapped frame ids, a wrong message type on a
    topic, and storage errors). Once a calibration exists, ``~/fused_pose`` and
    ``~/uncertainty_markers`` (``ros.uncertainty_outputs``). The live checks
    (``ros.live_checks``) add two statuses to each /diagnostics message: guidance while
    collecting (``<node>: guidance``) and the watchdog of the published calibration
    (``<node>: watchdog``); and publish ``~/calibration_stale``.
Persistence
    The result is stored atomically in ``storage_dir`` under a name of the node and its
    configuration (model, topics, frames) and republished at start-up only by a node of that
    configuration, stamped with its calibration time. The accepted samples are journalled to
    rosbag2 chunks in ``storage_dir`` every ``FLUSH_PERIOD`` s, so a kill loses at most that;
    a left-over journal is reported at start-up and resumed with ``resume_samples``. On SIGINT
    or SIGTERM the samples not yet saved go to a bag in ``storage_dir`` (or, if it cannot be
    written, a named temporary folder).

Threads: the subscriptions live on a helper node (``<name>_streams``) spun by its own
single-threaded executor in the main thread; services, publishers and the diagnostics timer
live on ``coreg_node`` spun in a second thread, so a calibration never blocks the streams.
(rclpy's MultiThreadedExecutor with callback groups was measured to handle only a few hundred
messages per second here; the single-threaded one with a callback per message 2 x 2 kHz at
~90 % of a core, losing 8 % at 2 x 5 kHz; with the raw intake 2 x 5 kHz loses none at about a
third of a core: bench/bench_node.py.)
"""

from __future__ import annotations

import os
from pathlib import Path
import sys
import tempfile
import threading
import time
import traceback
from typing import Optional

from coreg_ros.core.errors import BagError, ConfigError, CoregError
from coreg_ros.core.pipeline import calibrate_streams, pair_for
from coreg_ros.core.settings import Settings
from coreg_ros.files.bag.per_message import typestore as bag_typestore
from coreg_ros.files.results import load_prior
from coreg_ros.ros import persistence
from coreg_ros.ros.buffer import GapCounter, reason_hint, REASONS, StreamBuffer
from coreg_ros.ros.convert import ns_to_stamp, pose_stamped_values, uncertain_pose_to_msg
from coreg_ros.ros.live_checks import LiveChecks
from coreg_ros.ros.parameters import (
    CALIBRATION_KEYS,
    check_params_files,
    declare_parameters,
    read_config,
    settings_from_values,
)
from coreg_ros.ros.raw_intake import RawIntake
from coreg_ros.ros.uncertainty_outputs import stored_result_dict, UncertaintyOutputs
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import PoseStamped, PoseWithCovarianceStamped
from rcl_interfaces.msg import SetParametersResult
import rclpy
from rclpy.event_handler import SubscriptionEventCallbacks
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.signals import SignalHandlerOptions
from std_srvs.srv import Trigger

NODE_NAME = 'coreg_node'
#: Seconds between two warnings about the same topic and rejection reason.
WARN_PERIOD = 5.0
#: History depth of the subscriptions: absorbs a pause of the stream thread (the GIL held by
#: the estimator or the journal, the intake's own pace) of 2 s at 5 kHz before DDS drops any.
SUB_DEPTH = 10_000
#: Environment switch back to one deserialised message per callback (the path before the raw
#: intake; kept as the benchmark's baseline and as a fallback): ``COREG_NODE_PLAIN=1``.
PLAIN_ENV = 'COREG_NODE_PLAIN'
#: Seconds between two warnings about the set-up (swapped frames, a wrong message type).
SETUP_WARN_PERIOD = 60.0
#: Seconds /diagnostics stays WARN after a count of problems (rejected, lost...) went up.
WARN_HOLD = 10.0
#: Seconds between two writes of the new samples to the journal: what a kill can lose.
FLUSH_PERIOD = 0.5
#: The message type of the pose topics.
POSE_TYPE = 'geometry_msgs/msg/PoseStamped'
RCLError = _rclpy.RCLError


def _os_reason(error: BaseException) -> str:
    """Return an OSError as 'strerror: file' (other errors as their text)."""
    if isinstance(error, OSError) and error.strerror:
        return f'{error.strerror}: {error.filename}' if error.filename else error.strerror
    return str(error) or type(error).__name__


def shutdown_quietly(context=None) -> None:
    """
    ``rclpy.try_shutdown`` that tolerates losing the race with rclpy's signal handler.

    On SIGINT/SIGTERM rclpy shuts the context down from its own thread; ``try_shutdown``
    checks ``ok()`` and then shuts down, so the handler can win in between and rcl raises
    "rcl_shutdown already called". The context is shut down either way.
    """
    try:
        rclpy.try_shutdown(context=context)
    except RCLError:
        if rclpy.ok(context=context):
            raise


def stream_qos(reliable: bool) -> QoSProfile:
    """Return the pose subscriptions' QoS: sensor-data (best effort) or reliable, deep history."""
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST, depth=SUB_DEPTH,
        reliability=ReliabilityPolicy.RELIABLE if reliable else ReliabilityPolicy.BEST_EFFORT,
        durability=DurabilityPolicy.VOLATILE)


#: QoS of the result topics: late subscribers get the last result.
LATCHED_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                         reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL)


class CoregNode(Node):
    """
    The coregistration node (see the module docstring for its interface).

    Parameters
    ----------
    **kwargs
        Passed to ``rclpy.node.Node`` (e.g. ``context``, ``parameter_overrides``).

    Raises
    ------
    ConfigError
        If the parameters are invalid.

    """

    def __init__(self, **kwargs):
        super().__init__(NODE_NAME, **kwargs)
        for line in declare_parameters(self):
            self.get_logger().warning(line)
        self.config = read_config(self)
        settings = self.config.settings
        self.topics = (settings.topic_a, *settings.topic_b)
        self.buffers = {t: StreamBuffer(self.config.buffer_capacity) for t in self.topics}
        self._warn_state = {}          # (topic, reason) -> [last log time, count since]
        self._saved_accepted = 0       # accepted-sample total at the last bag save
        self._io_lock = threading.Lock()
        self._last = None              # summary of the last calibration, for diagnostics
        self._pairing = {'n_paired': None, 'rate': None, 'summary': 'not yet paired',
                         'at_accepted': -1, 'next_time': 0.0}
        self._prev_problems = 0
        self._warn_until = 0.0         # monotonic time until which diagnostics stay WARN
        # What a stored result is valid for: one file per node name and configuration.
        self.config_key = persistence.config_key(settings.as_dict(), self.config.frames)
        self.result_name = persistence.result_file_name(self.get_name(), self.config_key)
        self._storage_error: Optional[str] = None   # one line; /diagnostics goes ERROR
        self._internal_error: Optional[str] = None  # a failed service or timer, ditto
        self._fallback_dir: Optional[str] = None    # named temporary folder if storage fails
        self.lost = dict.fromkeys(self.topics, 0)   # middleware message-lost events
        self.gaps = {t: GapCounter() for t in self.topics}
        self._marks = dict.fromkeys(self.topics, 0)  # accepted count at the last flush
        self._chunk_marks: list = []  # (start marks, end marks) of the unmerged chunks
        self.journal: Optional[persistence.SampleJournal] = None
        self._left_over: list = []     # journals of interrupted sessions, not resumed
        self._frame_problem: Optional[str] = None
        self._type_problems: dict = {}

        # The subscriptions get a node (and so an executor and a thread) of their own.
        self.stream_node = Node(f'{self.get_name()}_streams', namespace=self.get_namespace(),
                                context=self.context, use_global_arguments=False,
                                start_parameter_services=False)
        qos = stream_qos(self.config.qos_reliable)
        self.intake: Optional[RawIntake] = None
        if os.environ.get(PLAIN_ENV, '').strip() in ('', '0'):
            self.intake = RawIntake(self.buffers, self._warn_rejected, self._warn_undecodable)
        self._subs = [self._subscribe(t, qos) for t in self.topics]
        # rclpy's signal handler does not always wake both executors (seen with SIGTERM):
        # a cheap 2 Hz no-op timer makes the stream executor look at the context regularly.
        self.stream_node.create_timer(0.5, lambda: None)
        self.pub_base = self.create_publisher(PoseWithCovarianceStamped, '~/base_to_base',
                                              LATCHED_QOS)
        self.pub_tool = self.create_publisher(PoseWithCovarianceStamped, '~/tool_to_marker',
                                              LATCHED_QOS)
        self.pub_diag = self.create_publisher(DiagnosticArray, '/diagnostics', 10)
        self.create_service(Trigger, '~/calibrate', self._guarded('calibrate', self._on_calibrate))
        self.create_service(Trigger, '~/reset', self._guarded('reset', self._on_reset))
        self.create_service(Trigger, '~/save_samples',
                            self._guarded('save_samples', self._on_save_samples))
        self.create_timer(1.0, self._guarded_timer('diagnostics', self._publish_diagnostics))
        self.add_on_set_parameters_callback(self._check_parameters)
        self.uncertainty = UncertaintyOutputs(self)
        self.live = LiveChecks(self)
        self._republish_stored()
        self._start_journal()
        # rosbags' type store takes ~0.2 s to build (more under load): built now, not at the
        # first journal flush, where it would hold up the fused-pose and diagnostics timers.
        bag_typestore()
        self.create_timer(FLUSH_PERIOD, self._guarded_timer('journal', self.flush_journal))
        self.get_logger().info(
            f'listening to A {settings.topic_a}, B {", ".join(settings.topic_b)} '
            f'({"reliable" if self.config.qos_reliable else "sensor-data"} QoS); model '
            f'{settings.model}, method {settings.method}; storage {self.config.storage_dir}')

    # --- robustness ------------------------------------------------------------------------

    def _guarded(self, name: str, handler):
        """Wrap a service handler: any exception is answered (success=false), never raised."""
        def call(request, response):
            try:
                return handler(request, response)
            except Exception as e:  # a bug or an OS failure must not end the services thread
                self.get_logger().error(f'~/{name} failed: {traceback.format_exc()}')
                response.success = False
                response.message = (f'~/{name} failed: {type(e).__name__}: {_os_reason(e)}; '
                                    f'the node keeps its samples and runs on (see its log)')
                self._internal_error = response.message
                return response
        return call

    def _guarded_timer(self, name: str, callback):
        """Wrap a timer callback: an exception is logged (throttled) and shown in diagnostics."""
        def tick():
            try:
                callback()
            except Exception as e:
                self._internal_error = f'{name} failed: {type(e).__name__}: {_os_reason(e)}'
                self._warn_throttled(('timer', name), f'{self._internal_error}\n'
                                     f'{traceback.format_exc()}', level='error')
        return tick

    def _warn_throttled(self, key, line: str, level: str = 'warning',
                        period: float = WARN_PERIOD) -> None:
        """Log ``line`` at most once every ``period`` seconds per ``key``."""
        state = self._warn_state.setdefault(key, [-period, 0])
        now = time.monotonic()
        if now - state[0] >= period:
            getattr(self.get_logger(), level)(line)
            state[0] = now

    def _storage_failed(self, what: str, error: BaseException) -> str:
        """Record that ``storage_dir`` failed (diagnostics ERROR); return the one line."""
        self._storage_error = (f'cannot {what} in storage_dir {self.config.storage_dir} '
                               f'({_os_reason(error)}); fix storage_dir (a directory on a '
                               f'mounted disk with free space) and restart')
        self._warn_throttled(('storage', what), self._storage_error, level='error')
        return self._storage_error

    def fallback_dir(self) -> str:
        """Return a named temporary folder for what storage_dir cannot take (made once)."""
        if self._fallback_dir is None:
            self._fallback_dir = tempfile.mkdtemp(prefix=f'{self.get_name()}_samples_')
            self.get_logger().error(f'storage_dir failed: samples go to {self._fallback_dir}')
        return self._fallback_dir

    # --- subscriptions -------------------------------------------------------------------

    def _subscribe(self, topic: str, qos: QoSProfile):
        """Subscribe to a pose topic, counting the messages the middleware reports lost."""
        def on_lost(status) -> None:
            self.lost[topic] += int(status.total_count_change)

        raw = self.intake is not None
        callback = self.intake.callback(topic) if raw else self._make_callback(topic)
        try:
            sub = self.stream_node.create_subscription(
                PoseStamped, topic, callback, qos, raw=raw,
                event_callbacks=SubscriptionEventCallbacks(message_lost=on_lost))
        except Exception:  # an rmw without the message-lost event: the stamp gaps still count
            sub = self.stream_node.create_subscription(PoseStamped, topic, callback, qos,
                                                       raw=raw)
        if raw:
            self.intake.attach(topic, sub)
        return sub

    def _make_callback(self, topic: str):
        push = self.buffers[topic].push
        time_ns = time.time_ns

        def on_pose(msg: PoseStamped) -> None:
            # Cheap on purpose: scalars into a preallocated ring, no numpy, no logging.
            stamp, x, y, z, qw, qx, qy, qz = pose_stamped_values(msg)
            reason = push(stamp, time_ns(), x, y, z, qw, qx, qy, qz, msg.header.frame_id)
            if reason is not None:
                self._warn_rejected(topic, reason)

        return on_pose

    def _warn_rejected(self, topic: str, reason: str, count: int = 1) -> None:
        """Throttled warning: at most one per topic and reason every WARN_PERIOD seconds."""
        state = self._warn_state.setdefault((topic, reason), [-WARN_PERIOD, 0])
        state[1] += count
        now = time.monotonic()
        if now - state[0] >= WARN_PERIOD:
            self.get_logger().warning(
                f'{topic}: rejected {state[1]} message(s): {reason_hint(reason)} '
                f'(counts in /diagnostics)')
            state[0], state[1] = now, 0

    def _warn_undecodable(self, topic: str, count: int, error: BaseException) -> None:
        """Throttled warning about bytes on a pose topic that are not a PoseStamped."""
        self._warn_throttled(('undecodable', topic), (
            f'{topic}: {count} message(s) are not a serialized {POSE_TYPE} '
            f'({type(error).__name__}: {error}); a publisher sends raw bytes of another type: '
            f'fix that publisher (counts in /diagnostics)'))

    # --- services ------------------------------------------------------------------------

    def current_settings(self) -> Settings:
        """Calibration settings from the current parameter values."""
        return settings_from_values({k: self.get_parameter(k).value for k in CALIBRATION_KEYS})

    def snapshot(self) -> dict:
        """Return copies of the accumulated raw samples: topic -> PoseStream."""
        return {t: b.snapshot() for t, b in self.buffers.items()}

    def _on_calibrate(self, request, response):
        response.success, response.message = self.calibrate_and_publish()
        return response

    def calibrate_and_publish(self, streams: Optional[dict] = None, prior=None,
                              what: str = 'calibrate') -> tuple[bool, str]:
        """
        Calibrate, judge, publish and store (``~/calibrate``, ``auto_calibrate``...).

        Parameters
        ----------
        streams : dict of topic to PoseStream, optional
            The samples (default: a snapshot of everything held).
        prior : Prior, optional
            Default: ``prior_file``, else the stored result if ``use_last_result_as_prior``.
        what : str
            Who asks, for the log lines.

        Returns
        -------
        (success, message) : (bool, str)
            As the Trigger answer; never raises.

        """
        t0 = time.monotonic()
        try:
            settings = self.current_settings()
            prior = self._prior() if prior is None else prior
            streams = self.snapshot() if streams is None else streams
            result, report = calibrate_streams(
                streams[settings.topic_a], [streams[t] for t in settings.topic_b], settings,
                prior, frames=(self.config.frame_base_a, self.config.frame_base_b))
        except CoregError as e:
            self.get_logger().warning(f'{what} refused: {e}')
            return False, str(e)
        except Exception as e:  # a bug must not kill the node: answer, log the traceback
            self.get_logger().error(f'{what} failed: {traceback.format_exc()}')
            return False, f'internal error ({type(e).__name__}: {e}); see the node log'
        seconds = time.monotonic() - t0
        chi2_dof = result.chi2 / result.dof if result.dof > 0 else float('nan')
        timing = result.time_offset
        self._last = {'n_pairs': result.n_pairs, 'chi2_dof': chi2_dof,
                      'p_value': result.p_value, 'success': result.success,
                      'seconds': seconds, 'pairing': report.summary(),
                      'fit_consistent': result.fit_consistent,
                      'rejected_pairs': result.n_rejected,
                      'time_offset_s': None if timing is None else timing.value_s,
                      'time_offset_sigma_s': None if timing is None else timing.sigma_s,
                      'verdict': result.verdict}
        inconsistent = result.fit_consistent is False and result.status > 0
        publish_anyway = inconsistent and bool(
            self.get_parameter('publish_inconsistent').value)
        if not result.success and not publish_anyway:
            message = (
                f'not published: {result.verdict} ({report.summary()}); set '
                f'publish_inconsistent:=true to publish it anyway' if inconsistent else
                f'no convergence after {result.iterations} iterations: {result.message}; '
                f'{report.summary()}')
            self.get_logger().warning(f'{what}: {message}')
            return False, message
        stamp_ns = self._publish_result(result.base_to_base, result.tool_to_marker)
        self.uncertainty.set_result(result)
        self.live.set_result(result)
        try:
            with self._io_lock:
                path = persistence.save_result(
                    self.config.storage_dir, stored_result_dict(result), self.config.frames,
                    settings.as_dict(), name=self.result_name,
                    extra={'node': self.get_fully_qualified_name(),
                           'config_key': self.config_key, 'stamp_ns': stamp_ns})
            stored = f'stored in {path}'
        except OSError as e:
            stored = f'NOT stored: {self._storage_failed("store the result", e)}'
        p0 = result.base_to_base.position
        p1 = result.tool_to_marker.position
        offset = '' if timing is None else (
            f'time offset {timing.value_s * 1e3:.3f} ± {timing.sigma_s * 1e3:.3f} ms, '
            if timing.estimated else f'time offset {timing.value_s * 1e3:.3f} ms (given), ')
        message = (
            ('PUBLISHED ALTHOUGH INCONSISTENT: ' + result.verdict + '; ' if inconsistent
             else '') +
            f'{result.n_pairs} pairs, {settings.method}/{settings.model}: chi2/dof '
            f'{chi2_dof:.3g}, p {result.p_value:.3g}, {offset}{result.n_rejected} rejected, '
            f'{result.iterations} iterations, '
            f'{seconds:.2f} s; base_to_base p [{p0[0]:.4f}, {p0[1]:.4f}, {p0[2]:.4f}] m, '
            f'tool_to_marker p [{p1[0]:.4f}, {p1[1]:.4f}, {p1[2]:.4f}] m; {stored}')
        self.get_logger().info(f'calibrated ({what}): {message}')
        return not inconsistent, message

    def _prior(self):
        """Return the prior of the next calibration: prior_file, else the stored result."""
        path = str(self.get_parameter('prior_file').value).strip()
        if path:
            return load_prior(os.path.expanduser(path))
        if bool(self.get_parameter('use_last_result_as_prior').value):
            stored = Path(self.config.storage_dir) / self.result_name
            if stored.is_file():
                return load_prior(stored)
        return None

    def _on_reset(self, request, response):
        with self._io_lock:
            held = sum(len(b) for b in self.buffers.values())
            for b in self.buffers.values():
                b.clear()
            for g in self.gaps.values():
                g.restart()
            self._saved_accepted = self._accepted_total()
            # the journal holds the session's samples: forgotten with them
            self._marks = {t: b.accepted for t, b in self.buffers.items()}
            if self.journal is not None:
                self.journal.remove()
                self.journal = None
        self._start_journal()
        self.live.reset()
        response.success = True
        response.message = f'forgot {held} samples; the published result is kept'
        return response

    def _on_save_samples(self, request, response):
        try:
            path = self.save_samples()
        except CoregError as e:
            response.success, response.message = False, str(e)
            return response
        if path is None:
            response.success, response.message = False, 'no samples to save yet'
        elif self._last_save_error:
            response.success = False
            response.message = f'{self._last_save_error}; the samples were saved to {path}'
        else:
            response.success, response.message = True, str(path)
        return response

    # --- results, persistence ------------------------------------------------------------

    def _publish_result(self, base_to_base, tool_to_marker,
                        stamp_ns: Optional[int] = None) -> int:
        """Publish the two transforms stamped ``stamp_ns`` (default: now); return the stamp."""
        if stamp_ns is None:
            stamp_ns = self.get_clock().now().nanoseconds
        stamp = ns_to_stamp(int(stamp_ns))
        self.pub_base.publish(uncertain_pose_to_msg(base_to_base, self.config.frame_base_b,
                                                    stamp))
        self.pub_tool.publish(uncertain_pose_to_msg(tool_to_marker, self.config.frame_tool,
                                                    stamp))
        return int(stamp_ns)

    def _describe_config(self) -> str:
        return persistence.describe_config({'settings': self.config.settings.as_dict(),
                                            'frames': self.config.frames})

    def _republish_stored(self) -> None:
        """Republish the stored result of this node and configuration, and only that."""
        storage, log = self.config.storage_dir, self.get_logger()
        settings, frames = self.config.settings.as_dict(), self.config.frames
        try:
            stored = persistence.load_result(storage, self.result_name)
        except CoregError as e:
            log.error(str(e))
            stored = None
        for path in persistence.other_results(storage, self.get_name(), self.config_key):
            try:
                other = persistence.load_result(storage, path.name)
            except CoregError as e:
                log.warning(f'{e} (not republished)')
                continue
            if other is None:
                continue
            if (stored is None and path.name == persistence.RESULT_FILE
                    and persistence.matches_config(other[0], settings, frames)):
                stored = other  # an older version's result.yaml of this very configuration
                continue
            log.info(f'not republishing {path}: it was calibrated for '
                     f'{persistence.describe_config(other[0])}; this node is configured for '
                     f'{self._describe_config()}')
        if stored is None:
            return
        doc, base_to_base, tool_to_marker = stored
        stamp_ns = persistence.stamp_ns_of(doc)
        self._publish_result(base_to_base, tool_to_marker, stamp_ns)
        self.uncertainty.set_stored(doc, base_to_base, tool_to_marker)
        self.live.set_stored(doc, base_to_base, tool_to_marker)
        r = doc['result']
        dof = r.get('dof') or 0
        self._last = {'n_pairs': r.get('n_pairs'), 'success': r.get('success'),
                      'chi2_dof': (r['chi2'] / dof) if dof and r.get('chi2') is not None
                      else float('nan'),
                      'p_value': r.get('p_value'), 'seconds': None,
                      'pairing': f'stored result of {doc.get("saved_at", "?")}'}
        log.info(f'republished the stored result of {doc.get("saved_at", "?")} '
                 f'({r.get("n_pairs")} pairs, {self._describe_config()}), stamped with its '
                 f'calibration time')

    def _accepted_total(self) -> int:
        return sum(b.accepted for b in self.buffers.values())

    def save_samples(self, report=None) -> Optional[str]:
        """
        Write the held samples to a new bag in storage_dir; None if there are none.

        If storage_dir cannot be written, the bag goes to a named temporary folder instead
        and ``_last_save_error`` says why (diagnostics go ERROR). ``report`` (a callable
        taking one line) replaces the node logger, which cannot publish to /rosout any more
        once the context is shut down.
        """
        self._last_save_error = None
        with self._io_lock:
            accepted = self._accepted_total()
            streams = self.snapshot()
            if not any(len(s) for s in streams.values()):
                return None
            try:
                path = persistence.save_samples(self.config.storage_dir, streams)
            except (OSError, BagError) as e:
                self._last_save_error = self._storage_failed('save the samples', e)
                path = persistence.save_samples(self.fallback_dir(), streams)
            self._saved_accepted = accepted
        line = f'saved {sum(len(s) for s in streams.values())} samples to {path}'
        (report or self.get_logger().info)(line)
        return str(path)

    _last_save_error: Optional[str] = None

    def save_on_shutdown(self) -> bool:
        """
        Save the samples received since the last save, if any (called on shutdown).

        Returns False if they could not be saved anywhere (the journal is then kept).
        """
        def report(line):
            print(f'coreg_node: {line}', file=sys.stderr)

        saved = True
        if self._accepted_total() != self._saved_accepted:
            try:
                self.save_samples(report=report)
                if self._last_save_error:
                    report(self._last_save_error)
            except Exception as e:  # shutting down: report, do not raise over the real exit
                report(f'could not save the samples on shutdown: {_os_reason(e)}')
                saved = False
        if saved and self.journal is not None:
            self.journal.remove()  # a clean end: the samples are in the bag
        elif self.journal is not None:
            report(f'the samples are still in the journal {self.journal.folder}')
        return saved

    # --- journal ----------------------------------------------------------------------------

    def _start_journal(self) -> None:
        """Open this session's journal; resume or report a journal a killed session left."""
        storage, name, key = self.config.storage_dir, self.get_name(), self.config_key
        left = persistence.left_over_journals(storage, name, key)
        if self.journal is not None:
            left = [p for p in left if p != self.journal.folder]
        if left and self.config.resume_samples and self._accepted_total() == 0:
            try:
                self._resume(left[-1])
                left = left[:-1]
            except Exception as e:
                self.get_logger().error(f'cannot resume the journal {left[-1]}: '
                                        f'{_os_reason(e)}; it is kept, starting afresh')
        self._left_over = left
        for path in left:
            self.get_logger().warning(
                f'an interrupted session (the node was killed) left samples in {path}; '
                f'restart with resume_samples:=true to continue from them (the newest)')
        if self.journal is None:
            try:
                self.journal = persistence.SampleJournal(
                    persistence.new_journal_path(storage, name, key))
            except (OSError, BagError) as e:
                self._storage_failed('write the sample journal', e)
                self.journal = persistence.SampleJournal(
                    persistence.new_journal_path(self.fallback_dir(), name, key))

    def _resume(self, folder: Path) -> None:
        """Load a left-over journal into the buffers and continue writing it."""
        streams = persistence.read_journal(folder, self.topics)
        n = 0
        for topic, s in streams.items():
            b = self.buffers[topic]
            before = b.accepted
            b.push_many(s.stamps, s.receive_stamps, s.position, s.quat_wxyz, s.frame_id)
            n += b.accepted - before
            self.gaps[topic].update(s.stamps)
        # This session's journal starts with them, in one bag; then the old one goes.
        self.journal = persistence.SampleJournal(persistence.new_journal_path(
            self.config.storage_dir, self.get_name(), self.config_key))
        self.journal.append({t: b.since(0)[1] for t, b in self.buffers.items()})
        persistence.remove_journal(folder)
        self._marks = {t: b.accepted for t, b in self.buffers.items()}
        self._saved_accepted = 0
        self.get_logger().info(f'resumed {n} samples of an interrupted session from {folder} '
                               f'({", ".join(f"{t}: {len(b)}" for t, b in self.buffers.items())})')

    def flush_journal(self) -> None:
        """Write the samples accepted since the last flush to the journal (timer)."""
        with self._io_lock:
            new, ends = {}, {}
            starts = dict(self._marks)
            for topic, b in self.buffers.items():
                ends[topic], new[topic], _ = b.since(self._marks[topic])
                self.gaps[topic].update(new[topic].stamps)
            self._marks = ends
            if self.journal is None or not any(len(s.stamps) for s in new.values()):
                return
            try:
                self.journal.append(new)
            except (OSError, BagError) as e:
                self._journal_failed(e)
                return
            self._chunk_marks.append((self.journal.next_seq - 1, starts, ends))
            if len(self._chunk_marks) >= persistence.MERGE_AFTER:
                self._merge_journal()

    def _journal_failed(self, error: Exception) -> None:
        """Move the journal to the fallback folder and write every held sample there."""
        self._storage_failed('write the sample journal', error)
        self.journal = persistence.SampleJournal(persistence.new_journal_path(
            self.fallback_dir(), self.get_name(), self.config_key))
        self._chunk_marks = []
        held = {t: b.since(0)[1] for t, b in self.buffers.items()}
        self.journal.append(held)

    def _merge_journal(self) -> None:
        """Merge the small chunks into one bag from the samples still held (io lock held)."""
        (seq0, first, _), (seq1, _, last) = self._chunk_marks[0], self._chunk_marks[-1]
        self._chunk_marks = []
        streams = {}
        for topic, b in self.buffers.items():
            _, streams[topic], complete = b.since(first[topic], last[topic])
            if not complete:
                return  # overwritten or forgotten meanwhile: leave the chunks as they are
        self.journal.merge(streams, seq0, seq1)

    # --- parameters ------------------------------------------------------------------------

    def _check_parameters(self, params) -> SetParametersResult:
        """Refuse run-time changes that would make invalid Settings."""
        changed = {p.name: p.value for p in params if p.name in CALIBRATION_KEYS}
        if not changed:
            return SetParametersResult(successful=True)
        values = {k: self.get_parameter(k).value for k in CALIBRATION_KEYS
                  if self.has_parameter(k)}
        values.update(changed)
        try:
            settings_from_values(values)
        except CoregError as e:
            return SetParametersResult(successful=False, reason=str(e))
        return SetParametersResult(successful=True)

    # --- diagnostics -------------------------------------------------------------------------

    def _update_pairing(self) -> None:
        """Pair the held samples now and then (rate-limited to a few % of one core)."""
        state = self._pairing
        accepted = self._accepted_total()
        now = time.monotonic()
        if accepted == state['at_accepted'] or now < state['next_time']:
            return
        t0 = time.monotonic()
        settings = self.current_settings()
        streams = self.snapshot()
        try:
            pairs, report = pair_for(streams[settings.topic_a],
                                     [streams[t] for t in settings.topic_b], settings,
                                     self.uncertainty.timing)
            state['n_paired'] = report.n_paired
            state['rate'] = report.n_paired / report.n_b if report.n_b else None
            state['summary'] = report.summary()
        except CoregError as e:
            state['n_paired'], state['rate'], state['summary'] = 0, None, str(e)
        spent = time.monotonic() - t0
        state['at_accepted'] = accepted
        state['next_time'] = now + max(1.0, 20.0 * spent)

    def _check_frames(self) -> Optional[str]:
        """Name swapped devices from the header frame ids (warned, throttled)."""
        base_a, base_b = self.config.frame_base_a, self.config.frame_base_b
        topic_a, topic_b = self.config.settings.topic_a, self.config.settings.topic_b[0]
        frame_a, frame_b = self.buffers[topic_a].frame_id, self.buffers[topic_b].frame_id
        problem = None
        if base_a != base_b and (frame_a == base_b or frame_b == base_a):
            got = ', '.join(f'{t} in {f!r}' for t, f in ((topic_a, frame_a), (topic_b, frame_b))
                            if f is not None)
            problem = (f"the messages arrive in the other device's base frame ({got}; "
                       f'configured: frame_base_a {base_a!r} for {topic_a}, frame_base_b '
                       f'{base_b!r} for {topic_b}): the devices look swapped; exchange topic_a '
                       f'and topic_b (a calibration would give the inverse transforms)')
            self._warn_throttled(('frames',), problem, period=SETUP_WARN_PERIOD)
        self._frame_problem = problem
        return problem

    def _check_types(self) -> dict:
        """Find publishers of another message type on the pose topics (warned, throttled)."""
        problems = {}
        for topic in self.topics:
            try:
                infos = self.get_publishers_info_by_topic(topic)
            except Exception:  # the graph is not available (shutting down)
                continue
            wrong = sorted({i.topic_type for i in infos} - {POSE_TYPE})
            if wrong:
                problems[topic] = (f'{topic} is published as {", ".join(wrong)}, but coreg_node '
                                   f'expects {POSE_TYPE}: those messages never arrive; publish '
                                   f'PoseStamped (convert it) or point the topic parameter at '
                                   f'a PoseStamped topic')
                self._warn_throttled(('type', topic), problems[topic],
                                     period=SETUP_WARN_PERIOD)
        self._type_problems = problems
        return problems

    def diagnostics(self) -> DiagnosticStatus:
        """Return the diagnostic status: counts by topic and reason, pairing, last result."""
        self._update_pairing()
        values = []
        problems = 0
        types = self._check_types()
        for topic, b in self.buffers.items():
            rejected = sum(b.rejected.values())
            missing = self.gaps[topic].missing
            undecodable = 0 if self.intake is None else self.intake.undecodable[topic]
            problems += rejected + b.dropped + self.lost[topic] + missing + undecodable
            values += [KeyValue(key=f'{topic} received', value=str(b.received)),
                       KeyValue(key=f'{topic} accepted', value=str(b.accepted)),
                       KeyValue(key=f'{topic} rejected', value=str(rejected))]
            values += [KeyValue(key=f'{topic} rejected {r}', value=str(b.rejected[r]))
                       for r in REASONS]
            period = self.gaps[topic].period_ns
            values += [KeyValue(key=f'{topic} held', value=str(len(b))),
                       KeyValue(key=f'{topic} buffer fill',
                                value=f'{len(b) / b.capacity:.3f}'),
                       KeyValue(key=f'{topic} dropped oldest', value=str(b.dropped)),
                       KeyValue(key=f'{topic} lost in middleware', value=str(self.lost[topic])),
                       KeyValue(key=f'{topic} missing from stamps', value=str(missing)),
                       KeyValue(key=f'{topic} undecodable', value=str(undecodable)),
                       KeyValue(key=f'{topic} stamp rate',
                                value='n/a' if not period else f'{1e9 / period:.4g} Hz'),
                       KeyValue(key=f'{topic} frame_id', value=str(b.frame_id)),
                       KeyValue(key=f'{topic} type problem', value=types.get(topic, 'none'))]
        pairing = self._pairing
        values += [KeyValue(key='paired', value=str(pairing['n_paired'])),
                   KeyValue(key='pairing rate',
                            value='n/a' if pairing['rate'] is None else f'{pairing["rate"]:.3f}'),
                   KeyValue(key='pairing', value=pairing['summary'])]
        last = self._last or {}
        for key in ('n_pairs', 'chi2_dof', 'p_value', 'success', 'fit_consistent',
                    'time_offset_s', 'time_offset_sigma_s', 'rejected_pairs', 'seconds',
                    'verdict'):
            v = last.get(key)
            values.append(KeyValue(key=f'last calibration {key}',
                                   value='n/a' if v is None else
                                   (f'{v:.6g}' if isinstance(v, float) else str(v))))
        frames = self._check_frames()
        journal = self.journal
        values += [KeyValue(key='frames', value=frames or 'as configured'),
                   KeyValue(key='storage', value=self._storage_error or 'ok'),
                   KeyValue(key='journal', value='none' if journal is None else
                            f'{journal.folder} ({journal.n_chunks} bags)'),
                   KeyValue(key='interrupted sessions',
                            value=', '.join(map(str, self._left_over)) or 'none'),
                   KeyValue(key='internal error', value=self._internal_error or 'none')]
        status = DiagnosticStatus(name=f'{self.get_name()}: coregistration',
                                  hardware_id=' + '.join(self.topics), values=values)
        if self._storage_error or self._internal_error:
            status.level = DiagnosticStatus.ERROR
            status.message = self._storage_error or self._internal_error
        elif types or frames:
            status.level = DiagnosticStatus.WARN
            status.message = next(iter(types.values())) if types else frames
        elif problems > self._prev_problems or time.monotonic() < self._warn_until:
            if problems > self._prev_problems:  # held a while, so a 1 Hz reader sees it
                self._warn_until = time.monotonic() + WARN_HOLD
            status.level = DiagnosticStatus.WARN
            status.message = ('rejecting, dropping or losing samples (see the counts: lost in '
                              'middleware, missing from stamps, rejected, dropped oldest)')
        else:
            status.level = DiagnosticStatus.OK
            status.message = (f'{min(len(b) for b in self.buffers.values())} samples held'
                              if not last else f'last calibration: {last.get("n_pairs")} pairs')
        self._prev_problems = problems
        return status

    def _publish_diagnostics(self) -> None:
        msg = DiagnosticArray()
        msg.header.stamp = self.get_clock().now().to_msg()
        live = self.live.tick()  # guidance and watchdog (they never raise)
        msg.status = [self.diagnostics(), *live]
        self.pub_diag.publish(msg)


def main(args=None) -> int:
    """Run coreg_node until SIGINT or SIGTERM; return the exit code."""
    argv = list(sys.argv if args is None else args)
    try:  # a bad parameter file: one line, not rcl's traceback
        check_params_files(argv, NODE_NAME)
    except ConfigError as e:
        print(f'coreg_node: {e}', file=sys.stderr)
        return 1
    # ALL: rclpy's handlers for both SIGINT and SIGTERM shut the context down, so spin
    # returns and the finally block saves the samples in either case.
    try:
        rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.ALL)
    except RCLError as e:
        reason = str(e).split(', at ')[0]
        print(f'coreg_node: cannot start ROS: {reason}; check the --ros-args arguments',
              file=sys.stderr)
        return 1
    node = None
    code = 0
    services = None
    try:
        node = CoregNode()
        streams = SingleThreadedExecutor()
        streams.add_node(node.stream_node)
        control = SingleThreadedExecutor()
        control.add_node(node)
        services = threading.Thread(target=_spin_quietly, args=(control,), daemon=True,
                                    name='coreg_services')
        services.start()
        streams.spin()
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except RCLError:
        # A signal can shut the context down between spin's ok() check and its wait set;
        # rcl then refuses the wait set. That is a normal shutdown, anything else is not.
        if rclpy.ok():
            raise
    except CoregError as e:
        print(f'coreg_node: {e}', file=sys.stderr)
        code = 1
    finally:
        try:
            shutdown_quietly()  # also stops the services thread's spin
        finally:  # the samples are saved even if shutting down fails otherwise
            if services is not None:
                services.join(10.0)
            if node is not None:
                if not node.save_on_shutdown():
                    code = code or 1
                node.stream_node.destroy_node()
                node.destroy_node()
    return code


def _spin_quietly(executor) -> None:
    """
    Spin in a thread until shutdown; the shutdown race of main() is normal here too.

    No exception ends this thread while ROS runs: the callbacks answer their own failures,
    and anything else is printed and the spin goes on.
    """
    while True:
        try:
            executor.spin()
            return
        except (KeyboardInterrupt, ExternalShutdownException):
            return
        except Exception:
            if not rclpy.ok():
                return
            print(f'coreg_node: services thread: {traceback.format_exc()}', file=sys.stderr)
            time.sleep(0.1)


if __name__ == '__main__':
    sys.exit(main())

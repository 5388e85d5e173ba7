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
    ``~/calibrate`` runs ``calibration.pipeline.calibrate_streams`` on a snapshot of the
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

Modules: this one assembles the node (its subscriptions, robustness wrappers and ``main``);
``node_services`` (calibrate, reset, save_samples, parameters), ``node_storage`` (stored
result, journal, samples on shutdown) and ``node_status`` (/diagnostics) hold its other parts;
``lifecycle`` the shutdown race ``main`` shares with the tools.

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
import sys
import threading
import time
import traceback
from typing import Optional

from coreg_ros.core.errors import ConfigError, CoregError
from coreg_ros.files.bag.per_message import typestore as bag_typestore
from coreg_ros.ros import persistence
from coreg_ros.ros.buffer import GapCounter, reason_hint, StreamBuffer
from coreg_ros.ros.interface import LATCHED_QOS, NODE_NAME, POSE_TYPE, stream_qos
from coreg_ros.ros.lifecycle import (
    ended_by_shutdown,
    RCLError,
    record_stop_signals,
    shutdown_quietly,
)
from coreg_ros.ros.live_checks import LiveChecks
from coreg_ros.ros.messages import pose_stamped_values
from coreg_ros.ros.node_services import NodeServices
from coreg_ros.ros.node_status import NodeStatus
from coreg_ros.ros.node_storage import NodeStorage, os_reason
from coreg_ros.ros.parameters import check_params_files, declare_parameters, read_config
from coreg_ros.ros.raw_intake import RawIntake
from coreg_ros.ros.throttle import Throttle, WARN_PERIOD
from coreg_ros.ros.uncertainty_outputs import UncertaintyOutputs
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped, PoseWithCovarianceStamped
import rclpy
from rclpy.event_handler import SubscriptionEventCallbacks
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import QoSProfile
from rclpy.signals import SignalHandlerOptions
from std_srvs.srv import Trigger

#: What other modules and the tests import from here (the interface's names too).
__all__ = ['CoregNode', 'FLUSH_PERIOD', 'LATCHED_QOS', 'main', 'NODE_NAME', 'PLAIN_ENV',
           'RCLError', 'shutdown_quietly']

#: Environment switch back to one deserialised message per callback (the path before the raw
#: intake; kept as the benchmark's baseline and as a fallback): ``COREG_NODE_PLAIN=1``.
PLAIN_ENV = 'COREG_NODE_PLAIN'
#: Seconds between two writes of the new samples to the journal: what a kill can lose.
FLUSH_PERIOD = 0.5


class CoregNode(NodeServices, NodeStorage, NodeStatus, Node):
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
        self._log_throttle = Throttle()  # one line per problem and WARN_PERIOD
        self._rejected_since: dict = {}  # (topic, reason) -> rejections since its last line
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
                response.message = (f'~/{name} failed: {type(e).__name__}: {os_reason(e)}; '
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
                self._internal_error = f'{name} failed: {type(e).__name__}: {os_reason(e)}'
                self._warn_throttled(('timer', name), f'{self._internal_error}\n'
                                     f'{traceback.format_exc()}', level='error')
        return tick

    def _warn_throttled(self, key, line: str, level: str = 'warning',
                        period: float = WARN_PERIOD) -> None:
        """Log ``line`` at most once every ``period`` seconds per ``key``."""
        if self._log_throttle.ready(key, period):
            getattr(self.get_logger(), level)(line)

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
        key = (topic, reason)
        self._rejected_since[key] = self._rejected_since.get(key, 0) + count
        if self._log_throttle.ready(key):
            self.get_logger().warning(
                f'{topic}: rejected {self._rejected_since[key]} message(s): '
                f'{reason_hint(reason)} (counts in /diagnostics)')
            self._rejected_since[key] = 0

    def _warn_undecodable(self, topic: str, count: int, error: BaseException) -> None:
        """Throttled warning about bytes on a pose topic that are not a PoseStamped."""
        self._warn_throttled(('undecodable', topic), (
            f'{topic}: {count} message(s) are not a serialized {POSE_TYPE} '
            f'({type(error).__name__}: {error}); a publisher sends raw bytes of another type: '
            f'fix that publisher (counts in /diagnostics)'))


def main(args=None) -> int:
    """Run coreg_node until SIGINT or SIGTERM; return the exit code."""
    argv = list(sys.argv if args is None else args)
    try:  # a bad parameter file: one line, not rcl's traceback
        check_params_files(argv, NODE_NAME)
    except ConfigError as e:
        print(f'coreg_node: {e}', file=sys.stderr)
        return 1
    # ALL: rclpy's handlers for both SIGINT and SIGTERM shut the context down, so spin
    # returns and the finally block saves the samples in either case; Python's own handler
    # only records the signal, so that no late KeyboardInterrupt cuts the saving short.
    stops = record_stop_signals()
    try:
        rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.ALL)
    except RCLError as e:
        reason = str(e).split(', at ')[0]
        print(f'coreg_node: cannot start ROS: {reason}; check the --ros-args arguments',
              file=sys.stderr)
        return 1
    if stops:  # stopped before ROS was up: nothing was collected yet
        shutdown_quietly()
        return 128 + int(stops[0])
    node = None
    code = 0
    services = None
    try:
        # A signal can shut the context down between spin's ok() check and its wait set; rcl
        # then refuses the wait set. That is a normal shutdown, as a Ctrl-C is (lifecycle).
        with ended_by_shutdown():
            node = CoregNode()
            streams = SingleThreadedExecutor()
            streams.add_node(node.stream_node)
            control = SingleThreadedExecutor()
            control.add_node(node)
            services = threading.Thread(target=_spin_quietly, args=(control,), daemon=True,
                                        name='coreg_services')
            services.start()
            streams.spin()
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
            with ended_by_shutdown():
                executor.spin()
            return
        except Exception:
            if not rclpy.ok():
                return
            print(f'coreg_node: services thread: {traceback.format_exc()}', file=sys.stderr)
            time.sleep(0.1)


if __name__ == '__main__':
    sys.exit(main())

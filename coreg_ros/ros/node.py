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
    so late subscribers get the last result; the same two transforms on ``/tf_static``
    (``publish_tf``: ``frame_base_b`` -> ``frame_base_a``, ``frame_tool`` -> ``frame_marker``,
    ``ros.static_tf``); ``/diagnostics`` at 1 Hz (with messages lost in
    the middleware or missing from the stamps, swapped frame ids, a wrong message type on a
    topic, and storage errors). Once a calibration exists, ``~/fused_pose`` and
    ``~/uncertainty_markers`` (``ros.uncertainty_outputs``). The live checks
    (``ros.live_checks``) add two statuses to each /diagnostics message: guidance while
    collecting (``<node>: guidance``) and the watchdog of the published calibration
    (``<node>: watchdog``); and publish ``~/calibration_stale``.
A rig
    With a devices list in the parameter file (``devices``, ``device.<name>.*``) every topic
    above and the /diagnostics statuses are per device (``~/<name>/base_to_base``...,
    ``<node>/<name>: ...``): one channel per device, each calibrated with A
    (``ros.rig_channels``); ``~/calibrate`` calibrates them all.
Persistence
    The result is stored atomically in ``storage_dir`` under a name of the node and its
    configuration (model, topics, frames) and republished at start-up only by a node of that
    configuration, stamped with its calibration time. The accepted samples are journalled to
    rosbag2 chunks in ``storage_dir`` every ``FLUSH_PERIOD`` s, so a kill loses at most that;
    a left-over journal is reported at start-up and resumed with ``resume_samples``. On SIGINT
    or SIGTERM the samples not yet saved go to a bag in ``storage_dir`` (or, if it cannot be
    written, a named temporary folder).

Composition: ``CoregNode`` declares the parameters, owns the ROS handles (subscriptions,
publishers, services, timers, parameter callbacks) and hands its collaborators what each
uses: ``Alerts`` (``ros.alerts``: throttled log lines, the standing errors, the callback
guards), ``SampleStore`` (``ros.sample_store``: intake, buffers, counts, journal, sample
bags), ``Calibrator`` (``ros.calibrator``: the fit off the executor thread, the result topics,
the stored result), ``UncertaintyOutputs``, ``LiveChecks`` and ``StatusPublisher``
(``ros.status_publisher``: /diagnostics). ``lifecycle`` holds the shutdown race ``main``
shares with the tools.

Threads: the subscriptions live on a helper node (``<name>_streams``) spun by its own
single-threaded executor in the main thread; services, publishers and the timers live on
``coreg_node`` spun in a second thread (``NodeExecutors``), so a calibration never blocks the
streams; a ``~/calibrate`` fit runs in a third, so it does not block the timers either.
(rclpy's MultiThreadedExecutor with callback groups was measured to handle only a few hundred
messages per second here; the single-threaded one with a callback per message 2 x 2 kHz at
~90 % of a core, losing 8 % at 2 x 5 kHz; with the raw intake 2 x 5 kHz loses none at about a
third of a core: bench/bench_node.py.)
"""

from __future__ import annotations

from dataclasses import dataclass
import os
import sys
import threading
import time
import traceback

from coreg_ros.core.errors import ConfigError, CoregError
from coreg_ros.files.bag.per_message import typestore as bag_typestore
from coreg_ros.ros import persistence
from coreg_ros.ros.alerts import Alerts
from coreg_ros.ros.calibrator import Calibrator
from coreg_ros.ros.interface import LATCHED_QOS, NODE_NAME, stream_qos
from coreg_ros.ros.lifecycle import (
    ended_by_shutdown,
    RCLError,
    record_stop_signals,
    shutdown_quietly,
)
from coreg_ros.ros.live_checks import LiveChecks, STALE_QOS
from coreg_ros.ros.live_noise import NoiseSources
from coreg_ros.ros.parameters import (
    check_params_files,
    declare_parameters,
    NodeConfig,
    ParameterView,
    read_config,
)
from coreg_ros.ros.rig_channels import device_config, DeviceView, rig_topics
from coreg_ros.ros.sample_store import FLUSH_PERIOD, SampleStore
from coreg_ros.ros.static_tf import StaticTf
from coreg_ros.ros.status_publisher import StatusPublisher
from coreg_ros.ros.uncertainty_outputs import (
    DRAIN_PERIOD,
    FUSED_QOS,
    MARKER_QOS,
    UncertaintyOutputs,
)
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped, PoseWithCovarianceStamped
import rclpy
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.event_handler import SubscriptionEventCallbacks
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import QoSProfile
from rclpy.signals import SignalHandlerOptions
from std_msgs.msg import Bool
from std_srvs.srv import Trigger
from visualization_msgs.msg import MarkerArray

#: What other modules and the tests import from here (the interface's names too).
__all__ = ['CoregNode', 'FLUSH_PERIOD', 'LATCHED_QOS', 'main', 'NODE_NAME', 'NodeExecutors',
           'PLAIN_ENV', 'RCLError', 'shutdown_quietly']

#: Environment switch back to one deserialised message per callback (the path before the raw
#: intake; kept as the benchmark's baseline and as a fallback): ``COREG_NODE_PLAIN=1``.
PLAIN_ENV = 'COREG_NODE_PLAIN'
#: Longest wait of the main thread's spin (s): how soon it sees a SIGINT or SIGTERM.
STOP_POLL_S = 0.1


@dataclass(frozen=True)
class Channel:
    """What calibrates, guides and watches one device B against A (a rig has one per device)."""

    device: str
    calibrator: Calibrator
    outputs: UncertaintyOutputs
    live: LiveChecks
    status: StatusPublisher
    noise: NoiseSources


class CoregNode(Node):
    """
    The coregistration node (see the module docstring for its interface).

    Parameters
    ----------
    **kwargs
        Passed to ``rclpy.node.Node`` (e.g. ``context``, ``cli_args``,
        ``parameter_overrides``).

    Attributes
    ----------
    config : NodeConfig
        What the parameters say at start-up.
    params : ParameterView
        Their current values.
    alerts, store, calibrator, outputs, live, status
        The collaborators (``Alerts``, ``SampleStore``, ``Calibrator``,
        ``UncertaintyOutputs``, ``LiveChecks``, ``StatusPublisher``).
    stream_node : rclpy.node.Node
        The helper node of the subscriptions (its own executor and thread).

    Raises
    ------
    ConfigError
        If the parameters are invalid.

    """

    def __init__(self, **kwargs):
        super().__init__(NODE_NAME, **kwargs)
        for line in declare_parameters(self):
            self.get_logger().warning(line)
        self.config = config = read_config(self)
        self.noise = NoiseSources(config.noise_file, config.settings)
        self.params = ParameterView(self, self.noise)
        settings, log, name = config.settings, self.get_logger(), self.get_name()
        # What a stored result or a journal is valid for: one per node name and configuration
        # (a rig's journal holds every device's topics; a noise file's covariances are part
        # of it).
        topics_b = rig_topics(config.devices) or settings.topic_b
        stated = settings.noise_dict()
        key = persistence.config_key({**settings.as_dict(), 'topic_b': list(topics_b), **(
            {'noise_file': stated} if stated else {})}, config.frames)
        io_lock = threading.Lock()  # the node's disk writes, one at a time
        self.alerts = Alerts(log, config.storage_dir, self.context)
        raw = os.environ.get(PLAIN_ENV, '').strip() in ('', '0')
        self.store = SampleStore(config, name, key, self.alerts, log, io_lock, raw=raw,
                                 topics_b=topics_b)

        # The subscriptions get a node (and so an executor and a thread) of their own.
        self.stream_node = Node(f'{name}_streams', namespace=self.get_namespace(),
                                context=self.context, use_global_arguments=False,
                                start_parameter_services=False)
        qos = stream_qos(config.qos_reliable)
        self._subs = [self._subscribe(t, qos) for t in self.store.topics]
        # rclpy's signal handler does not always wake both executors (seen with SIGTERM):
        # a cheap 2 Hz no-op timer makes the stream executor look at the context regularly.
        self.stream_node.create_timer(0.5, lambda: None)

        pub_diag = self.create_publisher(DiagnosticArray, '/diagnostics', 10)
        # Wakes the services executor when a ~/calibrate fit in the worker thread is done.
        fitted = self.create_guard_condition(lambda: None)
        wiring = (pub_diag, fitted.trigger, io_lock)
        self.channels: list[Channel] = []
        for spec in config.devices:  # a rig: one channel per device, each calibrated with A
            own = device_config(config, spec)
            own_key = persistence.config_key(own.settings.as_dict(), own.frames)
            # its own noise sources: its stated noise, what it measures while still
            noise = NoiseSources(None, own.settings)
            self.channels.append(self._channel(
                own, DeviceView(ParameterView(self), spec, noise), own_key, spec.name, wiring,
                noise))
        if not config.devices:
            self.channels.append(self._channel(config, self.params, key, '', wiring,
                                               self.noise))
        # the two-device node's collaborators (a rig's: its first device's)
        first = self.channels[0]
        self.calibrator, self.outputs, self.live, self.status, self.noise = (
            first.calibrator, first.outputs, first.live, first.status, first.noise)
        self.static_tf = self.calibrator.static_tf

        guard = self.alerts.guard_service
        # A group of its own: while ~/calibrate awaits its fit, the node's default group (the
        # timers, the other services, the wake-up above) stays free to run.
        self.create_service(Trigger, '~/calibrate',
                            guard('calibrate', self._on_calibrate if config.devices
                                  else self.calibrator.on_calibrate),
                            callback_group=MutuallyExclusiveCallbackGroup())
        self.create_service(Trigger, '~/reset', guard('reset', self._on_reset))
        self.create_service(Trigger, '~/save_samples',
                            guard('save_samples', self.store.on_save_samples))
        self.create_timer(1.0, self.alerts.guard_timer('diagnostics', self._publish_status))
        self.add_on_set_parameters_callback(self.params.check_change)
        for channel in self.channels:
            self.add_post_set_parameters_callback(channel.outputs.on_parameters)
            channel.calibrator.republish_stored()
        self.store.start_journal()
        # rosbags' type store takes ~0.2 s to build (more under load): built now, not at the
        # first journal flush, where it would hold up the fused-pose and diagnostics timers.
        bag_typestore()
        self.create_timer(FLUSH_PERIOD,
                          self.alerts.guard_timer('journal', self.store.flush_journal))
        listening = (', '.join(f'{s.name} {" ".join(s.topics)} ({s.model})'
                               for s in config.devices) if config.devices else
                     f'B {", ".join(settings.topic_b)}; model {settings.model}')
        log.info(
            f'listening to A {settings.topic_a}, {listening} '
            f'({"reliable" if config.qos_reliable else "sensor-data"} QoS); method '
            f'{settings.method}; storage {config.storage_dir}')

    def _channel(self, config: NodeConfig, params, key: str, device: str, wiring,
                 noise: NoiseSources) -> Channel:
        """
        Build the collaborators that calibrate, guide and watch one device B against A.

        ``device`` is '' for the two-device node (topics ``~/base_to_base``...); a rig's device
        name puts them under ``~/<device>/`` and names its statuses ``<node>/<device>``.
        """
        pub_diag, wake, io_lock = wiring
        name, log, prefix = self.get_name(), self.get_logger(), '~/'
        if device:
            name, prefix = f'{name}/{device}', f'~/{device}/'
        pub_base = self.create_publisher(PoseWithCovarianceStamped, f'{prefix}base_to_base',
                                         LATCHED_QOS)
        pub_tool = self.create_publisher(PoseWithCovarianceStamped, f'{prefix}tool_to_marker',
                                         LATCHED_QOS)
        static_tf = StaticTf(self, config.frames, config.publish_tf, log,
                             base_parent='a' if device else 'b')
        calibrator = Calibrator(config, key, name.replace('/', '_'),
                                self.get_fully_qualified_name(), params, self.store, pub_base,
                                pub_tool, self.get_clock(), log, self.alerts, io_lock, wake,
                                static_tf)
        fuse: list = []  # the fused-pose timer ticks the outputs made with it
        outputs = UncertaintyOutputs(
            config, params, self.store.buffers,
            self.create_publisher(PoseWithCovarianceStamped, f'{prefix}fused_pose', FUSED_QOS),
            self.create_publisher(MarkerArray, f'{prefix}uncertainty_markers', MARKER_QOS),
            self.create_timer(DRAIN_PERIOD, lambda: fuse[0].tick(), autostart=False),
            self.get_clock(), log)
        fuse.append(outputs)
        live = LiveChecks(name, (config.settings.topic_a, *config.settings.topic_b), params,
                          self.store.buffers, calibrator, outputs,
                          self.create_publisher(Bool, f'{prefix}calibration_stale', STALE_QOS),
                          log)
        calibrator.add_listener(outputs)
        calibrator.add_listener(live)
        calibrator.add_listener(noise)
        status = StatusPublisher(name, config, params, self.store, calibrator, live,
                                 self.alerts, pub_diag, self.get_clock(),
                                 self.get_publishers_info_by_topic, noise)
        return Channel(device, calibrator, outputs, live, status, noise)

    def _publish_status(self) -> None:
        """Publish every channel's /diagnostics (the diagnostics timer)."""
        for channel in self.channels:
            channel.status.publish()

    async def _on_calibrate(self, request, response):
        """Answer a rig's ``~/calibrate``: every device with A, in turn; each says how it went."""
        lines, ok = [], True
        for channel in self.channels:
            answer = await channel.calibrator.on_calibrate(request, Trigger.Response())
            ok = ok and answer.success
            lines.append(f'{channel.device}: {answer.message}')
        response.success, response.message = ok, ' | '.join(lines)
        return response

    def _subscribe(self, topic: str, qos: QoSProfile):
        """Subscribe to a pose topic, counting the messages the middleware reports lost."""
        store = self.store
        callback, raw = store.callback(topic), store.raw
        try:
            sub = self.stream_node.create_subscription(
                PoseStamped, topic, callback, qos, raw=raw,
                event_callbacks=SubscriptionEventCallbacks(message_lost=store.on_lost(topic)))
        except Exception:  # an rmw without the message-lost event: the stamp gaps still count
            sub = self.stream_node.create_subscription(PoseStamped, topic, callback, qos,
                                                       raw=raw)
        store.attach(topic, sub)
        return sub

    def _on_reset(self, request, response):
        """Answer ``~/reset``: forget the samples, start guidance afresh; keep the result."""
        held = self.store.forget()
        for channel in self.channels:
            channel.live.reset()
            channel.noise.forget()
        response.success = True
        response.message = f'forgot {held} samples; the published result is kept'
        return response

    def close(self) -> bool:
        """
        Save the samples not yet saved and destroy the nodes (once the executors have ended).

        Returns False if the samples could not be saved anywhere.
        """
        try:
            return self.store.save_on_shutdown()
        finally:
            self.stream_node.destroy_node()
            self.destroy_node()


class NodeExecutors:
    """
    The two single-threaded executors of a ``CoregNode``: the streams' and the services'.

    ``main`` spins the streams in the main thread (``streams.spin()``) after ``start()``; a
    node in a test's own process runs with ``start(streams=True)``. Either ends when the
    node's context is shut down; ``join`` then waits for the threads.

    Parameters
    ----------
    node : CoregNode
        The node (on its context).

    """

    def __init__(self, node: CoregNode):
        self.streams = SingleThreadedExecutor(context=node.context)
        self.streams.add_node(node.stream_node)
        self.services = SingleThreadedExecutor(context=node.context)
        self.services.add_node(node)
        self.threads: list[threading.Thread] = []

    def start(self, streams: bool = False) -> None:
        """Spin the services executor in a thread (and with ``streams`` the streams one too)."""
        run = [(self.services, 'coreg_services')]
        if streams:
            run.append((self.streams, 'coreg_streams'))
        for executor, name in run:
            thread = threading.Thread(target=_spin_quietly, args=(executor,), daemon=True,
                                      name=name)
            thread.start()
            self.threads.append(thread)

    def alive(self) -> bool:
        """Tell whether every started thread still spins."""
        return all(t.is_alive() for t in self.threads)

    def join(self, timeout: float = 10.0) -> None:
        """Wait for the threads (after the context was shut down)."""
        for thread in self.threads:
            thread.join(timeout)


def main(args=None) -> int:
    """Run coreg_node until SIGINT or SIGTERM; return the exit code."""
    argv = list(sys.argv if args is None else args)
    try:  # a bad parameter file: one line, not rcl's traceback
        check_params_files(argv, NODE_NAME)
    except ConfigError as e:
        print(f'coreg_node: {e}', file=sys.stderr)
        return 1
    # SIGINT and SIGTERM are taken by Python's handler, which only records them; the main
    # thread sees that between spins (at most STOP_POLL_S apart), leaves the loop and shuts
    # the context down itself, and the finally block saves the samples. rclpy's own handlers
    # (NO) would shut the context down from their thread while this one may be inside rmw
    # (the node just made, its executors being made): an early Ctrl-C ended in SIGSEGV.
    stops = record_stop_signals()
    try:
        rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
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
    executors = None
    try:
        # A signal can shut the context down between spin's ok() check and its wait set; rcl
        # then refuses the wait set. That is a normal shutdown, as a Ctrl-C is (lifecycle).
        with ended_by_shutdown():
            node = CoregNode()
            executors = NodeExecutors(node)
            executors.start()
            while not stops and rclpy.ok():
                executors.streams.spin_once(timeout_sec=STOP_POLL_S)
    except CoregError as e:
        print(f'coreg_node: {e}', file=sys.stderr)
        code = 1
    finally:
        try:
            shutdown_quietly()  # also stops the services thread's spin
        finally:  # the samples are saved even if shutting down fails otherwise
            if executors is not None:
                executors.join(10.0)
            if node is not None and not node.close():
                code = code or 1
    return code


def _spin_quietly(executor) -> None:
    """
    Spin in a thread until shutdown; the shutdown race of main() is normal here too.

    No exception ends this thread while ROS runs: the callbacks answer their own failures,
    and anything else is printed and the spin goes on.
    """
    context = executor.context
    while True:
        try:
            with ended_by_shutdown(context):
                executor.spin()
            return
        except Exception:
            if not rclpy.ok(context=context):
                return
            print(f'coreg_node: services thread: {traceback.format_exc()}', file=sys.stderr)
            time.sleep(0.1)


if __name__ == '__main__':
    sys.exit(main())

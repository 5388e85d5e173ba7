"""
``coreg_node``: accumulate two pose streams live, calibrate on request, publish the result.

Subscriptions
    ``topic_a`` and each ``topic_b`` (geometry_msgs/PoseStamped; sensor-data QoS, or reliable
    with ``qos_reliable``). Each message is validated cheaply and stored in a bounded,
    preallocated buffer (``coreg_ros.ros.buffer``); rejections are counted by reason.
Services (std_srvs/Trigger)
    ``~/calibrate`` runs ``coreg_ros.core.pipeline.calibrate_streams`` on a snapshot of the
    raw samples, the very function ``coreg calibrate BAG`` runs, so live and offline results
    agree; ``~/reset`` forgets the samples; ``~/save_samples`` writes them to a rosbag2 in
    ``storage_dir``.
Publications
    ``~/base_to_base`` (pose of ``frame_base_a`` in ``frame_base_b``) and ``~/tool_to_marker``
    (pose of ``frame_marker`` in ``frame_tool``), PoseWithCovarianceStamped, transient-local
    so late subscribers get the last result; ``/diagnostics`` at 1 Hz. Once a calibration
    exists, ``~/fused_pose`` and ``~/uncertainty_markers`` (``ros.uncertainty_outputs``).
Persistence
    The result is stored atomically in ``storage_dir/result.yaml`` and republished at
    start-up; on SIGINT or SIGTERM the samples not yet saved go to a bag in ``storage_dir``.

Threads: the subscriptions live on a helper node (``<name>_streams``) spun by its own
single-threaded executor in the main thread; services, publishers and the diagnostics timer
live on ``coreg_node`` spun in a second thread, so a calibration never blocks the streams.
(rclpy's MultiThreadedExecutor with callback groups was measured to handle only a few hundred
messages per second here, the single-threaded one 2 kHz at ~40 % of a core.)
"""

from __future__ import annotations

import os
from pathlib import Path
import sys
import threading
import time
import traceback
from typing import Optional

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import PoseStamped, PoseWithCovarianceStamped
from rcl_interfaces.msg import SetParametersResult
import rclpy
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.signals import SignalHandlerOptions
from std_srvs.srv import Trigger

from coreg_ros.core.errors import CoregError
from coreg_ros.core.pipeline import calibrate_streams, pair_for
from coreg_ros.core.result_io import load_prior
from coreg_ros.core.settings import Settings
from coreg_ros.ros import persistence
from coreg_ros.ros.buffer import REASONS, StreamBuffer, reason_hint
from coreg_ros.ros.convert import pose_stamped_values, uncertain_pose_to_msg
from coreg_ros.ros.parameters import (
    CALIBRATION_KEYS,
    declare_parameters,
    read_config,
    settings_from_values,
)
from coreg_ros.ros.uncertainty_outputs import UncertaintyOutputs, stored_result_dict

NODE_NAME = 'coreg_node'
#: Seconds between two warnings about the same topic and rejection reason.
WARN_PERIOD = 5.0
#: History depth of the subscriptions: absorbs a pause of the executor (GIL held by the
#: estimator, a slow disk) of a second at 1 kHz before DDS drops anything.
SUB_DEPTH = 1000
RCLError = _rclpy.RCLError


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
    """QoS of the pose subscriptions: sensor-data (best effort) or reliable, deep history."""
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
        declare_parameters(self)
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

        # The subscriptions get a node (and so an executor and a thread) of their own.
        self.stream_node = Node(f'{self.get_name()}_streams', namespace=self.get_namespace(),
                                context=self.context, use_global_arguments=False,
                                start_parameter_services=False)
        qos = stream_qos(self.config.qos_reliable)
        self._subs = [self.stream_node.create_subscription(PoseStamped, t,
                                                           self._make_callback(t), qos)
                      for t in self.topics]
        # rclpy's signal handler does not always wake both executors (seen with SIGTERM):
        # a cheap 2 Hz no-op timer makes the stream executor look at the context regularly.
        self.stream_node.create_timer(0.5, lambda: None)
        self.pub_base = self.create_publisher(PoseWithCovarianceStamped, '~/base_to_base',
                                              LATCHED_QOS)
        self.pub_tool = self.create_publisher(PoseWithCovarianceStamped, '~/tool_to_marker',
                                              LATCHED_QOS)
        self.pub_diag = self.create_publisher(DiagnosticArray, '/diagnostics', 10)
        self.create_service(Trigger, '~/calibrate', self._on_calibrate)
        self.create_service(Trigger, '~/reset', self._on_reset)
        self.create_service(Trigger, '~/save_samples', self._on_save_samples)
        self.create_timer(1.0, self._publish_diagnostics)
        self.add_on_set_parameters_callback(self._check_parameters)
        self.uncertainty = UncertaintyOutputs(self)
        self._republish_stored()
        self.get_logger().info(
            f'listening to A {settings.topic_a}, B {", ".join(settings.topic_b)} '
            f'({"reliable" if self.config.qos_reliable else "sensor-data"} QoS); model '
            f'{settings.model}, method {settings.method}; storage {self.config.storage_dir}')

    # --- subscriptions -------------------------------------------------------------------

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

    def _warn_rejected(self, topic: str, reason: str) -> None:
        """Throttled warning: at most one per topic and reason every WARN_PERIOD seconds."""
        state = self._warn_state.setdefault((topic, reason), [-WARN_PERIOD, 0])
        state[1] += 1
        now = time.monotonic()
        if now - state[0] >= WARN_PERIOD:
            self.get_logger().warning(
                f'{topic}: rejected {state[1]} message(s): {reason_hint(reason)} '
                f'(counts in /diagnostics)')
            state[0], state[1] = now, 0

    # --- services ------------------------------------------------------------------------

    def current_settings(self) -> Settings:
        """Calibration settings from the current parameter values."""
        return settings_from_values({k: self.get_parameter(k).value for k in CALIBRATION_KEYS})

    def snapshot(self) -> dict:
        """Return copies of the accumulated raw samples: topic -> PoseStream."""
        return {t: b.snapshot() for t, b in self.buffers.items()}

    def _on_calibrate(self, request, response):
        t0 = time.monotonic()
        try:
            settings = self.current_settings()
            prior = self._prior()
            streams = self.snapshot()
            result, report = calibrate_streams(
                streams[settings.topic_a], [streams[t] for t in settings.topic_b], settings,
                prior, frames=(self.config.frame_base_a, self.config.frame_base_b))
        except CoregError as e:
            response.success, response.message = False, str(e)
            self.get_logger().warning(f'calibrate refused: {e}')
            return response
        except Exception as e:  # a bug must not kill the node: answer, log the traceback
            self.get_logger().error(f'calibrate failed: {traceback.format_exc()}')
            response.success = False
            response.message = f'internal error ({type(e).__name__}: {e}); see the node log'
            return response
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
            response.success = False
            response.message = (
                f'not published: {result.verdict} ({report.summary()}); set '
                f'publish_inconsistent:=true to publish it anyway' if inconsistent else
                f'no convergence after {result.iterations} iterations: {result.message}; '
                f'{report.summary()}')
            self.get_logger().warning(f'calibrate: {response.message}')
            return response
        self._publish_result(result.base_to_base, result.tool_to_marker)
        self.uncertainty.set_result(result)
        try:
            with self._io_lock:
                path = persistence.save_result(self.config.storage_dir, stored_result_dict(result),
                                               self.config.frames, settings.as_dict())
            stored = f'stored in {path}'
        except OSError as e:
            stored = f'NOT stored ({e})'
        p0 = result.base_to_base.position
        p1 = result.tool_to_marker.position
        response.success = not inconsistent
        offset = '' if timing is None else (
            f'time offset {timing.value_s * 1e3:.3f} ± {timing.sigma_s * 1e3:.3f} ms, '
            if timing.estimated else f'time offset {timing.value_s * 1e3:.3f} ms (given), ')
        response.message = (
            ('PUBLISHED ALTHOUGH INCONSISTENT: ' + result.verdict + '; ' if inconsistent
             else '') +
            f'{result.n_pairs} pairs, {settings.method}/{settings.model}: chi2/dof '
            f'{chi2_dof:.3g}, p {result.p_value:.3g}, {offset}{result.n_rejected} rejected, '
            f'{result.iterations} iterations, '
            f'{seconds:.2f} s; base_to_base p [{p0[0]:.4f}, {p0[1]:.4f}, {p0[2]:.4f}] m, '
            f'tool_to_marker p [{p1[0]:.4f}, {p1[1]:.4f}, {p1[2]:.4f}] m; {stored}')
        self.get_logger().info(f'calibrated: {response.message}')
        return response

    def _prior(self):
        """Return the prior of the next calibration: prior_file, else the stored result."""
        path = str(self.get_parameter('prior_file').value).strip()
        if path:
            return load_prior(os.path.expanduser(path))
        if bool(self.get_parameter('use_last_result_as_prior').value):
            stored = Path(self.config.storage_dir) / persistence.RESULT_FILE
            if stored.is_file():
                return load_prior(stored)
        return None

    def _on_reset(self, request, response):
        held = sum(len(b) for b in self.buffers.values())
        for b in self.buffers.values():
            b.clear()
        self._saved_accepted = self._accepted_total()
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
        else:
            response.success, response.message = True, str(path)
        return response

    # --- results, persistence ------------------------------------------------------------

    def _publish_result(self, base_to_base, tool_to_marker) -> None:
        stamp = self.get_clock().now().to_msg()
        self.pub_base.publish(uncertain_pose_to_msg(base_to_base, self.config.frame_base_b,
                                                    stamp))
        self.pub_tool.publish(uncertain_pose_to_msg(tool_to_marker, self.config.frame_tool,
                                                    stamp))

    def _republish_stored(self) -> None:
        try:
            stored = persistence.load_result(self.config.storage_dir)
        except CoregError as e:
            self.get_logger().error(str(e))
            return
        if stored is None:
            return
        doc, base_to_base, tool_to_marker = stored
        self._publish_result(base_to_base, tool_to_marker)
        self.uncertainty.set_stored(doc, base_to_base, tool_to_marker)
        r = doc['result']
        dof = r.get('dof') or 0
        self._last = {'n_pairs': r.get('n_pairs'), 'success': r.get('success'),
                      'chi2_dof': (r['chi2'] / dof) if dof and r.get('chi2') is not None
                      else float('nan'),
                      'p_value': r.get('p_value'), 'seconds': None,
                      'pairing': f'stored result of {doc.get("saved_at", "?")}'}
        self.get_logger().info(f'republished the stored result of {doc.get("saved_at", "?")} '
                               f'({r.get("n_pairs")} pairs)')

    def _accepted_total(self) -> int:
        return sum(b.accepted for b in self.buffers.values())

    def save_samples(self, report=None) -> Optional[str]:
        """
        Write the held samples to a new bag in storage_dir; None if there are none.

        ``report`` (a callable taking one line) replaces the node logger, which cannot publish
        to /rosout any more once the context is shut down.
        """
        with self._io_lock:
            accepted = self._accepted_total()
            streams = self.snapshot()
            if not any(len(s) for s in streams.values()):
                return None
            path = persistence.save_samples(self.config.storage_dir, streams)
            self._saved_accepted = accepted
        line = f'saved {sum(len(s) for s in streams.values())} samples to {path}'
        (report or self.get_logger().info)(line)
        return str(path)

    def save_on_shutdown(self) -> Optional[str]:
        """Save the samples received since the last save, if any (called on shutdown)."""
        if self._accepted_total() == self._saved_accepted:
            return None
        try:
            return self.save_samples(report=lambda line: print(f'coreg_node: {line}',
                                                               file=sys.stderr))
        except Exception as e:  # shutting down: report, do not raise over the real exit
            print(f'coreg_node: could not save the samples on shutdown: {e}', file=sys.stderr)
            return None

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

    def diagnostics(self) -> DiagnosticStatus:
        """Return the diagnostic status: counts by topic and reason, pairing, last result."""
        self._update_pairing()
        values = []
        problems = 0
        for topic, b in self.buffers.items():
            rejected = sum(b.rejected.values())
            problems += rejected + b.dropped
            values += [KeyValue(key=f'{topic} received', value=str(b.received)),
                       KeyValue(key=f'{topic} accepted', value=str(b.accepted)),
                       KeyValue(key=f'{topic} rejected', value=str(rejected))]
            values += [KeyValue(key=f'{topic} rejected {r}', value=str(b.rejected[r]))
                       for r in REASONS]
            values += [KeyValue(key=f'{topic} held', value=str(len(b))),
                       KeyValue(key=f'{topic} buffer fill',
                                value=f'{len(b) / b.capacity:.3f}'),
                       KeyValue(key=f'{topic} dropped oldest', value=str(b.dropped))]
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
        status = DiagnosticStatus(name=f'{self.get_name()}: coregistration',
                                  hardware_id=' + '.join(self.topics), values=values)
        if problems > self._prev_problems:
            status.level = DiagnosticStatus.WARN
            status.message = 'rejecting or dropping samples (see the counts)'
        else:
            status.level = DiagnosticStatus.OK
            status.message = (f'{min(len(b) for b in self.buffers.values())} samples held'
                              if not last else f'last calibration: {last.get("n_pairs")} pairs')
        self._prev_problems = problems
        return status

    def _publish_diagnostics(self) -> None:
        msg = DiagnosticArray()
        msg.header.stamp = self.get_clock().now().to_msg()
        msg.status = [self.diagnostics()]
        self.pub_diag.publish(msg)


def main(args=None) -> int:
    """Run coreg_node until SIGINT or SIGTERM; return the exit code."""
    # ALL: rclpy's handlers for both SIGINT and SIGTERM shut the context down, so spin
    # returns and the finally block saves the samples in either case.
    rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.ALL)
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
                node.save_on_shutdown()
                node.stream_node.destroy_node()
                node.destroy_node()
    return code


def _spin_quietly(executor) -> None:
    """Spin in a thread until shutdown; the shutdown race of main() is normal here too."""
    try:
        executor.spin()
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except RCLError:
        if rclpy.ok():
            raise


if __name__ == '__main__':
    sys.exit(main())

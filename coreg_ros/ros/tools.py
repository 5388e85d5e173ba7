"""
Stand-ins for the ros2 CLI: play a bag, record topics, call a Trigger service, echo a topic.

Each tool works on a ``RosSession`` (a context, a node and an executor), so the same code
serves the ``coreg`` subcommands, the live demo and the tests (which give every session its
own ROS domain). Failures raise ``ToolError`` with one line saying what is wrong and what to do.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping
from contextlib import suppress
import math
import time
from typing import Optional

from coreg_ros.core.errors import CoregError
from coreg_ros.core.types import PoseStream
from coreg_ros.ros.convert import make_pose_stamped, msg_to_uncertain_pose, pose_stamped_values
from coreg_ros.ros.node import LATCHED_QOS, NODE_NAME, RCLError, shutdown_quietly
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from geometry_msgs.msg import PoseStamped, PoseWithCovarianceStamped
import numpy as np
import rclpy
from rclpy.context import Context
from rclpy.duration import Duration
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.signals import SignalHandlerOptions
from std_srvs.srv import Trigger
from visualization_msgs.msg import Marker, MarkerArray

#: Publisher QoS of ``play``: reliable with a deep history, so a reliable subscriber loses
#: nothing, and it still matches best-effort (sensor-data) subscribers.
PLAY_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=10000,
                      reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.VOLATILE)


class ToolError(CoregError):
    """A tool cannot do what was asked (no subscriber, no service, timeout)."""


class RosSession:
    """
    An rclpy context, one node and a single-threaded executor, as a context manager.

    Parameters
    ----------
    name : str
        Node name.
    domain_id : int, optional
        ROS domain; default ``ROS_DOMAIN_ID`` of the environment.
    signals : bool
        Install rclpy's SIGINT/SIGTERM handlers (command-line tools: yes; tests: no).

    """

    def __init__(self, name: str, domain_id: Optional[int] = None, signals: bool = True):
        self.context = Context()
        options = SignalHandlerOptions.ALL if signals else SignalHandlerOptions.NO
        #: Set once a Ctrl-C (KeyboardInterrupt) or an external shutdown was seen.
        self.interrupted = False
        try:
            rclpy.init(context=self.context, domain_id=domain_id,
                       signal_handler_options=options)
            self.node = Node(name, context=self.context)
            self.executor = SingleThreadedExecutor(context=self.context)
            self.executor.add_node(self.node)
        except RCLError as e:
            stopped = not self.context.ok()
            shutdown_quietly(self.context)
            if stopped:  # a signal shut the context down while the node was being made
                raise KeyboardInterrupt from e
            raise
        except BaseException:  # e.g. Ctrl-C right now: do not leave the context running
            shutdown_quietly(self.context)
            raise

    def ok(self) -> bool:
        """Return False once interrupted (SIGINT) or the context is shut down."""
        return not self.interrupted and self.context.ok()

    def interrupt(self) -> None:
        """Mark the session as interrupted: ``ok()`` is False from now on."""
        self.interrupted = True

    def spin_until(self, done: Callable[[], bool], timeout: Optional[float]) -> bool:
        """Spin until ``done()`` or the timeout (s; None: forever) or shutdown; return done()."""
        end = math.inf if timeout is None else time.monotonic() + timeout
        while not self._check(done):
            left = end - time.monotonic()
            if left <= 0 or not self.ok():
                break
            try:
                self.executor.spin_once(timeout_sec=min(0.1, left))
            except (KeyboardInterrupt, ExternalShutdownException):
                # rclpy shuts the context down from another thread: it may still look ok
                self.interrupt()
                break
            except RCLError:
                if self.ok():  # only the shutdown race (see coreg_ros.ros.node.main) is normal
                    raise
                break
        return self._check(done)

    def _check(self, done: Callable[[], bool]) -> bool:
        """Return ``done()``; False when it fails because the context was shut down (Ctrl-C)."""
        try:
            return done()
        except RCLError:
            if self.context.ok():
                raise
            self.interrupt()
            return False
        except KeyboardInterrupt:
            self.interrupt()
            return False

    def close(self) -> None:
        """Destroy the node and shut the context down."""
        self.executor.shutdown()
        self.node.destroy_node()
        shutdown_quietly(self.context)

    def __enter__(self) -> RosSession:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


# --- play ------------------------------------------------------------------------------------

def play_streams(session: RosSession, streams: Mapping[str, PoseStream], *, rate: float = 1.0,
                 wait_subscribers: float = 10.0, log: Callable[[str], None] = print) -> int:
    """
    Publish recorded streams on live topics with their original timing.

    Parameters
    ----------
    session : RosSession
        The ROS context and node that publish.
    streams : mapping of str to PoseStream
        Topic -> stream; messages are sent in the order of their record time
        (``receive_stamps``, else header stamps), the gaps scaled by ``1 / rate``. Header stamps
        are sent as recorded; values too, bad ones included.
    rate : float
        Speed factor (> 0; ``inf`` sends as fast as possible).
    wait_subscribers : float
        Seconds to wait for at least one subscriber on every topic (0: do not wait).
    log : callable
        Where progress lines go.

    Returns
    -------
    n : int
        Messages published; fewer than all when the session was shut down meanwhile (Ctrl-C),
        which the caller sees as ``not session.ok()``.

    Raises
    ------
    ToolError
        If ``rate`` is not positive or no subscriber appeared in time.

    """
    if not rate > 0:
        raise ToolError(f'--rate must be > 0 (1 = real time), got {rate}')
    node = session.node
    topics = list(streams)
    pubs = [node.create_publisher(PoseStamped, t, PLAY_QOS) for t in topics]
    if wait_subscribers > 0:
        def all_heard():
            return all(p.get_subscription_count() > 0 for p in pubs)
        if not session.spin_until(all_heard, wait_subscribers):
            if not session.ok():  # interrupted while waiting
                return 0
            missing = [t for t, p in zip(topics, pubs, strict=True)
                       if p.get_subscription_count() == 0]
            raise ToolError(f'no subscriber on {", ".join(missing)} after {wait_subscribers:g} s; '
                            f'start coreg_node (same ROS_DOMAIN_ID) first or pass --wait 0')
        # A matched writer may still be unknown to the reader for a moment; let both settle.
        session.spin_until(lambda: False, 0.3)
    # Plain Python lists: building messages from numpy scalars is several times slower.
    order_t, order_k, order_i = [], [], []
    for k, t in enumerate(topics):
        s = streams[t]
        times = s.receive_stamps if s.receive_stamps is not None else s.stamps
        order_t.append(np.asarray(times, dtype=np.int64))
        order_k.append(np.full(len(s), k))
        order_i.append(np.arange(len(s)))
    times = np.concatenate(order_t) if topics else np.zeros(0, np.int64)
    order = np.argsort(times, kind='stable')
    which = np.concatenate(order_k)[order].tolist() if topics else []
    index = np.concatenate(order_i)[order].tolist() if topics else []
    offsets = ((times[order] - times[order][0]) / 1e9 / rate).tolist() if len(times) else []
    stamps = [np.asarray(streams[t].stamps, dtype=np.int64).tolist() for t in topics]
    pos = [np.asarray(streams[t].position, dtype=float).tolist() for t in topics]
    quat = [np.asarray(streams[t].quat_wxyz, dtype=float).tolist() for t in topics]
    frames = [streams[t].frame_id for t in topics]
    log(f'playing {len(which)} messages on {", ".join(topics)} at rate {rate:g}')
    start = time.perf_counter()
    sent = 0
    try:
        for k, i, due in zip(which, index, offsets, strict=True):
            if not _sleep_until(session, start + due):
                break
            try:
                pubs[k].publish(make_pose_stamped(stamps[k][i], frames[k], pos[k][i],
                                                  quat[k][i]))
            except RCLError:
                if session.ok():  # a shutdown (Ctrl-C) after the check is normal
                    raise
                break
            sent += 1
        if session.ok():
            for p in pubs:  # reliable: do not tear down before the readers have everything
                p.wait_for_all_acked(Duration(seconds=5))
    except KeyboardInterrupt:
        session.interrupt()
    except RCLError:
        if session.ok():
            raise
    if session.ok():
        log(f'published {sent} messages in {time.perf_counter() - start:.2f} s')
    return sent


def _sleep_until(session: RosSession, when: float) -> bool:
    """Sleep until ``time.perf_counter() >= when`` in short steps; False once shut down."""
    while session.ok():
        wait = when - time.perf_counter()
        if wait <= 0.0005:
            return True
        try:
            time.sleep(min(wait, 0.05))
        except KeyboardInterrupt:
            session.interrupt()
    return False


# --- record ----------------------------------------------------------------------------------

def _auto_qos(node: Node, topic: str) -> QoSProfile:
    """Reliable if every current publisher of ``topic`` is reliable, else best effort."""
    infos = node.get_publishers_info_by_topic(topic)
    reliable = bool(infos) and all(i.qos_profile.reliability == ReliabilityPolicy.RELIABLE
                                   for i in infos)
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1000,
                      reliability=(ReliabilityPolicy.RELIABLE if reliable
                                   else ReliabilityPolicy.BEST_EFFORT))


def record_streams(session: RosSession, topics: Iterable[str], *,
                   duration: Optional[float] = None, wait_publishers: float = 2.0,
                   log: Callable[[str], None] = print,
                   on_flush: Optional[Callable[[dict], None]] = None,
                   flush_period: float = 0.5) -> dict[str, PoseStream]:
    """
    Record PoseStamped topics until ``duration`` (s) has passed or the session shuts down.

    The QoS follows the publishers found within ``wait_publishers`` seconds (reliable if all
    are reliable); the record time (receive time, ns) goes to ``receive_stamps``.

    ``on_flush(streams)``, when given, receives the samples that arrived since its last call
    every ``flush_period`` seconds and once at the end (so a caller can write them as they
    arrive: a killed recorder then loses at most one period).

    Returns
    -------
    streams : dict of str to PoseStream
        Raw values as received (no checks), one stream per topic (possibly empty).

    """
    node = session.node
    topics = list(dict.fromkeys(topics))
    if not topics:
        raise ToolError('no topics to record; pass --topics /device_a/pose /device_b/pose')
    session.spin_until(lambda: all(node.count_publishers(t) > 0 for t in topics),
                       wait_publishers)
    if not session.ok():  # a signal while waiting for the publishers: nothing recorded yet
        raise KeyboardInterrupt
    rows: dict[str, list] = {t: [] for t in topics}
    frames: dict[str, str] = {}

    def make_cb(topic: str):
        store = rows[topic].append

        def cb(msg: PoseStamped) -> None:
            store((*pose_stamped_values(msg), time.time_ns()))
            frames.setdefault(topic, msg.header.frame_id)
        return cb

    subs = [node.create_subscription(PoseStamped, t, make_cb(t), _auto_qos(node, t))
            for t in topics]
    log(f'recording {", ".join(topics)}'
        + (f' for {duration:g} s' if duration else ' until Ctrl-C'))
    flushed = dict.fromkeys(topics, 0)

    def flush() -> None:
        new = {t: _rows_stream(rows[t][flushed[t]:], frames.get(t, '')) for t in topics}
        for t in topics:
            flushed[t] += len(new[t])
        on_flush(new)

    end = math.inf if duration is None else time.monotonic() + duration
    while session.ok():
        left = end - time.monotonic()
        if left <= 0:
            break
        try:
            session.spin_until(lambda: False, min(left, flush_period) if on_flush else left)
            if on_flush:
                flush()
        except KeyboardInterrupt:  # a Ctrl-C while writing a chunk ends the recording too
            session.interrupt()
    for s in subs:
        with suppress(RCLError):  # the context may be gone already (a signal)
            node.destroy_subscription(s)
    if on_flush:
        with suppress(KeyboardInterrupt):  # every sample is returned to the caller anyway
            flush()
    return {t: _rows_stream(rows[t], frames.get(t, '')) for t in topics}


def _rows_stream(rows: list, frame_id: str) -> PoseStream:
    """Build the PoseStream of received rows (stamp, x y z, w x y z, receive time)."""
    table = np.array(rows, dtype=float).reshape(-1, 9)
    return PoseStream(stamps=np.array([r[0] for r in rows], dtype=np.int64),
                      position=table[:, 1:4].copy(), quat_wxyz=table[:, 4:8].copy(),
                      frame_id=frame_id,
                      receive_stamps=np.array([r[8] for r in rows], dtype=np.int64))


# --- call, echo, diagnostics -----------------------------------------------------------------

def service_name(service: str, node_name: str = NODE_NAME) -> str:
    """Full name of a node's private service (``calibrate`` -> ``/coreg_node/calibrate``)."""
    return service if service.startswith('/') else f'/{node_name.strip("/")}/{service}'


def call_trigger(session: RosSession, service: str, timeout: float = 60.0,
                 wait_service: float = 10.0) -> tuple[bool, str]:
    """
    Call a std_srvs/Trigger service and return ``(success, message)``.

    Raises
    ------
    ToolError
        If the service does not appear within ``wait_service`` s or does not answer within
        ``timeout`` s.

    """
    client = session.node.create_client(Trigger, service)
    try:
        if not session.spin_until(client.service_is_ready, wait_service):
            raise ToolError(f'service {service} not available after {wait_service:g} s; is '
                            f'coreg_node running with the same ROS_DOMAIN_ID?')
        future = client.call_async(Trigger.Request())
        if not session.spin_until(future.done, timeout):
            raise ToolError(f'service {service} did not answer within {timeout:g} s; raise '
                            f'--timeout for big calibrations')
        response = future.result()
        return bool(response.success), response.message
    finally:
        session.node.destroy_client(client)


def wait_for_message(session: RosSession, msg_type, topic: str, qos: QoSProfile,
                     timeout: Optional[float], accept: Callable = lambda m: True):
    """Return the first message on ``topic`` that ``accept`` takes, or None on timeout."""
    got = []
    sub = session.node.create_subscription(
        msg_type, topic, lambda m: got.append(m) if not got and accept(m) else None, qos)
    try:
        session.spin_until(lambda: bool(got), timeout)
    finally:
        session.node.destroy_subscription(sub)
    return got[0] if got else None


def wait_for_result(session: RosSession, topic: str,
                    timeout: Optional[float] = 5.0) -> Optional[PoseWithCovarianceStamped]:
    """Receive the latched PoseWithCovarianceStamped of ``topic`` (transient local), or None."""
    return wait_for_message(session, PoseWithCovarianceStamped, topic, LATCHED_QOS, timeout)


def wait_for_diagnostics(session: RosSession, node_name: str = NODE_NAME,
                         timeout: Optional[float] = 3.0,
                         accept: Callable = lambda s: True) -> Optional[DiagnosticStatus]:
    """Return the next diagnostic status of ``node_name`` that ``accept`` takes, or None."""
    prefix = f'{node_name.strip("/")}:'

    def mine(msg: DiagnosticArray):
        return next((s for s in msg.status if s.name.startswith(prefix)), None)

    msg = wait_for_message(session, DiagnosticArray, '/diagnostics', 10, timeout,
                           accept=lambda m: mine(m) is not None and accept(mine(m)))
    return None if msg is None else mine(msg)


def diagnostics_values(status: DiagnosticStatus) -> dict:
    """Key -> value (strings) of a diagnostic status."""
    return {kv.key: kv.value for kv in status.values}


def format_pose_msg(msg: PoseWithCovarianceStamped, topic: str = '') -> str:
    """Lines for a person: frame, position, quaternion, std from the covariance diagonal."""
    pose = msg_to_uncertain_pose(msg)
    diag = np.diag(pose.covariance)
    std = ['n/a' if d < 0 else f'{math.sqrt(d):.3g}' for d in diag]
    p, q = pose.position, pose.quat_wxyz
    stamp = msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9
    return '\n'.join([
        f'{topic} (frame {msg.header.frame_id}, stamp {stamp:.3f})',
        f'  position  [m]     x {p[0]: .6f}  y {p[1]: .6f}  z {p[2]: .6f}',
        f'  quaternion (wxyz) w {q[0]: .6f}  x {q[1]: .6f}  y {q[2]: .6f}  z {q[3]: .6f}',
        f'  std position [m]  {std[0]}  {std[1]}  {std[2]}',
        f'  std rotation [rad] {std[3]}  {std[4]}  {std[5]}',
    ])


def format_pose_stamped(msg: PoseStamped, topic: str = '') -> str:
    """Lines for a person: frame, stamp, position and quaternion of a PoseStamped."""
    p, q = msg.pose.position, msg.pose.orientation
    return '\n'.join([
        f'{topic} (frame {msg.header.frame_id}, stamp {_stamp(msg.header):.3f})',
        f'  position  [m]     x {p.x: .6f}  y {p.y: .6f}  z {p.z: .6f}',
        f'  quaternion (wxyz) w {q.w: .6f}  x {q.x: .6f}  y {q.y: .6f}  z {q.z: .6f}',
    ])


#: Names of the DiagnosticStatus levels.
LEVEL_NAMES = {0: 'OK', 1: 'WARN', 2: 'ERROR', 3: 'STALE'}


def _level(status: DiagnosticStatus) -> str:
    level = status.level
    level = level[0] if isinstance(level, (bytes, bytearray)) else int(level)
    return LEVEL_NAMES.get(level, str(level))


def format_diagnostics(msg: DiagnosticArray, topic: str = '/diagnostics') -> str:
    """Lines for a person: one ``[LEVEL] name: message`` per status, then its key: value pairs."""
    lines = [f'{topic} (stamp {_stamp(msg.header):.3f}, {len(msg.status)} status)']
    for status in msg.status:
        lines.append(f'  [{_level(status)}] {status.name}: {status.message}')
        lines.extend(f'      {kv.key}: {kv.value}' for kv in status.values)
    return '\n'.join(lines)


_MARKER_TYPES = {v: k.lower() for k, v in vars(Marker).items()
                 if k.isupper() and isinstance(v, int)
                 and k not in ('ADD', 'MODIFY', 'DELETE', 'DELETEALL')}
_MARKER_ACTIONS = {Marker.ADD: 'add', Marker.DELETE: 'delete', Marker.DELETEALL: 'delete all'}


def format_marker_array(msg: MarkerArray, topic: str = '') -> str:
    """Lines for a person: one line per marker (namespace/id, type, frame, position, scale)."""
    lines = [f'{topic} ({len(msg.markers)} markers)']
    for m in msg.markers:
        p, sc = m.pose.position, m.scale
        lines.append(
            f'  {m.ns}/{m.id} {_MARKER_TYPES.get(m.type, m.type)} '
            f'{_MARKER_ACTIONS.get(m.action, m.action)} (frame {m.header.frame_id}) '
            f'at [{p.x:.4f}, {p.y:.4f}, {p.z:.4f}] scale [{sc.x:.4g}, {sc.y:.4g}, {sc.z:.4g}]')
    return '\n'.join(lines)


def _stamp(header) -> float:
    return header.stamp.sec + header.stamp.nanosec * 1e-9


#: What ``echo_topic`` can show: ROS type name -> (message class, formatter).
ECHO_TYPES = {
    'geometry_msgs/msg/PoseWithCovarianceStamped': (PoseWithCovarianceStamped, format_pose_msg),
    'geometry_msgs/msg/PoseStamped': (PoseStamped, format_pose_stamped),
    'diagnostic_msgs/msg/DiagnosticArray': (DiagnosticArray, format_diagnostics),
    'visualization_msgs/msg/MarkerArray': (MarkerArray, format_marker_array),
}


def matching_qos(infos, depth: int = 100) -> QoSProfile:
    """
    Return a subscription QoS that every publisher in ``infos`` serves.

    Reliable only if every publisher is reliable, transient-local (late subscribers get the
    stored messages) only if every publisher is; otherwise best effort, volatile, which any
    publisher matches.
    """
    reliable = bool(infos) and all(i.qos_profile.reliability == ReliabilityPolicy.RELIABLE
                                   for i in infos)
    latched = bool(infos) and all(
        i.qos_profile.durability == DurabilityPolicy.TRANSIENT_LOCAL for i in infos)
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth,
                      reliability=(ReliabilityPolicy.RELIABLE if reliable
                                   else ReliabilityPolicy.BEST_EFFORT),
                      durability=(DurabilityPolicy.TRANSIENT_LOCAL if latched
                                  else DurabilityPolicy.VOLATILE))


def find_publishers(session: RosSession, topic: str, timeout: Optional[float]) -> list:
    """Return the publishers (TopicEndpointInfo) of ``topic`` once any is found; [] on timeout."""
    infos: list = []

    def found() -> bool:
        try:
            infos[:] = session.node.get_publishers_info_by_topic(topic)
        except RCLError:  # shut down (Ctrl-C) since the last check
            if session.ok():
                raise
            infos.clear()
        return bool(infos)

    session.spin_until(found, timeout)
    return infos


def echo_topic(session: RosSession, topic: str, *, timeout: Optional[float] = None,
               once: bool = False, out: Callable[[str], None] = print) -> int:
    """
    Print the messages of ``topic`` with the type and QoS its publishers use.

    Waits for a publisher, takes its message type (one of ``ECHO_TYPES``) and a QoS every
    publisher serves (``matching_qos``: a transient-local result is received by a late echo,
    a volatile or best-effort stream is received too), then prints each message readably.

    Parameters
    ----------
    session : RosSession
        The ROS context and node that subscribe.
    topic : str
        Full topic name.
    timeout : float, optional
        Seconds to wait for a publisher and then for each message; None: until shutdown.
    once : bool
        Return after the first message.
    out : callable
        Where the lines go.

    Returns
    -------
    printed : int
        Messages printed (0 if the session was shut down, e.g. by Ctrl-C, before any came).

    Raises
    ------
    ToolError
        If no publisher appears within ``timeout``, the topic's type is not one of
        ``ECHO_TYPES``, or no message comes within ``timeout``.

    """
    infos = find_publishers(session, topic, timeout)
    if not infos:
        if not session.ok() or timeout is None:
            return 0
        raise ToolError(f'no publisher of {topic} within {timeout:g} s; is the node running on '
                        f'this ROS_DOMAIN_ID (and the topic name right)?')
    types = list(dict.fromkeys(i.topic_type for i in infos))
    known = [t for t in types if t in ECHO_TYPES]
    if not known:
        raise ToolError(f'{topic} carries {", ".join(types)}; coreg echo shows '
                        f'{", ".join(t.rsplit("/", 1)[-1] for t in ECHO_TYPES)} only')
    msg_type, formatter = ECHO_TYPES[known[0]]
    qos = matching_qos([i for i in infos if i.topic_type == known[0]])
    got: list = []
    sub = session.node.create_subscription(msg_type, topic, got.append, qos)
    printed = 0
    try:
        while session.ok():
            if not session.spin_until(lambda: bool(got), timeout):
                break
            while got:
                out(formatter(got.pop(0), topic))
                printed += 1
                if once:
                    return printed
    except KeyboardInterrupt:
        session.interrupt()
    finally:
        with suppress(RCLError):  # after a Ctrl-C the node may be gone already
            session.node.destroy_subscription(sub)
    if printed == 0 and session.ok() and timeout is not None:
        latched = qos.durability == DurabilityPolicy.TRANSIENT_LOCAL
        hint = ('it keeps its last message for late subscribers but has none yet (results '
                'appear after `coreg call calibrate`)' if latched
                else 'it has not published since echo started')
        raise ToolError(f'nothing received on {topic} ({known[0]}) within {timeout:g} s; {hint}')
    return printed

"""
Stand-ins for the ros2 CLI: play a bag, record topics, call a Trigger service, wait for a message.

Each tool works on a ``RosSession`` (``coreg_ros.ros.session``), so the same code serves the
``coreg`` subcommands, the live demo and the tests (which give every session its own ROS
domain). Failures raise ``ToolError`` with one line saying what is wrong and what to do.
``coreg echo`` is in ``coreg_ros.ros.echo``.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping
from contextlib import suppress
import math
import time
from typing import Any, Optional

from coreg_ros.core.types import PoseStream
from coreg_ros.ros.interface import LATCHED_QOS, matching_qos, NODE_NAME, PLAY_QOS
from coreg_ros.ros.lifecycle import RCLError
from coreg_ros.ros.messages import make_pose_stamped, pose_stamped_values
from coreg_ros.ros.session import RosSession, ToolError
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from geometry_msgs.msg import PoseStamped, PoseWithCovarianceStamped
import numpy as np
from rclpy.duration import Duration
from rclpy.qos import QoSProfile
from std_srvs.srv import Trigger

#: What tools, tests and benchmarks import from here (the session and the interface too).
__all__ = ['call_trigger', 'diagnostics_values', 'LATCHED_QOS', 'PLAY_QOS', 'play_streams',
           'record_streams', 'RosSession', 'ToolError', 'wait_for_diagnostics',
           'wait_for_message', 'wait_for_result', 'wait_for_subscribers']


# --- play ------------------------------------------------------------------------------------

#: Seconds to wait after a publisher has matched its subscribers before sending
#: (``wait_for_subscribers``).
SETTLE_S = 1.0


def wait_for_subscribers(session: RosSession, publishers: Mapping[str, Any],
                         timeout: float) -> list[str]:
    """
    Wait until every publisher has a subscriber, then ``SETTLE_S`` more.

    Returns the topics still without one after ``timeout`` s (empty: all were heard, and the
    settling wait was made). A writer that has matched its reader may not be known to the
    reader yet, and a best-effort reader (the node's default) drops what it sends meanwhile:
    0.3 s lost the first 31 of 150 messages on a loaded machine. ``SETTLE_S`` is what discovery
    takes there (no ROS API says when the reader's side has matched).
    """
    def all_heard() -> bool:
        return all(p.get_subscription_count() > 0 for p in publishers.values())

    if not session.spin_until(all_heard, timeout):
        return [t for t, p in publishers.items() if p.get_subscription_count() == 0]
    session.spin_until(lambda: False, SETTLE_S)
    return []


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
    topics = list(streams)
    pubs = [session.node.create_publisher(PoseStamped, t, PLAY_QOS) for t in topics]
    if wait_subscribers > 0:
        missing = wait_for_subscribers(session, dict(zip(topics, pubs, strict=True)),
                                       wait_subscribers)
        if missing:
            if not session.ok():  # interrupted while waiting
                return 0
            raise ToolError(f'no subscriber on {", ".join(missing)} after {wait_subscribers:g} s; '
                            f'start coreg_node (same ROS_DOMAIN_ID) first or pass --wait 0')
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
    with session.stoppable():  # a shutdown (Ctrl-C) ends the playing, quietly
        for k, i, due in zip(which, index, offsets, strict=True):
            if not _sleep_until(session, start + due):
                break
            pubs[k].publish(make_pose_stamped(stamps[k][i], frames[k], pos[k][i], quat[k][i]))
            sent += 1
        if session.ok():
            for p in pubs:  # reliable: do not tear down before the readers have everything
                p.wait_for_all_acked(Duration(seconds=5))
    if session.ok():
        log(f'published {sent} messages in {time.perf_counter() - start:.2f} s')
    return sent


def _sleep_until(session: RosSession, when: float) -> bool:
    """Sleep until ``time.perf_counter() >= when`` in short steps; False once shut down."""
    while session.ok():
        wait = when - time.perf_counter()
        if wait <= 0.0005:
            return True
        with session.stoppable():
            time.sleep(min(wait, 0.05))
    return False


# --- record ----------------------------------------------------------------------------------

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

    # reliable if every current publisher is, else best effort; volatile: from now on
    subs = [node.create_subscription(
        PoseStamped, t, make_cb(t),
        matching_qos(node.get_publishers_info_by_topic(t), depth=1000, latched=False))
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
        with session.stoppable():  # a Ctrl-C while writing a chunk ends the recording too
            session.spin_until(lambda: False, min(left, flush_period) if on_flush else left)
            if on_flush:
                flush()
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

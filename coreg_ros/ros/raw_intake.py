"""
The node's pose intake: serialized messages taken in bursts, decoded and validated in bulk.

Why (bench/bench_node.py, py-spy): with one message per callback, rclpy's executor costs
some 80 us of Python per message (wait set, task, guard conditions) and taking and
deserialising it into a Python message another ~40 us; such a node needs ~0.9 of a core at
2 x 2 kHz and loses 8-40 % of 2 x 5 kHz. Here the
subscriptions are ``raw`` (the callback gets the CDR bytes), and the first callback of a wake
takes *every* message waiting on *every* pose subscription (``take_message`` in a loop: a
C call and two list appends per message), decodes each topic's batch with one numpy call
(``coreg_ros.files.bag.cdr_pose``), validates and stores it with ``StreamBuffer.push_many``, and
then pauses ``PACE_S``, so the executor wakes at most ~1/``PACE_S`` times a second whatever
the message rate; the messages wait in the middleware's history meanwhile (``SUB_DEPTH`` of
the node is sized for that and for the GIL pauses of the other thread).

A batch the bulk decoder refuses (frames or sizes that differ within it, big-endian CDR) is
deserialised message by message with rclpy and pushed one by one: same result, slower. Bytes
that do not deserialise as a PoseStamped at all (a raw publisher sending garbage) are counted
as ``undecodable`` and warned about; they never reach the buffer.

Receive stamps are the middleware's reception times of the messages
(``received_timestamp``, the system clock), not the time the node got round to them.
"""

from __future__ import annotations

from collections.abc import Callable
import time

from coreg_ros.files.bag.cdr_pose import decode_pose_stamped
from coreg_ros.ros.messages import pose_stamped_values
from geometry_msgs.msg import PoseStamped
from rclpy.serialization import deserialize_message

#: Seconds the stream thread pauses after a burst: bounds the executor's wakes (and so its
#: per-callback cost) to ~1 / PACE_S a second; messages wait at most this long in the history.
PACE_S = 0.004
#: Messages taken from one subscription in one wake at most (the other topics get their turn).
MAX_TAKE = 20_000


class RawIntake:
    """
    Raw pose subscriptions drained together, decoded in bulk into their ``StreamBuffer`` s.

    Parameters
    ----------
    buffers : dict of str to StreamBuffer
        Topic -> buffer the samples go to.
    on_rejected : callable(topic, reason, count)
        Told of every rejection (``count`` messages of one reason), for the throttled warning.
    on_undecodable : callable(topic, count, error)
        Told of bytes that are not a PoseStamped.
    pace_s : float
        Pause after each burst, s (see ``PACE_S``).
    sequences : dict of str to SequenceCounter, optional
        Topic -> counter told of every message's info (the messages lost on the way).

    """

    def __init__(self, buffers: dict, on_rejected: Callable, on_undecodable: Callable,
                 pace_s: float = PACE_S, sequences: dict | None = None):
        self.buffers = buffers
        self.sequences = sequences or {}
        self.on_rejected = on_rejected
        self.on_undecodable = on_undecodable
        self.pace_s = float(pace_s)
        self.subscriptions: dict = {}
        self.undecodable = dict.fromkeys(buffers, 0)
        self.bursts = 0  # wakes that took messages (for the benchmark)

    def attach(self, topic: str, subscription) -> None:
        """Register the raw subscription of ``topic`` (its callback is ``callback(topic)``)."""
        self.subscriptions[topic] = subscription

    def callback(self, topic: str) -> Callable:
        """Return the subscription callback of ``topic`` (gets the CDR bytes and info)."""
        def on_raw(data: bytes, info: dict) -> None:  # two arguments: rclpy passes the info
            first = {topic: ([data], [_received(info)], [info])}
            self.drain(first)
        return on_raw

    def drain(self, first: dict | None = None) -> int:
        """Take what waits on every subscription, store it, pause; return messages taken."""
        batches = {}
        for topic, sub in self.subscriptions.items():
            blobs, recv, infos = first.get(topic, ([], [], [])) if first else ([], [], [])
            _take_all(sub, blobs, recv, infos)
            if blobs:
                batches[topic] = (blobs, recv, infos)
        n = 0
        for topic, (blobs, recv, infos) in batches.items():
            if topic in self.sequences:
                self.sequences[topic].update(infos)
            self._store(topic, blobs, recv)
            n += len(blobs)
        if n:
            self.bursts += 1
            _pause(self.pace_s)
        return n

    def _store(self, topic: str, blobs: list, recv: list) -> None:
        buffer = self.buffers[topic]
        arrays = decode_pose_stamped(blobs)
        if arrays is not None:
            for reason, count in buffer.push_many(arrays.stamps_ns, recv, arrays.position,
                                                  arrays.quat_wxyz, arrays.frame_id).items():
                self.on_rejected(topic, reason, count)
            return
        push = buffer.push  # not uniform: one by one, exactly as the plain path
        bad, error = 0, None
        for data, recv_ns in zip(blobs, recv, strict=True):
            try:
                msg = deserialize_message(data, PoseStamped)
            except Exception as e:  # not a PoseStamped: rclpy raises various types
                bad, error = bad + 1, e
                continue
            stamp, x, y, z, qw, qx, qy, qz = pose_stamped_values(msg)
            reason = push(stamp, recv_ns, x, y, z, qw, qx, qy, qz, msg.header.frame_id)
            if reason is not None:
                self.on_rejected(topic, reason, 1)
        if bad:
            self.undecodable[topic] += bad
            self.on_undecodable(topic, bad, error)


def _pause(seconds: float) -> None:
    """Let the messages gather in the middleware's history (a function: profiles name it)."""
    time.sleep(seconds)


def _received(info) -> int:
    """Reception time of a message from its info (system clock, ns); now if unknown."""
    t = info.get('received_timestamp') if info else None
    return int(t) if t else time.time_ns()


def _take_all(sub, blobs: list, recv: list, infos: list) -> None:
    """Append every waiting message of ``sub`` (bytes), its reception time and info, in order."""
    take = sub.handle.take_message
    msg_type = sub.msg_type
    now = time.time_ns
    try:
        with sub.handle:
            for _ in range(MAX_TAKE):
                got = take(msg_type, True)
                if got is None:
                    return
                blobs.append(got[0])
                recv.append(got[1].get('received_timestamp') or now())
                infos.append(got[1])
    except Exception:  # the subscription is being destroyed (shutdown): nothing more to take
        return

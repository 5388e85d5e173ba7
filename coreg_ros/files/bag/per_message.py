"""
rosbags' general path for PoseStamped bags: one message at a time, through its serializers.

Used when the bulk path (``bulk_read``, ``bulk_write``, ``cdr_pose``) does not apply: topics
whose messages differ in layout (frame_id changes, big-endian CDR), damaged or unusual
storage files, whose errors are reported from here; and on request (``bulk=False`` or
``COREG_BAG_BULK=0``) as the reference the bulk path is compared with.
"""

from __future__ import annotations

from collections.abc import Mapping
from functools import lru_cache
from pathlib import Path
from typing import Any

from coreg_ros.core.errors import BagError
from coreg_ros.core.types import PoseStream
import numpy as np
from rosbags.rosbag2 import Reader, Writer
from rosbags.typesys import get_typestore, Stores

#: The one message type read and written.
POSE_STAMPED = 'geometry_msgs/msg/PoseStamped'

#: Messages converted to Python values at a time by ``write_per_message`` (bounds memory).
_WRITE_CHUNK = 65536

#: How to salvage a damaged storage file (for error messages).
SALVAGE = '`coreg fix-bag BAG NEW_BAG --salvage`'


@lru_cache(maxsize=1)
def typestore() -> Any:
    """Return the Jazzy message type store, built once (it takes ~0.1 s)."""
    return get_typestore(Stores.ROS2_JAZZY)


def describe(err: BaseException) -> str:
    """One line: the exception type and its message."""
    text = ' '.join(str(err).split()) or 'no message'
    return f'{type(err).__name__}: {text}'


def read_per_message(reader: Reader, connections: list, wanted: list[str],
                     path: Path, store: Any) -> dict[str, PoseStream]:
    """Deserialize the topics' messages one by one with rosbags (the general path)."""
    columns: dict[str, tuple[list, list, list]] = {t: ([], [], []) for t in wanted}
    frames: dict[str, str] = {}
    deserialize = store.deserialize_cdr
    try:
        for conn, log_ns, raw in reader.messages(connections=connections):
            msg = deserialize(raw, POSE_STAMPED)
            stamps, logs, values = columns[conn.topic]
            header = msg.header
            frame = frames.setdefault(conn.topic, header.frame_id)
            if header.frame_id != frame:
                # One PoseStream has one base frame; mixing frames would silently corrupt
                # the calibration.
                raise BagError(
                    f'topic {conn.topic} in bag {str(path)!r}: header.frame_id changes from '
                    f'{frame!r} to {header.frame_id!r} at message {len(stamps)}; record '
                    f'one base frame per topic')
            stamps.append(header.stamp.sec * 1_000_000_000 + header.stamp.nanosec)
            logs.append(log_ns)
            p = msg.pose.position
            q = msg.pose.orientation
            values.append((p.x, p.y, p.z, q.w, q.x, q.y, q.z))
    except BagError:
        raise
    except Exception as err:  # truncated or corrupt storage or message bytes
        raise BagError(
            f'bag {str(path)!r} is truncated or corrupt ({describe(err)}); re-record it, or '
            f'salvage what is readable with {SALVAGE}') from err
    streams = {}
    for topic in wanted:
        stamps, logs, values = columns[topic]
        table = np.array(values, dtype=float).reshape(-1, 7)
        streams[topic] = PoseStream(
            stamps=np.array(stamps, dtype=np.int64),
            position=table[:, :3].copy(),
            quat_wxyz=table[:, 3:].copy(),
            frame_id=frames.get(topic, ''),
            receive_stamps=np.array(logs, dtype=np.int64),
        )
    return streams


def write_per_message(writer: Writer, conns: list, streams: Mapping[str, PoseStream],
                      topics: list[str], checked: list, which: np.ndarray, index: np.ndarray,
                      logs: np.ndarray) -> None:
    """
    Write all messages one by one through rosbags' message classes and serializer.

    ``which``/``index``/``logs`` (M,): topic, sample and log time (int64 ns) of each message in
    write order; ``checked[k][0]`` the header stamps (int64 ns) of topic k.
    """
    store = typestore()
    types = store.types
    msg_cls = types[POSE_STAMPED]
    header_cls, time_cls = types['std_msgs/msg/Header'], types['builtin_interfaces/msg/Time']
    pose_cls, point_cls = types['geometry_msgs/msg/Pose'], types['geometry_msgs/msg/Point']
    quat_cls = types['geometry_msgs/msg/Quaternion']
    frames = [streams[t].frame_id for t in topics]
    # All messages in write order as arrays (88 B each), turned into Python floats and ints
    # (the generated serializer is fastest on them) one chunk at a time: bounded memory.
    empty = np.zeros((0, 3))
    pos = np.concatenate([np.asarray(streams[t].position, dtype=float).reshape(-1, 3)
                          for t in topics] or [empty])
    quat = np.concatenate([np.asarray(streams[t].quat_wxyz, dtype=float).reshape(-1, 4)
                           for t in topics] or [np.zeros((0, 4))])
    stamps = np.concatenate([s for s, _ in checked]) if checked else logs
    start = np.cumsum([0] + [len(s) for s, _ in checked])[:-1] if checked else logs
    flat = start[which] + index if len(which) else which
    pos, quat, stamps = pos[flat], quat[flat], stamps[flat]
    serialize = store.serialize_cdr
    for lo in range(0, len(which), _WRITE_CHUNK):
        hi = lo + _WRITE_CHUNK
        chunk = zip(which[lo:hi].tolist(), logs[lo:hi].tolist(),
                    (stamps[lo:hi] // 1_000_000_000).tolist(),
                    (stamps[lo:hi] % 1_000_000_000).tolist(),
                    pos[lo:hi].tolist(), quat[lo:hi].tolist(), strict=True)
        for k, log_ns, sec, nsec, (x, y, z), (qw, qx, qy, qz) in chunk:
            msg = msg_cls(
                header=header_cls(stamp=time_cls(sec=sec, nanosec=nsec), frame_id=frames[k]),
                pose=pose_cls(position=point_cls(x=x, y=y, z=z),
                              orientation=quat_cls(x=qx, y=qy, z=qz, w=qw)))
            writer.write(conns[k], log_ns, serialize(msg, POSE_STAMPED))

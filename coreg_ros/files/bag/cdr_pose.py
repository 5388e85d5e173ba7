"""
Bulk CDR codec for ``geometry_msgs/msg/PoseStamped``: many messages per numpy call.

A little-endian CDR PoseStamped has a fixed layout once its ``header.frame_id`` is known
(offsets from the start of the serialized message, the 4-byte encapsulation header included;
CDR aligns relative to the byte after that header)::

    0   encapsulation   00 01 (CDR_LE), 2 option bytes
    4   int32   header.stamp.sec
    8   uint32  header.stamp.nanosec
    12  uint32  frame_id length L, terminating NUL included
    16  L bytes frame_id, NUL-terminated
        zero padding so that the float64s start 8-aligned in the CDR stream
    P   7 x float64  position x y z, orientation x y z w     (P = 4 + align8(12 + L))
    P+56 end

So N messages of one topic with one frame_id are N equal records, and the concatenation of
their bytes *is* a numpy structured array: ``np.frombuffer`` gives every field at once, with
no Python work per message. Whatever does not fit that picture (different lengths or frames
within the batch, big-endian CDR, a length field or terminator that disagrees with the
layout, non-UTF-8 frame names) makes the decoder return None, and the caller uses a
per-message deserializer (rosbags) that reports the problem or handles the general case.
A structurally corrupt message is therefore never decoded into wrong numbers; a flipped bit
inside a float is not detectable (CDR has no checksum), by either path.

Conventions: stamps are int64 nanoseconds ``sec * 10**9 + nanosec``; quaternions are
(w, x, y, z) in the arrays and (x, y, z, w) in the messages (docs/design.md §3).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Optional, Union

import numpy as np

#: Encapsulation header written: CDR little-endian, no options (what rosbag2 and rclpy use).
CDR_LE_HEADER = b'\x00\x01\x00\x00'

#: Byte offset of the frame_id length field and of the frame_id bytes.
_FRAME_LEN_AT = 12
_FRAME_AT = 16

#: Bytes of the pose: 7 float64.
_POSE_BYTES = 56

#: Reordering of the message's (x, y, z, w) quaternion columns (pose columns 3..6) to (w, x, y, z).
_WXYZ_COLUMNS = [6, 3, 4, 5]

BytesLike = Union[bytes, bytearray, memoryview]


@dataclass(frozen=True)
class PoseArrays:
    """
    Decoded PoseStamped messages of one frame.

    Attributes
    ----------
    stamps_ns : ndarray of int64, shape (N,)
        ``header.stamp`` as ``sec * 10**9 + nanosec``, nanoseconds.
    frame_id : str
        The common ``header.frame_id``.
    position : ndarray of float64, shape (N, 3)
        ``pose.position`` (x, y, z), metres.
    quat_wxyz : ndarray of float64, shape (N, 4)
        ``pose.orientation`` reordered to (w, x, y, z); values as in the messages (no checks).

    """

    stamps_ns: np.ndarray
    frame_id: str
    position: np.ndarray
    quat_wxyz: np.ndarray

    def __len__(self) -> int:
        return int(self.stamps_ns.shape[0])


def _pose_offset(frame_len: int) -> int:
    """Byte offset of the first float64 for a frame_id length field of ``frame_len``."""
    unaligned = _FRAME_AT - 4 + frame_len  # position in the CDR stream after the frame bytes
    return 4 + (unaligned + 7) // 8 * 8


def record_size(frame_len: int) -> int:
    """
    Size in bytes of one serialized PoseStamped.

    Parameters
    ----------
    frame_len : int
        The frame_id length field: UTF-8 bytes of the frame name plus its terminating NUL.

    Returns
    -------
    size : int
        Bytes of the whole message, encapsulation header included.

    """
    return _pose_offset(frame_len) + _POSE_BYTES


def record_dtype(frame_len: int) -> np.dtype:
    """
    Return the numpy structured dtype of one little-endian PoseStamped of this frame length.

    Fields: ``enc`` (4 uint8, encapsulation), ``sec`` (<i4), ``nanosec`` (<u4), ``frame_len``
    (<u4), ``frame`` (``frame_len`` uint8, NUL included), ``pose`` (7 <f8: x y z qx qy qz qw).
    Padding bytes are not fields (not read, not checked: deserializers ignore them).
    """
    return np.dtype({
        'names': ['enc', 'sec', 'nanosec', 'frame_len', 'frame', 'pose'],
        'formats': [('u1', (4,)), '<i4', '<u4', '<u4', ('u1', (frame_len,)), ('<f8', (7,))],
        'offsets': [0, 4, 8, _FRAME_LEN_AT, _FRAME_AT, _pose_offset(frame_len)],
        'itemsize': record_size(frame_len),
    })


def frame_len_of(message: BytesLike) -> Optional[int]:
    """
    Return the frame_id length field of one little-endian CDR PoseStamped, or None.

    None when the message is too short or not little-endian CDR.
    """
    if len(message) < _FRAME_AT or bytes(message[:2]) != CDR_LE_HEADER[:2]:
        return None
    return int.from_bytes(bytes(message[_FRAME_LEN_AT:_FRAME_AT]), 'little')


def decode_records(buffer: BytesLike, count: int) -> Optional[PoseArrays]:
    """
    Decode ``count`` serialized PoseStamped of equal size laid end to end in ``buffer``.

    The caller guarantees that the messages all have the same length (e.g. the bag index
    says so); the layout of every record is then checked here.

    Parameters
    ----------
    buffer : bytes-like
        The concatenated messages, ``count * size`` bytes (any C-contiguous buffer, e.g. an
        (N, size) uint8 array).
    count : int
        Number of messages (N).

    Returns
    -------
    arrays : PoseArrays or None
        The decoded arrays, or None when the records do not all have the fixed layout of the
        first one's frame_id (the caller then deserializes message by message).

    """
    if count <= 0:
        return None
    buffer = memoryview(buffer).cast('B')  # flat bytes, whatever the exporter's shape
    size, rest = divmod(len(buffer), count)
    frame_len = frame_len_of(buffer[:_FRAME_AT]) if not rest else None
    # A zero length field (no NUL) is not what ROS writes; leave it to the general path.
    if not frame_len or record_size(frame_len) != size:
        return None
    records = np.frombuffer(buffer, dtype=record_dtype(frame_len), count=count)
    enc = records['enc']
    frame = records['frame']
    if not (np.all(enc[:, 0] == 0) and np.all(enc[:, 1] == 1)
            and np.all(records['frame_len'] == frame_len)
            and np.all(frame == frame[0]) and frame[0, -1] == 0):
        return None
    try:
        frame_id = frame[0, :-1].tobytes().decode()
    except UnicodeDecodeError:
        return None
    pose = records['pose']
    stamps = records['sec'].astype(np.int64) * 1_000_000_000 + records['nanosec']
    return PoseArrays(stamps_ns=stamps, frame_id=frame_id,
                      position=np.ascontiguousarray(pose[:, :3]),
                      quat_wxyz=pose[:, _WXYZ_COLUMNS])


def decode_blocks(blocks: Sequence[np.ndarray]) -> Optional[PoseArrays]:
    """
    ``decode_records`` of consecutive blocks of messages, into one set of arrays.

    Each block is decoded on its own and its fields are written into arrays made once for all
    blocks, so the blocks need not be joined first (a copy of every message).

    Parameters
    ----------
    blocks : sequence of ndarray, each (n_i, S) uint8
        Serialized PoseStamped of equal size S, in order.

    Returns
    -------
    arrays : PoseArrays or None
        As ``decode_records`` of the joined blocks: None when they are empty, not all of the
        fixed layout of one frame_id, or of other frames from block to block.

    """
    blocks = [b for b in blocks if len(b)]
    n = sum(len(b) for b in blocks)
    if n == 0:
        return None
    if len(blocks) == 1:  # one block (an mcap file's): its decoded arrays are the result
        return decode_records(np.ascontiguousarray(blocks[0]), n)
    stamps, position, quat_wxyz = np.empty(n, np.int64), np.empty((n, 3)), np.empty((n, 4))
    frame_id, at = None, 0
    for block in blocks:
        got = decode_records(np.ascontiguousarray(block), len(block))
        if got is None or (frame_id is not None and got.frame_id != frame_id):
            return None
        frame_id, end = got.frame_id, at + len(block)
        stamps[at:end] = got.stamps_ns
        position[at:end] = got.position
        quat_wxyz[at:end] = got.quat_wxyz
        at = end
    return PoseArrays(stamps_ns=stamps, frame_id=frame_id, position=position,
                      quat_wxyz=quat_wxyz)


def decode_pose_stamped(blobs: Sequence[BytesLike]) -> Optional[PoseArrays]:
    """
    Decode serialized (CDR) ``geometry_msgs/msg/PoseStamped`` messages in bulk.

    Parameters
    ----------
    blobs : sequence of bytes-like
        N serialized messages, as stored in a bag or taken from a raw subscription.

    Returns
    -------
    arrays : PoseArrays or None
        ``stamps_ns`` (N,) int64 ns, ``frame_id``, ``position`` (N, 3) m, ``quat_wxyz``
        (N, 4). None when the batch is empty or not uniform (messages of different sizes or
        frames, big-endian CDR, malformed layout): deserialize those one by one instead.

    """
    n = len(blobs)
    if n == 0:
        return None
    size = len(blobs[0])
    if any(len(b) != size for b in blobs):
        return None
    return decode_records(b''.join(blobs), n)


def encode_records(stamps_ns: np.ndarray, frame_id: str, position: np.ndarray,
                   quat_wxyz: np.ndarray) -> np.ndarray:
    """
    Serialize N PoseStamped into one structured array (one record per message).

    Parameters
    ----------
    stamps_ns : array_like of int, shape (N,)
        Header stamps, nanoseconds; must lie in [0, 2**31 s) (builtin_interfaces/Time).
    frame_id : str
        ``header.frame_id`` of every message.
    position : array_like of float, shape (N, 3)
        Positions, metres.
    quat_wxyz : array_like of float, shape (N, 4)
        Orientations (w, x, y, z), written as the message's (x, y, z, w).

    Returns
    -------
    records : ndarray, shape (N,), dtype ``record_dtype(L)``
        ``records.tobytes()`` is the N messages laid end to end, each
        ``records.dtype.itemsize`` bytes, byte-identical to rosbags' ``serialize_cdr``.

    Raises
    ------
    ValueError
        If the shapes disagree or a stamp is outside [0, 2**31 s).

    """
    stamps = np.asarray(stamps_ns)
    n = stamps.shape[0] if stamps.ndim == 1 else -1
    position = np.asarray(position, dtype=np.float64)
    quat = np.asarray(quat_wxyz, dtype=np.float64)
    if n < 0 or position.shape != (n, 3) or quat.shape != (n, 4):
        raise ValueError(f'stamps (N,), position (N, 3) and quat_wxyz (N, 4) expected, got '
                         f'{stamps.shape}, {position.shape}, {quat.shape}')
    stamps = stamps.astype(np.int64)
    if n and (stamps.min() < 0 or stamps.max() >= 2**31 * 1_000_000_000):
        raise ValueError('header stamps must lie in [0, 2**31 s) (builtin_interfaces/Time)')
    name = frame_id.encode() + b'\x00'
    # np.zeros: the alignment padding is written as zeros, as rosbags and Fast-CDR do.
    records = np.zeros(n, dtype=record_dtype(len(name)))
    records['enc'] = np.frombuffer(CDR_LE_HEADER, dtype=np.uint8)
    records['sec'] = stamps // 1_000_000_000
    records['nanosec'] = stamps % 1_000_000_000
    records['frame_len'] = len(name)
    records['frame'] = np.frombuffer(name, dtype=np.uint8)
    pose = records['pose']
    pose[:, :3] = position
    pose[:, 3:6] = quat[:, 1:]
    pose[:, 6] = quat[:, 0]
    return records


def encode_pose_stamped(stamps_ns: np.ndarray, frame_id: str, position: np.ndarray,
                        quat_wxyz: np.ndarray) -> list[bytes]:
    """
    Serialize N PoseStamped messages (CDR little-endian), one ``bytes`` per message.

    Parameters and errors as :func:`encode_records`; the result is the list of the N
    serialized messages (for a bag writer or ``rclpy`` publishing of serialized messages).
    """
    records = encode_records(stamps_ns, frame_id, position, quat_wxyz)
    size = records.dtype.itemsize
    buf = records.tobytes()
    return [buf[i:i + size] for i in range(0, len(buf), size)]

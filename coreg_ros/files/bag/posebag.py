"""
rosbag2 recordings of ``geometry_msgs/msg/PoseStamped`` streams, as arrays.

The only module that touches bag files, through ``rosbags`` (no rclpy, so it also works
without a ROS installation). Both rosbag2 storage formats are supported: ``sqlite3`` (``.db3``)
and ``mcap``; the reader detects the format from ``metadata.yaml``.

Conventions (docs/design.md §3): ROS messages carry quaternions as (x, y, z, w); the arrays this
module returns and accepts are (w, x, y, z). Stamps are int64 nanoseconds,
``sec * 10**9 + nanosec``; the header stamp (the device's clock) goes to
``PoseStream.stamps`` and the bag's log (record) time to ``PoseStream.receive_stamps``.

Values are not checked here (NaN, non-unit quaternions, stamp order): the pairing core does
that, so that its errors can name the sample index.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from contextlib import suppress
import os
from pathlib import Path
import shutil
import tempfile
from typing import Any, Optional, Union

from coreg_ros.core.errors import BagError, InputError
from coreg_ros.core.types import PoseStream
from coreg_ros.files.bag import bulk_read, bulk_write
from coreg_ros.files.bag.cdr_pose import decode_blocks, encode_records
from coreg_ros.files.bag.light_open import open_light
from coreg_ros.files.bag.per_message import describe as _describe
from coreg_ros.files.bag.per_message import POSE_STAMPED, read_per_message, write_per_message
from coreg_ros.files.bag.per_message import typestore as _typestore
from coreg_ros.files.output_paths import check_new_bag
import numpy as np
from rosbags.rosbag2 import Reader, StoragePlugin, Writer
import yaml

#: Storage names accepted by ``write_pose_bag`` (the rosbag2 storage identifiers).
STORAGES = {'sqlite3': StoragePlugin.SQLITE3, 'mcap': StoragePlugin.MCAP}

#: rosbag2 metadata version written: 9 is what Jazzy's rosbag2 writes and reads.
BAG_VERSION = 9

#: builtin_interfaces/Time has an int32 ``sec``: header stamps must lie in [0, 2**31 s).
_MAX_HEADER_STAMP = 2**31 * 10**9

#: How to salvage a damaged storage file, by storage identifier (for error messages).
_SALVAGE = '`coreg fix-bag BAG NEW_BAG --salvage`'

#: Environment variable that, set to 0, forces rosbags' per-message path (for comparisons).
BULK_ENV = 'COREG_BAG_BULK'

PathLike = Union[str, os.PathLike]


def _check_bag_dir(path: Path) -> None:
    """Raise BagError unless ``path`` looks like a rosbag2 directory."""
    if not path.exists():
        raise BagError(
            f'bag {str(path)!r} does not exist; pass the directory that ros2 bag record '
            f'created (the one holding metadata.yaml)')
    if not path.is_dir():
        hint = (f'pass its directory {str(path.parent)!r}'
                if (path.parent / 'metadata.yaml').exists()
                else 'pass the rosbag2 directory that holds metadata.yaml and this file')
        raise BagError(f'bag {str(path)!r} is a file, not a rosbag2 directory; {hint}')
    if not (path / 'metadata.yaml').is_file():
        raise BagError(
            f'{str(path)!r} has no metadata.yaml, so it is not a (closed) rosbag2 directory; '
            f'pass the right directory, or recover an interrupted recording with '
            f'`coreg fix-bag {path} NEW_BAG --salvage`')


class _OpenBag:
    """Context manager: a rosbags Reader whose failures become one-line BagErrors."""

    def __init__(self, path: PathLike):
        self.path = Path(path)
        self.reader: Reader | None = None

    def __enter__(self) -> Reader:
        _check_bag_dir(self.path)
        try:
            reader = Reader(self.path)
            reader.open()
        except Exception as err:  # rosbags raises ReaderError, OSError, apsw and yaml errors
            raise BagError(_open_failure(self.path, err)) from err
        self.reader = reader
        return reader

    def __exit__(self, *exc: object) -> None:
        if self.reader is not None:
            # Closing a broken file must not mask the error that is propagating.
            with suppress(Exception):
                self.reader.close()


def _open_failure(path: Path, err: Exception) -> str:
    """Say whether the metadata or the storage file of a bag that fails to open is broken."""
    try:
        info = yaml.safe_load((path / 'metadata.yaml').read_text())
        files = info['rosbag2_bagfile_information']['relative_file_paths']
    except Exception:  # any failure here means the metadata itself is the problem
        return (f'metadata.yaml of bag {str(path)!r} is unreadable ({_describe(err)}); restore '
                f'it, or read the storage file directly with '
                f'`coreg fix-bag {path} NEW_BAG --salvage`')
    missing = [f for f in files if not (path / Path(f).name).exists()]
    if missing:
        return (f'bag {str(path)!r} lacks its storage file(s) {", ".join(missing)}; copy the '
                f'whole bag directory, not only metadata.yaml')
    return (f'storage file of bag {str(path)!r} is truncated or corrupt ({_describe(err)}); '
            f're-record it, or salvage what is readable with {_SALVAGE}')


def _topic_types(reader: Reader) -> dict[str, list[str]]:
    """Map each topic of an open bag to its message type(s), in bag order."""
    types: dict[str, list[str]] = {}
    for conn in reader.connections:
        seen = types.setdefault(conn.topic, [])
        if conn.msgtype not in seen:
            seen.append(conn.msgtype)
    return types


def list_topics(path: PathLike) -> dict[str, str]:
    """
    List the topics of a rosbag2 recording.

    Parameters
    ----------
    path : str or path-like
        The rosbag2 directory (holding ``metadata.yaml``), either storage format.

    Returns
    -------
    topics : dict of str to str
        Topic name to message type (e.g. ``'geometry_msgs/msg/PoseStamped'``); a topic
        recorded with several types lists them joined by ``', '``.

    Raises
    ------
    BagError
        If the path is not a readable rosbag2 directory.

    """
    with _OpenBag(path) as reader:
        return {topic: ', '.join(types) for topic, types in _topic_types(reader).items()}


def _describe_topics(types: Mapping[str, list[str]]) -> str:
    """Return 'topic (type), ...' for error messages."""
    if not types:
        return 'none'
    return ', '.join(f'{t} ({", ".join(ty)})' for t, ty in sorted(types.items()))


def read_pose_bag(path: PathLike, topics: Iterable[str], *,
                  bulk: Optional[bool] = None) -> dict[str, PoseStream]:
    """
    Read ``geometry_msgs/msg/PoseStamped`` topics of a rosbag2 recording into arrays.

    Parameters
    ----------
    path : str or path-like
        The rosbag2 directory (holding ``metadata.yaml``); sqlite3 and mcap storage are both
        read, the format is taken from the metadata.
    topics : iterable of str
        Topic names to read, e.g. ``['/device_a/pose', '/device_b/pose']``.
    bulk : bool, optional
        Decode each topic in bulk with numpy (``cdr_pose``) when its messages share one
        layout, else message by message with rosbags; both give identical arrays. Default:
        on, unless the environment variable ``COREG_BAG_BULK`` is ``0``. With bulk on, the
        bag is first opened lightly (``light_open``: rosbags without its sqlite3 message
        counts) and read in bulk; anything unusual starts over with plain rosbags.

    Returns
    -------
    streams : dict of str to PoseStream
        One stream per requested topic, messages in the bag's order (log time): ``stamps``
        the header stamps (int64 ns, the device's clock), ``position`` (N, 3) in m in the
        ``header.frame_id`` frame, ``quat_wxyz`` (N, 4) converted from the message's
        (x, y, z, w), ``frame_id`` the header frame, ``receive_stamps`` the log time (int64 ns).
        Values are returned as recorded, without checks (NaN stays NaN).

    Raises
    ------
    BagError
        If the path is missing or not a rosbag2 directory, the metadata or storage is
        unreadable, truncated or corrupt, a topic is not in the bag (the message lists the
        topics that are), a topic has another message type than PoseStamped, or the
        ``header.frame_id`` changes within a topic.

    """
    path = Path(path)
    wanted = list(dict.fromkeys(topics))
    if not wanted:
        raise BagError(f'no topics asked for from bag {str(path)!r}; name at least one topic '
                       f'(list_topics() shows what the bag holds)')
    if _use_bulk(bulk):
        fast = read_fast(path, wanted)
        if fast is not None:
            return fast
    with _OpenBag(path) as reader:
        types = _topic_types(reader)
        missing = [t for t in wanted if t not in types]
        if missing:
            raise BagError(
                f'topic(s) {", ".join(missing)} not in bag {str(path)!r}; it has: '
                f'{_describe_topics(types)}; pass one of these topic names')
        for topic in wanted:
            if POSE_STAMPED not in types[topic]:
                raise BagError(
                    f'topic {topic} in bag {str(path)!r} has type {", ".join(types[topic])}, '
                    f'but {POSE_STAMPED} is needed; record the device as PoseStamped or '
                    f'convert the topic first')
        connections = [c for c in reader.connections
                       if c.topic in wanted and c.msgtype == POSE_STAMPED]
        streams: dict[str, PoseStream] = {}
        if _use_bulk(bulk):
            streams = _read_bulk(reader, connections, wanted)
        rest = [t for t in wanted if t not in streams]
        if rest:
            streams.update(read_per_message(
                reader, [c for c in connections if c.topic in rest], rest, path,
                _typestore()))
    return {topic: streams[topic] for topic in wanted}


def read_fast(path: Path, wanted: list[str]) -> Optional[dict[str, PoseStream]]:
    """
    Try the fast path of ``read_pose_bag``: light open, every topic through the bulk path.

    The bag is opened by ``light_open`` (rosbags minus the sqlite3 message counts). Unless
    every wanted topic is a PoseStamped topic of the bag and comes out of the bulk fetch and
    decoder, this returns None and ``read_pose_bag`` starts over with plain rosbags, which
    gives the usual results and errors; so does any exception here.

    Parameters
    ----------
    path : Path
        The rosbag2 directory.
    wanted : list of str
        Topic names, without repeats.

    Returns
    -------
    streams : dict of str to PoseStream, or None
        As ``read_pose_bag`` returns them, or None when the bag needs the general path.

    """
    try:
        reader = open_light(path)
    except Exception:  # noqa: BLE001 - plain rosbags opens it again and names the problem
        return None
    try:
        types = _topic_types(reader)
        if any(types.get(t) != [POSE_STAMPED] for t in wanted):
            return None
        connections = [c for c in reader.connections if c.topic in wanted]
        streams = _read_bulk(reader, connections, wanted)
        if any(t not in streams for t in wanted):
            return None
        return {topic: streams[topic] for topic in wanted}
    except Exception:  # noqa: BLE001 - as above
        return None
    finally:
        with suppress(Exception):
            reader.close()


def _use_bulk(bulk: Optional[bool]) -> bool:
    """Whether to use the bulk path: the argument, else ``COREG_BAG_BULK`` (default on)."""
    if bulk is not None:
        return bulk
    return os.environ.get(BULK_ENV, '1').strip().lower() not in ('0', 'false', 'no', 'off')


def _read_bulk(reader: Reader, connections: list, wanted: list[str]) -> dict[str, PoseStream]:
    """
    Decode the topics whose messages share one layout (all, in a normal recording) in bulk.

    Topics that are missing from the result (messages of varying size or frame, big-endian
    CDR, a damaged or unusual storage file) are read message by message, which also gives
    the usual errors.
    """
    fetched = bulk_read.fetch_parts(reader, connections)
    if fetched is None:
        return {}
    streams = {}
    for topic in wanted:
        logs, blocks = fetched.pop(topic)  # freed before the next topic is decoded
        if blocks is None:
            continue
        if not len(logs):
            streams[topic] = PoseStream(
                stamps=np.zeros(0, np.int64), position=np.zeros((0, 3)),
                quat_wxyz=np.zeros((0, 4)), frame_id='', receive_stamps=np.zeros(0, np.int64))
            continue
        arrays = decode_blocks(blocks)
        del blocks
        if arrays is not None and len(arrays.stamps_ns) == len(logs):
            streams[topic] = PoseStream(
                stamps=arrays.stamps_ns, position=arrays.position, quat_wxyz=arrays.quat_wxyz,
                frame_id=arrays.frame_id, receive_stamps=logs)
    return streams


def _as_stamps(values: Any, what: str, n: int) -> np.ndarray:
    """Return stamps as int64 of shape (n,), refusing non-integral or wrongly shaped ones."""
    arr = np.asarray(values)
    if arr.shape != (n,):
        raise InputError(f'{what}: expected shape ({n},), got {arr.shape}; give one stamp per '
                         f'pose')
    if arr.dtype.kind not in 'iu':
        raise InputError(f'{what}: stamps must be integer nanoseconds (int64), got dtype '
                         f'{arr.dtype}; convert with (sec * 10**9 + nanosec)')
    return arr.astype(np.int64)


def _check_stream(topic: str, stream: PoseStream) -> tuple[np.ndarray, np.ndarray]:
    """Check shapes and stamp ranges of a stream to write; return (header, log) stamps."""
    if not isinstance(topic, str) or not topic:
        raise InputError(f'topic name {topic!r} is not a non-empty string; name it like '
                         f"'/device_a/pose'")
    if not isinstance(stream.frame_id, str):
        kind = type(stream.frame_id).__name__
        raise InputError(f'{topic}: frame_id must be a str, got {kind}; give the base frame '
                         f"name, e.g. 'world'")
    n = len(stream.stamps)
    stamps = _as_stamps(stream.stamps, f'{topic} stamps', n)
    if np.shape(stream.position) != (n, 3) or np.shape(stream.quat_wxyz) != (n, 4):
        raise InputError(
            f'{topic}: position must have shape ({n}, 3) and quat_wxyz ({n}, 4), got '
            f'{np.shape(stream.position)} and {np.shape(stream.quat_wxyz)}; give one pose per '
            f'stamp')
    bad = np.flatnonzero((stamps < 0) | (stamps >= _MAX_HEADER_STAMP))
    if bad.size:
        raise InputError(
            f'{topic}: header stamp {int(stamps[bad[0]])} ns at index {int(bad[0])} does not fit '
            f'builtin_interfaces/Time (0 <= sec < 2**31); use nanoseconds since the epoch')
    if stream.receive_stamps is None:
        logs = stamps
    else:
        logs = _as_stamps(stream.receive_stamps, f'{topic} receive_stamps', n)
        bad = np.flatnonzero(logs < 0)
        if bad.size:
            raise InputError(f'{topic}: receive stamp at index {int(bad[0])} is negative; '
                             f'rosbag2 log times are nanoseconds since the epoch')
    return stamps, logs


def _write_bulk(writer: Writer, conns: list, streams: Mapping[str, PoseStream],
                topics: list[str], checked: list, which: np.ndarray, index: np.ndarray,
                logs: np.ndarray) -> bool:
    """Serialize every topic with numpy and store all messages at once; False if unsupported."""
    blocks = []
    for k, topic in enumerate(topics):
        stream = streams[topic]
        records = encode_records(checked[k][0], stream.frame_id,
                                 np.asarray(stream.position, dtype=float).reshape(-1, 3),
                                 np.asarray(stream.quat_wxyz, dtype=float).reshape(-1, 4))
        block = records.view(np.uint8).reshape(len(records), records.dtype.itemsize)
        mine = index[which == k]  # the topic's samples in write (log time) order
        if np.any(mine != np.arange(mine.size)):
            block = block[mine]
        blocks.append(block)
    return bulk_write.write_bulk(writer, conns, which, logs, blocks)


def write_pose_bag(path: PathLike, streams: Mapping[str, PoseStream],
                   storage: str = 'sqlite3', *, bulk: Optional[bool] = None) -> None:
    """
    Write pose streams to a new rosbag2 recording as ``geometry_msgs/msg/PoseStamped``.

    The bag is written to a hidden temporary directory beside ``path`` and renamed to ``path``
    only once it is complete, so an interrupted write never leaves a partial bag under the
    final name.

    Parameters
    ----------
    path : str or path-like
        The rosbag2 directory to create; it must not exist.
    streams : mapping of str to PoseStream
        Topic name to stream. Each message gets header stamp ``stamps[i]`` (int64 ns),
        ``header.frame_id`` = ``frame_id``, position (m) and orientation converted from
        (w, x, y, z) to the message's (x, y, z, w). Values are written as given (no checks).
    storage : {'sqlite3', 'mcap'}
        rosbag2 storage plugin.
    bulk : bool, optional
        Serialize all messages with numpy (``cdr_pose``) and store them in bulk; else one by
        one through rosbags. Both give the same messages. Default: on, unless the
        environment variable ``COREG_BAG_BULK`` is ``0``.

    Notes
    -----
    The log (record) time of message i is ``receive_stamps[i]``, or the header stamp when the
    stream has no receive stamps. The messages of all topics are written in the order of the
    log time (stable: ties keep topic order, then sample order), as ``ros2 bag record`` would.

    Raises
    ------
    BagError
        If ``path`` exists, ``storage`` is unknown, or the bag cannot be written.
    InputError
        If a stream's shapes or stamps cannot be written (non-integer stamps, stamps outside
        builtin_interfaces/Time).

    """
    path = Path(path)
    if storage not in STORAGES:
        raise BagError(f'unknown storage {storage!r}; use one of {", ".join(STORAGES)}')
    check_new_bag(path)

    topics = list(streams)
    checked = [_check_stream(topic, streams[topic]) for topic in topics]
    # Interleave all topics by log time; a stable sort keeps ties in topic, then sample order.
    which = np.concatenate([np.full(len(s), k, dtype=np.int64) for k, (s, _) in
                            enumerate(checked)]) if checked else np.zeros(0, np.int64)
    index = np.concatenate([np.arange(len(s)) for s, _ in checked]) if checked else which
    logs = np.concatenate([lg for _, lg in checked]) if checked else which
    order = np.argsort(logs, kind='stable')

    which, index, logs = which[order], index[order], logs[order]

    staging = Path(tempfile.mkdtemp(prefix=f'.{path.name}.partial-', dir=path.parent))
    try:
        tmp_bag = staging / path.name  # the storage file is named after its directory
        with Writer(tmp_bag, version=BAG_VERSION, storage_plugin=STORAGES[storage]) as writer:
            conns = [writer.add_connection(t, POSE_STAMPED, typestore=_typestore())
                     for t in topics]
            if not (_use_bulk(bulk)
                    and _write_bulk(writer, conns, streams, topics, checked, which, index, logs)):
                write_per_message(writer, conns, streams, topics, checked, which, index, logs)
        if path.exists():
            raise BagError(f'{str(path)!r} appeared while the bag was being written; it was not '
                           f'overwritten; choose a new bag name')
        os.rename(tmp_bag, path)
    except BagError:
        raise
    except Exception as err:
        raise BagError(f'cannot write bag {str(path)!r} ({_describe(err)}); nothing was left '
                       f'under that name; check the stream contents (frame_id, values) and the '
                       f'disk space and permissions of {str(path.parent)!r}') from err
    finally:
        shutil.rmtree(staging, ignore_errors=True)

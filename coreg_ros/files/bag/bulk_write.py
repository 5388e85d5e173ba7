"""
Write many serialized messages into an open rosbags ``Writer`` at once, not one by one.

rosbags' ``Writer.write()`` takes about 5 us per message (200k messages/s).

rosbags still creates the bag: directory, storage file, schema, topics, connections,
metadata.yaml and (mcap) summary and footer. Only the messages go in by a faster route:

* sqlite3: one ``executemany`` INSERT on the writer's own connection and transaction.
* mcap: whole chunks built with numpy (Message records laid out in one buffer, one Message
  Index per channel from arrays), compressed like rosbags would, and registered in the
  writer's chunk index and statistics, so its ``close()`` writes a normal summary.

Both need rosbags' storage writers to be the ones this was written against (0.11); when
they are not, or when the writer compresses per message, ``write_bulk`` returns False and
the caller writes message by message.
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Sequence
from io import BytesIO
from typing import Any

import numpy as np
from numpy.lib.stride_tricks import as_strided

#: Uncompressed bytes per MCAP chunk (rosbags closes a chunk once it exceeds 1 MiB).
_CHUNK_BYTES = 1 << 20

#: Message record header: opcode u8, length u64, channel_id u16, sequence u32, log_time u64,
#: publish_time u64.
_MSG_HEAD = 31


def write_bulk(writer: Any, conns: Sequence[Any], which: np.ndarray, logs: np.ndarray,
               blocks: Sequence[np.ndarray]) -> bool:
    """
    Write messages into an open rosbags Writer in one go.

    Parameters
    ----------
    writer : rosbags.rosbag2.Writer
        Open writer; ``conns`` are its connections.
    conns : sequence of Connection
        Connection of each topic k.
    which : ndarray of int64, shape (M,)
        Topic k of each message, in write order (log time order).
    logs : ndarray of int64, shape (M,)
        Log time of each message, nanoseconds.
    blocks : sequence of ndarray, each (N_k, S_k) uint8
        The serialized messages of topic k, in write order within the topic.

    Returns
    -------
    done : bool
        False if nothing was written because this writer is not supported (the caller then
        writes message by message).

    """
    storage = writer.storage
    kind = type(storage).__name__
    if (getattr(writer.compression_mode, 'name', '') != 'NONE'
            or not all(hasattr(writer, a) for a in ('counts', 'min_timestamp', 'max_timestamp'))):
        return False
    if kind == 'Sqlite3Writer' and hasattr(storage, 'cursor'):
        _sqlite(storage, conns, which, logs, blocks)
    elif kind == 'McapWriter' and all(hasattr(storage, a) for a in (
            'chunk', 'chunks', 'channel_stats', 'compressor', 'compression', 'bio')):
        _mcap(storage, conns, which, logs, blocks)
    else:
        return False
    # The bookkeeping rosbags' Writer.write does per message, for metadata.yaml.
    for k, conn in enumerate(conns):
        writer.counts[conn.id] += len(blocks[k])
    if len(logs):
        writer.min_timestamp = min(writer.min_timestamp, int(logs.min()))
        writer.max_timestamp = max(writer.max_timestamp, int(logs.max()))
    return True


def _sqlite(storage: Any, conns: Sequence[Any], which: np.ndarray, logs: np.ndarray,
            blocks: Sequence[np.ndarray]) -> None:
    ids = np.array([c.id for c in conns], dtype=np.int64)
    # bytes per message: slicing one buffer per topic is C work; the generator below is the
    # only per-message Python step, inside executemany.
    blobs = []
    for block in blocks:
        size = block.shape[1] if block.ndim == 2 else 0
        buf = np.ascontiguousarray(block).tobytes()
        blobs.append([buf[i:i + size] for i in range(0, len(buf), size)] if size else [])
    cursors = [iter(b) for b in blobs]
    rows = zip(ids[which].tolist(), logs.tolist(),
               (next(cursors[k]) for k in which.tolist()), strict=True)
    storage.cursor.executemany(
        'INSERT INTO messages (topic_id, timestamp, data) VALUES(?, ?, ?)', rows)


def _mcap(storage: Any, conns: Sequence[Any], which: np.ndarray, logs: np.ndarray,
          blocks: Sequence[np.ndarray]) -> None:
    from rosbags.rosbag2.storage_mcap import PendingChunk  # noqa: PLC0415

    # Each message's place in its topic block, and its record size.
    index = np.zeros(which.size, np.int64)
    for k in range(len(blocks)):
        pick = which == k
        index[pick] = np.arange(int(pick.sum()))
    sizes = np.array([_MSG_HEAD + (b.shape[1] if b.ndim == 2 else 0) for b in blocks],
                     dtype=np.int64)
    rec_size = sizes[which]
    ends = np.cumsum(rec_size)
    # Schema and channel records that rosbags put into its pending chunk open the first one.
    prefix = storage.chunk.bio.getvalue()
    storage.chunk = PendingChunk(2**63 - 1, 0, BytesIO(), defaultdict(list))
    cut = np.flatnonzero(np.diff(ends // _CHUNK_BYTES)) + 1
    for lo, hi in zip(np.concatenate([[0], cut]).tolist(),
                      np.concatenate([cut, [which.size]]).tolist(), strict=True):
        if hi > lo:
            _mcap_chunk(storage, conns, which[lo:hi], index[lo:hi], logs[lo:hi],
                        rec_size[lo:hi], blocks, prefix)
            prefix = b''
    if prefix:  # no messages: keep the schema and channel records pending, as rosbags would
        storage.chunk.bio.write(prefix)


def _record_dtype(size: int) -> np.dtype:
    return np.dtype({
        'names': ['op', 'length', 'channel', 'sequence', 'log_time', 'publish_time', 'data'],
        'formats': ['u1', '<u8', '<u2', '<u4', '<u8', '<u8', ('u1', (size,))],
        'offsets': [0, 1, 9, 11, 15, 23, 31],
        'itemsize': _MSG_HEAD + size,
    })


def _mcap_chunk(storage: Any, conns: Sequence[Any], which: np.ndarray, index: np.ndarray,
                logs: np.ndarray, rec_size: np.ndarray, blocks: Sequence[np.ndarray],
                prefix: bytes) -> None:
    """Build, compress and write one chunk, its message indexes and its chunk index entry."""
    from rosbags.rosbag2.storage_mcap import (  # noqa: PLC0415
        write_record,
        write_string,
        write_uint16,
        write_uint32,
        write_uint64,
    )

    starts = len(prefix) + np.cumsum(rec_size) - rec_size
    total = len(prefix) + int(rec_size.sum())
    buf = np.zeros(total, np.uint8)
    buf[:len(prefix)] = np.frombuffer(prefix, np.uint8)
    index_entries = []
    for k, conn in enumerate(conns):
        pick = which == k
        if not pick.any():
            continue
        size = blocks[k].shape[1]
        recs = np.zeros(int(pick.sum()), dtype=_record_dtype(size))
        recs['op'] = 0x05
        recs['length'] = 22 + size
        recs['channel'] = conn.id
        recs['log_time'] = logs[pick]
        recs['publish_time'] = logs[pick]
        recs['data'] = blocks[k][index[pick]]
        width = _MSG_HEAD + size
        # A writable view with one row per byte offset: rows at the record starts are the
        # records' places in the chunk (they do not overlap).
        rows = as_strided(buf, shape=(total - width + 1, width), strides=(1, 1))
        rows[starts[pick]] = recs.view(np.uint8).reshape(-1, width)
        entries = np.empty((int(pick.sum()), 2), '<u8')
        entries[:, 0] = logs[pick]
        entries[:, 1] = starts[pick]
        index_entries.append((conn.id, entries.tobytes()))
        storage.channel_stats[conn.id] += int(pick.sum())
    raw = buf.tobytes()
    start_time, end_time = int(logs.min()), int(logs.max())
    storage.message_start_time = min(storage.message_start_time, start_time)
    storage.message_end_time = max(storage.message_end_time, end_time)

    # From here on the same bytes as rosbags' McapWriter.close_chunk.
    rec = BytesIO()
    write_uint64(rec, start_time)
    write_uint64(rec, end_time)
    write_uint64(rec, len(raw))
    write_uint32(rec, 0)
    compressed = storage.compressor(raw)
    write_string(rec, storage.compression)
    write_uint64(rec, len(compressed))
    rec.write(compressed)
    chunk_start = storage.bio.tell()
    write_record(storage.bio, 0x06, rec)
    chunk_end = storage.bio.tell()
    offsets = []
    for cid, entries in index_entries:
        offsets.append((cid, storage.bio.tell()))
        rec = BytesIO()
        write_uint16(rec, cid)
        write_uint32(rec, len(entries))
        rec.write(entries)
        write_record(storage.bio, 0x07, rec)
    rec = BytesIO()
    write_uint64(rec, start_time)
    write_uint64(rec, end_time)
    write_uint64(rec, chunk_start)
    write_uint64(rec, chunk_end - chunk_start)
    write_uint32(rec, len(offsets) * 10)
    for cid, offset in offsets:
        write_uint16(rec, cid)
        write_uint64(rec, offset)
    write_uint64(rec, storage.bio.tell() - chunk_end)
    write_string(rec, storage.compression)
    write_uint64(rec, len(compressed))
    write_uint64(rec, len(raw))
    storage.chunks.append(rec)

"""
Raw bytes of PoseStamped topics out of rosbag2 storage files, with no Python step per message.

rosbags' ``Reader.messages()`` yields one Python tuple per message, which caps any reader
built on it near a few hundred thousand messages a second. Here the storage files that
rosbags has opened (its Reader, or ``light_open``'s lighter sqlite3 plugin; rosbags keeps
the metadata, the connections, decompression of file-compressed bags and all error
reporting) are read in bulk:

* sqlite3: the rows are walked in rosbags' order (log time, ties by row id: its
  ``ORDER BY timestamp`` scan of the timestamp index; the query plans of both are compared)
  in pages of up to 2**16 rows split at log times, so ties never straddle two pages (two
  connections fetch two pages at a time, SQLite working outside Python's lock). One
  statement per page has SQLite concatenate the blobs (``group_concat``) and, as text, the
  log times and one integer per row holding blob size and topic id; numpy parses those in
  one call each, checks the order and the byte count, and splits the page by topic.
* mcap: each chunk holding a wanted channel is read and decompressed with rosbags' own
  routine (size and CRC checks included); its message index records give every message
  record's offset, and numpy gathers all record headers and payloads at once. Gaps between
  indexed records are walked to prove that no message record was left out of the index.
  Order is rosbags' too: log time, ties by chunk position, then record position.

The result is, per topic, the log times and the messages as blocks of equal-size records
(one per SQLite page or mcap file: ``fetch_parts``, which readers decode block by block without
joining them; ``fetch`` joins them), in exactly the order rosbags yields them; a topic whose
messages differ in size gets None. Anything this module does not recognise
(message-compressed bags, unindexed or inconsistent mcap files, SQLite errors, corrupt
structure) makes ``fetch`` return None and the caller reads the bag through rosbags, which
raises the usual errors for damaged files.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from contextlib import suppress
import os
from pathlib import Path
import re
from typing import Any, Optional

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

#: Rows per SQLite query: bounds the concatenated blob (SQLite's limit is 1e9 bytes). Small
#: enough that SQLite's growing group_concat string stays small: at 2**20 rows of PoseStamped
#: (~130 MB a page) its reallocations cost 2.2 s of system time on 4M rows, at 2**16 0.3 s
#: (bench/bag_bench.py); the pages' own queries cost little below that.
_SQLITE_PAGE = 1 << 16

#: Topic ids read in bulk are below this; a row's blob size and topic id travel as
#: ``size * _TOPIC_ID_LIMIT + topic_id``.
_TOPIC_ID_LIMIT = 1 << 20

#: MCAP opcodes and the fixed part of a Message record after opcode and length:
#: channel_id u16, sequence u32, log_time u64, publish_time u64.
_OP_MESSAGE = 0x05
_OP_MESSAGE_INDEX = 0x07
_MSG_HEAD = 1 + 8 + 22

_MSG_HEAD_DTYPE = np.dtype({
    'names': ['op', 'length', 'channel', 'log_time'],
    'formats': ['u1', '<u8', '<u2', '<u8'],
    'offsets': [0, 1, 9, 15],
    'itemsize': _MSG_HEAD,
})

#: Per topic: log times (int64 ns, (N,)) and the N messages as an (N, S) uint8 array, or
#: None as the second item when the messages do not all have the same size S.
Fetched = tuple[np.ndarray, Optional[np.ndarray]]
#: As ``Fetched``, the messages as consecutive (n_i, S) blocks (sum of n_i = N), or None.
Parts = tuple[np.ndarray, Optional[list]]


class Unsupported(Exception):
    """The bag is not in a shape this module reads; the caller reads it through rosbags."""


def fetch(reader: Any, connections: Sequence[Any]) -> Optional[dict[str, Fetched]]:
    """
    Read the messages of the given connections of an open rosbags Reader in bulk.

    Parameters
    ----------
    reader : rosbags.rosbag2.Reader
        An open reader.
    connections : sequence of Connection
        The reader connections to read (one or more per topic).

    Returns
    -------
    fetched : dict of str to (ndarray, ndarray or None), or None
        Per topic of ``connections``: log times (int64 ns, (N,)) and an (N, S) uint8 array of
        the serialized messages, in rosbags' order; the array is None when the sizes vary.
        None when the bag must be read through rosbags (unsupported layout, or damage).

    """
    parts = fetch_parts(reader, connections)
    if parts is None:
        return None
    out = {}
    for topic, (logs, blocks) in parts.items():
        if blocks is None:
            out[topic] = (logs, None)
        elif not blocks:
            out[topic] = (logs, np.zeros((0, 0), np.uint8))
        else:
            out[topic] = (logs, np.concatenate(blocks) if len(blocks) > 1 else blocks[0])
    return out


def fetch_parts(reader: Any, connections: Sequence[Any]) -> Optional[dict[str, Parts]]:
    """
    ``fetch`` without joining the blocks: per topic, log times and a list of message blocks.

    The blocks (one per SQLite page or mcap file, each (n_i, S) uint8, in order) are what
    the storage gave; joining them would copy every message once more (0.6 s of a 4M-message
    sqlite3 bag's 2.3 s) only for the decoder to copy the fields out again.

    Returns
    -------
    parts : dict of str to (ndarray, list of ndarray or None), or None
        Per topic: log times (int64 ns, (N,)) and the blocks (empty list: no messages; None:
        sizes vary). None when the bag must be read through rosbags.

    """
    try:
        return _fetch(reader, connections)
    except Exception:  # noqa: BLE001 - rosbags reads it again and reports the real problem
        return None


def _fetch(reader: Any, connections: Sequence[Any]) -> dict[str, Parts]:
    if reader.compression_mode == 'message':
        raise Unsupported('message-compressed bag')
    # A rosbag2 directory: rosbags' Reader delegates to a directory reader holding one
    # storage reader per file (file-compressed ones already decompressed to temporary files).
    storages = getattr(reader.storage, 'storages', None)
    if storages is None:
        raise Unsupported('not a rosbag2 directory reader')
    topics = list(dict.fromkeys(c.topic for c in connections))
    parts: dict[str, list[Parts]] = {t: [] for t in topics}
    for storage in storages:
        cids = _storage_topics(storage, connections)
        if not cids:
            continue
        kind = type(storage).__name__
        if kind in ('Sqlite3Reader', '_LightSqlite3Reader'):
            got = _sqlite_storage(storage, cids)
        elif kind == 'McapReader':
            got = _mcap_storage(storage, cids)
        else:
            raise Unsupported(kind)
        for topic, item in got.items():
            parts[topic].append(item)
    return {t: _concat(parts[t]) for t in topics}


def _storage_topics(storage: Any, connections: Sequence[Any]) -> dict[int, str]:
    """Map the storage's connection ids to topics, matched as rosbags' Reader.messages does."""
    out = {}
    for x in storage.connections:
        for y in connections:
            if (y.topic == x.topic and y.msgtype == x.msgtype and y.ext == x.ext
                    and (not x.digest or not y.digest or y.digest == x.digest)):
                out[x.id] = y.topic
                break
    return out


def _concat(parts: list[Parts]) -> Parts:
    """Join one topic's parts (pages, storage files: in bag order, as rosbags yields them)."""
    if not parts:
        return np.zeros(0, np.int64), []
    logs = np.concatenate([p[0] for p in parts]) if len(parts) > 1 else parts[0][0]
    if any(p[1] is None for p in parts):
        return logs, None
    blocks = [b for p in parts for b in p[1] if len(b)]
    if len({b.shape[1] for b in blocks}) > 1:
        return logs, None
    return logs, blocks


def _ordered(logs: np.ndarray, ties: np.ndarray, block: Optional[np.ndarray]) -> Fetched:
    """Sort by log time, ties by ``ties`` (already ascending in the given order)."""
    if logs.size and np.any(logs[1:] < logs[:-1]):
        order = np.lexsort((ties, logs))
        logs = logs[order]
        block = None if block is None else block[order]
    return logs, block


# --- sqlite3 --------------------------------------------------------------------------------

def _sqlite_storage(storage: Any, cids: dict[int, str]) -> dict[str, Parts]:
    db = storage.dbconn
    if db is None:
        raise Unsupported('closed storage')
    (encoding,), = db.execute('PRAGMA encoding').fetchall()
    if encoding != 'UTF-8':
        # group_concat passes blobs through text, which is byte-exact only in UTF-8 databases.
        raise Unsupported(f'database encoding {encoding}')
    ids = sorted(cids)
    if ids[0] <= 0 or ids[-1] >= _TOPIC_ID_LIMIT:
        raise Unsupported('topic ids out of range')
    # rosbags' own query must walk the timestamp index too (its tie order is then the row
    # id order of the index; a sorting step could order ties otherwise).
    theirs = ('SELECT topics.id,messages.timestamp,messages.data FROM messages JOIN topics '
              'ON messages.topic_id=topics.id WHERE topics.id IN '
              f"({','.join('?' * len(ids))}) ORDER BY timestamp")
    index = _index_walked(db, theirs, ids)
    parts: dict[str, list[Parts]] = {t: [] for t in cids.values()}
    (total,), = db.execute('SELECT count(*) FROM messages').fetchall()
    (in_table,), = db.execute('SELECT count(*) FROM messages NOT INDEXED').fetchall()
    reached = 0
    for in_range, page in _fetched_pages(storage, db, ids, _sqlite_pages(db, total), index):
        reached += in_range
        if page is None:
            continue
        log_ns, tid, size, mem = page
        starts = np.cumsum(size) - size
        for topic in parts:
            pick = slice(None) if len(cids) == 1 else _rows_of(tid, _ids_of(cids, topic))
            mine = size[pick]
            if not mine.size:
                continue
            block = None
            if mine.size == size.size and np.all(mine == mine[0]):
                block = mem.reshape(mine.size, -1)  # every row of the page: no copy
            elif np.all(mine == mine[0]):
                block = _gather(mem, starts[pick], int(mine[0]))
            parts[topic].append((log_ns[pick], None if block is None else [block]))
    if reached != in_table:
        raise Unsupported(f'the timestamp index reaches {reached} of the {in_table} rows')
    return {topic: _concat(items) for topic, items in parts.items()}


def _sqlite_pages(db: Any, total: int) -> list[tuple[Optional[int], Optional[int]]]:
    """
    Log-time ranges [lo, hi) of the ``total`` rows, about equal in rows (None: unbounded).

    As few pages as keep each at about ``_SQLITE_PAGE`` rows or less. Bounds are log times
    taken from the timestamp index, so that the rows of one log time (ties) always fall into
    one page and each page is one index range scan.
    """
    count = max(1, -(-total // _SQLITE_PAGE))
    step = max(1, -(-total // count))
    bounds: list[Optional[int]] = [None]
    while total > step:
        lo = bounds[-1]
        where = '' if lo is None else 'WHERE timestamp >= ?'
        args = () if lo is None else (lo,)
        got = db.execute(f'SELECT timestamp FROM messages {where} ORDER BY timestamp '
                         f'LIMIT 1 OFFSET ?', (*args, step)).fetchall()
        if not got:
            break
        (nxt,), = got
        if lo is not None and nxt <= lo:  # more than a page of ties at lo: skip past them
            (nxt,), = db.execute('SELECT min(timestamp) FROM messages WHERE timestamp > ?',
                                 (lo,)).fetchall()
            if nxt is None:
                break
        bounds.append(int(nxt))
    bounds.append(None)
    return list(zip(bounds[:-1], bounds[1:], strict=True))


def _fetched_pages(storage: Any, db: Any, ids: list[int], pages: list, index: str
                   ) -> Iterator[tuple]:
    """
    Yield ``_sqlite_page`` of each page in order, two at a time on two connections.

    SQLite runs a page's statement without Python's lock (rosbags' binding, apsw, releases
    it), so a second connection to the same read-only file fetches the next page meanwhile:
    a 4M-message recording is fetched in 1.1 instead of 1.7 s on two cores.
    """
    second = _second_reader(storage) if len(pages) > 1 and _cores() > 1 else None
    try:
        yield from _two_at_a_time(
            lambda conn, page: _sqlite_page(conn, ids, page[0], page[1], index), pages,
            (db,) if second is None else (db, second.dbconn))
    finally:
        if second is not None:
            second.close()


def _two_at_a_time(work: Callable, items: list, handles: tuple) -> Iterator:
    """
    Yield ``work(handle, item)`` for the items in order, the next one made meanwhile.

    Item k is worked on ``handles[k % len(handles)]``; with two handles (two connections or
    file handles of one file) two threads work, one item ahead at most, so no more than two
    items' data are held; with one, the items are worked one by one here. Both ways give
    the same results; the first error (in item order) is raised.
    """
    if len(handles) < 2:
        for item in items:
            yield work(handles[0], item)
        return
    with ThreadPoolExecutor(max_workers=2, thread_name_prefix='coreg-bag') as pool:
        ahead = None
        try:
            for k, item in enumerate(items):
                current = ahead or pool.submit(work, handles[k % 2], item)
                ahead = None
                if k + 1 < len(items):
                    ahead = pool.submit(work, handles[(k + 1) % 2], items[k + 1])
                yield current.result()
        finally:
            if ahead is not None:
                ahead.cancel()
                with suppress(Exception):  # the error that stopped the walk is the one told
                    ahead.result()


def _second_reader(storage: Any) -> Any:
    """
    Open the storage file a second time, as ``storage`` was opened; None if it does not.

    Only ``light_open``'s reader: rosbags' own counts every topic's messages on open.
    """
    if type(storage).__name__ != '_LightSqlite3Reader' or not isinstance(storage.path, Path):
        return None
    other = type(storage)(storage.path)
    try:
        other.open()
    except Exception:  # noqa: BLE001 - the pages are then fetched on one connection
        return None
    return other


def _ids_of(cids: dict[int, str], topic: str) -> list[int]:
    """Return the storage's connection (or topic) ids of one topic: several if recorded so."""
    return [c for c, t in cids.items() if t == topic]


def _rows_of(ids: np.ndarray, wanted: list[int]) -> np.ndarray:
    """Tell which rows carry one of the ``wanted`` ids (bool, the shape of ``ids``)."""
    return ids == wanted[0] if len(wanted) == 1 else np.isin(ids, wanted)


def _cores() -> int:
    """CPU cores this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        return os.cpu_count() or 1


def _index_walked(db: Any, query: str, args: Sequence[int]) -> str:
    """Name the index SQLite walks to answer ``query`` (no sorting step), else Unsupported."""
    plan = ' '.join(str(r[-1]) for r in db.execute(f'EXPLAIN QUERY PLAN {query}', args))
    found = re.search(r'(?:SCAN|SEARCH) messages USING INDEX (\S+)', plan)
    if found is None or 'TEMP B-TREE' in plan or 'AUTOMATIC' in plan:
        raise Unsupported(f'query plan {plan}')
    return found.group(1)


def _sqlite_page(
    db: Any, ids: list[int], lo: Optional[int], hi: Optional[int], index: str,
) -> tuple[int, Optional[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]]:
    """
    One page of the wanted rows in rosbags' order, fetched in one SQLite statement.

    Returns the number of rows of any topic the index reaches in the page's range, and the
    log times, topic ids and blob sizes (int64, (N,)) and the N blobs laid end to end
    (uint8) of the wanted rows, or None for none.
    """
    cond: list[str] = []
    args: list[int] = []
    if lo is not None:
        cond.append('timestamp >= ?')
        args.append(lo)
    if hi is not None:
        cond.append('timestamp < ?')
        args.append(hi)
    # the rows the page's index range reaches (a covering count): their sum over the pages
    # must be the table's rows, which a damaged index that rosbags' full walk refuses may
    # not be when walked by ranges (rows left out without an error)
    where = f" WHERE {' AND '.join(cond)}" if cond else ''
    (reached,), = db.execute(f'SELECT count(*) FROM messages INDEXED BY "{index}"{where}',
                             args).fetchall()
    cond.insert(0, f"topic_id IN ({','.join(str(int(c)) for c in ids)})")
    # Per row, one integer holds both the blob size and the topic id (parsed from text in
    # one numpy call): cheaper for SQLite than per-topic size aggregates. A value that is not
    # a blob (rosbags would hand it on as text or a number) gets size -1.
    tag = f"iif(typeof(data) = 'blob', length(data), -1) * {_TOPIC_ID_LIMIT} + topic_id"
    rows = (f'SELECT data, timestamp, {tag} AS tag '
            f"FROM messages WHERE {' AND '.join(cond)} ORDER BY timestamp, id")
    # rosbags reads with ORDER BY timestamp, which SQLite answers by walking the timestamp
    # index: (timestamp, row id) order. The same plan here (no sorting step) gives the same
    # order, and group_concat appends the rows in the order the subquery yields them.
    if _index_walked(db, rows, args) != index:
        raise Unsupported('the page query walks another index than rosbags')
    query = (f"SELECT CAST(group_concat(data, x'') AS BLOB), group_concat(timestamp), "
             f'group_concat(tag), count(*) FROM ({rows})')
    (blob, ts_text, tag_text, count), = db.execute(query, args).fetchall()
    if not count:
        return reached, None
    log_ns, tag = (np.fromstring(t, dtype=np.int64, sep=',') for t in (ts_text, tag_text))
    if log_ns.size != count or tag.size != count:
        raise Unsupported('log times or tags did not parse')
    if np.any(log_ns[1:] < log_ns[:-1]):
        raise Unsupported('rows did not come in log-time order')
    if (lo is not None and log_ns[0] < lo) or (hi is not None and log_ns[-1] >= hi):
        raise Unsupported('rows outside their page')
    size, tid = np.divmod(tag, _TOPIC_ID_LIMIT)
    if np.any(size < 0) or not isinstance(blob, bytes) or len(blob) != int(size.sum()):
        raise Unsupported('concatenated blobs have the wrong size')
    return reached, (log_ns, tid, size, np.frombuffer(blob, dtype=np.uint8))


# --- mcap -----------------------------------------------------------------------------------

def _mcap_storage(storage: Any, cids: dict[int, str]) -> dict[str, Parts]:
    bio = storage.bio
    if bio is None or not storage.chunks:
        # Unindexed files are read by rosbags' record scan.
        raise Unsupported('mcap file without chunk index')
    chunks = sorted((c for c in storage.chunks
                     if any(c.channel_count.get(cid, 0) for cid in cids)),
                    key=lambda c: c.chunk_start_offset)
    topics = list(dict.fromkeys(cids.values()))
    logs: dict[str, list[np.ndarray]] = {t: [] for t in topics}
    rows: dict[str, list[np.ndarray]] = {t: [] for t in topics}
    for found in _mcap_chunks(storage, chunks, cids):
        for topic, (log_time, block) in found.items():
            logs[topic].append(log_time)
            rows[topic].append(block)
    out = {}
    for topic in topics:
        if not logs[topic]:
            out[topic] = (np.zeros(0, np.int64), [])
            continue
        log_ns = np.concatenate(logs[topic])
        blocks = rows[topic]
        block = None
        if all(b is not None for b in blocks) and len({b.shape[1] for b in blocks}) == 1:
            block = np.concatenate(blocks)
        # Concatenation is in (chunk position, record position) order: a stable sort by log
        # time reproduces rosbags' heapq merge of time-sorted chunks.
        log_ns, block = _ordered(log_ns, np.arange(log_ns.size), block)
        out[topic] = (log_ns, None if block is None else [block])
    return out


def _mcap_chunks(storage: Any, chunks: list, cids: dict[int, str]) -> Iterator[dict]:
    """
    Yield ``_mcap_chunk`` of each chunk in order, two at a time on two file handles.

    Reading a chunk, its checksum and the larger copies run outside Python's lock: a
    4M-message recording is read in 0.42 instead of 0.51 s on two cores.
    """
    other = None
    if len(chunks) > 1 and _cores() > 1 and isinstance(getattr(storage, 'path', None), Path):
        with suppress(OSError):
            other = open(storage.path, 'rb')  # noqa: SIM115 - closed below
    try:
        yield from _two_at_a_time(lambda bio, chunk: _mcap_chunk(bio, chunk, cids), chunks,
                                  (storage.bio,) if other is None else (storage.bio, other))
    finally:
        if other is not None:
            other.close()


def _mcap_chunk(bio: Any, chunk: Any, cids: dict[int, str]) -> dict:
    """
    Per wanted topic of one chunk: its log times and its messages' rows (None: sizes vary).

    A topic's messages are picked from all its connections at once (a topic recorded with two
    QoS has two), so they stay in record order, as rosbags yields ties.
    """
    from rosbags.rosbag2.storage_mcap import decompress, read_exact  # noqa: PLC0415

    # Exactly what rosbags' msgsrc reads: CRC from the chunk record, sizes from the index.
    bio.seek(chunk.chunk_start_offset + 9 + 24)
    crc = int.from_bytes(read_exact(bio, 4), 'little')
    bio.seek(chunk.chunk_start_offset + 9 + 40 + len(chunk.compression))
    raw = decompress(read_exact(bio, chunk.compressed_size), chunk.compression,
                     chunk.uncompressed_size, crc)
    mem = np.frombuffer(raw, dtype=np.uint8)
    offsets = _indexed_offsets(bio, chunk, read_exact)
    heads = _message_heads(mem, offsets)
    found = {}
    for topic in dict.fromkeys(cids.values()):
        pick = _rows_of(heads['channel'], _ids_of(cids, topic))
        if not pick.any():
            continue
        head = heads[pick]
        log_time = head['log_time']
        # rosbags keeps a chunk's messages inside the chunk's declared time range only.
        keep = (log_time >= chunk.message_start_time) & (log_time <= chunk.message_end_time)
        if not keep.all():
            head, log_time = head[keep], log_time[keep]
        lengths = head['length'] - 22
        block = None
        if lengths.size and np.all(lengths == lengths[0]):
            starts = offsets[pick][keep] + _MSG_HEAD
            block = _gather(mem, starts, int(lengths[0]))
        found[topic] = (log_time.astype(np.int64), block)
    return found


def _indexed_offsets(bio: Any, chunk: Any, read_exact: Any) -> np.ndarray:
    """Offsets (into the decompressed chunk) of all message records its index lists, sorted."""
    found = []
    for cid, where in chunk.message_index_offsets.items():
        bio.seek(where)
        head = read_exact(bio, 1 + 8 + 2 + 4)
        length = int.from_bytes(head[1:9], 'little')
        if (head[0] != _OP_MESSAGE_INDEX or int.from_bytes(head[9:11], 'little') != cid):
            raise Unsupported('message index record does not match the chunk index')
        nbytes = int.from_bytes(head[11:15], 'little')
        if nbytes % 16 or nbytes + 6 != length:
            raise Unsupported('malformed message index record')
        entries = np.frombuffer(read_exact(bio, nbytes), dtype='<u8').reshape(-1, 2)
        found.append(entries[:, 1])
    offsets = np.concatenate(found) if found else np.zeros(0, np.uint64)
    return np.sort(offsets).astype(np.int64)


def _message_heads(mem: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """Headers of the message records at ``offsets``, checked to tile the chunk with the rest."""
    size = mem.size
    if offsets.size and (offsets[0] < 0 or offsets[-1] + _MSG_HEAD > size):
        raise Unsupported('indexed record outside its chunk')
    heads = _gather(mem, offsets, _MSG_HEAD).view(_MSG_HEAD_DTYPE).reshape(-1)
    if not np.all(heads['op'] == _OP_MESSAGE) or np.any(heads['length'] < 22):
        raise Unsupported('indexed offset is not a message record')
    ends = offsets + 9 + heads['length'].astype(np.int64)
    if offsets.size and ends[-1] > size:
        raise Unsupported('message record overruns its chunk')
    # Walk whatever lies between indexed messages (schemas, channels...): it must hold no
    # message record, or rosbags (which scans every record) would yield messages we miss.
    starts = np.concatenate([[0], ends])
    stops = np.concatenate([offsets, [size]])
    if np.any(stops < starts):
        raise Unsupported('overlapping records')
    for gap in np.flatnonzero(stops > starts).tolist():
        _walk_gap(mem, int(starts[gap]), int(stops[gap]))
    return heads


def _walk_gap(mem: np.ndarray, pos: int, stop: int) -> None:
    """Check that [pos, stop) is a run of whole non-message records."""
    while pos < stop:
        if pos + 9 > stop or mem[pos] == _OP_MESSAGE:
            raise Unsupported('unindexed message record in chunk')
        pos += 9 + int(mem[pos + 1:pos + 9].view('<u8')[0])
    if pos != stop:
        raise Unsupported('record overruns the next indexed message')


def _gather(mem: np.ndarray, starts: np.ndarray, width: int) -> np.ndarray:
    """Rows ``mem[s:s + width]`` for each start, as an (N, width) uint8 array (one copy)."""
    if not starts.size or width == 0:
        return np.zeros((starts.size, width), np.uint8)
    if starts[-1] + width > mem.size:
        raise Unsupported('record outside its chunk')
    return sliding_window_view(mem, width)[starts]

"""
Salvage the PoseStamped messages of a damaged rosbag2: what the storage file still holds.

A recording cut short (power cut, kill) has no metadata.yaml, an mcap file without its summary
and footer, or a sqlite3 file whose last pages are broken; rosbags' Reader refuses all three.
The messages written before the damage are usually intact. ``salvage_streams`` reads the
storage files directly, in order, and stops at the first record it cannot read:

- sqlite3 (``.db3``): the ``topics`` and ``messages`` tables, row by row;
- mcap: the records from the start of the data section (rosbags' own record parser, with
  the file's end taken as the data's end), chunks decompressed as they come.

It is the ``coreg fix-bag --salvage`` behind the error messages of ``posebag``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
import os
from pathlib import Path
import sqlite3
from typing import Union

from coreg_ros.core.errors import BagError
from coreg_ros.core.types import PoseStream
import numpy as np

POSE_STAMPED = 'geometry_msgs/msg/PoseStamped'
_MCAP_MAGIC = b'\x89MCAP0\r\n'


@dataclass
class Salvaged:
    """
    What was read from the damaged storage files.

    Attributes
    ----------
    streams : dict of str to PoseStream
        PoseStamped topics: header stamps, poses, log times as ``receive_stamps``.
    messages : int
        Messages recovered (all topics).
    stopped : list of str
        Where and why reading stopped early, one line per storage file.

    """

    streams: dict = field(default_factory=dict)
    messages: int = 0
    stopped: list = field(default_factory=list)


def _storage_files(path: Path) -> list[Path]:
    if path.is_file():
        return [path]
    if not path.is_dir():
        raise BagError(f'{str(path)!r} does not exist; pass the damaged bag directory or its '
                       f'.mcap/.db3 file')
    files = sorted(p for p in path.iterdir() if p.suffix in ('.mcap', '.db3'))
    if not files:
        raise BagError(f'{str(path)!r} holds no .mcap or .db3 storage file; nothing to '
                       f'salvage')
    return files


def _varint(buf: bytes, i: int) -> tuple[int, int]:
    """Decode the SQLite varint at ``buf[i:]``: (value, next index)."""
    value = 0
    for k in range(9):
        byte = buf[i + k]
        if k == 8:
            return (value << 8) | byte, i + 9
        value = (value << 7) | (byte & 0x7F)
        if byte < 0x80:
            return value, i + k + 1
    return value, i + 9


_INT_SIZES = {1: 1, 2: 2, 3: 3, 4: 4, 5: 6, 6: 8}


def _record(payload: bytes) -> list:
    """Decode a SQLite record (integers, blobs and text; floats as raw bytes)."""
    size, i = _varint(payload, 0)
    types = []
    while i < size:
        t, i = _varint(payload, i)
        types.append(t)
    out, j = [], size
    for t in types:
        if t == 0:
            out.append(None)
        elif t in _INT_SIZES:
            n = _INT_SIZES[t]
            out.append(int.from_bytes(payload[j:j + n], 'big', signed=True))
            j += n
        elif t in (8, 9):
            out.append(t - 8)
        elif t == 7:
            out.append(payload[j:j + 8])
            j += 8
        elif t >= 12:
            n = (t - 12) // 2
            out.append(bytes(payload[j:j + n]))
            j += n
        else:
            raise ValueError(f'serial type {t}')
    return out


def _leaf_rows(raw: bytes):
    """Yield (rowid, columns) of every readable table-leaf cell, page by page (no overflow)."""
    page = int.from_bytes(raw[16:18], 'big')
    page = 65536 if page == 1 else page
    usable = page - raw[20]
    local_max = usable - 35
    for k in range(len(raw) // page):
        start = k * page
        head = start + (100 if k == 0 else 0)
        if raw[head] != 0x0D:
            continue
        n_cells = int.from_bytes(raw[head + 3:head + 5], 'big')
        for c in range(n_cells):
            try:
                ptr = start + int.from_bytes(raw[head + 8 + 2 * c:head + 10 + 2 * c], 'big')
                size, i = _varint(raw, ptr)
                rowid, i = _varint(raw, i)
                if size > local_max:
                    continue  # spills to overflow pages: not a small message row
                yield rowid, _record(raw[i:i + size])
            except (IndexError, ValueError):
                continue


def _sqlite_rows(db: Path, stopped: list):
    """
    Yield (topic, type, log time ns, raw CDR) from a sqlite3 storage file, damaged or not.

    An intact file is read with SQLite. A file SQLite calls malformed (its tail cut off, so
    the B-tree's interior pages may be gone) is read page by page: every table-leaf cell
    that decodes as a ``messages`` row (id, topic_id, timestamp, data) is kept, in id order.
    """
    try:
        con = sqlite3.connect(f'file:{db}?mode=ro', uri=True)
        topics = {tid: (name, ty) for tid, name, ty in
                  con.execute('SELECT id, name, type FROM topics')}
        rows = con.execute('SELECT topic_id, timestamp, data FROM messages ORDER BY id')
        for tid, stamp, data in rows:
            name, ty = topics.get(tid, ('', ''))
            yield name, ty, int(stamp), bytes(data)
        return
    except sqlite3.Error as err:
        stopped.append(f'{db.name}: SQLite cannot read it ({err}); read page by page')
    raw = db.read_bytes()
    if not raw.startswith(b'SQLite format 3\x00'):
        return
    cells = list(_leaf_rows(raw))
    topics = {}
    for rowid, cols in cells:  # topics rows: (id, name, type, serialization_format, ...)
        if (len(cols) >= 3 and isinstance(cols[1], bytes) and isinstance(cols[2], bytes)
                and b'/msg/' in cols[2]):
            topics[rowid if cols[0] is None else cols[0]] = (
                cols[1].decode(errors='replace'), cols[2].decode(errors='replace'))
    messages = sorted((rowid, cols) for rowid, cols in cells
                      if len(cols) == 4 and isinstance(cols[1], int)
                      and isinstance(cols[2], int) and isinstance(cols[3], bytes))
    for _, (_, tid, stamp, data) in messages:
        if tid in topics:
            name, ty = topics[tid]
            yield name, ty, int(stamp), data


def _mcap_rows(path: Path, stopped: list):
    """Yield (topic, type, log time ns, raw CDR) from an mcap file until damage."""
    from rosbags.rosbag2.storage_mcap import McapReader, read_sized

    reader = McapReader(path)
    try:
        reader.bio = path.open('rb')
        if reader.bio.read(8) != _MCAP_MAGIC or reader.bio.read(1) != b'\x01':
            stopped.append(f'{path.name}: not an mcap file (no magic and header)')
            return
        read_sized(reader.bio)  # the header record
        reader.data_start = reader.bio.tell()
        reader.data_end = os.path.getsize(path)
        try:
            reader.meta_scan()  # schemas and channels, as far as they are readable
        except Exception:  # noqa: BLE001 - the damage ends the scan; what was read is kept
            pass
        try:
            for conn, stamp, data in reader.messages_scan(reader.connections):
                yield conn.topic, conn.msgtype, int(stamp), bytes(data)
        except Exception as err:  # noqa: BLE001 - truncated or corrupt record: stop there
            stopped.append(f'{path.name}: stopped at a damaged record ({type(err).__name__})')
    finally:
        if reader.bio is not None:
            reader.bio.close()


def salvage_streams(path: Union[str, os.PathLike]) -> Salvaged:
    """
    Read every intact PoseStamped message of a damaged bag (directory or storage file).

    Raises
    ------
    BagError
        If there is no storage file, or no PoseStamped message could be read.

    """
    from coreg_ros.files.bag.posebag import _typestore

    store = _typestore()
    out = Salvaged()
    columns: dict = {}
    frames: dict = {}
    for f in _storage_files(Path(path)):
        rows = _sqlite_rows(f, out.stopped) if f.suffix == '.db3' else _mcap_rows(f, out.stopped)
        for topic, msgtype, log_ns, data in rows:
            if msgtype != POSE_STAMPED:
                continue
            try:
                msg = store.deserialize_cdr(data, POSE_STAMPED)
            except Exception:  # noqa: BLE001 - one damaged message: skip it, keep going
                continue
            h, p, q = msg.header, msg.pose.position, msg.pose.orientation
            columns.setdefault(topic, []).append(
                (h.stamp.sec * 1_000_000_000 + h.stamp.nanosec, log_ns,
                 (p.x, p.y, p.z, q.w, q.x, q.y, q.z)))
            frames.setdefault(topic, h.frame_id)
            out.messages += 1
    if not columns:
        raise BagError(f'no intact {POSE_STAMPED} message in {str(path)!r}; nothing to '
                       f'salvage (' + ('; '.join(out.stopped) or 'no such topic') + ')')
    for topic, rows in columns.items():
        rows.sort(key=lambda r: r[1])  # record order
        table = np.array([r[2] for r in rows], dtype=float).reshape(-1, 7)
        out.streams[topic] = PoseStream(
            stamps=np.array([r[0] for r in rows], dtype=np.int64), position=table[:, :3].copy(),
            quat_wxyz=table[:, 3:].copy(), frame_id=frames[topic],
            receive_stamps=np.array([r[1] for r in rows], dtype=np.int64))
    return out

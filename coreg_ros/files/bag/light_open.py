"""
rosbags' Reader, opened without its per-topic message count of sqlite3 storage files.

rosbags' ``Sqlite3Reader`` counts each topic's messages on open with a ``LEFT JOIN`` of
``topics`` and ``messages`` for which SQLite builds a temporary index over every row: 0.4 s
for a million messages, as long as the bulk fetch itself. Those counts are never used when
reading (``Reader.connections`` takes its counts from ``metadata.yaml``; the storage-level
connections only serve to match topic, type, QoS and type hash), so the reader here is
rosbags' own ``Reader`` and ``DirectoryReader`` (metadata parsing and all its checks, file
decompression, the mcap plugin unchanged) with a sqlite3 storage plugin whose ``_open`` runs
rosbags' queries minus the count join and the whole-table ``MIN/MAX/COUNT``.

It is a fast first try only: ``posebag`` reads through it when every wanted topic then comes
out of the bulk path, and otherwise (any error, anything unusual) drops it and opens the
bag with plain rosbags, which reports errors exactly as before. The bulk fetch walks every
row of ``messages`` through the timestamp index as rosbags' read does (in pages of index
ranges whose row counts must add up to the table's), so a table or index that the skipped
count would have found damaged still fails there, or sends the read to rosbags.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from rosbags.interfaces import (
    Connection,
    ConnectionExtRosbag2,
    MessageDefinition,
    MessageDefinitionFormat,
)
from rosbags.rosbag2 import Reader
from rosbags.rosbag2.metadata import parse_qos
from rosbags.rosbag2.reader import DirectoryReader
from rosbags.rosbag2.storage_mcap import McapReader
from rosbags.rosbag2.storage_sqlite3 import Sqlite3Reader

#: Message definition encodings, as rosbags maps them (an unknown one fails there too).
_FORMATS = {'ros2msg': MessageDefinitionFormat.MSG, 'ros2idl': MessageDefinitionFormat.IDL}


class LightOpenUnsupported(Exception):
    """The bag is not one the light open handles; open it with plain rosbags."""


class _LightSqlite3Reader(Sqlite3Reader):
    """rosbags' sqlite3 storage reader without the message counts on open."""

    def _open(self) -> None:
        if not isinstance(self.path, Path) or self.dbconn is None:
            raise LightOpenUnsupported('not a plain storage file')
        cur = self.dbconn.cursor()
        # The same checks and queries as rosbags' Sqlite3Reader._open, in the same order.
        (tables,), = cur.execute(
            "SELECT count(*) FROM sqlite_master WHERE type='table' "
            "AND name IN ('messages', 'topics')").fetchall()
        if tables != 2:
            raise LightOpenUnsupported('database missing tables')
        if not cur.execute('PRAGMA table_info(schema)').fetchall():
            # Schemas 1-3 (no schema table, Foxy/Galactic) are rare: plain rosbags reads them.
            raise LightOpenUnsupported('old database schema')
        (schema,) = cur.execute('SELECT schema_version FROM schema').fetchone() or (-1,)
        if schema < 4:
            raise LightOpenUnsupported(f'database schema {schema}')
        msgtypes = [
            {'name': name, 'encoding': enc, 'msgdef': text, 'digest': digest}
            for name, enc, text, digest in cur.execute(
                'SELECT topic_type, encoding, encoded_message_definition, '
                'type_description_hash FROM message_definitions ORDER BY id')]

        def msgdef(name: str) -> MessageDefinition:
            found = next((x for x in msgtypes if x['name'] == name), None)
            if found is None:
                return MessageDefinition(MessageDefinitionFormat.NONE, '')
            return MessageDefinition(_FORMATS[found['encoding']], found['msgdef'])

        # rosbags' LEFT JOIN ... GROUP BY topics.id gives one row per topic in id order;
        # the count column (-1 here: not counted) is the only difference.
        self.connections = [
            Connection(cid, topic, msgtype, msgdef(msgtype), digest, -1,
                       ConnectionExtRosbag2(fmt, parse_qos(qos)), self)
            for cid, topic, msgtype, fmt, qos, digest in cur.execute(
                'SELECT id, name, type, serialization_format, offered_qos_profiles, '
                'type_description_hash FROM topics ORDER BY id')]
        self.schema = schema
        self.msgtypes = msgtypes


class _LightDirectoryReader(DirectoryReader):
    """rosbags' directory reader with the light sqlite3 storage plugin."""

    STORAGE_PLUGINS = {'mcap': McapReader, 'sqlite3': _LightSqlite3Reader}


def open_light(path: Path) -> Any:
    """
    Open a rosbag2 directory like ``rosbags.rosbag2.Reader`` does, minus the sqlite3 counts.

    Parameters
    ----------
    path : Path
        The rosbag2 directory (holding ``metadata.yaml``).

    Returns
    -------
    reader : rosbags.rosbag2.Reader
        An open reader (close it); its storage-level sqlite3 connections have ``msgcount``
        -1, everything else is as rosbags opens it.

    Raises
    ------
    Exception
        Whatever rosbags raises, or ``LightOpenUnsupported``; the caller then opens the bag
        with plain rosbags, which reports the problem.

    """
    reader = Reader(path)
    if type(reader.storage) is not DirectoryReader:
        raise LightOpenUnsupported('not a rosbag2 directory')
    reader.storage = _LightDirectoryReader(reader.path)
    reader.open()
    return reader

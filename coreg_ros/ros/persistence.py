"""
What the node keeps on disk: the last result (YAML, written atomically) and sample bags.

Files live in the node's ``storage_dir``:

- ``result_<node>_<config key>.yaml`` (``result_file_name``): ``{'result': result_to_dict(...),
  'frames': {...}, 'settings': {...}, 'node': name, 'config_key': key, 'stamp_ns': calibration
  time, 'saved_at': ISO time}``, replaced atomically (temp file + ``os.replace``) so a crash
  never leaves half a file. The key hashes what a result is valid for (model, topics, frames),
  so nodes sharing a ``storage_dir`` and a node restarted with another configuration never
  republish each other's results. (``result.yaml`` is the name of older versions.)
- ``samples_<YYYYmmdd-HHMMSS>[_k]/``: rosbag2 recordings of the raw accumulated messages
  (``coreg calibrate`` and ``coreg play`` take them as they are).
- ``journal_<node>_<config key>_<YYYYmmdd-HHMMSS>/``: the accepted samples of a running
  session, written as they arrive (``SampleJournal``): one small rosbag2 per flush, named
  ``<first>-<last>`` after the flush numbers it holds, merged now and then into larger ones.
  A clean shutdown removes it; one left by a killed node is reported at start-up and resumed
  with ``resume_samples``.
"""

from __future__ import annotations

from collections.abc import Mapping
import datetime
import hashlib
import json
import os
from pathlib import Path
import re
import shutil
import tempfile
from typing import Optional

from coreg_ros.core.errors import InputError
from coreg_ros.core.types import PoseStream, UncertainPose
from coreg_ros.files.bag.posebag import read_pose_bag, write_pose_bag
from coreg_ros.files.results import pose_from_dict
import numpy as np
import yaml

RESULT_FILE = 'result.yaml'
#: Keys of the settings a stored result depends on (besides the frames).
CONFIG_KEYS = ('model', 'topic_a', 'topic_b')


def _safe(name: str) -> str:
    """Return a node name as a file name part (namespaces and odd characters become '_')."""
    return re.sub(r'[^A-Za-z0-9_.-]+', '_', name).strip('_') or 'node'


def config_key(settings: dict, frames: dict) -> str:
    """Return a short hash of what a result is valid for: model, topics and frame ids."""
    what = {k: settings.get(k) for k in CONFIG_KEYS}
    what['topic_b'] = list(what['topic_b'] or [])
    what['frames'] = dict(sorted(frames.items()))
    return hashlib.sha1(json.dumps(what, sort_keys=True).encode()).hexdigest()[:10]


def result_file_name(node_name: str, key: str) -> str:
    """Name of the stored result of a node and configuration key."""
    return f'result_{_safe(node_name)}_{key}.yaml'


def describe_config(doc: dict) -> str:
    """One-line summary of the configuration a stored document was made with."""
    settings = doc.get('settings') or {}
    frames = doc.get('frames') or {}
    return (f'model {settings.get("model", "?")}, topics {settings.get("topic_a", "?")} / '
            f'{", ".join(settings.get("topic_b") or ["?"])}, frames '
            f'{frames.get("base_a", "?")} / {frames.get("base_b", "?")}')


def matches_config(doc: dict, settings: dict, frames: dict) -> bool:
    """Tell whether a stored document was made with this model, these topics and frames."""
    stored = doc.get('settings')
    if not isinstance(stored, dict) or not isinstance(doc.get('frames'), dict):
        return False
    return config_key(stored, doc['frames']) == config_key(settings, frames)


def save_result(storage_dir: str, result_dict: dict, frames: dict, settings: dict, *,
                name: str = RESULT_FILE, extra: Optional[dict] = None) -> Path:
    """
    Write the result YAML atomically and return its path.

    Parameters
    ----------
    storage_dir : str
        Directory (created if missing).
    result_dict : dict
        ``coreg_ros.files.results.result_to_dict`` of the result.
    frames, settings : dict
        Frame ids of the published poses and the calibration settings used.
    name : str
        File name in ``storage_dir`` (``result_file_name`` for the node).
    extra : dict, optional
        More top-level entries (node name, configuration key, calibration stamp).

    """
    folder = Path(storage_dir)
    folder.mkdir(parents=True, exist_ok=True)
    doc = {'result': result_dict, 'frames': frames, 'settings': settings, **(extra or {}),
           'saved_at': datetime.datetime.now().astimezone().isoformat(timespec='seconds')}
    fd, tmp = tempfile.mkstemp(prefix='.result-', suffix='.yaml.tmp', dir=folder)
    try:
        with os.fdopen(fd, 'w') as f:
            yaml.safe_dump(doc, f, sort_keys=False)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, folder / name)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return folder / name


def load_result(storage_dir: str, name: str = RESULT_FILE
                ) -> Optional[tuple[dict, UncertainPose, UncertainPose]]:
    """
    Read the stored result ``storage_dir/name``, if any.

    Returns
    -------
    stored : tuple or None
        ``(document, base_to_base, tool_to_marker)``, or None when there is no stored result.

    Raises
    ------
    InputError
        If the file exists but is malformed (the message says to delete it and recalibrate).

    """
    path = Path(storage_dir) / name
    try:
        if not path.is_file():
            return None
        doc = yaml.safe_load(path.read_text())
        result = doc['result']
        return (doc, pose_from_dict(result['base_to_base']),
                pose_from_dict(result['tool_to_marker']))
    except InputError:
        raise
    except (OSError, yaml.YAMLError, KeyError, TypeError) as e:
        raise InputError(f'stored result {str(path)!r} is unreadable ({e!r}); delete it and '
                         f'recalibrate') from e


def other_results(storage_dir: str, node_name: str, key: str) -> list[Path]:
    """Return the results of this node stored for other configurations (or as result.yaml)."""
    folder = Path(storage_dir)
    try:
        found = sorted(folder.glob(f'result_{_safe(node_name)}_*.yaml'))
        legacy = folder / RESULT_FILE
        found += [legacy] if legacy.is_file() else []
    except OSError:
        return []
    return [p for p in found if p.name != result_file_name(node_name, key)]


def stamp_ns_of(doc: dict) -> Optional[int]:
    """Return the calibration time of a stored document (ns since the epoch), if known."""
    stamp = doc.get('stamp_ns')
    if isinstance(stamp, int) and stamp > 0:
        return stamp
    saved = doc.get('saved_at')
    try:
        when = datetime.datetime.fromisoformat(str(saved))
    except ValueError:
        return None
    return int(when.timestamp() * 1e9)


def new_bag_path(storage_dir: str, prefix: str = 'samples') -> Path:
    """Return a new bag path in ``storage_dir`` (time-stamped, suffixed if it exists)."""
    folder = Path(storage_dir)
    folder.mkdir(parents=True, exist_ok=True)
    base = f'{prefix}_{datetime.datetime.now():%Y%m%d-%H%M%S}'
    path, k = folder / base, 1
    while path.exists():
        path, k = folder / f'{base}_{k}', k + 1
    return path


def save_samples(storage_dir: str, streams: Mapping[str, PoseStream],
                 storage: str = 'sqlite3') -> Path:
    """Write the streams (topic -> PoseStream) to a new bag in ``storage_dir``; return its path."""
    path = new_bag_path(storage_dir)
    write_pose_bag(path, dict(streams), storage=storage)
    return path


# --------------------------------------------------------------------------- sample journal

#: Flushes merged into one bag when this many small ones have piled up (10 s at 2 Hz).
MERGE_AFTER = 20
_CHUNK = re.compile(r'^(\d{8})-(\d{8})$')


def journal_prefix(node_name: str, key: str) -> str:
    """Directory name prefix of the journals of a node and configuration."""
    return f'journal_{_safe(node_name)}_{key}_'


def left_over_journals(storage_dir: str, node_name: str, key: str) -> list[Path]:
    """Journals of this node and configuration left by a session that did not end cleanly."""
    try:
        return sorted(p for p in Path(storage_dir).glob(journal_prefix(node_name, key) + '*')
                      if p.is_dir())
    except OSError:
        return []


def _chunks_all(folder: Path) -> list[tuple[int, int, Path]]:
    """Return every complete chunk bag of a journal as (first, last, path)."""
    found = []
    for p in folder.iterdir():
        m = _CHUNK.match(p.name)
        if m and (p / 'metadata.yaml').is_file():
            found.append((int(m.group(1)), int(m.group(2)), p))
    return sorted(found, key=lambda c: (c[0], -c[1]))


def _chunks(folder: Path) -> list[tuple[int, int, Path]]:
    """Return the complete chunk bags of a journal as (first, last, path), overlaps removed."""
    kept, covered = [], -1
    for first, last, p in _chunks_all(folder):
        if last > covered:  # a merge that was cut short leaves chunks it also holds
            kept.append((first, last, p))
            covered = last
    return kept


def read_journal(folder, topics) -> dict[str, PoseStream]:
    """
    Read every sample of a journal: topic -> PoseStream (header stamps, receive stamps).

    Raises
    ------
    BagError
        If a chunk is unreadable (the message names it).

    """
    parts = {t: [] for t in topics}
    for _, _, path in _chunks(Path(folder)):
        held = set(_topics_of(path))
        streams = read_pose_bag(path, [t for t in topics if t in held])
        for t, s in streams.items():
            parts[t].append(s)
    out = {}
    for t in topics:
        got = parts[t]
        if not got:
            out[t] = PoseStream(stamps=np.zeros(0, np.int64), position=np.zeros((0, 3)),
                                quat_wxyz=np.zeros((0, 4)), frame_id='',
                                receive_stamps=np.zeros(0, np.int64))
            continue
        out[t] = PoseStream(
            stamps=np.concatenate([s.stamps for s in got]),
            position=np.concatenate([s.position for s in got]),
            quat_wxyz=np.concatenate([s.quat_wxyz for s in got]),
            frame_id=got[0].frame_id,
            receive_stamps=np.concatenate([s.receive_stamps for s in got]))
    return out


def _topics_of(path: Path) -> list[str]:
    from coreg_ros.files.bag.posebag import list_topics
    return list(list_topics(path))


def _fsync_tree(path: Path) -> None:
    """Push a freshly written bag directory (files, then the directories) to the disk."""
    for p in [*path.iterdir(), path, path.parent]:
        fd = os.open(p, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


class SampleJournal:
    """
    The accepted samples of a session on disk as they arrive, so a crash loses at most a flush.

    Parameters
    ----------
    folder : path-like
        The journal directory (created; an existing one is continued, e.g. when resuming).
    storage : str
        rosbag2 storage of the chunks (mcap: the cheapest to write).

    Notes
    -----
    ``append(streams)`` writes one complete, fsynced rosbag2 per call (written beside its final
    name and renamed, so a kill never leaves half a chunk under a chunk name). ``merge`` turns
    the chunks into one bag from samples the caller still holds, so a long session does not
    pile up thousands of directories.

    """

    def __init__(self, folder, storage: str = 'mcap'):
        self.folder = Path(folder)
        self.folder.mkdir(parents=True, exist_ok=True)
        self.storage = storage
        chunks = _chunks(self.folder)
        self.next_seq = chunks[-1][1] + 1 if chunks else 0
        self.n_chunks = len(chunks)

    def append(self, streams: Mapping[str, PoseStream]) -> Optional[Path]:
        """Write the streams (only new samples) as the next chunk; None if all are empty."""
        streams = {t: s for t, s in streams.items() if len(s.stamps)}
        if not streams:
            return None
        seq = self.next_seq
        path = self.folder / f'{seq:08d}-{seq:08d}'
        write_pose_bag(path, streams, storage=self.storage)
        _fsync_tree(path)
        self.next_seq, self.n_chunks = seq + 1, self.n_chunks + 1
        return path

    def merge(self, streams: Mapping[str, PoseStream], first: int, last: int) -> Path:
        """
        Replace the chunks ``first..last`` by one bag of ``streams`` (exactly their samples).

        The merged bag is named after the chunks it replaces and is complete on disk before
        they are removed; a kill in between leaves chunks that ``read_journal`` skips.
        """
        path = self.folder / f'{first:08d}-{last:08d}'
        if first == last:
            return path
        if not (path / 'metadata.yaml').is_file():  # else a merge cut short wrote it already
            shutil.rmtree(path, ignore_errors=True)
            write_pose_bag(path, {t: s for t, s in streams.items() if len(s.stamps)},
                           storage=self.storage)
            _fsync_tree(path)
        for lo, hi, p in _chunks_all(self.folder):
            if first <= lo and hi <= last and p != path:
                shutil.rmtree(p, ignore_errors=True)
        self.n_chunks = len(_chunks(self.folder))
        return path

    def remove(self) -> None:
        """Delete the journal (the session ended cleanly, or its samples were forgotten)."""
        shutil.rmtree(self.folder, ignore_errors=True)
        self.n_chunks = 0


def new_journal_path(storage_dir: str, node_name: str, key: str) -> Path:
    """Return a new journal directory path for this node and configuration."""
    base = journal_prefix(node_name, key) + f'{datetime.datetime.now():%Y%m%d-%H%M%S}'
    path, k = Path(storage_dir) / base, 1
    while path.exists():
        path, k = Path(storage_dir) / f'{base}_{k}', k + 1
    return path


def remove_journal(folder) -> None:
    """Delete a journal directory (its samples are elsewhere now)."""
    shutil.rmtree(folder, ignore_errors=True)

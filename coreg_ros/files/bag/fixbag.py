"""
Repair a PoseStamped recording: sort by header stamp, drop repeated stamps, split at a clock jump.

``fix_bag`` is ``coreg fix-bag``: the coreg way to do what the pairing's refusals ask for
(out-of-order or repeated stamps, a clock jump), reading and writing with
``coreg_ros.files.bag.posebag`` (so the result is an ordinary rosbag2, either storage format).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Optional

from coreg_ros.core.errors import BagError, ConfigError
from coreg_ros.core.types import PoseStream
from coreg_ros.files.bag.posebag import list_topics, POSE_STAMPED, read_pose_bag, write_pose_bag
import numpy as np


@dataclass(frozen=True)
class FixReport:
    """
    What ``fix_bag`` did.

    Attributes
    ----------
    outputs : list of (Path, dict of str to int)
        Each bag written and its message count per topic.
    reordered : dict of str to int
        Messages per topic that were out of stamp order (``sort``).
    dropped : dict of str to int
        Messages per topic dropped because their stamp repeated an earlier one's.
    jumps : list of (str, int, int)
        The clock jumps split at: topic, header stamp before and after (ns).
    skipped_topics : list of str
        Topics not copied (not PoseStamped).
    salvage_stopped : list of str
        Where reading a damaged storage file stopped (``salvage``).

    """

    outputs: list
    reordered: dict
    dropped: dict
    jumps: list
    skipped_topics: list
    salvage_stopped: list = field(default_factory=list)


def sort_stream(stream: PoseStream) -> tuple[PoseStream, int]:
    """
    Sort a stream by header stamp (stable); return it and how many messages moved.

    The record times (``receive_stamps``) stay in increasing order, given to the messages in
    their new order, so the bag holds the messages in stamp order.
    """
    order = np.argsort(stream.stamps, kind='stable')
    moved = int(np.count_nonzero(order != np.arange(order.size)))
    receive = None if stream.receive_stamps is None else np.sort(stream.receive_stamps)
    return replace(stream.take(order), receive_stamps=receive), moved


def drop_duplicate_stamps(stream: PoseStream) -> tuple[PoseStream, int]:
    """Drop messages whose header stamp repeats an earlier one's (keep the first)."""
    _, first = np.unique(stream.stamps, return_index=True)
    keep = np.sort(first)
    return stream.take(keep), len(stream) - keep.size


def find_jumps(stream: PoseStream, jump_ns: int) -> np.ndarray:
    """Return the indices i where the header stamp steps by more than ``jump_ns`` from i-1."""
    step = np.diff(stream.stamps)
    return np.flatnonzero(np.abs(step) > jump_ns) + 1


def fix_bag(src, dst, *, sort: bool = False, drop_duplicates: bool = False,
            split_at_jump: Optional[float] = None, storage: str = 'sqlite3',
            salvage: bool = False) -> FixReport:
    """
    Write a repaired copy of the PoseStamped topics of a rosbag2 recording.

    Parameters
    ----------
    src : str or path-like
        The recording (rosbag2 directory).
    dst : str or path-like
        The new bag; with ``split_at_jump`` and a jump found, ``dst_1``, ``dst_2``, ... (one
        per part) instead.
    sort : bool
        Sort each topic by header stamp.
    drop_duplicates : bool
        Drop messages whose header stamp repeats an earlier one's on the same topic.
    split_at_jump : float, optional
        Split the recording wherever a topic's header stamp steps by more than this many
        seconds (forward or back): every topic is cut at the record time of the first message
        after the jump, so each part holds one clock segment of every device.
    storage : {'sqlite3', 'mcap'}
        Storage of the new bag(s).
    salvage : bool
        Read the storage file(s) directly (``coreg_ros.files.bag.salvage``): a recording cut short
        (no metadata.yaml, a truncated mcap or sqlite3 file) gives what it still holds.

    Returns
    -------
    FixReport

    Raises
    ------
    ConfigError
        If nothing was asked for, or ``split_at_jump`` is not a positive number.
    BagError
        If the recording cannot be read, has no PoseStamped topic, or a new bag exists.

    """
    if not (sort or drop_duplicates or salvage or split_at_jump is not None):
        raise ConfigError('nothing to do; pass --salvage, --sort, --drop-duplicates and/or '
                          '--split-at-jump SECONDS')
    if split_at_jump is not None and not (np.isfinite(split_at_jump) and split_at_jump > 0):
        raise ConfigError(f'--split-at-jump must be a positive number of seconds, got '
                          f'{split_at_jump}')
    stopped = []
    if salvage:
        from coreg_ros.files.bag.salvage import salvage_streams
        found = salvage_streams(src)
        streams, stopped = found.streams, found.stopped
        topics, skipped = list(streams), []
    else:
        types = list_topics(src)
        topics = [t for t, ty in types.items() if POSE_STAMPED in ty.split(', ')]
        skipped = [t for t in types if t not in topics]
        if not topics:
            raise BagError(f'bag {str(src)!r} has no {POSE_STAMPED} topic; nothing to fix')
        streams = read_pose_bag(src, topics)
    reordered, dropped = {}, {}
    for t in topics:
        if sort:
            streams[t], reordered[t] = sort_stream(streams[t])
        if drop_duplicates:
            streams[t], dropped[t] = drop_duplicate_stamps(streams[t])

    jumps, cuts = [], []
    if split_at_jump is not None:
        for t in topics:
            s = streams[t]
            for i in find_jumps(s, int(round(split_at_jump * 1e9))):
                jumps.append((t, int(s.stamps[i - 1]), int(s.stamps[i])))
                cuts.append(int(s.receive_stamps[i]))
    cuts = sorted(set(cuts))
    dst = Path(dst)
    parts = [dst] if not cuts else [
        dst.with_name(f'{dst.name}_{k + 1}') for k in range(len(cuts) + 1)]
    for part in parts:
        if part.exists():
            raise BagError(f'{str(part)!r} exists already; choose a new output name')
    outputs = []
    bounds = [-np.inf, *cuts, np.inf]
    for k, part in enumerate(parts):
        chunk = {}
        for t in topics:
            s = streams[t]
            index = np.flatnonzero((s.receive_stamps >= bounds[k])
                                   & (s.receive_stamps < bounds[k + 1]))
            chunk[t] = s.take(index)
        write_pose_bag(part, chunk, storage=storage)
        outputs.append((part, {t: len(s) for t, s in chunk.items()}))
    return FixReport(outputs=outputs, reordered=reordered, dropped=dropped, jumps=jumps,
                     skipped_topics=skipped, salvage_stopped=stopped)

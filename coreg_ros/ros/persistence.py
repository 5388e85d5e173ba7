"""
What the node keeps on disk: the last result (YAML, written atomically) and sample bags.

Files live in the node's ``storage_dir``:

- ``result.yaml``: ``{'result': result_to_dict(...), 'frames': {...}, 'settings': {...},
  'saved_at': ISO time}``, replaced atomically (temp file + ``os.replace``) so a crash never
  leaves half a file; read back and republished at start-up.
- ``samples_<YYYYmmdd-HHMMSS>[_k]/``: rosbag2 recordings of the raw accumulated messages
  (``coreg calibrate`` and ``coreg play`` take them as they are).
"""

from __future__ import annotations

from collections.abc import Mapping
import datetime
import os
from pathlib import Path
import tempfile
from typing import Optional

import yaml

from coreg_ros.bag.posebag import write_pose_bag
from coreg_ros.core.errors import InputError
from coreg_ros.core.result_io import pose_from_dict
from coreg_ros.core.types import PoseStream, UncertainPose

RESULT_FILE = 'result.yaml'


def save_result(storage_dir: str, result_dict: dict, frames: dict, settings: dict) -> Path:
    """
    Write the result YAML atomically and return its path.

    Parameters
    ----------
    storage_dir : str
        Directory (created if missing).
    result_dict : dict
        ``coreg_ros.core.result_io.result_to_dict`` of the result.
    frames, settings : dict
        Frame ids of the published poses and the calibration settings used.

    """
    folder = Path(storage_dir)
    folder.mkdir(parents=True, exist_ok=True)
    doc = {'result': result_dict, 'frames': frames, 'settings': settings,
           'saved_at': datetime.datetime.now().astimezone().isoformat(timespec='seconds')}
    fd, tmp = tempfile.mkstemp(prefix='.result-', suffix='.yaml.tmp', dir=folder)
    try:
        with os.fdopen(fd, 'w') as f:
            yaml.safe_dump(doc, f, sort_keys=False)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, folder / RESULT_FILE)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return folder / RESULT_FILE


def load_result(storage_dir: str) -> Optional[tuple[dict, UncertainPose, UncertainPose]]:
    """
    Read the stored result, if any.

    Returns
    -------
    stored : tuple or None
        ``(document, base_to_base, tool_to_marker)``, or None when there is no stored result.

    Raises
    ------
    InputError
        If the file exists but is malformed (the message says to delete it and recalibrate).

    """
    path = Path(storage_dir) / RESULT_FILE
    if not path.is_file():
        return None
    try:
        doc = yaml.safe_load(path.read_text())
        result = doc['result']
        return (doc, pose_from_dict(result['base_to_base']),
                pose_from_dict(result['tool_to_marker']))
    except InputError:
        raise
    except (OSError, yaml.YAMLError, KeyError, TypeError) as e:
        raise InputError(f'stored result {str(path)!r} is unreadable ({e!r}); delete it and '
                         f'recalibrate') from e


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

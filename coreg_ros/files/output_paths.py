"""
Where a command will write, checked before it starts working: one line, never a traceback.

A user's ``--report X`` may be an existing file, ``--out X`` a path under a file or in a
read-only place, a new bag's name may be taken: found at the end of a long calibration, each
was a traceback and the work lost. Every command that writes checks its outputs first with
these (``cli/``), and the writers check again when they write (the atomic writer, the bag
writer, which use ``check_new_bag``).
"""

from __future__ import annotations

import os
from pathlib import Path
import tempfile

from coreg_ros.core.errors import BagError, ConfigError


def _nearest_existing(path: Path) -> Path:
    """Return the path or its nearest ancestor that exists (where a mkdir -p would start)."""
    path = Path(os.path.abspath(path))
    while not path.exists() and path != path.parent:
        path = path.parent
    return path


def _probe_writable(directory: Path, shown, option: str) -> None:
    """Create and remove a file in ``directory``: the only test root and mounts cannot fool."""
    try:
        fd, probe = tempfile.mkstemp(prefix='.coreg-probe-', dir=directory)
        os.close(fd)
        os.unlink(probe)
    except OSError as e:
        raise ConfigError(f'{option} {shown}: cannot write in {directory} ({e.strerror}); '
                          f'choose a writable place') from e


def check_output_file(path, option: str) -> None:
    """
    Check that a file can be written at ``path`` (``-``, standard output, always can).

    Raises
    ------
    ConfigError
        ``path`` is a directory, lies under a file, or its directory cannot be written.

    """
    if path is None or str(path) == '-':
        return
    p = Path(path)
    if p.is_dir():
        raise ConfigError(f'{option} {path} is a directory; give a file name (e.g. '
                          f'{p / "result.json"})')
    base = _nearest_existing(p.parent)
    if not base.is_dir():
        raise ConfigError(f'{option} {path}: {base} is a file, not a directory; give a path '
                          f'in a directory')
    _probe_writable(base, path, option)


def check_output_dir(path, option: str) -> None:
    """
    Check that ``path`` is, or can be made, a directory to write in.

    Raises
    ------
    ConfigError
        ``path`` is an existing file or lies under one, or cannot be written.

    """
    if path is None:
        return
    p = Path(path)
    if p.exists() and not p.is_dir():
        raise ConfigError(f'{option} {path} is a file; give a directory (it is created if '
                          f'missing), e.g. {p.with_suffix("")}_out')
    base = _nearest_existing(p)
    if not base.is_dir():
        raise ConfigError(f'{option} {path}: {base} is a file, not a directory; give a path '
                          f'that is not under a file')
    _probe_writable(base, path, option)


def check_new_bag(path, option: str = 'the new bag') -> None:
    """
    Check that a new rosbag2 directory can be created at ``path``.

    Raises
    ------
    BagError
        ``path`` exists (a bag is never overwritten), its directory does not exist or cannot
        be written.

    """
    p = Path(path)
    if p.exists() or p.is_symlink():
        raise BagError(f'{str(p)!r} exists already and will not be overwritten; choose a new '
                       f'bag name or remove the old one')
    if not p.parent.is_dir():
        raise BagError(f'cannot write bag {str(p)!r}: directory {str(p.parent)!r} does not '
                       f'exist; create it first')
    try:
        _probe_writable(p.parent, path, option)
    except ConfigError as e:
        raise BagError(str(e)) from e

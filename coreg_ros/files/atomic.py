"""
The one atomic writer: results, reports and node files never exist half-written.

A file is written to a temporary file in the same directory, flushed to disk, then renamed over
the final name (``os.replace``), so a crash leaves the old file or the new one, never a mix.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
import tempfile

from coreg_ros.core.errors import CoregError


def write_atomic(path, text: str) -> Path:
    """Write ``text`` to ``path`` atomically (UTF-8); returns the path."""
    return write_bytes(path, text.encode('utf-8'))


def write_bytes(path, data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically; returns the path."""
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f'.{path.name}.', dir=path.parent)
        with os.fdopen(fd, 'wb') as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)  # mkstemp creates 0600; give the usual mode
        os.replace(tmp, path)
    except OSError as e:
        raise CoregError(f'cannot write {path}: {e.strerror}; check the directory') from e
    return path


def write_json(path, data) -> Path:
    """Write ``data`` as indented JSON, atomically."""
    return write_atomic(path, json.dumps(data, indent=2) + '\n')


def write_yaml(path, data) -> Path:
    """Write ``data`` as block YAML (keys in their order), atomically."""
    import yaml

    return write_atomic(path, yaml.safe_dump(data, sort_keys=False))

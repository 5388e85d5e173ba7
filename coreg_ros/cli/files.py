"""
Small file helpers of the front ends: atomic writes and the ROS parameter YAML.

Results are written atomically (temporary file in the same directory, then ``os.replace``), so a
crash never leaves a half-written result under the final name.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
import tempfile

from coreg_ros.core.errors import ConfigError, CoregError


def write_atomic(path, text: str) -> Path:
    """Write ``text`` to ``path`` atomically; returns the path."""
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f'.{path.name}.', dir=path.parent)
        with os.fdopen(fd, 'w', encoding='utf-8') as f:
            f.write(text)
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


def load_parameters(path, node_name: str = 'coreg_node') -> dict:
    """
    Read the ``ros__parameters`` of ``node_name`` from a ROS parameter YAML file.

    Returns the raw mapping (node-only keys included); pass it to
    ``settings.settings_from_mapping``.
    """
    import yaml

    try:
        with open(path, encoding='utf-8') as f:
            doc = yaml.safe_load(f) or {}
    except OSError as e:
        raise ConfigError(f'cannot read config file {path}: {e.strerror}') from e
    except yaml.YAMLError as e:
        raise ConfigError(f'config file {path} is not valid YAML: {e}') from e
    for key in (node_name, '/' + node_name, '/**'):
        section = doc.get(key) if isinstance(doc, dict) else None
        if isinstance(section, dict) and isinstance(section.get('ros__parameters'), dict):
            return dict(section['ros__parameters'])
    raise ConfigError(f'config file {path} has no "{node_name}: ros__parameters:" section; '
                      f'see config/coreg.yaml')

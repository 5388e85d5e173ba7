"""ROS parameter YAML (``config/coreg.yaml``): the node and ``coreg --config`` read the same."""

from __future__ import annotations

import sys

from coreg_ros.core.errors import ConfigError

#: Warnings already printed (a file is read more than once per command).
_WARNED: set = set()


def yaml_loader():
    """Return a safe YAML loader that also reads ``1e-3`` as a number, as the ROS parser does."""
    import re

    import yaml

    class Loader(yaml.SafeLoader):
        pass

    Loader.add_implicit_resolver(
        'tag:yaml.org,2002:float',
        re.compile(r'^[-+]?(?:[0-9]+(?:\.[0-9]*)?|\.[0-9]+)[eE][-+]?[0-9]+$'),
        list('-+0123456789.'))
    return Loader


def _warn_once(line: str) -> None:
    if line not in _WARNED:
        _WARNED.add(line)
        print(f'coreg: warning: {line}', file=sys.stderr)


def load_parameters(path, node_name: str = 'coreg_node', warn=_warn_once,
                    warn_section=None) -> dict:
    """
    Read and check the ``ros__parameters`` of ``node_name`` from a ROS parameter YAML file.

    The sections ``/**`` (every node), ``coreg_node`` and ``/coreg_node`` are merged in that
    order, as ROS does. The values are checked by
    ``coreg_ros.core.config_schema.check_parameters``, the check the node applies to the same
    file, so the command line and the node accept and refuse the same files.

    Parameters
    ----------
    path : str or path-like
        The parameter file.
    node_name : str
        Node whose section is read.
    warn : callable
        Gets one line per unknown key (with the nearest valid name); by default printed to
        stderr once.
    warn_section : callable, optional
        Gets the line saying that the file is empty or has no section of the node (default:
        ``warn``).

    Returns
    -------
    values : dict
        The known keys, converted to their types (node-only keys included); pass it to
        ``settings.settings_from_mapping``.

    Raises
    ------
    ConfigError
        If the file is unreadable, not YAML (or uses anchors, which ROS refuses), or a value
        has the wrong type or lies outside its range (one line naming the key, the expected
        type and an example). A file without a section of the node is warned about and sets
        nothing, as ROS treats it.

    """
    from coreg_ros.core.config_schema import check_parameters
    import yaml

    try:
        with open(path, encoding='utf-8') as f:
            text = f.read()
        for event in yaml.parse(text, Loader=yaml_loader()):  # noqa: S506 - a SafeLoader
            if isinstance(event, yaml.AliasEvent) or getattr(event, 'anchor', None):
                line = event.start_mark.line + 1
                raise ConfigError(f'config file {path} uses a YAML anchor or alias (& or *) at '
                                  f'line {line}, which ROS parameter files do not support; '
                                  f'write the values out')
        doc = yaml.load(text, Loader=yaml_loader()) or {}  # noqa: S506 - a SafeLoader
    except OSError as e:
        raise ConfigError(f'cannot read config file {path}: {e.strerror}') from e
    except yaml.YAMLError as e:
        where = getattr(e, 'problem_mark', None)
        at = f' at line {where.line + 1}, column {where.column + 1}' if where else ''
        problem = getattr(e, 'problem', None) or str(e).splitlines()[0]
        raise ConfigError(f'config file {path} is not valid YAML{at}: {problem}; compare with '
                          f'config/coreg.yaml') from e
    except ConfigError:
        raise
    except (ValueError, TypeError) as e:  # e.g. an impossible date or number literal
        raise ConfigError(f'config file {path} is not valid YAML: {e}; compare with '
                          f'config/coreg.yaml') from e
    values, found = {}, False
    for key in dict.fromkeys(('/**', node_name.lstrip('/'), '/' + node_name.lstrip('/'))):
        section = doc.get(key) if isinstance(doc, dict) else None
        if section is None:
            continue
        params = section.get('ros__parameters') if isinstance(section, dict) else None
        if not isinstance(params, dict):
            raise ConfigError(f'config file {path}: section {key!r} has no '
                              f'"ros__parameters:" mapping; see config/coreg.yaml')
        values.update(params)
        found = True
    if not found:
        # as ROS does for the node: a file for other nodes sets nothing here (said, not fatal)
        sections = ', '.join(map(str, doc)) if isinstance(doc, dict) else ''
        (warn_section or warn)(
            f'config file {path} is empty: the defaults apply; see config/coreg.yaml' if not doc
            else f'config file {path} has no "{node_name}: ros__parameters:" section (it has '
                 f'{sections}): nothing in it applies to {node_name}, the defaults do; name the '
                 f'section after the node (see config/coreg.yaml)')
        return {}
    checked, warnings = check_parameters(values, where=f'{path}: ')
    for line in warnings:
        warn(line)
    return checked

"""
A calibration as other tools read it: the document of ``coreg export`` and what it is read from.

``load_export`` reads a ``coreg calibrate --json`` result, a node's ``result_*.yaml`` or a
document this module wrote (YAML or JSON) and returns the export document, one layout for all::

    {"format": "coreg_ros calibration 1",
     "date": ISO time of the calibration (node: saved_at; --json: the file's modification time),
     "source": the file it came from,
     "frames": {"base_a", "base_b", "tool", "marker"},
     "base_to_base": {"parent", "child", "position", "orientation", "covariance"},
     "tool_to_marker": {same},
     "markers", "cov_joint", "cov_determined", "unobservable" (as in the result),
     "fit": {"success", "status", "message", "method", "model", "n_pairs", "chi2", "dof",
             "p_value", "iterations", "fit_consistent", "verdict", "rejected_pairs" (count,
             share), and "prior_check", "direction_check", "rescaled_covariance" when present},
     "time_offset", "clock_drift" (when estimated),
     "settings": the calibration's configuration, "node": the node's name (node results)}

``base_to_base`` and ``tool_to_marker`` keep the result's layout (position m, orientation
``{w, x, y, z}``, covariance 36 numbers in the ROS layout), so ``--prior`` and the node's
``prior_file`` read the document back (``files.results.prior_from_dict``); ``parent`` and
``child`` are tf2's frame ids: T0 is ``base_b`` -> ``base_a``, T1 ``tool`` -> ``marker``.
The text formats (tf2 static publishers, launch file, URDF) are in ``files.tf_snippets``.
"""

from __future__ import annotations

from collections.abc import Mapping
import datetime
import math
import os
from pathlib import Path
from typing import Any, Optional

from coreg_ros.core.config_schema import DEFAULTS
from coreg_ros.core.errors import InputError

FORMAT = 'coreg_ros calibration 1'
FRAME_KEYS = ('base_a', 'base_b', 'tool', 'marker')
#: The transforms: key, tf2 parent and child (keys of ``frames``), what it is.
TRANSFORMS = (('base_to_base', 'base_b', 'base_a', "T0: pose of A's base in B's base"),
              ('tool_to_marker', 'tool', 'marker', "T1: pose of B's marker in A's tool"))
#: Keys of a result that describe the fit (``fit`` of the document).
FIT_KEYS = ('success', 'status', 'message', 'method', 'model', 'n_pairs', 'chi2', 'dof',
            'p_value', 'iterations', 'fit_consistent', 'verdict', 'prior_check',
            'direction_check', 'rescaled_covariance')
#: Keys of a result copied as they are.
KEPT_KEYS = ('markers', 'cov_joint', 'cov_determined', 'unobservable')
#: What a result file must look like, for the error that says it is not one.
EXPECTED = "give a `coreg calibrate --json` result or a node's result_*.yaml"


def default_frames() -> dict:
    """Return the node's default frame ids (``frame_*`` parameters) by ``FRAME_KEYS``."""
    return {k: DEFAULTS[f'frame_{k}'] for k in FRAME_KEYS}


def frame_problem(frames: Mapping[str, str], spell=lambda key: f'frame_{key}') -> Optional[str]:
    """
    Return why tf2 would refuse these frame ids, or None.

    tf2 refuses an empty frame id, one that starts with '/' and a transform of a frame to
    itself (T0: ``base_b`` -> ``base_a``; T1: ``tool`` -> ``marker``).

    Parameters
    ----------
    frames : mapping
        ``{"base_a", "base_b", "tool", "marker"}``.
    spell : callable
        The name of a frame's setting in the message: ``frame_base_a`` (the node's
        parameters, the default) or ``--frame-base-a`` (``coreg export``).

    """
    for _, parent, child, what in TRANSFORMS:
        for key in (parent, child):
            value = str(frames[key])
            if not value.strip() or value.startswith('/'):
                return (f'{spell(key)} {value!r} is no tf2 frame id (tf2 refuses an empty one '
                        f'and a leading /); give one such as {DEFAULTS["frame_" + key]}')
        if frames[parent] == frames[child]:
            return (f'{what.split(":")[0]} would be a transform of {frames[parent]!r} to '
                    f'itself; give {spell(parent)} and {spell(child)} distinct frame ids')
    return None


def held_directions(doc: Mapping[str, Any]) -> list[str]:
    """
    Return the directions the fit held (a restricted rig's motion), each in words.

    The direction's description and where it is held, e.g. "T1's position along [..] (A's
    tool frame) ...; held at tool_to_marker position z = 0.0425 m (the closed-form start)".
    """
    out = []
    for u in doc.get('unobservable') or []:
        if not isinstance(u, Mapping) or u.get('by') != 'held':
            continue
        text, at = str(u.get('description', '?')), u.get('held_at')
        if isinstance(at, Mapping) and isinstance(at.get('value'), (int, float)):
            text += (f'; held at {at.get("component", "?")} = {at["value"]:.6g} '
                     f'{at.get("unit", "")} ({at.get("from", "?")})')
        out.append(text)
    return out


def _numbers(value, n: int, what: str, where: str) -> list:
    try:
        out = [float(v) for v in value]
    except (TypeError, ValueError):
        out = []
    if len(out) != n or not all(math.isfinite(v) for v in out):
        raise InputError(f'{where}: {what} must be {n} finite numbers, got {value!r}; '
                         f'{EXPECTED}')
    return out


def _pose(entry, key: str, parent: str, child: str, where: str) -> dict:
    """Check one transform of a result; return it in the document's layout."""
    if not isinstance(entry, Mapping):
        raise InputError(f'{where} has no {key}; {EXPECTED}')
    position = _numbers(entry.get('position'), 3, f'{key} position', where)
    o = entry.get('orientation')
    if not isinstance(o, Mapping):
        raise InputError(f'{where}: {key} orientation must be {{w, x, y, z}}; {EXPECTED}')
    w, x, y, z = _numbers([o.get(k) for k in 'wxyz'], 4, f'{key} orientation', where)
    norm = math.sqrt(w * w + x * x + y * y + z * z)
    if abs(norm - 1.0) > 1e-6:
        raise InputError(f'{where}: {key} orientation is no unit quaternion (norm {norm:.9g}); '
                         f'it was edited or is not a result: recalibrate')
    cov = entry.get('covariance')
    if cov is not None:
        cov = _numbers(cov, 36, f'{key} covariance', where)
    return {'parent': parent, 'child': child, 'position': position,
            'orientation': {'w': w, 'x': x, 'y': y, 'z': z}, 'covariance': cov}


def _file_date(path: Path) -> str:
    stamp = datetime.datetime.fromtimestamp(path.stat().st_mtime).astimezone()
    return stamp.isoformat(timespec='seconds')


def export_document(doc: Mapping[str, Any], source: str, date: str,
                    frames: Optional[Mapping[str, str]] = None) -> dict:
    """
    Build the export document of a parsed result file (layout in the module docstring).

    Parameters
    ----------
    doc : mapping
        A ``coreg calibrate --json`` result, a node's stored result (``{"result", "frames",
        "settings", "saved_at", ...}``) or an export document.
    source : str
        Where it came from (kept in the document; an export document keeps its own).
    date : str
        The date to give when the file has none (its modification time).
    frames : mapping, optional
        Frame ids replacing the file's (``FRAME_KEYS``; None: the file's, else the node's
        defaults).

    Raises
    ------
    InputError
        One line: the file is not a result, or a transform in it is malformed.

    """
    if not isinstance(doc, Mapping):
        raise InputError(f'{source} is not a calibration result (no mapping of keys); '
                         f'{EXPECTED}')
    if doc.get('format') == FORMAT:  # written by this module: taken as it is
        result = {**doc.get('fit', {}), **doc}
        meta = {'date': doc.get('date', date), 'source': doc.get('source', source),
                'settings': doc.get('settings'), 'node': doc.get('node')}
        stored_frames = doc.get('frames')
    elif isinstance(doc.get('result'), Mapping):  # a node's result_*.yaml
        result = doc['result']
        meta = {'date': str(doc.get('saved_at', date)), 'source': source,
                'settings': doc.get('settings'), 'node': doc.get('node')}
        stored_frames = doc.get('frames')
    else:  # coreg calibrate --json
        result = doc
        meta = {'date': date, 'source': source, 'settings': doc.get('settings'), 'node': None}
        stored_frames = None
    if 'base_to_base' not in result or 'success' not in result:
        what = ('a partial prior, not a result' if 'base_to_base' in result
                or 'tool_to_marker' in result else 'not a calibration result')
        raise InputError(f'{source} is {what} (no base_to_base with a fit); {EXPECTED}')
    chosen = default_frames()
    if isinstance(stored_frames, Mapping):
        chosen.update({k: str(stored_frames[k]) for k in FRAME_KEYS if k in stored_frames})
    chosen.update({k: str(v) for k, v in (frames or {}).items() if v is not None})
    problem = frame_problem(chosen, spell=lambda key: '--frame-' + key.replace('_', '-'))
    if problem is not None:
        raise InputError(problem)
    out = {'format': FORMAT, 'date': meta['date'], 'source': meta['source'], 'frames': chosen}
    for key, parent, child, _ in TRANSFORMS:
        out[key] = _pose(result.get(key), key, chosen[parent], chosen[child], source)
    out.update({k: result[k] for k in KEPT_KEYS if result.get(k) is not None})
    fit = {k: result[k] for k in FIT_KEYS if k in result}
    rejected = result.get('rejected_pairs')
    if isinstance(rejected, Mapping):  # the count and share; the stamps stay in the result
        fit['rejected_pairs'] = {k: rejected[k] for k in ('count', 'share') if k in rejected}
    out['fit'] = fit
    out.update({k: result[k] for k in ('time_offset', 'clock_drift')
                if result.get(k) is not None})
    out.update({k: meta[k] for k in ('settings', 'node') if meta[k] is not None})
    return out


def load_export(path, frames: Optional[Mapping[str, str]] = None) -> dict:
    """
    Read a result file (JSON or YAML) into the export document (``export_document``).

    Raises
    ------
    InputError
        One line: the file is missing, unreadable, not JSON/YAML, or not a result.

    """
    import yaml

    path = Path(os.path.expanduser(str(path)))
    try:
        with open(path, encoding='utf-8') as f:
            doc = yaml.safe_load(f)
    except IsADirectoryError:
        raise InputError(f'{path} is a directory; {EXPECTED}') from None
    except OSError as e:
        raise InputError(f'cannot read {path}: {e.strerror}; {EXPECTED}') from e
    except (yaml.YAMLError, UnicodeDecodeError) as e:
        raise InputError(f'{path} is neither JSON nor YAML ({type(e).__name__}); '
                         f'{EXPECTED}') from e
    return export_document(doc, str(path), _file_date(path), frames)

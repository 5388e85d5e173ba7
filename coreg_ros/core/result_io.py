"""
Plain-dict form of calibration results (the ``--json`` output and the node's stored YAML).

Layout (relied upon by checks)::

    {"success", "status", "message", "method", "model", "n_pairs", "chi2", "dof", "p_value",
     "iterations",
     "base_to_base": {"position": [x, y, z], "orientation": {"w", "x", "y", "z"},
                      "covariance": [36 numbers, ROS row-major layout]},
     "tool_to_marker": {same},
     "markers": [[x, y, z], ...]}

``base_to_base`` is T_bbase_abase (A's base frame in B's base frame); ``tool_to_marker`` is
T_atool_bmarker (B's marker frame in A's tool frame).
"""

from __future__ import annotations

from collections.abc import Mapping
import math
from typing import Any

import numpy as np

from coreg_ros.core.errors import InputError
from coreg_ros.core.types import CalibrationResult, UncertainPose


def pose_to_dict(pose: UncertainPose) -> dict:
    """JSON-friendly dict of an uncertain pose (covariance as 36 numbers or None)."""
    w, x, y, z = (float(v) for v in pose.quat_wxyz)
    cov = None if pose.covariance is None else [float(v) for v in np.ravel(pose.covariance)]
    return {'position': [float(v) for v in pose.position],
            'orientation': {'w': w, 'x': x, 'y': y, 'z': z},
            'covariance': cov}


def pose_from_dict(d: Mapping[str, Any]) -> UncertainPose:
    """Inverse of ``pose_to_dict``; raises InputError naming the missing key."""
    try:
        o = d['orientation']
        quat = np.array([o['w'], o['x'], o['y'], o['z']], dtype=float)
        position = np.array(d['position'], dtype=float).reshape(3)
        cov = d.get('covariance')
        cov = None if cov is None else np.array(cov, dtype=float).reshape(6, 6)
    except (KeyError, TypeError, ValueError) as e:
        raise InputError(
            f'stored pose is malformed ({e!r}); delete the file and recalibrate') from e
    return UncertainPose(position, quat, cov)


def result_to_dict(result: CalibrationResult) -> dict:
    """JSON-friendly dict of a calibration result (layout in the module docstring)."""
    def num(v):
        v = float(v)
        return v if math.isfinite(v) else None

    return {
        'success': bool(result.success),
        'status': int(result.status),
        'message': result.message,
        'method': result.method,
        'model': result.model,
        'n_pairs': int(result.n_pairs),
        'chi2': num(result.chi2),
        'dof': int(result.dof),
        'p_value': num(result.p_value),
        'iterations': int(result.iterations),
        'base_to_base': pose_to_dict(result.base_to_base),
        'tool_to_marker': pose_to_dict(result.tool_to_marker),
        'markers': [[float(v) for v in m] for m in np.atleast_2d(result.markers)],
    }

"""
Plain-dict form of calibration results (the ``--json`` output and the node's stored YAML).

Layout (relied upon by checks)::

    {"success", "status", "message", "method", "model", "n_pairs", "chi2", "dof", "p_value",
     "iterations", "fit_consistent", "verdict",
     "time_offset": {"value_s", "sigma_s", "estimated", "message"},
     "clock_drift": {"value_ppm", "sigma_ppm", "reference_ns"} (only when estimated),
     "rejected_pairs": {"count", "share", "stamps_ns"},
     "rescaled_covariance": {"factor", "base_to_base", "tool_to_marker"} (inconsistent fits:
                            the covariances multiplied by chi2/dof),
     "prior_check": {"chi2", "dof", "p_value", "consistent"} (with a prior),
     "cov_joint": [144 numbers] (12×12 of (T0, T1), ROS layout, when estimated),
     "cov_determined": [144 numbers] (with directions held: the determined part of it),
     "base_to_base": {"position": [x, y, z], "orientation": {"w", "x", "y", "z"},
                      "covariance": [36 numbers, ROS row-major layout]},
     "tool_to_marker": {same},
     "markers": [[x, y, z], ...],
     "unobservable": [{"direction": [12 numbers], "description", "held_at", "by", "determine"}]
                     (the directions the motion does not determine: empty for a free rig),
     "data_sketch": {"samples", "hashes"} (added by coreg calibrate and the node: which
                    samples it was calibrated on, ``core.provenance``),
     "noise": {"device_a": {"position_sigma_m", "rotation_sigma_rad", "estimated",
                            "sigma_of_estimate", "stated", ...}, "device_b": {...},
               "statements", "verdict"} (noise: auto; ``noise_verdict.estimate_dict``)}

``base_to_base`` is T_bbase_abase (A's base frame in B's base frame); ``tool_to_marker`` is
T_atool_bmarker (B's marker frame in A's tool frame).
"""

from __future__ import annotations

from collections.abc import Mapping
import math
from typing import Any

from coreg_ros.core.errors import InputError
from coreg_ros.core.estimator.priors import Prior
from coreg_ros.core.types import CalibrationResult, UncertainPose
import numpy as np


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
            f'pose is malformed ({e!r}): a pose needs position [x, y, z], orientation {{w, x, '
            f'y, z}} and covariance (36 numbers, 6×6 ROS layout) or none; a stored result '
            f'that is malformed: delete the file and recalibrate') from e
    return UncertainPose(position, quat, cov)


def result_to_dict(result: CalibrationResult) -> dict:
    """JSON-friendly dict of a calibration result (layout in the module docstring)."""
    def num(v):
        v = float(v)
        return v if math.isfinite(v) else None

    out = {
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
        'fit_consistent': result.fit_consistent,
        'verdict': result.verdict,
    }
    if result.cov_joint is not None:
        out['cov_joint'] = [float(v) for v in np.ravel(result.cov_joint)]
    if result.cov_determined is not None:
        out['cov_determined'] = [float(v) for v in np.ravel(result.cov_determined)]
    if result.time_offset is not None:
        out['time_offset'] = result.time_offset.as_dict()
        if result.time_offset.drift_dict() is not None:
            out['clock_drift'] = result.time_offset.drift_dict()
    stamps = [] if result.rejected_stamps is None else [int(t) for t in result.rejected_stamps]
    out['rejected_pairs'] = {'count': len(stamps),
                             'share': len(stamps) / result.n_pairs if result.n_pairs else 0.0,
                             'stamps_ns': stamps}
    if result.fit_consistent is False and result.dof > 0:
        factor = max(1.0, result.reduced_chi2)
        out['rescaled_covariance'] = {
            'factor': factor,
            **{name: None if pose.covariance is None else
               [float(v) * factor for v in np.ravel(pose.covariance)]
               for name, pose in (('base_to_base', result.base_to_base),
                                  ('tool_to_marker', result.tool_to_marker))}}
    if result.prior_check is not None:
        out['prior_check'] = dict(result.prior_check)
    out['unobservable'] = [u.as_dict() for u in result.unobservable]
    if result.noise is not None:
        from coreg_ros.core.calibration.noise_verdict import estimate_dict
        out['noise'] = estimate_dict(result.noise)
    return out


def prior_from_dict(doc: Mapping[str, Any]) -> Prior:
    """
    Build a prior (Ikits B.3) from a previous result or a partial prior written by hand.

    Accepted layouts: ``result_to_dict`` output (``coreg calibrate --json``), the node's
    ``result.yaml`` (the same under ``result``), or a mapping with ``base_to_base`` and/or
    ``tool_to_marker``, each ``{"position", "orientation", and "covariance" (36 numbers) or
    "sigma" (6 numbers: x y z m, rotation about x y z rad)}``. A ``sigma`` entry of null (or
    .inf) leaves that axis free: e.g. T1's position from CAD with its orientation unknown.
    """
    if isinstance(doc, Mapping) and isinstance(doc.get('result'), Mapping):
        doc = doc['result']
    if not isinstance(doc, Mapping):
        raise InputError('the prior file holds no mapping; give a coreg calibrate --json '
                         'result, a node result.yaml, or base_to_base/tool_to_marker entries')
    poses = {}
    for key in ('base_to_base', 'tool_to_marker'):
        entry = doc.get(key)
        if entry is None:
            continue
        if not isinstance(entry, Mapping):
            raise InputError(f'prior {key} must be a mapping with position, orientation and '
                             f'covariance or sigma')
        entry = dict(entry)
        entry.setdefault('orientation', {'w': 1.0, 'x': 0.0, 'y': 0.0, 'z': 0.0})
        sigma = entry.pop('sigma', None)
        pose = pose_from_dict(entry)
        if sigma is not None:
            try:
                sd = np.array([np.inf if v is None else float(v) for v in sigma], dtype=float)
            except (TypeError, ValueError) as e:
                raise InputError(f'prior {key} sigma must be 6 numbers (or null for a free '
                                 f'axis), got {sigma!r}') from e
            if sd.shape != (6,) or not (sd > 0).all():
                raise InputError(f'prior {key} sigma must be 6 positive numbers (x y z m, '
                                 f'rotation rad), or null for a free axis; got {sigma!r}')
            pose = UncertainPose(pose.position, pose.quat_wxyz, np.diag(sd ** 2))
        elif pose.covariance is None:
            raise InputError(f'prior {key} has no covariance; give "covariance" (36 numbers) '
                             f'or "sigma" (6 numbers)')
        else:
            cov = np.array(pose.covariance, dtype=float)
            unknown = np.diag(cov) < 0  # the "not estimated" mark of published results
            cov[unknown, :] = 0.0
            cov[:, unknown] = 0.0
            cov[unknown, unknown] = np.inf
            pose = UncertainPose(pose.position, pose.quat_wxyz, cov)
        poses[key] = pose
    if not poses:
        raise InputError('the prior file has neither base_to_base nor tool_to_marker; give a '
                         'previous result or a partial prior')
    joint = doc.get('cov_joint')
    if joint is not None and len(poses) == 2:
        try:
            joint = np.array(joint, dtype=float).reshape(12, 12)
        except (TypeError, ValueError) as e:
            raise InputError('prior cov_joint must be 144 numbers (12×12 of T0, T1)') from e
        unknown = np.diag(joint) < 0  # the "not estimated" mark, e.g. q1 of position-only
        joint[unknown, :] = 0.0
        joint[:, unknown] = 0.0
        joint[unknown, unknown] = np.inf
    else:
        joint = None
    sketch = doc.get('data_sketch')
    return Prior(poses.get('base_to_base'), poses.get('tool_to_marker'), joint,
                 data_sketch=dict(sketch) if isinstance(sketch, Mapping) else None)


def load_prior(path) -> Prior:
    """Read a prior from a JSON or YAML file (``prior_from_dict``); one-line errors."""
    import yaml

    try:
        with open(path, encoding='utf-8') as f:
            doc = yaml.safe_load(f)
    except OSError as e:
        raise InputError(f'cannot read the prior file {path}: {e.strerror}') from e
    except yaml.YAMLError as e:
        raise InputError(f'the prior file {path} is neither JSON nor YAML ({e}); give a '
                         f'coreg calibrate --json result or a node result.yaml') from e
    return prior_from_dict(doc)

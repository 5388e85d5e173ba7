"""
A rig's result as JSON: every device with its transforms, clock and χ² share; the joint covariance.

Layout (``coreg calibrate --json`` of a rig)::

    {"success", "status", "message", "method", "chi2", "dof", "p_value", "fit_consistent",
     "verdict", "iterations", "shared_instants": [[names]],
     "devices": [{"name", "topic", "topics", "model", "base", "chi2_share", "sigma_ratio",
                  ...every key of a two-device result (``results.result_to_dict``):
                  "base_to_base", "tool_to_marker", "time_offset", "chi2", "dof", ...,
                  "pairing": {...}, "alone": {the device calibrated with A alone}}],
     "cov_joint": {"labels": [...], "values": [13K × 13K numbers, row-major]},
     "relative_bases": [{"from", "to", "position", "orientation", "covariance"}],
     "loops": {"checks": [...], "off": [names], "message"}}

``cov_joint`` is over every device's base_to_base and tool_to_marker (ROS layout, 6 each) and
its time_offset (s), in that order, device by device, then the offsets; -1 on the diagonal
of a component not estimated.
"""

from __future__ import annotations

import math

from coreg_ros.core.rig.loops import relative_base
from coreg_ros.files.results import pose_to_dict, result_to_dict
import numpy as np

_AXES = ('x', 'y', 'z', 'rx', 'ry', 'rz')


def joint_labels(names) -> list:
    """Labels of ``cov_joint``'s rows: ``<name>.base_to_base.x`` ... ``<name>.time_offset``."""
    rows = [f'{n}.{pose}.{a}' for n in names for pose in ('base_to_base', 'tool_to_marker')
            for a in _AXES]
    return rows + [f'{n}.time_offset' for n in names]


def _pairing(report) -> dict:
    return {'n_a': report.n_a, 'n_b': report.n_b, 'n_paired': report.n_paired,
            'unpaired': dict(report.unpaired)}


def rig_to_dict(rig) -> dict:
    """JSON-friendly dict of a ``RigResult`` (layout in the module docstring)."""
    def num(v):
        v = float(v)
        return v if math.isfinite(v) else None

    devices = []
    for d in rig.devices:
        entry = {'name': d.name, 'topic': d.topics[0] if d.topics else None,
                 'topics': list(d.topics), 'base': d.base, 'chi2_share': num(d.chi2_share),
                 'sigma_ratio': [num(v) for v in d.sigma_ratio]}
        entry.update(result_to_dict(d.result))
        entry['pairing'] = _pairing(d.pairing)
        entry['alone'] = result_to_dict(d.alone)
        devices.append(entry)
    out = {'success': bool(rig.success), 'status': int(rig.status), 'message': rig.message,
           'method': rig.method, 'chi2': num(rig.chi2), 'dof': int(rig.dof),
           'p_value': num(rig.p_value), 'fit_consistent': bool(rig.fit_consistent),
           'verdict': rig.verdict, 'iterations': int(rig.iterations),
           'shared_instants': [list(g) for g in rig.shared_instants], 'devices': devices}
    if rig.cov_joint is not None:
        out['cov_joint'] = {'labels': joint_labels(rig.names),
                            'values': [float(v) for v in np.ravel(rig.cov_joint)]}
        out['relative_bases'] = [
            {'from': rig.names[i], 'to': rig.names[j], **pose_to_dict(relative_base(rig, i, j))}
            for i in range(len(rig.devices)) for j in range(len(rig.devices))
            if i < j and rig.devices[i].base != rig.devices[j].base]
    if rig.loops is not None:
        out['loops'] = rig.loops.as_dict()
    return out

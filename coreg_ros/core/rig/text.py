"""The text ``coreg calibrate`` prints for a rig: the joint fit, then every device in it."""

from __future__ import annotations

from coreg_ros.core.result_text import fit_verdict, format_pose, format_time_offset
import numpy as np


def _ratio(r: np.ndarray) -> str:
    """Format the σ ratios of T0 and T1 (rig over alone) as two ranges."""
    parts = []
    for name, block in (('T0', r[0:6]), ('T1', r[6:12])):
        known = block[np.isfinite(block)]
        if known.size:
            parts.append(f'{name} {known.min():.2f}-{known.max():.2f}')
    return ', '.join(parts) or 'n/a'


def format_rig(rig) -> str:
    """Render what a person reads after calibrating a rig (``RigResult``)."""
    state = 'success' if rig.success else (
        'INCONSISTENT (converged, but the data contradict the fit)'
        if rig.status > 0 else 'FAILED')
    out = [f'rig of device A and {len(rig.devices)} devices, method {rig.method.upper()}: '
           f'{state}: {rig.message}',
           f'joint fit: chi2 = {rig.chi2:.1f}, dof = {rig.dof}, chi2/dof = '
           f'{rig.chi2 / max(rig.dof, 1):.3f}, p = {rig.p_value:.3g}: '
           f'{fit_verdict(rig.p_value)}']
    if rig.verdict:
        out.append(f'verdict: {rig.verdict}')
    for group in rig.shared_instants:
        out.append(f'shared instants: {", ".join(group)} measure the body at the same '
                   f'instants (one input pose each)')
    for d in rig.devices:
        r = d.result
        topics = f' ({", ".join(d.topics)})' if d.topics else ''
        out.append('')
        out.append(f'device {d.name}{topics}: model {r.model}, base {d.base}; '
                   f'{d.pairing.summary()}')
        out.append(f'  chi2 share {d.chi2_share:.1%} (chi2/dof {r.reduced_chi2:.3f}); σ in the '
                   f'rig / σ alone: {_ratio(d.sigma_ratio)}')
        if r.time_offset is not None:
            out.append('  ' + format_time_offset(r.time_offset))
        out.append(format_pose('base_to_base', f"pose of device A's base frame in {d.name}'s "
                               'base frame', r.base_to_base))
        out.append(format_pose('tool_to_marker', f"pose of {d.name}'s marker in device A's "
                               'tool frame', r.tool_to_marker, r.model == 'full_pose'))
    out.append('σ are 1-sigma marginals of the joint posterior (Ikits B.4.2) over every '
               "device's transforms and clock offset; layout geometry_msgs/PoseWithCovariance.")
    return '\n'.join(out)

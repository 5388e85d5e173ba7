"""The text ``coreg calibrate`` prints for a rig: the joint fit, then every device in it."""

from __future__ import annotations

from coreg_ros.core.result_text import fit_verdict, format_pose, format_time_offset
from coreg_ros.core.rig.loops import relative_base
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
        # a device named by its topic (--topic-b T1 T2) is not named twice
        topics = (f' ({", ".join(d.topics)})' if d.topics and tuple(d.topics) != (d.name,)
                  else '')
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
    names = rig.names
    for i in range(len(names)):
        for j in range(i + 1, len(names)):
            if rig.cov_joint is not None and rig.devices[i].base != rig.devices[j].base:
                out.append('')
                out.append(format_pose(f'{names[i]} in {names[j]}', f"pose of {names[i]}'s base "
                                       f"frame in {names[j]}'s base frame, from the rig",
                                       relative_base(rig, i, j)))
    if rig.loops is not None:
        out.append('')
        out.append(f'loops: {rig.loops.message}')
        for c in rig.loops.checks:
            out.append('  ' + _check_line(c))
    out.append('σ are 1-sigma marginals of the joint posterior (Ikits B.4.2) over every '
               "device's transforms and clock offset; layout geometry_msgs/PoseWithCovariance.")
    return '\n'.join(out)


def _check_line(c) -> str:
    """One line of the loop report: what was compared, and how far apart."""
    what = (f'{c.devices[0]} with A alone against the rig' if c.what == 'alone' else
            f'{c.devices[1]} calibrated against {c.devices[0]} directly, against the rig')
    if not np.isfinite(c.chi2):
        return f'{what}: not compared ({c.note})'
    verdict = 'agree' if c.consistent else 'DISAGREE'
    return (f'{what}: chi2 {c.chi2:.1f} for {c.dof} dof, p = {c.p_value:.2g}: {verdict} '
            f'(up to {c.error_mm_deg[0]:.3g} mm, {c.error_mm_deg[1]:.3g}°)')

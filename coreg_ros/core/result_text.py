"""
Human-readable rendering of a calibration result (`coreg calibrate`, `result.summary()`).

The records it renders (``types.CalibrationResult``, ``PairingReport``, ``TimeOffset``,
``UncertainPose``) are read by their attributes only: ``CalibrationResult.summary()`` imports
this module, so this module does not import ``types`` back (no import circle).
"""

from __future__ import annotations

from coreg_ros.core import quaternion as quat
import numpy as np


def fit_verdict(p_value: float) -> str:
    """One phrase on the chi-square p-value (Ikits B.4.1)."""
    if not np.isfinite(p_value):
        return 'no degrees of freedom left'
    if p_value < 1e-3:
        return ('the data do NOT fit the model with the stated noise: check the noise settings, '
                'the time offset and the stream directions (coreg diagnose tells why)')
    if p_value > 0.999:
        return 'residuals are smaller than the stated noise: the noise is overstated'
    return 'consistent with the stated noise'


def format_time_offset(timing) -> str:
    """One line on the clock offset (and drift) the pairs were made with."""
    if not timing.estimated:
        return f'time offset: {timing.value_s * 1e3:.3f} ms ({timing.message or "given"})'
    line = (f'time offset: {timing.value_s * 1e3:.3f} ± {timing.sigma_s * 1e3:.3f} ms '
            f"(B's clock minus A's; estimated jointly with the transforms)")
    if timing.drift_ppm is not None:
        line += f', clock drift {timing.drift_ppm:.2f} ± {timing.drift_sigma_ppm:.2f} ppm'
    return line


def format_pose(name: str, meaning: str, pose, rotation_known: bool = True,
                cov=None) -> str:
    """
    Pose with 1σ uncertainties: position in m (σ in mm), orientation (σ in degrees).

    ``cov`` (6×6), when given, is the covariance the σ are taken from instead of the pose's.
    """
    lines = [f'{name}  ({meaning})']
    p = pose.position
    cov = pose.covariance if cov is None else cov
    sd = None if cov is None else np.sqrt(np.clip(np.diag(cov), 0.0, None))
    pos = f'  position     [{p[0]: .6f}, {p[1]: .6f}, {p[2]: .6f}] m'
    if sd is not None:
        pos += f'   σ [{sd[0] * 1e3:.3f}, {sd[1] * 1e3:.3f}, {sd[2] * 1e3:.3f}] mm'
    lines.append(pos)
    if rotation_known:
        w, x, y, z = pose.quat_wxyz
        rv = np.degrees(quat.log(pose.quat_wxyz))
        ori = f'  orientation  w x y z = [{w:.6f}, {x:.6f}, {y:.6f}, {z:.6f}]'
        if sd is not None:
            ori += f'   σ [{np.degrees(sd[3]):.4f}, {np.degrees(sd[4]):.4f}, ' \
                   f'{np.degrees(sd[5]):.4f}] ° about x y z'
        lines.append(ori)
        lines.append(f'  rotation vector [{rv[0]:.3f}, {rv[1]:.3f}, {rv[2]:.3f}] °')
    else:
        lines.append('  orientation  not estimated by this model (covariance marked -1)')
    return '\n'.join(lines)


def format_unobservable(u) -> str:
    """One line on a direction the motion does not determine (``types.Unobservable``)."""
    at = u.held_at
    value = (f'{at["value"]:.6f} m' if at['unit'] == 'm' else
             f'{np.degrees(at["value"]):.4f}° (rotation vector)')
    if u.by == 'held':
        return (f'unobservable: {u.description}: held at {at["component"]} = {value} '
                f'({at["from"]}), variance marked unknown; to determine it: {u.determine}')
    return f'determined by the prior only: {u.description} ({at["component"]} = {value})'


def format_noise_estimate(estimate) -> list:
    """
    Return the lines of a noise estimated with the calibration (``CalibrationResult.noise``).

    Each device channel's principal σ with its standard error, or why it is held, then the
    comparison with the stated noise.
    """
    out = [f'noise: estimated with the calibration from {estimate.n_pairs} pairs '
           f'({estimate.method.upper()}); the fit above used it']
    shown = {'position': (1e3, 'mm'), 'rotation': (1e3, 'mrad')}
    for d in 'ab':
        for kind, ch in estimate.devices[d].items():
            k, unit = shown[kind]
            name = f'  {d.upper()} {kind:<8}'
            if ch.status == 'estimated':
                sig = ', '.join(f'{s * k:.3g} ± {e * k:.2g}' for s, e in zip(ch.sigma, ch.sigma_se,
                                                                             strict=True))
                what = 'full covariance' if ch.mode == 'full' else 'the stated shape scaled'
                out.append(f'{name} σ {sig} {unit} (principal; {what})')
            elif ch.status == 'held':
                sig = ', '.join(f'{s * k:.3g}' for s in ch.sigma)
                out.append(f'{name} σ {sig} {unit} held at the stated value: {ch.note}')
    for s in estimate.statements:
        if s.ratio_se > 0:
            out.append(f'  {s.text}' + ('  <- misstated' if s.misstated else ''))
    if not estimate.converged:
        out.append('  the estimation did not converge: take these as rough')
    return out


def format_result(result, report=None) -> str:
    """Render the full report a person reads after ``coreg calibrate``."""
    state = 'success' if result.success else (
        'INCONSISTENT (converged, but the data contradict the fit)'
        if result.flagged and result.fit_consistent is False else
        'REFUSED (converged, but not to be used as it stands: see the verdict)'
        if result.flagged else 'FAILED')
    out = [f'model {result.model}, method {result.method.upper()}: {state}: {result.message}']
    if report is not None:
        out.append(f'pairing: {report.summary()}')
    said = fit_verdict(result.p_value)
    if result.noise is not None:  # judged against the noise estimated with it
        said = said.replace('the stated noise', 'the estimated noise') + (
            f' (p of F(dof, {result.noise.dof}): the noise was estimated from '
            f'{result.noise.dof} of these errors, so an effect the model lacks shows as noise, '
            f'not here: coreg diagnose looks for its structure)')
    out.append(f'fit: chi2 = {result.chi2:.1f}, dof = {result.dof}, '
               f'chi2/dof = {result.reduced_chi2:.3f}, p = {result.p_value:.3g}: {said}')
    if result.verdict:
        out.append(f'verdict: {result.verdict}')
    if result.time_offset is not None:
        out.append(format_time_offset(result.time_offset))
    if result.n_rejected:
        share = result.n_rejected / max(result.n_pairs, 1)
        out.append(f'outliers: {result.n_rejected} of {result.n_pairs} pairs rejected '
                   f'({share:.2%}), far outside the stated noise')
    if result.noise is not None:
        out += format_noise_estimate(result.noise)
    if result.prior_check is not None:
        pc = result.prior_check
        out.append(f"prior: chi2 = {pc['chi2']:.2f} for {pc['dof']} dof, p = "
                   f"{pc['p_value']:.3g}: {'agrees' if pc['consistent'] else 'DISAGREES'} "
                   f'with the data')
    determined = result.cov_determined
    blocks = (None, None) if determined is None else (determined[0:6, 0:6],
                                                      determined[6:12, 6:12])
    out.append(format_pose('base_to_base', "pose of device A's base frame in device B's base "
                           'frame', result.base_to_base, cov=blocks[0]))
    out.append(format_pose('tool_to_marker', "pose of device B's marker in device A's tool "
                           'frame', result.tool_to_marker, result.model == 'full_pose',
                           cov=blocks[1]))
    if result.model == 'three_marker':
        for j, m in enumerate(result.markers):
            out.append(f'  marker {j + 1} in the tool frame [{m[0]: .6f}, {m[1]: .6f}, '
                       f'{m[2]: .6f}] m')
    out += [format_unobservable(u) for u in result.unobservable]
    out.append('σ are 1-sigma posterior standard deviations (Ikits B.4.2); the covariance '
               'layout is geometry_msgs/PoseWithCovariance (x y z, rotation about x y z).')
    if determined is not None:
        out.append('with directions held (unobservable above), the σ are those of the part the '
                   'motion determines; the published covariances are unknown along them')
    return '\n'.join(out)

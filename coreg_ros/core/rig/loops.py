"""
Loops of a rig: the pose of any device's base in another's, and whether the loops close.

``relative_base``: B_i's base in B_j's base, ``T_bj_bi = T0_j · T0_i⁻¹`` (T0_k = A's base in
B_k's base), with the covariance from the joint posterior, cross terms included (Hoff &
Vincent eqs. 6-7: the inverse, then the product with its correlated operand).

``loop_report`` checks the rig against the devices calibrated pairwise: each device with A
alone (its T0, T1 against the rig's: a device whose own fit the rig pulls beyond its σ is off),
and every two devices calibrated directly with each other (B_i as the reference, when it gives
a full pose): the loop A → B_i → B_j must close on the rig's relative pose. Where loops do not
close, the device common to them is named; with two devices a failed loop cannot say which.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

from coreg_ros.core.calibration.pipeline import calibrate_streams
from coreg_ros.core.distributions import chi2_sf
from coreg_ros.core.errors import CoregError
from coreg_ros.core.settings import Settings
from coreg_ros.core.types import CalibrationResult, UncertainPose
from coreg_ros.core.uncertainty import chain, pose_error
from coreg_ros.core.uncertainty.composition import inverse_jacobian, invert
import numpy as np

#: A loop (or a device's own fit) disagrees when its χ² has a p-value below this.
LOOP_P = 1e-3


def relative_base(rig, i: int, j: int) -> UncertainPose:
    """
    Return B_i's base in B_j's base, ``T0_j · T0_i⁻¹``, with its covariance from the rig.

    Parameters
    ----------
    rig : RigResult
        The joint calibration.
    i, j : int
        Device indices (``RigResult.index(name)``).

    Returns
    -------
    UncertainPose
        Covariance about B_j's base axes (ROS layout).

    """
    t0_i, t0_j = rig.base_to_base(i), rig.base_to_base(j)
    inv_i = invert(t0_i)
    J = inverse_jacobian(t0_i.position, t0_i.quat_wxyz)
    rows_i, rows_j = np.arange(12 * i, 12 * i + 6), np.arange(12 * j, 12 * j + 6)
    C = rig.block(np.concatenate([rows_j, rows_i]))
    # (δ_j, δ_i) to (δ_j, δ of T0_i⁻¹)
    M = np.eye(12)
    M[6:, 6:] = J
    return chain([t0_j, inv_i], M @ C @ M.T)


@dataclass(frozen=True)
class Disagreement:
    """
    One comparison of the rig with a pairwise calibration.

    Attributes
    ----------
    devices : tuple of str
        The device (its fit with A alone) or the two devices (their direct fit).
    what : str
        ``'alone'`` (T0, T1 of the device with A alone) or ``'loop'`` (B_i's base in B_j's).
    chi2 : float
        Of the difference in its covariance.
    dof : int
    p_value : float
    error_mm_deg : tuple of float
        The largest position (mm) and rotation (°) component of the difference.
    note : str
        Why a comparison could not be made (then chi2 is NaN).

    """

    devices: tuple
    what: str
    chi2: float
    dof: int
    p_value: float
    error_mm_deg: tuple = (float('nan'), float('nan'))
    note: str = ''

    @property
    def consistent(self) -> bool:
        """Whether the difference is within its covariance (NaN: not compared)."""
        return not (np.isfinite(self.p_value) and self.p_value < LOOP_P)

    def as_dict(self) -> dict:
        """JSON form."""
        def num(v):
            return float(v) if np.isfinite(v) else None
        return {'devices': list(self.devices), 'what': self.what, 'chi2': num(self.chi2),
                'dof': int(self.dof), 'p_value': num(self.p_value),
                'consistent': self.consistent,
                'max_error': {'position_mm': num(self.error_mm_deg[0]),
                              'rotation_deg': num(self.error_mm_deg[1])},
                'note': self.note}


@dataclass(frozen=True)
class LoopReport:
    """
    The rig against its pairwise calibrations.

    Attributes
    ----------
    checks : tuple of Disagreement
    off : tuple of str
        The devices named as off (empty: every loop closes).
    message : str
        One line for a person.

    """

    checks: tuple
    off: tuple
    message: str

    def as_dict(self) -> dict:
        """JSON form."""
        return {'checks': [c.as_dict() for c in self.checks], 'off': list(self.off),
                'message': self.message}


def _compare(devices: tuple, what: str, e: np.ndarray, cov: np.ndarray) -> Disagreement:
    known = np.diag(cov) > 0
    e, cov = e[known], cov[np.ix_(known, known)]
    chi2 = float(e @ np.linalg.lstsq(cov, e, rcond=None)[0])
    dof = int(np.linalg.matrix_rank(cov))
    pos = np.abs(e[:min(3, e.size)]).max() * 1e3 if e.size else float('nan')
    rot = np.degrees(np.abs(e[3:]).max()) if e.size > 3 else float('nan')
    return Disagreement(devices, what, chi2, dof, float(chi2_sf(chi2, dof)), (pos, rot))


def _alone_check(name: str, rig_result: CalibrationResult,
                 alone: CalibrationResult) -> Disagreement:
    """Compare the device's fit with A alone with its result in the rig (T0, T1)."""
    if rig_result is alone or alone.cov_joint is None or rig_result.cov_joint is None:
        return Disagreement((name,), 'alone', float('nan'), 0, float('nan'),
                            note='the rig adds nothing to this device')
    e = np.concatenate([
        pose_error(alone.base_to_base.position, alone.base_to_base.quat_wxyz,
                   rig_result.base_to_base.position, rig_result.base_to_base.quat_wxyz),
        pose_error(alone.tool_to_marker.position, alone.tool_to_marker.quat_wxyz,
                   rig_result.tool_to_marker.position, rig_result.tool_to_marker.quat_wxyz)])
    # the rig holds all of the device's own information: the difference of the two
    # estimates has the difference of their covariances (a device the rig does not inform
    # has none, and nothing to disagree in)
    known = np.diag(alone.cov_joint) > 0
    e = e[known]
    cov = (alone.cov_joint - rig_result.cov_joint)[np.ix_(known, known)]
    w, V = np.linalg.eigh(0.5 * (cov + cov.T))
    floor = 1e-3 * np.diag(alone.cov_joint)[known].max()
    keep = w > floor
    if not keep.any():
        return Disagreement((name,), 'alone', float('nan'), 0, float('nan'),
                            note='the rig adds nothing to this device')
    z = V[:, keep].T @ e
    chi2 = float(np.sum(z * z / w[keep]))
    dof = int(keep.sum())
    position = np.isin(np.flatnonzero(known), [0, 1, 2, 6, 7, 8])
    return Disagreement((name,), 'alone', chi2, dof, float(chi2_sf(chi2, dof)),
                        (np.abs(e[position]).max() * 1e3, np.degrees(np.abs(e[~position]).max())))


def loop_report(rig, direct: Optional[dict] = None) -> LoopReport:
    """
    Check the rig against its pairwise calibrations and name the device that is off.

    Parameters
    ----------
    rig : RigResult
        The joint calibration.
    direct : dict, optional
        ``{(i, j): CalibrationResult or str}``: device j calibrated directly against device i
        as the reference (its T0 is B_i's base in B_j's base), or why it could not be.

    Returns
    -------
    LoopReport

    """
    names = rig.names
    checks = [_alone_check(d.name, d.result, d.alone) for d in rig.devices]
    for (i, j), fit in sorted((direct or {}).items()):
        pair = (names[i], names[j])
        if isinstance(fit, str) or fit.base_to_base.covariance is None:
            checks.append(Disagreement(pair, 'loop', float('nan'), 0, float('nan'),
                                       note=fit if isinstance(fit, str) else 'no covariance'))
            continue
        ours = relative_base(rig, i, j)
        e = pose_error(fit.base_to_base.position, fit.base_to_base.quat_wxyz, ours.position,
                       ours.quat_wxyz)
        # both use B_i's and B_j's samples: the sum of their covariances is the conservative
        # bound of the difference's
        checks.append(_compare(pair, 'loop', e, fit.base_to_base.covariance + ours.covariance))
    bad = [c for c in checks if not c.consistent]
    if not bad:
        done = [c for c in checks if np.isfinite(c.chi2)]
        return LoopReport(tuple(checks), (), f'consistent: {len(done)} comparison(s) with the '
                          f'pairwise calibrations within their covariance')
    off, suspects = _culprits(names, checks, bad)
    worst = max(bad, key=lambda c: c.chi2)
    what = (f'{"/".join(worst.devices)} {worst.what}: chi2 {worst.chi2:.1f} for {worst.dof} '
            f'dof, up to {worst.error_mm_deg[0]:.3g} mm, {worst.error_mm_deg[1]:.3g}°')
    if off:
        return LoopReport(tuple(checks), off,
                          f'device {off[0]} is off: its pairwise calibration disagrees with '
                          f'the rig beyond their covariance ({what}); check its mount, noise '
                          f'(sigma) and stream, or run coreg diagnose on it')
    return LoopReport(tuple(checks), (),
                      f'the pairwise calibrations disagree with the rig ({what}) and cannot '
                      f'tell which of {", ".join(suspects)} is off (or their fits with A): '
                      f'a further device on the body would, each loop through it testing one '
                      f'of them (add its topic to the rig)')


def _culprits(names: tuple, checks: list, bad: list) -> tuple:
    """
    Name the device the failed comparisons point at (a 1-tuple, or empty), and the suspects.

    Loops decide first: the device in every failed loop and in no closed one. A shared base
    spreads one sensor's error to its siblings' own fits, so those say only which devices
    disagree, unless one alone does.
    """
    loops = [c for c in bad if c.what == 'loop']
    if loops:
        common = set.intersection(*(set(c.devices) for c in loops))
        closed = {n for c in checks if c.what == 'loop' and np.isfinite(c.chi2)
                  and c.consistent for n in c.devices}
        off = tuple(n for n in names if n in common and n not in closed)
        suspects = tuple(n for n in names if n in common) or tuple(
            n for n in names if any(n in c.devices for c in loops))
        return (off if len(off) == 1 else ()), suspects
    suspects = tuple(n for n in names if any(n in c.devices for c in bad))
    return (suspects if len(suspects) == 1 else ()), suspects


def direct_fits(devices: list, settings: Settings) -> dict:
    """
    Calibrate every two devices directly, the one with a full pose as the reference.

    Parameters
    ----------
    devices : list of RigDevice
        The rig's devices B_k.
    settings : Settings
        The rig's (pairing, offsets, method); each device's model and noise are its own.

    Returns
    -------
    dict
        ``{(i, j): CalibrationResult or str}``: B_j calibrated against B_i (its T0 is B_i's
        base in B_j's base), or why it could not be.

    """
    out = {}
    for i, ref in enumerate(devices):
        if ref.model != 'full_pose':
            continue
        for j, other in enumerate(devices):
            if j == i or (j, i) in out:
                continue
            n = 3 if other.model == 'three_marker' else 1
            cfg = settings.updated(
                model=other.model, topic_a=f'/{ref.name}',
                topic_b=tuple(f'/{other.name}/{m}' for m in range(n)),
                sigma_a=tuple(settings.sigma_b if ref.sigma_b is None else ref.sigma_b),
                sigma_b=tuple(settings.sigma_b if other.sigma_b is None else other.sigma_b))
            try:
                out[(i, j)], _ = calibrate_streams(ref.streams[0], list(other.streams), cfg,
                                                   direction_check=False)
            except CoregError as e:
                out[(i, j)] = f'{other.name} against {ref.name}: {e}'
    return out

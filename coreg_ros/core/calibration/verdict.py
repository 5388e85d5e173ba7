"""
Does the fit match the stated noise? The verdict users and scripts act on, with likely causes.

A fit whose chi-square is improbable under the stated noise (p below ``CONSISTENT_P``, Ikits
B.4.1) is not a success: its covariance is too small, and something the model does not know
about is in the data. The verdict names the causes it can see cheaply (positions in different
units, devices swapped according to the messages' frame ids, a prior that disagrees) and points
to ``coreg diagnose`` for the rest. Only the upper tail counts: noise stated too large makes
the covariance conservative, not wrong in the dangerous direction.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace
from typing import Optional

from coreg_ros.core import quaternion as quat
from coreg_ros.core.distributions import chi2_sf
from coreg_ros.core.estimator.priors import gravity_tilt, Prior
from coreg_ros.core.models import SPECS
from coreg_ros.core.settings import Settings
from coreg_ros.core.types import CalibrationResult, PoseStream
from coreg_ros.core.uncertainty import pose_error
import numpy as np

#: A fit (or a prior) with a p-value below this does not match the stated noise.
CONSISTENT_P = 1e-3


#: Position-spread ratios of the two devices that mean a unit between them (the spreads of
#: one rigidly linked body differ by far less): mm against m, cm against m.
UNIT_FACTORS = {'mm': (300.0, 3000.0), 'cm': (50.0, 300.0)}
#: Spread (m) of a tracked tool's positions about their median in a calibration recording:
#: of the two devices, the one farther from it (by a factor) is the one in other units.
TYPICAL_SPREAD = 0.2
#: Rotation (rad) within which a device's orientation counts as constant: a tracker that
#: measures its orientation never repeats it exactly, its noise alone moves it more.
CONSTANT_ROTATION = 1e-9
#: Rotation (rad) of A's tool beyond which a constant orientation of B cannot be the motion.
MOVING_ROTATION = 0.1


def _spread(position: np.ndarray) -> float:
    p = np.asarray(position, dtype=float).reshape(-1, 3)
    return float(np.median(np.linalg.norm(p - np.median(p, axis=0), axis=1)))


def unit_mismatch(stream_a: PoseStream, stream_b: PoseStream,
                  units: Sequence[str] = ('m', 'm')) -> Optional[str]:
    """
    Name a device whose positions are in other units, and the ``coreg convert`` option to fix.

    The spreads of the two devices' positions (median distance from their median) differ by
    a unit factor (``UNIT_FACTORS``). The device to blame: the one converted from other units
    than metres (``units``, what ``coreg convert`` was given), else the one whose spread is
    farther from a tracked tool's (``TYPICAL_SPREAD``): 200 m against 0.2 m is a device in
    mm, 0.2 mm against 0.2 m one scaled down.

    Parameters
    ----------
    stream_a, stream_b : PoseStream
        The two devices' streams (B: its first).
    units : (str, str)
        The units the positions were converted from (A, B): ``m`` when not known.

    Returns
    -------
    str or None
        One line naming the device and the option (``--units-a``/``--units-b`` of ``coreg
        convert``: m, cm, mm); None when the spreads agree.

    """
    spreads = {'A': _spread(stream_a.position), 'B': _spread(stream_b.position)}
    if not (spreads['A'] > 0 and spreads['B'] > 0):
        return None
    big, small = ('A', 'B') if spreads['A'] > spreads['B'] else ('B', 'A')
    ratio = spreads[big] / spreads[small]
    unit = next((u for u, (lo, hi) in UNIT_FACTORS.items() if lo < ratio <= hi), None)
    if unit is None:
        return None
    given = dict(zip('AB', units, strict=True))
    head = (f"device {big}'s positions spread {ratio:.0f}× more than device {small}'s "
            f'({spreads[big]:.3g} against {spreads[small]:.3g})')
    if given[small] != 'm':  # converted from other units although in metres
        return (f'{head}: {small} is likely in metres but was converted as {given[small]} (its '
                f'positions {ratio:.0f}× too small); convert it again with --units-'
                f'{small.lower()} m')
    if given[big] != 'm':
        return (f'{head}: a unit factor between the devices; check the units of both '
                f'exports (coreg convert --units-a, --units-b: m, cm, mm)')
    off = {k: abs(np.log(v / TYPICAL_SPREAD)) for k, v in spreads.items()}
    if off[big] >= off[small]:
        return (f'{head}: {big} is likely in {unit} (convert it to metres, e.g. coreg convert '
                f'--units-{big.lower()} {unit})')
    return (f'{head}: {small} is likely in metres but was scaled as if in {unit} (its '
            f'positions {ratio:.0f}× too small); convert it again with --units-'
            f'{small.lower()} m')


def orientation_missing(stream_a: PoseStream, stream_b: PoseStream,
                        model: str) -> Optional[str]:
    """Name a position-only device B calibrated with a model that uses B's orientation."""
    if model != 'full_pose' or len(stream_a) < 2 or len(stream_b) < 2:
        return None
    turn = {name: float(np.max(quat.angle_between(s.quat_wxyz, s.quat_wxyz[:1])))
            for name, s in (('A', stream_a), ('B', stream_b))}
    if turn['B'] < CONSTANT_ROTATION and turn['A'] > MOVING_ROTATION:
        return (f"device B's orientation is the same in every message while A's tool turns by "
                f'up to {np.degrees(turn["A"]):.0f}°: B is likely a position-only tracker '
                f'(one marker): calibrate with the position_only model (coreg calibrate '
                f"--model position_only; the node's model parameter)")
    return None


def swapped_frames(stream_a: PoseStream, stream_b: PoseStream,
                   frames: Optional[Sequence[str]]) -> Optional[str]:
    """Name swapped devices: the frame ids are the configured base frames the other way round."""
    if not frames or not all(frames):
        return None
    base_a, base_b = frames
    if stream_a.frame_id == base_b and stream_b.frame_id == base_a and base_a != base_b:
        return (f'the messages on topic A are in frame {base_b!r} and those on topic B in '
                f'{base_a!r}, the configured base frames the other way round: the devices are '
                f'swapped (exchange topic_a and topic_b), and the transforms are their '
                f'inverses; if the topics are right and only the frame ids mislead, confirm '
                f'the roles (`roles_confirmed`)')
    return None


def roles_swapped(result: CalibrationResult, stream_a: PoseStream) -> Optional[str]:
    """Name swapped roles of T0 and T1: a tool-to-marker lever far larger than A's workspace."""
    lever = float(np.linalg.norm(result.tool_to_marker.position))
    pos = np.asarray(stream_a.position, dtype=float)
    extent = float(np.max(np.ptp(pos, axis=0))) if len(pos) else 0.0
    if lever > 1.0 and lever > 5.0 * max(extent, 1e-9):
        return (f'the tool-to-marker translation is {lever:.2f} m, {lever / max(extent, 1e-9):.0f}'
                f"× the extent of A's motion: the streams are likely base-in-tool (T0 and T1 "
                f'swap roles); invert both streams (coreg convert --invert-a --invert-b)')
    return None


def prior_check(result: CalibrationResult, prior: Prior) -> Optional[dict]:
    """
    Test a prior against the data: ``d = x̂ - x_prior`` has covariance ``C_prior - C_post``.

    The rows are the constrained components of the prior's poses and, with
    ``gravity_sigma``, the tilt of T0 between the two z axes (``gravity_tilt``; prior 0).

    Returns
    -------
    dict or None
        ``{"chi2", "dof", "p_value", "consistent"}``; None if there is no posterior covariance.

    """
    if result.cov_joint is None:
        return None
    spec = SPECS[result.model]
    idx = prior.axes(spec)
    est = {0: result.base_to_base, 1: result.tool_to_marker}
    full = np.zeros(12)
    for w, p in prior.poses():
        full[6 * w:6 * w + 6] = -pose_error(p.position, p.quat_wxyz, est[w].position,
                                            est[w].quat_wxyz)
    M = np.eye(12)[idx]  # the rows tested, as maps of the 12 (T0, T1) errors
    d = full[idx]
    c_prior = prior.covariance()[np.ix_(idx, idx)] if len(idx) else np.zeros((0, 0))
    if prior.gravity_sigma is not None:
        tilt, rows = gravity_tilt(quat.to_matrix(est[0].quat_wxyz))
        G = np.zeros((2, 12))
        G[:, 3:6] = rows
        M, d = np.vstack([M, G]), np.concatenate([d, tilt])
        c_prior = np.block([[c_prior, np.zeros((len(idx), 2))],
                            [np.zeros((2, len(idx))), prior.gravity_sigma ** 2 * np.eye(2)]])
    if not len(d):
        return None
    D = c_prior - M @ result.cov_for_propagation @ M.T
    lam, U = np.linalg.eigh(0.5 * (D + D.T))
    keep = lam > 1e-9 * max(float(lam.max()), 0.0)
    if not keep.any():
        return None
    chi2 = float(np.sum((U[:, keep].T @ d) ** 2 / lam[keep]))
    dof = int(keep.sum())
    p = float(chi2_sf(chi2, dof))
    return {'chi2': chi2, 'dof': dof, 'p_value': p, 'consistent': p >= CONSISTENT_P}


def cheap_causes(stream_a: PoseStream, streams_b: Sequence[PoseStream], settings: Settings,
                 frames: Optional[Sequence[str]] = None,
                 roles_confirmed: bool = False) -> list:
    """Return what the streams alone say is wrong (units, a position-only B, a swap)."""
    swap = None if roles_confirmed else swapped_frames(stream_a, streams_b[0], frames)
    return [c for c in (unit_mismatch(stream_a, streams_b[0]),
                        orientation_missing(stream_a, streams_b[0], settings.model), swap) if c]


def judge(result: CalibrationResult, stream_a: PoseStream, streams_b: Sequence[PoseStream],
          settings: Settings, prior: Optional[Prior] = None,
          frames: Optional[Sequence[str]] = None,
          roles_confirmed: bool = False, clock: Optional[str] = None) -> CalibrationResult:
    """
    Return the result with ``fit_consistent``, ``verdict``, ``prior_check`` and ``success`` set.

    ``success`` stays True only if the estimator converged, the fit matches the stated noise,
    the prior (if any) agrees with the data and no check refuses it: devices swapped according
    to the messages' frame ids (``swapped_frames``) are refused whatever the fit
    (``refusals``), since swapped devices fit as well as the right ones, with the inverse
    transforms, unless ``roles_confirmed`` says the topics are right. ``clock``, the clock
    story that explains a bad fit (``clock_check.clock_problem``), is named as its cause.
    """
    checks = prior_check(result, prior) if prior is not None else None
    swap = None if roles_confirmed else swapped_frames(stream_a, streams_b[0], frames)
    p = float(result.p_value)
    reasons = []
    if np.isfinite(p) and p < CONSISTENT_P:
        causes = cheap_causes(stream_a, streams_b, settings, frames, roles_confirmed)
        if clock:
            causes.append(clock)
        if not causes and settings.method == 'ols':
            causes.append("OLS leaves device A's noise (sigma_a) out of the fit, where it "
                          'shows as excess; --method tls includes it')
        ratio = result.chi2 / result.dof if result.dof > 0 else float('nan')
        reasons.append(
            f'the fit does not match the stated noise (chi2/dof {ratio:.3g}, p = {p:.2g}): '
            + ('; '.join(causes) if causes else
               'the noise is understated, or the data hold an effect the model lacks'))
    if checks is not None and not checks['consistent']:
        reasons.append(
            f"the prior disagrees with the data (chi2 {checks['chi2']:.1f} for "
            f"{checks['dof']} dof, p = {checks['p_value']:.2g}): the calibration changed since, "
            f'or the prior covariance is too small; recalibrate without --prior')
    consistent = not reasons
    verdict = '' if consistent else '; '.join(reasons) + '; run coreg diagnose for details'
    refusals = ()
    if swap:
        refusals = ('devices_swapped',)
        if consistent:  # else the swap is already named as the cause of the bad fit
            verdict = f'not used although the fit matches the noise: {swap}'
    warning = roles_swapped(result, stream_a)
    if warning:
        verdict = '; '.join(v for v in (verdict, 'warning: ' + warning) if v)
    return replace(result, fit_consistent=consistent, verdict=verdict, prior_check=checks,
                   refusals=refusals, success=bool(result.success and consistent and not swap))

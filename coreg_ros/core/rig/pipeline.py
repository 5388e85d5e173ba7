"""
A rig's streams in, its joint calibration out.

1. Each device B_k is calibrated with A alone, exactly as two devices are
   (``calibration.pipeline.calibrate_streams``): its clock offset found whatever its stamps
   (``offset_search``), its outliers rejected, its fit judged. A device that cannot be
   calibrated so is refused, by name, with its reason.
2. The sensors of one base share one clock: their offsets are combined (inverse-variance),
   and every device is paired with A at its clock's offset, its outliers left out.
3. The joint fit (``joint``) from the devices' own solutions, over φ with shared bases once;
   the joint posterior over φ and the clocks (``posterior``). Devices that share neither a
   base nor a clock are independent given A: their joint fit is their fits alone
   (``_independent``), used as they are.
4. Each device's result in the rig, its share of χ², the σ ratio against its fit alone, and
   the verdict naming any device whose fit does not match its stated noise.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace
from typing import Optional

from coreg_ros.core.calibration.observability import (
    MOTION_SAMPLE,
    rotation_spread,
    STILL_M,
    STILL_RAD,
)
from coreg_ros.core.calibration.pair_input import validated_arrays
from coreg_ros.core.calibration.pairing import pair_for, validate_stream
from coreg_ros.core.calibration.pipeline import calibrate_streams
from coreg_ros.core.calibration.verdict import CONSISTENT_P
from coreg_ros.core.distributions import chi2_sf
from coreg_ros.core.errors import CoregError, UnobservableError
from coreg_ros.core.estimator import noise_covariance, output_covariance, whitening
from coreg_ros.core.estimator.posterior import result_poses, tangent_map, UNKNOWN
from coreg_ros.core.estimator.problem import Problem
from coreg_ros.core.models import Parameters, SPECS
from coreg_ros.core.rig.devices import checked_devices, RigDevice
from coreg_ros.core.rig.joint import solve_rig
from coreg_ros.core.rig.layout import RigLayout, RigParameters
from coreg_ros.core.rig.loops import direct_fits, loop_report
from coreg_ros.core.rig.posterior import (
    ATrajectory,
    Clock,
    input_shift,
    joint_covariance,
    ros_covariance,
    time_information,
)
from coreg_ros.core.rig.result import DeviceResult, RigResult
from coreg_ros.core.rig.shared_instants import sharing_groups
from coreg_ros.core.settings import Settings
from coreg_ros.core.types import CalibrationResult, Pairs, PoseStream, TimeOffset
import numpy as np


def device_settings(settings: Settings, device: RigDevice) -> Settings:
    """Return the settings of one device's fit: its model, noise and topics, the rest the rig's."""
    n = 3 if device.model == 'three_marker' else 1
    topics = tuple(device.topics) if len(device.topics) == n else tuple(
        f'/{device.name}/marker{j + 1}' if n == 3 else f'/{device.name}' for j in range(n))
    return settings.updated(model=device.model, topic_b=topics, sigma_b=tuple(
        settings.sigma_b if device.sigma_b is None else device.sigma_b))


def _refuse_if_still(device: RigDevice, sigma_b) -> None:
    """
    Refuse a device that did not move: it does not watch the body A tracks.

    The same noise-level limits as A's (``observability.refuse_if_nothing_moved``): below
    them its fit would only match A's motion to its noise.
    """
    first = device.streams[0]
    step = max(1, len(first) // MOTION_SAMPLE)
    pos = np.asarray(first.position)[::step]
    moved = float(np.sqrt(np.mean(np.sum((pos - pos.mean(axis=0)) ** 2, axis=1))))
    turned = float(rotation_spread(np.asarray(first.quat_wxyz)[::step])[0][0]) if (
        device.model == 'full_pose') else 0.0
    if moved < max(STILL_M, 10.0 * sigma_b[0]) and turned < max(STILL_RAD, 5.0 * sigma_b[1]):
        raise UnobservableError(
            f'device {device.name} did not move ({moved * 1e3:.2f} mm RMS translation, '
            f"{np.degrees(turned):.2f}° RMS rotation) while device A's tool did: it does not "
            f'watch the body A tracks; check its topic and its mount, or leave it out')


def _alone(stream_a: PoseStream, device: RigDevice, settings: Settings, frames):
    """Calibrate the device with A alone; a refusal names the device."""
    _refuse_if_still(device, settings.sigma_b)
    try:
        result, report = calibrate_streams(stream_a, list(device.streams), settings,
                                           frames=frames)
    except CoregError as e:
        raise e.with_message(f'device {device.name}: {e}') from e
    if result.held:
        raise UnobservableError(
            f'device {device.name}: the motion leaves '
            f'{"; ".join(u.description for u in result.held)} undetermined (held in its own '
            f'fit); a rig needs every device determined: record the motion it names, or '
            f'calibrate that device alone', tuple(u.description for u in result.held))
    return result, report


def _clocks(layout: RigLayout, alone: list, settings: Settings) -> tuple[list, list]:
    """One clock per base: its sensors' offsets combined by their σ."""
    clocks, device_clock = [], [0] * len(alone)
    for g, base in enumerate(layout.base_names):
        members = [k for k, b in enumerate(layout.bases) if b == base]
        for k in members:
            device_clock[k] = g
        found = [alone[k].time_offset for k in members if alone[k].time_offset is not None
                 and alone[k].time_offset.estimated]
        if not found:
            clocks.append(Clock(tuple(members), TimeOffset(settings.time_offset,
                                                           message='given'), 0))
            continue
        w = np.array([1.0 / t.sigma_s ** 2 for t in found])
        tau = float(np.sum(w * [t.value_s for t in found]) / w.sum())
        drifts = [t for t in found if t.drift_ppm is not None]
        n_time, drift_ppm, sigma = 1, None, [float(1.0 / np.sqrt(w.sum()))]
        if len(drifts) == len(found):
            wd = np.array([1.0 / t.drift_sigma_ppm ** 2 for t in drifts])
            drift_ppm = float(np.sum(wd * [t.drift_ppm for t in drifts]) / wd.sum())
            n_time, sigma = 2, sigma + [float(1e-6 / np.sqrt(wd.sum()))]
        how = found[0].message if len(members) == 1 else (
            f'the sensors of base {base} share one clock: their offsets combined')
        timing = TimeOffset(tau, sigma[0], True, drift_ppm=drift_ppm,
                            reference_ns=found[0].reference_ns, message=how)
        clocks.append(Clock(tuple(members), timing, n_time, tuple(sigma)))
    return clocks, device_clock


def _independent(devices: list, fits: list, settings: Settings) -> RigResult:
    """
    Make the rig of devices sharing neither base nor clock: each device calibrated with A.

    Given A's samples their information is block-diagonal (no shared parameter, no shared
    instant: every device its own clock), so the joint fit is their fits alone, used as they
    are, and the joint covariance has no cross terms between them. One device is today's
    two-device calibration, unchanged.
    """
    K = len(devices)
    cov = np.zeros((13 * K, 13 * K))
    out, off = [], []
    for k, (device, (result, report)) in enumerate(zip(devices, fits, strict=True)):
        t = result.time_offset
        if result.cov_joint is None:
            cov = None
        elif cov is not None:
            cov[12 * k:12 * k + 12, 12 * k:12 * k + 12] = result.cov_joint
            row = 12 * K + k
            cov[row, row] = t.sigma_s ** 2 if t is not None and t.estimated else UNKNOWN
            if t is not None and t.estimated and t.cross_cov is not None:
                cov[12 * k:12 * k + 12, row] = cov[row, 12 * k:12 * k + 12] = t.cross_cov[:, 0]
        ratio = (np.full(12, np.nan) if result.cov_joint is None else
                 np.where(np.diag(result.cov_joint) > 0, 1.0, np.nan))
        out.append(DeviceResult(device.name, tuple(device.topics), device.base_name, result,
                                result, report, 0.0, ratio))
        if not result.success:
            off.append(f'device {device.name}: {result.verdict or result.message}')
    chi2 = float(sum(r.chi2 for r, _ in fits))
    dof = int(sum(r.dof for r, _ in fits))
    out = [replace(d, chi2_share=d.result.chi2 / chi2 if chi2 > 0 else 0.0) for d in out]
    if K == 1:
        r = fits[0][0]
        return RigResult(bool(r.success), int(r.status), r.message, settings.method, tuple(out),
                         chi2, dof, float(r.p_value), bool(r.fit_consistent), r.verdict, cov,
                         iterations=int(r.iterations))
    p_value = float(chi2_sf(chi2, dof)) if dof > 0 else float('nan')
    status = min(int(r.status) for r, _ in fits)
    return RigResult(not off, status, f'{K} devices that share neither base nor clock: each '
                     f'calibrated with A', settings.method, tuple(out), chi2, dof, p_value,
                     all(bool(r.fit_consistent) for r, _ in fits), '; '.join(off), cov,
                     iterations=max(int(r.iterations) for r, _ in fits))


def _moved(clock: Clock, delta: np.ndarray) -> Clock:
    """Return the clock with its parameters moved by the joint step (τ s[, κ])."""
    if clock.n_time == 0:
        return clock
    t = clock.timing
    drift = t.drift_ppm if clock.n_time < 2 else t.drift_ppm + float(delta[1]) * 1e6
    return replace(clock, timing=replace(t, value_s=t.value_s + float(delta[0]),
                                         drift_ppm=drift))


def _take(pairs: Pairs, keep: np.ndarray) -> Pairs:
    idx = np.flatnonzero(keep)

    def sub(x):
        return None if x is None else np.take(np.asarray(x), idx, axis=0)

    return Pairs(sub(pairs.stamps), sub(pairs.pos_a), sub(pairs.quat_a), sub(pairs.pos_b),
                 sub(pairs.quat_b), sub(pairs.a_var_scale))


def _query_ns(stamps: np.ndarray, timing: TimeOffset) -> np.ndarray:
    """Return the A-clock times (ns) at which the pairs of B stamps ``stamps`` interpolate A."""
    query = stamps - np.int64(timing.offset_ns())
    if timing.drift:
        since = (stamps - np.int64(timing.reference_ns)).astype(float)
        query = query - np.round(timing.drift * since).astype(np.int64)
    return query


def calibrate_rig(stream_a: PoseStream, devices: Sequence[RigDevice], settings: Settings,
                  frames: Optional[tuple] = None, loops: bool = False) -> RigResult:
    """
    Calibrate device A and the devices B_k jointly (the module docstring says how).

    Parameters
    ----------
    stream_a : PoseStream
        Device A: tool pose in A's base frame, A's clock.
    devices : sequence of RigDevice
        The devices B_k (``devices.RigDevice``: stream(s), model, noise, base).
    settings : Settings
        Method, A's noise, pairing, offsets, robust fit, iteration limit (each device's model
        and noise are its own).
    frames : (str, str), optional
        The configured base frames, as ``calibrate_streams``.
    loops : bool
        Also calibrate every two devices directly (a full-pose device as the reference) and
        check the rig's loops against them (``loops.loop_report``); the devices' fits with A
        alone are checked in any case.

    Returns
    -------
    RigResult

    Raises
    ------
    CoregError
        Bad input (``devices.checked_devices``), or a device its own calibration refuses
        (the message names it).

    """
    devices = checked_devices(stream_a, devices)
    own = [device_settings(settings, d) for d in devices]
    fits = [_alone(stream_a, d, s, frames) for d, s in zip(devices, own, strict=True)]
    if len({d.base_name for d in devices}) == len(devices):
        rig = _independent(devices, fits, settings)
        return rig if len(devices) == 1 else replace(rig, loops=loop_report(
            rig, direct_fits(devices, settings) if loops else None))
    alone = [f[0] for f in fits]
    layout = RigLayout.build([d.name for d in devices], [d.model for d in devices],
                             [d.base_name for d in devices])
    clocks, device_clock = _clocks(layout, alone, settings)
    cov_a = noise_covariance(settings.sigma_a)
    problems, stamps, query, reports, metrics = [], [], [], [], []
    for k, (d, s) in enumerate(zip(devices, own, strict=True)):
        timing = clocks[device_clock[k]].timing
        pairs, report = pair_for(stream_a, list(d.streams), s, timing)
        rejected = alone[k].rejected_stamps
        if rejected is not None and len(rejected):
            pairs = _take(pairs, ~np.isin(pairs.stamps, rejected))
        spec = SPECS[d.model]
        pos_a, quat_a, pos_b, quat_b, scale = validated_arrays(pairs, spec, s)
        cov_b = noise_covariance(s.sigma_b)
        problems.append(Problem(spec, pos_a, quat_a, pos_b, quat_b, whitening(cov_b, spec, 'b'),
                                whitening(cov_a, None, 'a'), scale))
        metrics.append(output_covariance(cov_b, spec))
        stamps.append(np.asarray(pairs.stamps, dtype=np.int64))
        query.append(_query_ns(stamps[-1], timing))
        reports.append(report)
    start = RigParameters.from_starts(layout, [Parameters(SPECS[r.model], r.params, r.charts)
                                               for r in alone])
    sol = solve_rig(problems, query, start, settings.method, int(settings.max_iterations))
    if sol.cov is None:
        raise UnobservableError("the rig's joint fit has a singular information matrix; "
                                'calibrate its devices one by one to see which is undetermined')
    cov, time_cols, step = _with_clocks(stream_a, problems, stamps, metrics, sol, clocks,
                                        device_clock, cov_a, settings)
    # the clocks' joint optimum (a linear step: the devices' own offsets are within their σ
    # of it), φ moved with them, as the two-device search's last step (offset_search)
    sol = replace(sol, params=sol.params.stepped(step[:layout.n_params]).recharted(),
                  chi2=max(0.0, sol.chi2 - float(step @ np.linalg.solve(cov, step))))
    clocks = [_moved(c, step[tc]) for c, tc in zip(clocks, time_cols, strict=True)]
    cov_ros = ros_covariance(cov, sol.params, device_clock, time_cols)
    rig = _rig_result(layout, devices, alone, reports, sol, cov, time_cols, clocks,
                      device_clock, settings, cov_ros, query)
    return replace(rig, loops=loop_report(rig, direct_fits(devices, settings) if loops
                                          else None))


def _with_clocks(stream_a, problems, stamps, metrics, sol, clocks, device_clock, cov_a,
                 settings):
    """Return the joint covariance over φ and the clocks (``posterior``); refuse if singular."""
    motion = ATrajectory(validate_stream(stream_a, 'stream_a'))
    layout = sol.params.layout
    contributions, halves = [], {}
    for k, p in enumerate(sol.params.devices):
        clock = clocks[device_clock[k]]
        if clock.n_time == 0:
            continue
        cols = layout.columns[k]
        h, halves[k] = time_information(motion, problems[k], stamps[k], p,
                                        sol.cov[np.ix_(cols, cols)], clock, cov_a, metrics[k],
                                        settings.method == 'tls', settings.max_gap)
        if h is not None and not _shares_instants(sol, k):
            contributions.append((cols, device_clock[k], *h))
    for unit, x in zip(sol.units, sol.inputs or [], strict=False):
        if len(unit.devices) < 2:
            continue
        g = device_clock[unit.devices[0]]
        clock = clocks[g]
        if clock.n_time == 0:
            continue
        shift = input_shift(motion, unit.group.times, clock, halves[unit.devices[0]],
                            settings.max_gap)
        contributions.append((unit.cols, g, *unit.time_information(sol.params, x, shift)))
    cov, time_cols, step = joint_covariance(sol.info, clocks, contributions)
    if cov is None:
        raise UnobservableError("the rig's joint covariance with the clock offsets is singular; "
                                'give the offsets (--time-offset) or record a livelier motion')
    return cov, time_cols, step


def _shares_instants(sol, k: int) -> bool:
    """Whether device k is linearised with others (its clock's information comes from there)."""
    return sol.inputs is not None and any(k in u.devices and len(u.devices) > 1
                                          for u in sol.units)


def _device_dof(layout: RigLayout, k: int, n_rows: int, clock: Clock) -> float:
    """Degrees of freedom of a device's share: its rows less its parameters (shared ones split)."""
    own = SPECS[layout.models[k]].n_params - 6 + 6.0 / layout.sharing(k)
    return n_rows - own - clock.n_time / len(clock.devices)


def _rig_result(layout, devices, alone, reports, sol, cov, time_cols, clocks, device_clock,
                settings, cov_ros, query) -> RigResult:
    """Assemble every device's result in the rig and the rig's verdict."""
    n_time = sum(c.n_time for c in clocks)
    n_rows = [r.shape[0] * r.shape[1] for r in sol.residuals]
    dof = int(sum(n_rows) - layout.n_params - n_time)
    p_value = float(chi2_sf(sol.chi2, dof)) if dof > 0 else float('nan')
    out, off = [], []
    for k, d in enumerate(devices):
        clock = clocks[device_clock[k]]
        params = sol.params.devices[k]
        cols, tc = layout.columns[k], time_cols[device_clock[k]]
        t0, t1, joint = result_poses(params, cov[np.ix_(cols, cols)])
        timing = clock.timing
        if clock.n_time:
            T, _ = tangent_map(params)
            tcov = cov[np.ix_(tc, tc)]
            timing = replace(timing, sigma_s=float(np.sqrt(tcov[0, 0])), cov=tcov,
                             cross_cov=T @ cov[np.ix_(cols, tc)],
                             drift_sigma_ppm=(float(np.sqrt(tcov[1, 1])) * 1e6
                                              if clock.n_time == 2 else None))
        chi2_k = float(sol.device_chi2[k])
        total = float(np.sum(sol.device_chi2))
        dof_k = _device_dof(layout, k, n_rows[k], clock)
        p_k = float(chi2_sf(chi2_k, dof_k)) if dof_k > 0 else float('nan')
        consistent = not (np.isfinite(p_k) and p_k < CONSISTENT_P)
        verdict = '' if consistent else (
            f'its pairs do not match its stated noise (chi2/dof {chi2_k / dof_k:.3g}, '
            f'p = {p_k:.2g}): its noise is understated or its data hold an effect the model '
            f'lacks; coreg diagnose with --topic-b {d.topics[0] if d.topics else d.name}')
        if alone[k].direction_check is not None and alone[k].direction_check.flagged:
            verdict = '; '.join(v for v in (alone[k].direction_check.message, verdict) if v)
            consistent = False
        if not consistent:
            off.append(f'device {d.name}: {verdict}')
        result = replace(
            alone[k], success=bool(sol.status > 0 and consistent), status=sol.status,
            message=sol.message, n_pairs=len(query[k]), base_to_base=t0, tool_to_marker=t1,
            markers=params.markers.copy(), params=params.phi.copy(),
            param_cov=cov[np.ix_(cols, cols)], chi2=chi2_k, dof=int(round(dof_k)), p_value=p_k,
            residuals=sol.residuals[k], iterations=sol.iterations, cov_joint=joint,
            input_residuals=None, charts=tuple(params.charts), inliers=None, time_offset=timing,
            fit_consistent=consistent, verdict=verdict, cov_determined=None)
        out.append(DeviceResult(d.name, tuple(d.topics), d.base_name, result, alone[k],
                                reports[k], chi2_k / total if total > 0 else 0.0,
                                _sigma_ratio(result, alone[k])))
    consistent = not (np.isfinite(p_value) and p_value < CONSISTENT_P) and not off
    reasons = list(off)
    if np.isfinite(p_value) and p_value < CONSISTENT_P and not off:
        reasons.append(f"the rig's fit does not match the stated noise (chi2/dof "
                       f'{sol.chi2 / dof:.3g}, p = {p_value:.2g})')
    groups = sharing_groups(query)
    shared = tuple(tuple(devices[k].name for k in g) for g in groups if len(g) > 1)
    return RigResult(success=bool(sol.status > 0 and consistent), status=sol.status,
                     message=sol.message, method=settings.method, devices=tuple(out),
                     chi2=sol.chi2, dof=dof, p_value=p_value, fit_consistent=consistent,
                     verdict='; '.join(reasons), cov_joint=cov_ros, shared_instants=shared,
                     iterations=sol.iterations)


def _sigma_ratio(rig: CalibrationResult, alone: CalibrationResult) -> np.ndarray:
    """σ in the rig over σ alone per (T0, T1) component, ROS layout (NaN: not estimated)."""
    if rig.cov_joint is None or alone.cov_joint is None:
        return np.full(12, np.nan)
    a, b = np.diag(rig.cov_joint), np.diag(alone.cov_joint)
    with np.errstate(invalid='ignore', divide='ignore'):
        return np.where((a > 0) & (b > 0), np.sqrt(np.abs(a) / np.abs(b)), np.nan)

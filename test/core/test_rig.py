"""
Whole rigs calibrated jointly (issue 23): device A and K devices B_k.

The joint posterior's NEES over every device's T0, T1 and clock offset by Monte Carlo (fixed
seeds, random draws of the rig), each device's σ against its fit with A alone, shared bases
and shared instants, and the layout of the rig's parameter vector.
"""

from coreg_ros.core.rig.devices import RigDevice
from coreg_ros.core.rig.layout import RigLayout
from coreg_ros.core.rig.pipeline import calibrate_rig
from coreg_ros.core.settings import Settings
from coreg_ros.core.uncertainty import pose_error
from coreg_ros.sim.rig import SimDevice, simulate_rig
import numpy as np
import pytest
from scipy import stats


def test_layout_places_a_shared_base_once():
    layout = RigLayout.build(['em1', 'em2', 'cam'], ['full_pose', 'position_only', 'three_marker'],
                             ['em', 'em', 'cam'])
    assert layout.n_params == 6 + 6 + 6 + 3 + 9
    c = layout.columns
    assert np.array_equal(c[0][:6], c[1][:6])  # one T0 for the sensors of one base
    assert not set(c[2][:6]) & set(c[0])
    every = np.concatenate([c[0], c[1][6:], c[2]])
    assert sorted(every) == list(range(layout.n_params))
    labels = layout.labels()
    assert labels[c[1][0]] == 'em.p0x' and labels[c[1][6]] == 'em2.p1x'


def _devices(sim_devices, rig):
    return [RigDevice(d.name, tuple(s), d.model, d.sigma, d.base)
            for d, s in zip(sim_devices, rig.streams, strict=True)]


def _errors(result, rig, sim_devices):
    """Truth minus estimate of every independent parameter, and its covariance."""
    K = len(sim_devices)
    err, idx, seen = np.zeros(13 * K), [], set()
    for k, (d, truth, sd) in enumerate(zip(result.devices, rig.truths, sim_devices,
                                           strict=True)):
        r = d.result
        err[12 * k:12 * k + 6] = pose_error(truth.p0, truth.q0, r.base_to_base.position,
                                            r.base_to_base.quat_wxyz)
        err[12 * k + 6:12 * k + 12] = pose_error(truth.markers[0], truth.q1,
                                                 r.tool_to_marker.position,
                                                 r.tool_to_marker.quat_wxyz)
        err[12 * K + k] = sd.clock_offset - r.time_offset.value_s
        if d.base not in seen:  # a shared base (and its clock) counts once
            idx += list(range(12 * k, 12 * k + 6)) + [12 * K + k]
            seen.add(d.base)
        idx += list(range(12 * k + 6, 12 * k + (12 if r.model == 'full_pose' else 9)))
    return err[idx], result.cov_joint[np.ix_(idx, idx)]


def _rigs(seed: int, n: int, shared: bool):
    """Random rigs of A + 2 devices: models, noises, rates, offsets from ms to an hour."""
    rng = np.random.default_rng(seed)
    for _ in range(n):
        # A, the reference (a robot, an optical tracker): up to 3 mm and 3 mrad. Beyond a few
        # mrad of A's rotation noise the two-device TLS itself exceeds its NEES (its O(σ²)
        # bias grows against a σ that shrinks with N): not what this test is about
        sigma_a = (float(10 ** rng.uniform(-3.7, -2.5)), float(10 ** rng.uniform(-3.3, -2.5)))

        def noise():
            return (float(10 ** rng.uniform(-3.7, -3)), float(10 ** rng.uniform(-3.3, -2.5)))

        tau = [float(rng.choice([-1, 1]) * 10 ** rng.uniform(-3, 3.5)) for _ in range(2)]
        rates = [float(r) for r in rng.choice([30.0, 50.0, 100.0], size=2)]
        if shared:  # two sensors of one EM device: one base, one clock, the same instants
            devices = [SimDevice('em1', 'full_pose', rates[0], noise(), tau[0], 'em'),
                       SimDevice('em2', str(rng.choice(['full_pose', 'position_only'])),
                                 rates[0], noise(), tau[0], 'em')]
        else:
            devices = [SimDevice('cam', 'full_pose', rates[0], noise(), tau[0]),
                       SimDevice('opt', str(rng.choice(['position_only', 'three_marker'])),
                                 rates[1], noise(), tau[1])]
        yield int(rng.integers(1 << 30)), sigma_a, devices


@pytest.mark.parametrize('shared', [False, True], ids=['own_bases', 'shared_base'])
def test_joint_nees_and_sigma_against_each_device_alone(shared):
    nees, dims, ratios = [], [], []
    for seed, sigma_a, devices in _rigs(23 + int(shared), 6, shared):
        rig = simulate_rig(seed, 20.0, devices, sigma_a=sigma_a)
        result = calibrate_rig(rig.stream_a, _devices(devices, rig), Settings(sigma_a=sigma_a))
        assert result.status > 0 and result.cov_joint is not None
        e, C = _errors(result, rig, devices)
        nees.append(float(e @ np.linalg.solve(C, e)))
        dims.append(len(e))
        ratios.append([d.sigma_ratio for d in result.devices])
    # the sum of the runs' NEES is χ² with the summed dimensions: inside its 99 % band
    total, dof = float(np.sum(nees)), int(np.sum(dims))
    assert stats.chi2.ppf(0.005, dof) < total < stats.chi2.ppf(0.995, dof), (total, dof, nees)
    ratios = np.array(ratios)  # (runs, devices, 12)
    # no device is worse in the rig than alone, but for where the offset's information is
    # evaluated (the joint solution, re-paired at the final offset, against the pair's last
    # round before its final step): independent devices, whose information is the same in
    # theory, measure that difference at a few per cent either way
    assert np.nanmax(ratios) < 1.05, np.nanmax(ratios)
    if shared:
        # the sensors inform each other through their base (and A's inputs at their instants)
        t0 = np.nanmedian(ratios[:, :, 0:6], axis=2)
        assert np.max(np.min(t0, axis=1)) < 0.95, t0
    else:
        assert np.nanmin(ratios) > 0.95  # independent devices: nothing to share


def test_one_device_in_a_rig_is_its_pair_at_a_given_offset():
    devices = [SimDevice('cam', 'full_pose', 50.0, (5e-4, 2e-3), 0.0)]
    rig = simulate_rig(3, 20.0, devices)
    result = calibrate_rig(rig.stream_a, _devices(devices, rig),
                           Settings(estimate_time_offset=False))
    d = result.devices[0]
    r, alone = d.result, d.alone
    sd = np.sqrt(np.diag(alone.cov_joint))
    delta = pose_error(alone.base_to_base.position, alone.base_to_base.quat_wxyz,
                       r.base_to_base.position, r.base_to_base.quat_wxyz)
    assert np.all(np.abs(delta) < 1e-3 * sd[:6])
    assert np.allclose(d.sigma_ratio, 1.0, atol=1e-3)
    assert abs(r.chi2 - alone.chi2) < 1e-3 * alone.chi2

"""
Tests of the observability checks.

Motion that cannot determine the calibration is refused with a message that names the
unobservable parameter and the motion that would fix it.
"""

from coreg_ros.core import quaternion as quat
from coreg_ros.core.calibration.calibrate import calibrate
from coreg_ros.core.calibration.observability import (
    check_motion,
    check_observability,
    rotation_spread,
)
from coreg_ros.core.errors import CoregError, UnobservableError
from coreg_ros.core.estimator import noise_covariance, Problem, solve_ols, whitening
from coreg_ros.core.models import Parameters, SPECS
from coreg_ros.core.settings import Settings
from coreg_ros.sim import simulate_pairs
import numpy as np
import pytest

MODELS = tuple(SPECS)
METHODS = ('ols', 'tls')


def offsets_phrase(model):
    return 'tool-to-marker translation' if model != 'three_marker' else 'marker positions'


@pytest.mark.parametrize('model', MODELS)
@pytest.mark.parametrize('method', METHODS)
def test_single_axis_rotation_is_refused(model, method):
    noisy, _, _ = simulate_pairs(np.random.default_rng(1), 150, model, motion='single_axis')
    with pytest.raises(UnobservableError) as info:
        calibrate(noisy, Settings(model=model, method=method))
    msg = str(info.value)
    assert '\n' not in msg
    for words in ('rotation about only one axis', offsets_phrase(model), 'along that axis',
                  'unobservable', 'rotate about a second axis'):
        assert words in msg, f'{words!r} not in {msg!r}'
    assert info.value.directions and offsets_phrase(model) in info.value.directions[0]


@pytest.mark.parametrize('model', MODELS)
@pytest.mark.parametrize('method', METHODS)
@pytest.mark.parametrize('preset', ['no_rotation', 'static'])
def test_no_rotation_is_refused(model, method, preset):
    noisy, _, _ = simulate_pairs(np.random.default_rng(2), 150, model, motion=preset)
    with pytest.raises(UnobservableError) as info:
        calibrate(noisy, Settings(model=model, method=method))
    msg = str(info.value)
    assert '\n' not in msg
    for words in ('hardly rotated', offsets_phrase(model), 'unobservable',
                  'rotate the tool about at least two different axes'):
        assert words in msg, f'{words!r} not in {msg!r}'
    if SPECS[model].has_q1:
        assert 'rotation split between base-to-base and tool-to-marker' in msg
        assert len(info.value.directions) == 2
    else:
        assert len(info.value.directions) == 1
    assert isinstance(info.value, CoregError)


def test_rotation_at_the_noise_level_counts_as_none():
    """A tool held still but measured with rotation noise has not rotated."""
    noisy, _, _ = simulate_pairs(np.random.default_rng(3), 300, 'full_pose',
                                 motion='no_rotation', sigma_a=(2e-4, 5e-3))
    spread, _ = rotation_spread(noisy.quat_a)
    assert spread[0] > 0.004  # measurable jitter, yet far below real motion
    with pytest.raises(UnobservableError, match='hardly rotated'):
        calibrate(noisy, Settings(model='full_pose', sigma_a=(2e-4, 5e-3)))


@pytest.mark.parametrize('model', MODELS)
@pytest.mark.parametrize('method', METHODS)
def test_diverse_motion_passes(model, method):
    noisy, _, _ = simulate_pairs(np.random.default_rng(4), 150, model, motion='diverse')
    check_motion(noisy.quat_a, SPECS[model], 5e-4)
    r = calibrate(noisy, Settings(model=model, method=method))
    assert r.success and r.param_cov is not None


@pytest.mark.parametrize('motion', ['diverse', 'single_axis', 'no_rotation'])
def test_the_motion_check_of_a_long_recording_reads_a_subsample_to_the_same_verdict(
        monkeypatch, motion):
    """Every k-th orientation (MOTION_SAMPLE) gives the spread of all and the same verdict."""
    from coreg_ros.core.calibration import observability

    noisy, _, _ = simulate_pairs(np.random.default_rng(7), 4000, 'full_pose', motion=motion,
                                 sigma_a=(2e-4, 2e-3))
    full, _ = rotation_spread(noisy.quat_a)
    sub, _ = rotation_spread(noisy.quat_a[::4])
    np.testing.assert_allclose(sub, full, rtol=0.05, atol=1e-3)

    def verdict():
        try:
            check_motion(noisy.quat_a, SPECS['full_pose'], 2e-3)
        except UnobservableError as e:
            return str(e).split(' (')[0]
        return 'observable'

    everything = verdict()
    monkeypatch.setattr(observability, 'MOTION_SAMPLE', 1000)  # every 4th of 4000
    assert verdict() == everything == {'diverse': 'observable',
                                       'single_axis': 'rotation about only one axis',
                                       'no_rotation': "device A's tool hardly rotated"}[motion]


def test_rotation_spread_finds_the_single_axis():
    noisy, _, _ = simulate_pairs(np.random.default_rng(5), 400, 'full_pose',
                                 motion='single_axis', sigma_a=(0.0, 0.0))
    spread, axes = rotation_spread(noisy.quat_a)
    assert spread[0] > 0.3 and spread[1] < 1e-9 and spread[2] < 1e-9
    # The axis is fixed in the tool frame: every relative rotation is about it.
    rel = quat.log(quat.multiply(quat.conjugate(noisy.quat_a[0]), noisy.quat_a[1:]))
    rel = rel[np.linalg.norm(rel, axis=1) > 1e-3]
    cos = np.abs(rel @ axes[0]) / np.linalg.norm(rel, axis=1)
    np.testing.assert_allclose(cos, 1.0, atol=1e-9)


@pytest.mark.parametrize('model', MODELS)
def test_rank_check_names_the_null_direction(model):
    """The information-matrix check on its own, on single-axis data that passed no pre-check."""
    spec = SPECS[model]
    noisy, _, truth = simulate_pairs(np.random.default_rng(6), 200, model,
                                     motion='single_axis', sigma_a=(0.0, 0.0))
    problem = Problem(spec, noisy.pos_a, noisy.quat_a, noisy.pos_b, noisy.quat_b,
                      whitening(noise_covariance((5e-4, 2e-3)), spec, 'b'),
                      whitening(noise_covariance((2e-4, 5e-4)), None, 'a'))
    start = Parameters.from_transforms(spec, truth.p0, truth.q0, truth.markers, truth.q1)
    sol = solve_ols(problem, start)
    with pytest.raises(UnobservableError) as info:
        check_observability(sol.info, sol.params, noisy.quat_a)
    msg = str(info.value)
    assert 'unobservable' in msg and 'rotate about a second axis' in msg
    name = 'tool-to-marker translation' if spec.n_markers == 1 else 'marker'
    assert any(name in d for d in info.value.directions), info.value.directions
    # and the well-posed problem passes
    noisy, _, truth = simulate_pairs(np.random.default_rng(6), 200, model, sigma_a=(0.0, 0.0))
    problem = Problem(spec, noisy.pos_a, noisy.quat_a, noisy.pos_b, noisy.quat_b,
                      problem.whiten_b, problem.whiten_a)
    sol = solve_ols(problem, Parameters.from_transforms(spec, truth.p0, truth.q0,
                                                        truth.markers, truth.q1))
    check_observability(sol.info, sol.params, noisy.quat_a)

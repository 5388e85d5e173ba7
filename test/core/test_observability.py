"""
Tests of what the motion determines (core.calibration.observability).

A motion that leaves directions undetermined (rotation about one axis, none) is calibrated with
those directions held, named and marked unknown; only a tool that did not move is refused, with
the reason.
"""

from coreg_ros.core import quaternion as quat
from coreg_ros.core.calibration import calibrate as calibrate_module
from coreg_ros.core.calibration.calibrate import calibrate
from coreg_ros.core.calibration.observability import (
    rotation_spread,
    undetermined,
    UNKNOWN_VARIANCE,
)
from coreg_ros.core.errors import CoregError, UnobservableError
from coreg_ros.core.estimator import noise_covariance, ols_information, Problem, whitening
from coreg_ros.core.models import Parameters, SPECS
from coreg_ros.core.settings import Settings
from coreg_ros.sim import make_motion, random_truth, simulate_pairs
import numpy as np
import pytest

MODELS = tuple(SPECS)
METHODS = ('ols', 'tls')


def single_axis_null(truth, rng_seed=None, quat_a=None) -> np.ndarray:
    """
    Return the analytic null direction of rotation about one tool axis u ((T0, T1) layout).

    R_A u = a is constant (A's base frame): shifting every marker by t·u (tool frame) moves B's
    measurements by t·R0 a, which T0's translation takes back: (δp0, δθ0, δp1, δθ1) ∝
    (-R0 a, 0, u, 0).
    """
    spread, axes = rotation_spread(quat_a)
    u = axes[0]
    a = quat.to_matrix(quat_a[0]) @ u
    out = np.concatenate([-quat.to_matrix(truth.q0) @ a, np.zeros(3), u, np.zeros(3)])
    return out / np.linalg.norm(out)


def angle_deg(u, v) -> float:
    """Angle between two directions (either sign), degrees."""
    c = abs(float(np.dot(u, v))) / (np.linalg.norm(u) * np.linalg.norm(v))
    return float(np.degrees(np.arccos(min(1.0, c))))


@pytest.mark.parametrize('model', MODELS)
@pytest.mark.parametrize('method', METHODS)
def test_single_axis_rotation_is_held_and_named(model, method):
    noisy, _, truth = simulate_pairs(np.random.default_rng(1), 400, model, motion='single_axis')
    result = calibrate(noisy, Settings(model=model, method=method))
    assert result.success
    assert [u.by for u in result.unobservable] == ['held']
    held = result.unobservable[0]
    assert angle_deg(held.direction, single_axis_null(truth, quat_a=noisy.quat_a)) < 1.0
    assert "T1's position" in held.description and "T0's translation" in held.description
    assert 'rotating the tool about a second axis' in held.determine
    assert held.held_at['component'].startswith('tool_to_marker position')
    # the published covariance is unknown along the held direction, determined elsewhere
    C = result.cov_joint
    along = float(held.direction @ C @ held.direction)
    # (three markers: the (T0, T1) layout holds marker 1 only, half of the direction's length)
    assert along > (0.45 if model == 'three_marker' else 0.9) * UNKNOWN_VARIANCE
    assert np.sqrt(np.diag(C)[3:6]).max() < 0.01  # T0's rotation: determined (rad)
    if model == 'three_marker':
        assert held.markers is not None and held.markers.shape == (9,)


@pytest.mark.parametrize('model', MODELS)
@pytest.mark.parametrize('method', METHODS)
@pytest.mark.parametrize('preset', ['no_rotation', 'static'])
def test_no_rotation_holds_the_lever_and_a_still_tool_is_refused(model, method, preset):
    noisy, _, _ = simulate_pairs(np.random.default_rng(2), 150, model, motion=preset)
    settings = Settings(model=model, method=method)
    if preset == 'no_rotation':
        # a gantry: T1's position against T0's translation, three directions; T0's rotation
        # and (full pose) T1's are determined by the translations
        result = calibrate(noisy, settings)
        assert result.success and len(result.held) == 3
        assert all("T1's position" in u.description for u in result.held)
        blocks = np.array([u.direction for u in result.held])
        assert np.abs(blocks[:, 3:6]).max() < 1e-6 and np.abs(blocks[:, 9:12]).max() < 1e-6
        return
    with pytest.raises(UnobservableError) as info:
        calibrate(noisy, settings)
    msg = str(info.value)
    assert '\n' not in msg
    for words in ('did not move', 'nothing can be estimated', 'move and rotate the tool'):
        assert words in msg, f'{words!r} not in {msg!r}'
    assert len(info.value.directions) == 1
    assert isinstance(info.value, CoregError)


def test_rotation_at_the_noise_level_counts_as_none():
    """A tool held still but measured with rotation noise has not rotated: nothing borrowed."""
    noisy, _, _ = simulate_pairs(np.random.default_rng(3), 300, 'full_pose',
                                 motion='no_rotation', sigma_a=(2e-4, 5e-3))
    spread, _ = rotation_spread(noisy.quat_a)
    assert spread[0] > 0.004  # measurable jitter, yet far below real motion
    result = calibrate(noisy, Settings(model='full_pose', sigma_a=(2e-4, 5e-3)))
    assert result.success and len(result.held) == 3


@pytest.mark.parametrize('model', MODELS)
@pytest.mark.parametrize('method', METHODS)
def test_diverse_motion_determines_everything(model, method):
    noisy, _, _ = simulate_pairs(np.random.default_rng(4), 150, model, motion='diverse')
    r = calibrate(noisy, Settings(model=model, method=method))
    assert r.success and r.param_cov is not None and r.unobservable == ()
    variances = np.diag(r.cov_joint)
    # nothing unknown anywhere (-1: T1's orientation, which the position models do not have)
    assert np.sqrt(variances[variances > 0]).max() < 0.01
    assert (variances > 0).sum() == (12 if model == 'full_pose' else 9)


@pytest.mark.parametrize('motion', ['diverse', 'single_axis', 'no_rotation'])
def test_the_analysis_of_a_long_recording_reads_a_subsample_to_the_same_answer(
        monkeypatch, motion):
    """Every k-th pair (OBSERVABILITY_SAMPLE) gives the directions all pairs give."""
    noisy, _, _ = simulate_pairs(np.random.default_rng(7), 4000, 'full_pose', motion=motion,
                                 sigma_a=(2e-4, 2e-3))
    full, _ = rotation_spread(noisy.quat_a)
    sub, _ = rotation_spread(noisy.quat_a[::4])
    np.testing.assert_allclose(sub, full, rtol=0.05, atol=1e-3)
    settings = Settings(sigma_a=(2e-4, 2e-3))
    everything = calibrate(noisy, settings)
    monkeypatch.setattr(calibrate_module, 'OBSERVABILITY_SAMPLE', 1000)  # every 4th of 4000
    sampled = calibrate(noisy, settings)
    expected = {'diverse': 0, 'single_axis': 1, 'no_rotation': 3}[motion]
    assert len(everything.held) == len(sampled.held) == expected
    if expected:  # the same subspace: every principal angle below 0.1°
        a = np.linalg.qr(np.array([u.direction for u in everything.held]).T)[0]
        b = np.linalg.qr(np.array([u.direction for u in sampled.held]).T)[0]
        cosines = np.linalg.svd(a.T @ b, compute_uv=False)
        assert np.degrees(np.arccos(np.clip(cosines.min(), -1.0, 1.0))) < 0.1


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
def test_the_information_names_the_null_direction(model):
    """The analysis on its own, at the truth: one direction for single-axis data, none else."""
    spec = SPECS[model]
    noisy, _, truth = simulate_pairs(np.random.default_rng(6), 200, model,
                                     motion='single_axis', sigma_a=(0.0, 0.0))
    problem = Problem(spec, noisy.pos_a, noisy.quat_a, noisy.pos_b, noisy.quat_b,
                      whitening(noise_covariance((5e-4, 2e-3)), spec, 'b'),
                      whitening(noise_covariance((2e-4, 5e-4)), None, 'a'))
    at = Parameters.from_transforms(spec, truth.p0, truth.q0, truth.markers, truth.q1)
    found = undetermined(ols_information(problem, at), None, at, 0.0)
    assert found.held.shape[1] == 1 and found.by_prior.shape[1] == 0
    u = found.held[:, 0]
    null = single_axis_null(truth, quat_a=noisy.quat_a)
    assert angle_deg(np.concatenate([u[0:9], np.zeros(3)]) if spec.n_params != 12 else u,
                     null) < 0.01
    # and the well-posed problem has none
    noisy, _, truth = simulate_pairs(np.random.default_rng(6), 200, model, sigma_a=(0.0, 0.0))
    problem = Problem(spec, noisy.pos_a, noisy.quat_a, noisy.pos_b, noisy.quat_b,
                      problem.whiten_b, problem.whiten_a)
    at = Parameters.from_transforms(spec, truth.p0, truth.q0, truth.markers, truth.q1)
    assert undetermined(ols_information(problem, at), None, at, 0.0).empty


@pytest.mark.parametrize('method', METHODS)
def test_holding_directions_costs_no_gauss_newton_pass(method):
    """
    A restricted rig's fit converges in as many passes as a full-rank one (random draws).

    The gauge that holds the undetermined directions is a convention far tighter than the
    data; damped by Marquardt's scale like information it stiffened the steps of every
    component coupled to it, and a turntable crawled (3-5 passes where a full-rank rig takes
    2-3, and it stopped short of the minimum: ``priors.gauge_diagonal``).
    """
    sa, sb = (5e-5, 2e-4), (2e-4, 1e-3)
    settings = Settings(method=method, sigma_a=sa, sigma_b=sb, robust=False)
    passes = {}
    for rig in ('diverse', 'scara', 'planar', 'gantry', 'turntable'):
        passes[rig] = []
        for seed in range(4):
            rng = np.random.default_rng(300 + seed)
            truth, motion = random_truth(rng, 'full_pose'), make_motion(rng, rig)
            pairs, _, _ = simulate_pairs(rng, 20_000, 'full_pose', sigma_a=sa, sigma_b=sb,
                                         truth=truth, motion=motion)
            result = calibrate(pairs, settings)
            assert result.success and bool(result.held) == (rig != 'diverse')
            passes[rig].append(result.iterations)
    full_rank = max(passes.pop('diverse'))
    assert all(max(p) <= full_rank for p in passes.values()), (full_rank, passes)

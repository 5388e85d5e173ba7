"""
Tests of coreg_ros.core.planning.plan and the ``coreg plan`` command.

The bound is checked against the estimator's own posterior covariance on a simulated
recording, and the registration error against an independent propagation path
(``uncertainty.through_calibration`` with the bound as the calibration covariance).
"""

import argparse
import json
from pathlib import Path

from coreg_ros.cli import plan as plan_cli
from coreg_ros.core import quaternion as quat
from coreg_ros.core import uncertainty as unc
from coreg_ros.core.calibration.calibrate import calibrate
from coreg_ros.core.calibration.observability import rotation_spread
from coreg_ros.core.estimator import noise_covariance
from coreg_ros.core.planning.plan import (
    plan_recording,
    predict_accuracy,
)
from coreg_ros.core.settings import Settings
from coreg_ros.core.types import CalibrationResult, UncertainPose
from coreg_ros.sim import make_motion, random_truth, simulate_pairs
import numpy as np
import pytest

SIGMA_A, SIGMA_B = (2e-4, 5e-4), (5e-4, 2e-3)
COV_A, COV_B = noise_covariance(SIGMA_A), noise_covariance(SIGMA_B)
SAMPLE_BAG = Path(__file__).resolve().parents[2] / 'bags' / 'sample_full_pose'


def motion_samples(preset, n=1500, rate=50.0, seed=1):
    return make_motion(np.random.default_rng(seed), preset).pose(np.arange(n) / rate)


def test_bound_matches_the_estimators_posterior_covariance():
    rng = np.random.default_rng(3)
    pairs, clean, truth = simulate_pairs(rng, 1500, sigma_a=SIGMA_A, sigma_b=SIGMA_B)
    result = calibrate(pairs, Settings(sigma_a=SIGMA_A, sigma_b=SIGMA_B))
    pred = predict_accuracy('full_pose', truth.p0, truth.q0, truth.markers, clean.pos_a,
                            clean.quat_a, COV_A, COV_B)
    # same information, at the truth vs at the estimate: equal to well within 5 %
    np.testing.assert_allclose(np.sqrt(np.diag(pred.crlb)),
                               np.sqrt(np.diag(result.cov_joint)), rtol=0.05)


def test_registration_rms_agrees_with_uncertainty_propagation():
    truth = random_truth(np.random.default_rng(4))
    pos, q = motion_samples('diverse', n=600)
    pred = predict_accuracy('full_pose', truth.p0, truth.q0, truth.markers, pos, q, COV_A, COV_B)
    result = CalibrationResult(
        success=True, status=1, message='', model='full_pose', method='tls', n_pairs=len(pos),
        base_to_base=UncertainPose(truth.p0, truth.q0, pred.crlb[0:6, 0:6]),
        tool_to_marker=UncertainPose(truth.p1, truth.q1, pred.crlb[6:12, 6:12]),
        markers=truth.markers, params=np.zeros(12), param_cov=None, chi2=0.0, dof=1,
        p_value=0.5, residuals=np.zeros((0, 6)), iterations=0, cov_joint=pred.crlb)
    _, _, cov = unc.through_calibration_arrays(result, pos, q, np.zeros((6, 6)))
    rms_pos = np.sqrt(np.mean(np.trace(cov[:, 0:3, 0:3], axis1=1, axis2=2)))
    rms_rot = np.sqrt(np.mean(np.trace(cov[:, 3:6, 3:6], axis1=1, axis2=2)))
    np.testing.assert_allclose(pred.registration_rms, [rms_pos, rms_rot], rtol=1e-9)


def test_more_of_the_same_scales_as_one_over_root_n():
    truth = random_truth(np.random.default_rng(5))
    pos, q = motion_samples('diverse', n=800)
    plan = plan_recording('full_pose', truth.p0, truth.q0, truth.markers, pos, q, COV_A, COV_B,
                          rate=50.0, extra=1.0)
    longer = next(c for c in plan.candidates if c.name == 'longer')
    assert longer.gain == pytest.approx(np.sqrt(2.0), rel=1e-6)
    assert longer.prediction.n_pairs == 1600
    np.testing.assert_allclose(longer.prediction.crlb, plan.baseline.prediction.crlb / 2,
                               rtol=1e-6, atol=1e-20)
    assert plan.best.gain >= longer.gain


def test_single_axis_motion_is_unobservable_and_the_plan_says_how_to_fix_it():
    """One direction unobservable: named before recording, the rest bounded, the fix found."""
    truth = random_truth(np.random.default_rng(6))
    pos, q = motion_samples('single_axis')
    plan = plan_recording('full_pose', truth.p0, truth.q0, truth.markers, pos, q, COV_A, COV_B,
                          rate=50.0)
    base = plan.baseline.prediction
    assert base is not None and len(base.unobservable) == 1
    direction, words, determine = base.unobservable[0]
    assert "T1's position" in words and "T0's translation" in words
    assert 'rotating the tool about a second axis' in determine
    # the tool axis it turns about: T1's offset along it is what the motion cannot show
    _, axes = rotation_spread(q)
    assert abs(abs(direction[6:9] @ axes[0]) / np.linalg.norm(direction[6:9]) - 1.0) < 1e-6
    # the bound of the rest is finite; rotating about the weakest axis determines it all, and
    # more of the same motion never does
    assert all(np.isfinite(v).all() for v in base.sigma.values())
    by_name = {c.name: c.prediction for c in plan.candidates}
    assert by_name['rotate_weakest_axis'].unobservable == ()
    assert len(by_name['longer'].unobservable) == 1


def test_weakest_axis_is_the_one_not_rotated_about():
    t = np.linspace(0, 60, 1500)
    r = np.stack([0.6 * np.sin(0.3 * t), 0.4 * np.sin(0.17 * t + 1), 0.02 * np.sin(t)], axis=1)
    q0 = quat.exp([0.3, -1.0, 0.5])
    q = quat.multiply(q0, quat.exp(r))
    spread, axes = rotation_spread(q)  # descending; axes as rows, least excited last
    assert spread[2] < 0.05 < spread[1] < spread[0]
    assert abs(axes[2, 2]) > 0.99  # tool z


@pytest.mark.parametrize('model', ['position_only', 'three_marker'])
def test_other_models(model):
    truth = random_truth(np.random.default_rng(7), model)
    pos, q = motion_samples('diverse', n=600)
    plan = plan_recording(model, truth.p0, truth.q0, truth.markers, pos, q, COV_A, COV_B, 50.0)
    pred = plan.baseline.prediction
    assert np.isnan(pred.registration_rms[1]) and pred.registration_rms[0] > 0
    assert 'theta1' not in pred.sigma
    assert ('p3' in pred.sigma) == (model == 'three_marker')


def run_plan(argv):
    parser = argparse.ArgumentParser(prog='coreg')
    sub = parser.add_subparsers(dest='command')
    plan_cli.register(sub)
    args = parser.parse_args(['plan', *argv])
    return args.func(args)


def test_cli_plan_simulated(tmp_path, capsys):
    out = tmp_path / 'plan.json'
    assert run_plan(['--sigma-a', '2e-4', '5e-4', '--sigma-b', '5e-4', '2e-3', '--duration',
                     '20', '--motion', 'diverse', '--rate-b', '25', '--json', str(out)]) == 0
    text = capsys.readouterr().out
    assert 'Cramér-Rao' in text and 'what would improve it most' in text
    data = json.loads(out.read_text())
    assert data['baseline']['n_pairs'] == 500
    assert {c['name'] for c in data['candidates']} == {'longer', 'rotate_weakest_axis',
                                                       'wider_translation'}


@pytest.mark.skipif(not SAMPLE_BAG.exists(), reason='sample bag not shipped')
def test_cli_plan_from_bag_uses_its_calibration(capsys):
    assert run_plan(['--sigma-a', '2e-4', '5e-4', '--sigma-b', '5e-4', '2e-3', '--bag',
                     str(SAMPLE_BAG)]) == 0
    text = capsys.readouterr().out
    assert 'bound at the calibration of the bag' in text
    assert 'paired instants of B' in text


def test_cli_plan_rejects_both_sources():
    with pytest.raises(SystemExit):
        run_plan(['--sigma-a', '1', '1', '--sigma-b', '1', '1', '--duration', '1', '--bag',
                  'x'])


def test_plan_is_registered_in_coreg(capsys):
    from coreg_ros.cli.main import main

    assert main(['plan', '--sigma-a', '2e-4', '5e-4', '--sigma-b', '5e-4', '2e-3',
                 '--duration', '10', '--motion', 'single_axis']) == 0
    assert 'unobservable with this motion' in capsys.readouterr().out
    assert main(['plan', '--sigma-a', '2e-4', '5e-4', '--sigma-b', '5e-4', '2e-3',
                 '--duration', '10', '--motion', 'static']) == 0
    assert 'UNOBSERVABLE: this motion determines nothing' in capsys.readouterr().out

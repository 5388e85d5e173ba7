"""Tests of the stream-direction check (core.stream_directions) and its use in calibrate."""

import json

from coreg_ros.cli.main import main
from coreg_ros.core import quaternion as quat
from coreg_ros.core.calibration.stream_directions import (
    check_directions,
    DirectionFit,
    DirectionReport,
    MAX_PAIRS,
)
from coreg_ros.core.settings import Settings
from coreg_ros.core.so3 import invert_poses
from coreg_ros.core.types import PoseStream
from coreg_ros.files.bag.posebag import write_pose_bag
from coreg_ros.sim import simulate_recording
import numpy as np
import pytest

A = '/device_a/pose'
B = '/device_b/pose'


def inverted(s: PoseStream) -> PoseStream:
    p, q = invert_poses(s.position, s.quat_wxyz)
    return PoseStream(s.stamps, p, q, s.frame_id)


@pytest.fixture(scope='module')
def rec():
    return simulate_recording(21, 60.0)


def test_invert_poses_is_an_involution_and_an_inverse():
    rng = np.random.default_rng(1)
    p = rng.normal(size=(50, 3))
    q = quat.canonical(quat.exp(rng.normal(size=(50, 3)) * 1.5))
    ip, iq = invert_poses(p, q)
    pp, qq = invert_poses(ip, iq)
    assert np.allclose(pp, p) and np.allclose(qq, q)
    # T · T⁻¹ = identity
    R = quat.to_matrix(q)
    assert np.allclose(np.einsum('nij,nj->ni', R, ip) + p, 0.0, atol=1e-12)
    assert np.allclose(quat.canonical(quat.multiply(q, iq)), [1, 0, 0, 0], atol=1e-12)
    assert np.all(iq[:, 0] >= 0)


def test_correct_recording_is_not_flagged(rec):
    report = check_directions(rec.stream_a, rec.streams_b, Settings())
    assert len(report.fits) == 4
    assert report.best is report.as_given and not report.flagged
    assert report.as_given.chi2_dof < 1.5
    assert 'as given fit best' in report.message
    assert report.as_given.rms_position_m < 0.002
    assert all(f.n_pairs <= MAX_PAIRS for f in report.fits)
    json.dumps(report.as_dict())


@pytest.mark.parametrize('invert_a, invert_b, flag, device', [
    (False, True, '--invert-b', 'device B inverted'),
    (True, False, '--invert-a', 'device A inverted'),
])
def test_inverted_stream_is_detected_and_the_flag_named(rec, invert_a, invert_b, flag, device):
    a = inverted(rec.stream_a) if invert_a else rec.stream_a
    b = inverted(rec.streams_b[0]) if invert_b else rec.streams_b[0]
    report = check_directions(a, [b], Settings())
    assert report.flagged and report.ratio > 100
    assert (report.best.invert_a, report.best.invert_b) == (invert_a, invert_b)
    assert report.best.flags == flag
    assert flag in report.message and device in report.message
    assert report.as_dict()['flags'] == flag
    assert report.best.chi2_dof < 1.5


def test_position_only_checks_a_only():
    rec = simulate_recording(22, 60.0, 'position_only')
    settings = Settings(model='position_only')
    good = check_directions(rec.stream_a, rec.streams_b, settings)
    assert len(good.fits) == 2 and not good.flagged
    bad = check_directions(inverted(rec.stream_a), rec.streams_b, settings)
    assert bad.flagged and bad.best.flags == '--invert-a'


def test_report_arithmetic_and_failed_fits():
    fits = (DirectionFit(False, False, 500.0, 0.05, 100),
            DirectionFit(True, False, float('inf'), float('inf'), 100, 'did not converge'),
            DirectionFit(False, True, 2.0, 0.001, 100),
            DirectionFit(True, True, 60.0, 0.01, 100))
    report = DirectionReport(fits)
    assert report.best.label == 'B inverted' and report.ratio == pytest.approx(250.0)
    assert report.flagged and 'fit 250× better with device B inverted' in report.message
    d = report.as_dict()
    assert d['fits'][1]['chi2_dof'] is None and d['fits'][1]['error'] == 'did not converge'
    assert report.alternative is None                 # A and B inverted: only 8.3×
    both = DirectionReport(fits[:3] + (DirectionFit(True, True, 0.5, 0.001, 100),))
    assert both.best.label == 'A and B inverted' and both.alternative is None
    swapped = DirectionReport((fits[0], DirectionFit(True, False, 1.0, 0.001, 100),
                               DirectionFit(False, True, 4.0, 0.001, 100), fits[3]))
    assert swapped.best.flags == '--invert-a' and swapped.alternative.flags == '--invert-b'
    assert '--invert-a (or --invert-b)' in swapped.message
    assert swapped.as_dict()['alternative_flags'] == '--invert-b'
    mild = DirectionReport((fits[0], DirectionFit(True, True, 100.0, 0.01, 100)))
    assert not mild.flagged and 'below the 10×' in mild.message


# ------------------------------------------------------------------------------ calibrate

def write_bag(path, a, b):
    write_pose_bag(path, {A: a, B: b})
    return str(path)


def test_calibrate_refuses_a_wrongly_directed_recording(tmp_path, rec, capsys):
    bag = write_bag(tmp_path / 'bag', rec.stream_a, inverted(rec.streams_b[0]))
    out = tmp_path / 'r.json'
    code = main(['calibrate', bag, '--method', 'ols', '--json', str(out)])
    captured = capsys.readouterr()
    assert code == 1
    assert 'better with device B inverted' in captured.err and '--invert-b' in captured.err
    assert captured.err.count('\n') == 1
    data = json.loads(out.read_text())
    assert data['direction_check']['flagged'] and data['direction_check']['flags'] == '--invert-b'
    # and the check can be skipped: the (bad) fit is then returned as is
    code = main(['calibrate', bag, '--method', 'ols', '--no-direction-check'])
    captured = capsys.readouterr()
    assert 'direction check' not in captured.out + captured.err
    assert 'chi2/dof' in captured.out


def test_calibrate_good_recording_runs_no_check(tmp_path, rec, capsys):
    bag = write_bag(tmp_path / 'bag', rec.stream_a, rec.streams_b[0])
    out = tmp_path / 'r.json'
    assert main(['calibrate', bag, '--json', str(out)]) == 0
    assert 'direction_check' not in json.loads(out.read_text())
    assert 'direction check' not in capsys.readouterr().out


# ------------------------------------------------- the check in the shared pipeline (issue 21)


def test_the_front_door_refuses_a_wrongly_directed_stream(rec):
    """coreg_ros.calibrate runs the pipeline's check: an inverted B is no success, and named."""
    import coreg_ros as cr
    a, b = rec.stream_a, inverted(rec.streams_b[0])
    res = cr.calibrate(a.position, a.quat_wxyz, b.position, b.quat_wxyz, method='ols',
                       stamps_a=a.stamps, stamps_b=b.stamps,
                       sigma_a=rec.truth.sigma_a, sigma_b=rec.truth.sigma_b)
    assert not res.success
    assert res.direction_check is not None and res.direction_check.flagged
    assert res.direction_check.best.flags == '--invert-b'
    assert 'wrong way round' in res.verdict and '--invert-b' in res.verdict
    # a good recording is not checked at all (good data pay nothing)
    good = cr.calibrate(a.position, a.quat_wxyz, rec.streams_b[0].position,
                        rec.streams_b[0].quat_wxyz, stamps_a=a.stamps,
                        stamps_b=rec.streams_b[0].stamps, sigma_a=rec.truth.sigma_a,
                        sigma_b=rec.truth.sigma_b)
    assert good.success and good.direction_check is None


def test_pipeline_check_can_be_turned_off(rec):
    from coreg_ros.core.calibration.pipeline import calibrate_streams
    settings = Settings(method='ols', sigma_a=rec.truth.sigma_a, sigma_b=rec.truth.sigma_b)
    b = inverted(rec.streams_b[0])
    checked, _ = calibrate_streams(rec.stream_a, [b], settings)
    as_given, _ = calibrate_streams(rec.stream_a, [b], settings, direction_check=False)
    assert checked.direction_check.flagged and not checked.success
    assert as_given.direction_check is None and as_given.fit_consistent is False
    # the check changes no number of the fit, only whether it is accepted
    assert np.array_equal(checked.params, as_given.params)


def test_unobservable_error_keeps_its_directions_through_the_pipeline():
    """A tool that never moved, B in mm: the units note is added, the directions kept."""
    import coreg_ros as cr
    from coreg_ros.core.errors import UnobservableError
    r = simulate_recording(5, 30.0, motion='static')
    a, b = r.stream_a, r.streams_b[0]
    with pytest.raises(UnobservableError) as direct:
        cr.calibrate(a.position, a.quat_wxyz, b.position, b.quat_wxyz, stamps_a=a.stamps,
                     stamps_b=b.stamps)
    assert direct.value.directions
    with pytest.raises(UnobservableError) as mm:
        cr.calibrate(a.position, a.quat_wxyz, b.position * 1000.0, b.quat_wxyz,
                     stamps_a=a.stamps, stamps_b=b.stamps)
    assert 'but first' in str(mm.value) and 'mm' in str(mm.value)
    assert mm.value.directions == direct.value.directions

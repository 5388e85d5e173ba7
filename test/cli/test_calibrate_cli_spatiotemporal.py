"""`coreg calibrate` with the clock offset, priors and the verdict, as a user runs it."""

from dataclasses import replace
import json

from coreg_ros.cli.main import main
from coreg_ros.cli.options import EXIT_INCONSISTENT
from coreg_ros.core.so3 import invert_poses
from coreg_ros.files.bag.posebag import write_pose_bag
from coreg_ros.sim import simulate_recording
import numpy as np
import pytest

A, B = '/device_a/pose', '/device_b/pose'


@pytest.fixture(scope='module')
def rec():
    return simulate_recording(71, 20.0)


def _bag(tmp_path, rec, name='bag', shift_s=0.0, b_transform=None):
    streams = dict(rec.streams)
    b = streams[B]
    if b_transform is not None:
        b = b_transform(b)
    streams[B] = replace(b, stamps=b.stamps + np.int64(round(shift_s * 1e9)))
    path = tmp_path / name
    write_pose_bag(path, streams)
    return str(path)


def test_offset_auto_and_fixed_in_the_json(tmp_path, rec, capsys):
    bag = _bag(tmp_path, rec, shift_s=0.3)
    assert main(['calibrate', bag, '--json', '-']) == 0
    data = json.loads(capsys.readouterr().out)
    t = data['time_offset']
    assert t['estimated'] and abs(t['value_s'] - 0.3) < 3 * t['sigma_s'] + 1e-6
    assert data['fit_consistent'] is True and data['rejected_pairs']['count'] <= 2
    assert main(['calibrate', bag, '--time-offset', '0.3', '--json', '-']) == 0
    fixed = json.loads(capsys.readouterr().out)
    assert fixed['time_offset'] == {'value_s': 0.3, 'sigma_s': None, 'estimated': False,
                                    'message': 'given'}
    assert main(['calibrate', bag, '--clock-drift', 'auto', '--json', '-']) == 0
    drift = json.loads(capsys.readouterr().out)['clock_drift']
    assert abs(drift['value_ppm']) < 4 * drift['sigma_ppm']


def test_prior_file_refines_and_bad_prior_is_one_line(tmp_path, rec, capsys):
    bag = _bag(tmp_path, rec)
    first = tmp_path / 'first.json'
    # the prior: an earlier recording of the same rig (a prior from these very samples would
    # count them twice, and is refused: test_new_user_faults.py)
    earlier = simulate_recording(72, 20.0, truth=rec.truth)
    assert main(['calibrate', _bag(tmp_path, earlier, 'earlier'), '--json', str(first)]) == 0
    capsys.readouterr()
    assert main(['calibrate', bag, '--prior', str(first), '--json', '-']) == 0
    data = json.loads(capsys.readouterr().out)
    assert data['prior_check']['consistent']
    partial = tmp_path / 'cad.yaml'
    partial.write_text('tool_to_marker:\n  position: [0.1, 0.0, 0.05]\n'
                       '  sigma: [0.0001, 0.0001, 0.0001, .inf, .inf, .inf]\n')
    code = main(['calibrate', bag, '--prior', str(partial)])
    out = capsys.readouterr()
    assert code == EXIT_INCONSISTENT and 'prior disagrees' in out.out  # the CAD guess is off
    bad = tmp_path / 'bad.yaml'
    bad.write_text('tool_to_marker: {position: [0, 0, 0], sigma: [1, 2]}\n')
    assert main(['calibrate', bag, '--prior', str(bad)]) == 1
    err = capsys.readouterr().err
    assert err.count('\n') == 1 and 'sigma must be 6' in err


def test_millimetres_read_as_metres_exit_3_and_named(tmp_path, rec, capsys):
    bag = _bag(tmp_path, rec, b_transform=lambda b: replace(b, position=b.position * 1000))
    out = tmp_path / 'r.json'
    code = main(['calibrate', bag, '--json', str(out), '--no-direction-check'])
    text = capsys.readouterr()
    if code == 1:  # refused as a whole: still one line that names the units
        assert 'units' in text.err and text.err.count('\n') == 1
        return
    assert code == EXIT_INCONSISTENT
    data = json.loads(out.read_text())
    assert data['fit_consistent'] is False and 'mm' in data['verdict']
    assert data['rescaled_covariance']['factor'] > 1.0


def test_wrong_direction_found_at_the_right_offset(tmp_path, rec, capsys):
    def invert(b):
        p, q = invert_poses(b.position, b.quat_wxyz)
        return replace(b, position=p, quat_wxyz=q)

    bag = _bag(tmp_path, rec, shift_s=-0.45, b_transform=invert)
    code = main(['calibrate', bag])
    err = capsys.readouterr().err
    assert code == 1 and 'device B inverted' in err and '--invert-b' in err, err

"""
``coreg noise`` and ``--noise FILE|auto`` as a user runs them (issue 24), and their refusals.

One simulated recording whose tool stops twice (``sim.still.paused``): its noise measured,
written to a noise file, read back by calibrate and plan; ``--noise auto`` naming the device
stated at half its noise, and ``coreg diagnose`` taking the estimate as its floor; the Python
front door's ``noise=``; bad input refused in one line.
"""

import json

from coreg_ros.cli.main import main
from coreg_ros.files.bag.posebag import write_pose_bag
from coreg_ros.files.noise_file import load_noise_file
from coreg_ros.sim import make_motion, simulate_recording
from coreg_ros.sim.still import paused
import numpy as np
import pytest

SIGMA_A, SIGMA_B = (2e-4, 1e-3), (6e-4, 3e-3)


def _run(capsys, *args):
    code = main([str(a) for a in args])
    out, err = capsys.readouterr()
    return code, out, err


def one_line(code, err) -> bool:
    return code == 1 and 'Traceback' not in err and err.strip().count('\n') == 0 and \
        'error:' in err


@pytest.fixture(scope='module')
def bag(tmp_path_factory):
    motion = paused(make_motion(np.random.default_rng(9), 'diverse'), [(4.0, 7.0), (20.0, 7.0)])
    rec = simulate_recording(9, 34.0, rate_a=100.0, rate_b=100.0, sigma_a=SIGMA_A,
                             sigma_b=SIGMA_B, motion=motion)
    path = tmp_path_factory.mktemp('noise') / 'still'
    write_pose_bag(path, rec.streams)
    return path


def test_noise_measures_both_devices_and_writes_a_noise_file(bag, tmp_path, capsys):
    out_file, plot = tmp_path / 'n.yaml', tmp_path / 'n.png'
    code, out, err = _run(capsys, 'noise', bag, '--json', '-', '--out', out_file,
                          '--plot', plot)
    assert code == 0, err
    doc = json.loads(out)
    for device, truth in (('device_a', SIGMA_A), ('device_b', SIGMA_B)):
        d = doc[device]
        assert np.shape(d['position_covariance']) == (3, 3)
        assert np.shape(d['rotation_covariance']) == (3, 3)
        assert np.all(np.abs(np.array(d['position_sigma_m']) / truth[0] - 1) < 0.15), d
        assert np.all(np.abs(np.array(d['rotation_sigma_rad']) / truth[1] - 1) < 0.15), d
        assert len(d['segments']) == 2 and d['segments'][0]['start_s'] > 3.9
        assert d['allan']['position']['tau_s'] and d['sampling']['dropped'] == 0
    assert 'device A (/device_a/pose' in err and 'noise file written' in err
    assert plot.read_bytes()[:4] == b'\x89PNG'
    got = load_noise_file(out_file)
    assert got.topics == {'a': '/device_a/pose', 'b': ('/device_b/pose',)}
    np.testing.assert_allclose(got.device_b.position_cov, doc['device_b']['position_covariance'])


def test_calibrate_reads_the_noise_file_and_auto_names_the_misstated_device(
        bag, tmp_path, capsys):
    noise_file = tmp_path / 'n.yaml'
    assert _run(capsys, 'noise', bag, '--out', noise_file)[0] == 0
    code, out, err = _run(capsys, 'calibrate', bag, '--noise', noise_file, '--json', '-')
    assert code == 0, out + err
    doc = json.loads(out)
    assert doc['noise']['device_b']['estimated'] is False and doc['fit_consistent']
    np.testing.assert_allclose(doc['noise']['device_b']['position_covariance'],
                               load_noise_file(noise_file).device_b.position_cov)
    # B stated at half its noise: inconsistent as stated, named with --noise auto
    half = [f'{v / 2:g}' for v in SIGMA_B]
    code, out, err = _run(capsys, 'calibrate', bag, '--sigma-b', *half)
    assert code == 3, err
    code, out, err = _run(capsys, 'calibrate', bag, '--sigma-b', *half, '--noise', 'auto',
                          '--json', '-')
    assert code == 0, err
    doc = json.loads(out)
    b = doc['noise']['device_b']
    assert b['estimated'] is True and b['sigma_of_estimate']['rotation_sigma_rad']
    ratio = np.array(b['rotation_sigma_rad']) / np.array(b['stated']['rotation_sigma_rad'])
    assert np.all(np.abs(ratio - 2.0) < 0.3), ratio
    assert 'B rotation noise' in doc['verdict'] and 'B rotation noise' in err
    assert 'consistent with the estimated noise' in err


def test_plan_reads_the_noise_file(bag, tmp_path, capsys):
    noise_file = tmp_path / 'n.yaml'
    assert _run(capsys, 'noise', bag, '--out', noise_file)[0] == 0
    code, out, err = _run(capsys, 'plan', '--noise', noise_file, '--duration', '10')
    assert code == 0 and 'predicted 1σ accuracy' in out, err
    code, _, err = _run(capsys, 'plan', '--duration', '10', '--sigma-a', '2e-4', '1e-3')
    assert one_line(code, err) and "device B's noise is needed" in err


def test_bad_noise_input_is_refused_in_one_line(bag, tmp_path, capsys):
    noise_file = tmp_path / 'n.yaml'
    assert _run(capsys, 'noise', bag, '--out', noise_file)[0] == 0
    cases = [
        (['calibrate', bag, '--noise', tmp_path / 'none.yaml'], 'cannot read the noise file'),
        (['calibrate', bag, '--noise', noise_file, '--sigma-a', '2e-4', '1e-3'],
         'give it once'),
        (['calibrate', bag, '--noise', noise_file, '--topic-b', '/other'],
         'device B noise is for topic /device_b/pose'),
        (['noise', bag, '--window', '9', '2'], 'the end must come after the start'),
    ]
    mm = tmp_path / 'mm.yaml'
    mm.write_text('coreg_noise:\n  units: {position: mm}\n  device_a:\n'
                  '    position_sigma_m: 0.2\n    rotation_sigma_rad: 0.001\n')
    cases.append((['calibrate', bag, '--noise', mm], 'noise is in mm; coreg reads m'))
    for args, text in cases:
        code, _, err = _run(capsys, *args)
        assert one_line(code, err) and text in err, (args, err)


def test_a_recording_that_never_stands_still_says_how_long_to_stand(tmp_path, capsys):
    rec = simulate_recording(10, 12.0, rate_a=100.0, rate_b=100.0)
    path = tmp_path / 'moving'
    write_pose_bag(path, rec.streams)
    code, _, err = _run(capsys, 'noise', path)
    assert one_line(code, err) and 'no still segment' in err and 'hold the device still' in err


def test_diagnose_auto_takes_the_estimated_noise_as_its_floor(bag, tmp_path, capsys):
    """B stated at half its noise: the floor is the estimate, the stated one said beside it."""
    half = [f'{v / 2:g}' for v in SIGMA_B]
    out_json = tmp_path / 'd.json'
    code, out, err = _run(capsys, 'diagnose', bag, '--sigma-b', *half, '--noise', 'auto',
                          '--json', out_json, '--quiet')
    assert code == 0, err
    assert 'noise floor: estimated with the calibration' in out and 'B rotation noise' in out
    # every gap measured against the estimate, and said so
    gap = next(line for line in out.splitlines() if line.startswith('gap (held out'))
    assert 'at the estimated noise' in gap and 'estimated floor' in gap and 'stated' not in gap
    noise = json.loads(out_json.read_text())['noise']
    b = noise['device_b']
    ratio = np.array(b['rotation_sigma_rad']) / np.array(b['stated']['rotation_sigma_rad'])
    assert b['estimated'] is True and np.all(np.abs(ratio - 2.0) < 0.3), ratio


def test_python_front_door_takes_auto_a_device_noise_dict_and_refuses_the_rest():
    import coreg_ros
    from coreg_ros.core.errors import CoregError
    from coreg_ros.core.noise_model import DeviceNoise
    from coreg_ros.sim import simulate_pairs
    noisy, _, _ = simulate_pairs(np.random.default_rng(4), 3000, 'full_pose', sigma_a=SIGMA_A,
                                 sigma_b=SIGMA_B)
    args = (noisy.pos_a, noisy.quat_a, noisy.pos_b, noisy.quat_b)
    half_b = tuple(v / 2 for v in SIGMA_B)
    auto = coreg_ros.calibrate(*args, sigma_a=SIGMA_A, sigma_b=half_b, noise='auto')
    assert auto.noise is not None and auto.fit_consistent
    # B's position and rotation halved: its rotation named alone; its position reaches the
    # pairs summed with A's, whose ratio is sqrt((σa² + σb²) / (σa² + σb²/4))
    said = {s.channels: s.ratio for s in auto.noise.misstated}
    assert set(said) == {(('b', 'rotation'),), (('a', 'position'), ('b', 'position'))}, said
    together = np.hypot(SIGMA_A[0], SIGMA_B[0]) / np.hypot(SIGMA_A[0], half_b[0])
    assert abs(said[(('a', 'position'), ('b', 'position'))] / together - 1) < 0.05, said
    assert abs(said[(('b', 'rotation'),)] / 2.0 - 1) < 0.05, said
    given = coreg_ros.calibrate(*args, noise={'a': DeviceNoise.isotropic(SIGMA_A),
                                              'b': DeviceNoise.isotropic(SIGMA_B)})
    assert given.noise is None and given.fit_consistent
    with pytest.raises(CoregError, match="noise must be 'stated', 'auto'"):
        coreg_ros.calibrate(*args, noise=3.0)

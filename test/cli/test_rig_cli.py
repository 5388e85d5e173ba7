"""`coreg calibrate` of a rig (issue 23): several B topics, a devices list, bad input."""

import glob
import json
import os

from coreg_ros.cli.main import main
from coreg_ros.files.bag.posebag import read_pose_bag, write_pose_bag
from coreg_ros.sim.rig import SimDevice, simulate_rig
import numpy as np
import pytest

A = '/robot/tool'
DEVICES = (SimDevice('optical', 'full_pose', 60.0, (3e-4, 1e-3), 0.004),
           SimDevice('em', 'position_only', 40.0, (5e-4, 2e-3), 125.0),
           SimDevice('camera', 'full_pose', 30.0, (1e-3, 4e-3), 3600.0))


@pytest.fixture(scope='module')
def rig_bag(tmp_path_factory):
    rig = simulate_rig(7, 20.0, DEVICES, sigma_a=(2e-4, 5e-4))
    streams = {A: rig.stream_a}
    for d, s in zip(DEVICES, rig.streams, strict=True):
        streams[f'/{d.name}/pose'] = s[0]
    path = tmp_path_factory.mktemp('rig') / 'bag'
    write_pose_bag(path, streams)
    return str(path), rig


def _config(tmp_path, extra=''):
    path = tmp_path / 'rig.yaml'
    path.write_text(
        'coreg_node:\n  ros__parameters:\n    topic_a: /robot/tool\n'
        '    devices: [optical, em, camera]\n    device:\n'
        '      optical: {topic: [/optical/pose], sigma: [0.0003, 0.001]}\n'
        '      em: {topic: /em/pose, model: position_only, sigma: [0.0005, 0.002]}\n'
        '      camera: {topic: [/camera/pose], sigma: [0.001, 0.004]}\n' + extra)
    return str(path)


def test_devices_list_in_the_config_gives_every_device_and_the_joint_covariance(
        tmp_path, rig_bag, capsys):
    bag, rig = rig_bag
    assert main(['calibrate', bag, '--config', _config(tmp_path), '--json', '-']) == 0
    captured = capsys.readouterr()
    data = json.loads(captured.out)
    assert [d['name'] for d in data['devices']] == ['optical', 'em', 'camera']
    assert [d['model'] for d in data['devices']] == ['full_pose', 'position_only', 'full_pose']
    for d, sim, truth in zip(data['devices'], DEVICES, rig.truths, strict=True):
        t = d['time_offset']
        assert t['estimated'] and abs(t['value_s'] - sim.clock_offset) < 3 * t['sigma_s']
        p0 = np.array(d['base_to_base']['position'])
        sd = np.sqrt(np.diag(np.reshape(d['base_to_base']['covariance'], (6, 6)))[:3])
        assert np.all(np.abs(p0 - truth.p0) < 4 * sd)
        assert 0 < d['chi2_share'] < 1 and d['alone']['model'] == d['model']
    assert abs(sum(d['chi2_share'] for d in data['devices']) - 1.0) < 1e-9
    cov = data['cov_joint']
    assert len(cov['labels']) == 39 and len(cov['values']) == 39 ** 2
    assert cov['labels'][12] == 'em.base_to_base.x' and cov['labels'][37] == 'em.time_offset'
    assert {(r['from'], r['to']) for r in data['relative_bases']} == {
        ('optical', 'em'), ('optical', 'camera'), ('em', 'camera')}
    assert 'device camera (/camera/pose)' in captured.err


def test_several_topics_and_a_shared_base(tmp_path, capsys):
    # two EM sensors on one tool: one field generator (one base, one clock), the same instants
    devices = (SimDevice('s1', 'full_pose', 40.0, (4e-4, 1.5e-3), 0.02, 'em'),
               SimDevice('s2', 'full_pose', 40.0, (4e-4, 1.5e-3), 0.02, 'em'))
    rig = simulate_rig(8, 20.0, devices, sigma_a=(1e-3, 3e-3))
    path = tmp_path / 'em'
    write_pose_bag(path, {A: rig.stream_a, '/em/s1': rig.streams[0][0],
                          '/em/s2': rig.streams[1][0]})
    args = ['calibrate', str(path), '--topic-a', A, '--topic-b', '/em/s1', '/em/s2',
            '--sigma-a', '1e-3', '3e-3', '--sigma-b', '4e-4', '1.5e-3', '--json', '-']
    assert main(args + ['--shared-base']) == 0
    shared = json.loads(capsys.readouterr().out)
    assert shared['shared_instants'] == [['/em/s1', '/em/s2']]
    one, two = shared['devices']
    assert one['base'] == two['base'] == 'shared'
    assert one['base_to_base']['position'] == two['base_to_base']['position']
    assert max(one['sigma_ratio'][:6] + two['sigma_ratio'][:6]) < 1.0  # they inform each other
    assert main(args) == 0  # two devices of their own
    apart = json.loads(capsys.readouterr().out)
    assert apart['shared_instants'] == [] and 'relative_bases' in apart


@pytest.mark.parametrize('argv, words', [
    (['--topic-b', A, '/em/pose'], ['topic /robot/tool', 'against itself']),
    (['--topic-b', '/em/pose', '/em/pose'], ['topic /em/pose', 'two devices B']),
    (['--topic-b', '/optical/pose', '--shared-base'], ['--shared-base', 'two or more']),
])
def test_bad_rig_topics_are_one_line(rig_bag, capsys, argv, words):
    bag, _ = rig_bag
    assert main(['calibrate', bag, '--topic-a', A] + argv) == 1
    err = capsys.readouterr().err
    assert err.count('\n') == 1 and all(w in err for w in words), err


def test_bad_devices_in_the_config_are_one_line(tmp_path, rig_bag, capsys):
    bag, _ = rig_bag
    extra = '      lidar: {model: full_pose}\n'
    assert main(['calibrate', bag, '--config', _config(tmp_path, extra)]) == 1
    err = capsys.readouterr().err
    assert err.count('\n') == 1 and "'lidar' is not in devices" in err
    bad = tmp_path / 'bad.yaml'
    bad.write_text('coreg_node:\n  ros__parameters:\n    devices: [cam]\n    device:\n'
                   '      cam: {topic: [/camera/pose], sigma: [1.0]}\n')
    assert main(['calibrate', bag, '--config', str(bad)]) == 1
    err = capsys.readouterr().err
    assert err.count('\n') == 1 and 'device.cam.sigma' in err and 'position m' in err


def test_a_device_that_never_moves_with_the_others_is_refused_by_name(tmp_path, capsys):
    # the camera filmed something else: its motion never overlaps the tool's
    devices = (SimDevice('optical', 'full_pose', 50.0, (3e-4, 1e-3), 0.0),
               SimDevice('camera', 'full_pose', 30.0, (1e-3, 4e-3), 0.0))
    rig = simulate_rig(9, 20.0, devices)
    static = simulate_rig(10, 20.0, devices, motion='static')
    path = tmp_path / 'off'
    write_pose_bag(path, {A: rig.stream_a, '/optical/pose': rig.streams[0][0],
                          '/camera/pose': static.streams[1][0]})
    assert main(['calibrate', str(path), '--topic-a', A, '--topic-b', '/optical/pose',
                 '/camera/pose']) == 1
    err = capsys.readouterr().err
    assert err.count('\n') == 1 and 'device /camera/pose did not move' in err


def test_the_node_checks_a_devices_list_as_the_cli_does(tmp_path):
    # the node calibrates every device of the list with A (test/ros/test_node_rig.py); a file
    # the CLI refuses is refused by the node in one line, before ROS starts
    from coreg_ros.core.errors import ConfigError
    from coreg_ros.ros.parameters import check_params_files
    args = ['coreg_node', '--ros-args', '--params-file']
    check_params_files(args + [_config(tmp_path)], 'coreg_node')
    stray = tmp_path / 'stray'
    stray.mkdir()
    with pytest.raises(ConfigError) as err:
        check_params_files(args + [_config(stray, '      lidar: {model: full_pose}\n')],
                           'coreg_node')
    assert "'lidar' is not in devices" in str(err.value) and '\n' not in str(err.value)


#: Where the real three-phone recording lives on the team's machines (never committed).
TANGO = '/work/shared/data/real/eth_hand_eye/tango_triplet_hard'


@pytest.mark.skipif(not os.path.isdir(TANGO), reason='the real three-phone recording is absent')
def test_real_three_phone_rig_from_csv_exports(tmp_path, capsys):
    # three Tango phones on one mount, each with its own VIO pose and its own clock (stamps
    # 125 s and 76 min apart, none shared): converted from their CSV exports into one bag and
    # calibrated as a rig, CALIGULA as A, no offset given
    files = [glob.glob(f'{TANGO}/{name}_*.csv')[0] for name in ('CALIGULA', 'MARS', 'NERO')]
    bag = str(tmp_path / 'tango')
    assert main(['convert', *files, bag, '--sort', '--topic-a', '/caligula/pose',
                 '--topic-b', '/mars/pose', '/nero/pose']) == 0
    err = capsys.readouterr().err
    assert '/nero/pose and A do not overlap in time' in err and '--time-offset auto' in err
    # VIO poses are noisy at the centimetre level; the fit's verdict is theirs to give
    code = main(['calibrate', bag, '--topic-a', '/caligula/pose', '--topic-b', '/mars/pose',
                 '/nero/pose', '--sigma-a', '0.05', '0.05', '--sigma-b', '0.05', '0.05',
                 '--loops', '--json', '-'])
    out = capsys.readouterr()
    assert code in (0, 3), out.err
    data = json.loads(out.out)
    mars, nero = data['devices']
    for d in (mars, nero):
        paired = d['pairing']
        assert d['time_offset']['estimated'] and paired['n_paired'] > 0.9 * paired['n_b']
    # the coarse search's lags within a second, as for the pairs (test_own_clocks)
    assert abs(mars['time_offset']['value_s'] - 125.1) < 1.0
    assert abs(nero['time_offset']['value_s'] - 4583.4) < 1.0
    # the clock loop: NERO calibrated against MARS directly finds the difference of the two
    # offsets to the stamps' resolution (the exports print 10 ms)
    from coreg_ros.core.calibration.pipeline import calibrate_streams
    from coreg_ros.core.settings import Settings
    streams = read_pose_bag(bag, ['/mars/pose', '/nero/pose'])
    direct, _ = calibrate_streams(streams['/mars/pose'], [streams['/nero/pose']],
                                  Settings(sigma_a=(0.05, 0.05), sigma_b=(0.05, 0.05)))
    loop_s = (nero['time_offset']['value_s'] - mars['time_offset']['value_s']
              - direct.time_offset.value_s)
    assert abs(loop_s) < 0.02, loop_s
    # the pose loop closes to well within the phones' drift (their fits' residuals are
    # 0.1-0.2 m RMS); a wrong composition of the transforms would miss by the mount's lever
    # arms (about a metre here)
    (loop,) = [c for c in data['loops']['checks'] if c['what'] == 'loop']
    assert loop['devices'] == ['/mars/pose', '/nero/pose']
    assert loop['max_error']['position_mm'] < 50 and loop['max_error']['rotation_deg'] < 0.5
    (rel,) = data['relative_bases']
    assert np.all(np.isfinite(rel['covariance']))
    assert 'device /mars/pose:' in out.err and 'loops:' in out.err

"""
The new user's faults of issue 25 (item 4) in coreg_node: each test failed before its fix.

A real coreg_node (in the test's process, or a subprocess where start-up or QoS across
processes is the point) on a private domain, real publishers and service clients.
"""

import math
from pathlib import Path
import re
import shutil
import signal
import subprocess
import sys
import time

from coreg_ros.cli.main import main
from coreg_ros.files.bag.posebag import write_pose_bag
from coreg_ros.ros.tools import call_trigger, play_streams, wait_for_result
from coreg_ros.sim import simulate_recording
import numpy as np
import pytest
from rclpy.parameter import Parameter
from rosproc import wait_counts

A, B = '/device_a/pose', '/device_b/pose'
NODE = '/coreg_node'
CALIBRATE = f'{NODE}/calibrate'


def _quiet(_line):
    pass


def test_swapped_devices_are_not_published_unless_the_roles_are_confirmed(ros_session,
                                                                         start_node_here):
    rec = simulate_recording(26, 12.0)
    # the noise of each device stated for the topic it arrives on: the swap fits well
    node = start_node_here({'qos_reliable': True, 'sigma_a': list(rec.truth.sigma_b),
                            'sigma_b': list(rec.truth.sigma_a)})
    swapped = {A: rec.streams_b[0], B: rec.stream_a}  # each device on the other's topic
    play_streams(ros_session, swapped, rate=math.inf, wait_subscribers=20, log=_quiet)
    wait_counts(ros_session, {f'{t} accepted': len(s) for t, s in swapped.items()})
    ok, message = call_trigger(ros_session, CALIBRATE, timeout=60)
    assert not ok
    assert 'not published' in message and 'devices are swapped' in message, message
    assert 'roles_confirmed:=true' in message, message
    assert wait_for_result(ros_session, f'{NODE}/base_to_base', timeout=2.0) is None
    (changed,) = node.node.set_parameters([Parameter('roles_confirmed', value=True)])
    assert changed.successful
    ok, message = call_trigger(ros_session, CALIBRATE, timeout=60)
    assert ok, message
    assert wait_for_result(ros_session, f'{NODE}/base_to_base', timeout=10.0) is not None


def test_the_nodes_own_result_is_not_a_prior_for_its_own_samples(ros_session, start_node_here,
                                                                  tmp_path, capfd):
    rec = simulate_recording(27, 12.0)
    node = start_node_here({'qos_reliable': True, 'use_last_result_as_prior': True})
    play_streams(ros_session, rec.streams, rate=math.inf, wait_subscribers=20, log=_quiet)
    wait_counts(ros_session, {f'{t} accepted': len(s) for t, s in rec.streams.items()})
    ok, first = call_trigger(ros_session, CALIBRATE, timeout=60)
    assert ok, first
    (stored,) = node.storage.glob('result_*.yaml')
    sigma_first = _sigma(wait_for_result(ros_session, f'{NODE}/base_to_base', timeout=10.0))
    # the node again on the same samples: its stored result is not counted a second time
    ok, second = call_trigger(ros_session, CALIBRATE, timeout=60)
    assert ok, second
    assert 'prior' not in second
    sigma_second = _sigma(wait_for_result(ros_session, f'{NODE}/base_to_base', timeout=10.0))
    np.testing.assert_allclose(sigma_second, sigma_first, rtol=1e-6)
    # the user's recording of the same messages, calibrated with the node's result as prior
    write_pose_bag(tmp_path / 'recorded', rec.streams)
    capfd.readouterr()
    assert main(['calibrate', str(tmp_path / 'recorded'), '--prior', str(stored)]) == 1
    err = capfd.readouterr().err
    assert 'same samples' in err and 'count them twice' in err, err


def _sigma(msg):
    return np.sqrt(np.diag(np.asarray(msg.pose.covariance).reshape(6, 6)))


def test_an_unwritable_storage_dir_makes_calibrate_answer_false(ros_session, start_node_here,
                                                                tmp_path):
    blocker = tmp_path / 'a_file'
    blocker.write_text('storage_dir points below a regular file\n')
    rec = simulate_recording(28, 12.0)
    node = start_node_here({'qos_reliable': True, 'storage_dir': str(blocker / 'store')})
    play_streams(ros_session, rec.streams, rate=math.inf, wait_subscribers=20, log=_quiet)
    wait_counts(ros_session, {f'{t} accepted': len(s) for t, s in rec.streams.items()})
    ok, message = call_trigger(ros_session, CALIBRATE, timeout=60)
    assert not ok, message  # as the README says: the result is not stored
    assert 'published but NOT stored' in message and 'storage_dir' in message, message
    # the calibration itself is good and published (a restart would not have it)
    assert wait_for_result(ros_session, f'{NODE}/base_to_base', timeout=10.0) is not None
    assert node.stop() == 0
    for folder in re.findall(r'saved \d+ samples to (\S+)', node.log()):  # the fallback
        shutil.rmtree(Path(folder).parent, ignore_errors=True)


@pytest.mark.parametrize('text, words', [
    ('', 'is empty'),
    ('other_node:\n  ros__parameters:\n    model: position_only\n',
     'has no "coreg_node: ros__parameters:" section (it has other_node)'),
])
def test_a_parameter_file_that_sets_nothing_is_said_at_start_up(ros_domain, tmp_path, text,
                                                                 words):
    params = tmp_path / 'params.yaml'
    params.write_text(text)
    node = subprocess.Popen(
        [sys.executable, '-m', 'coreg_ros.ros.node', '--ros-args', '--params-file', str(params),
         '-p', f'storage_dir:={tmp_path / "store"}'],
        env=ros_domain.env(), stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        deadline = time.monotonic() + 30
        lines = []
        while time.monotonic() < deadline:
            line = node.stdout.readline()
            lines.append(line)
            if 'listening to' in line or not line:
                break
    finally:
        node.send_signal(signal.SIGINT)
        rest, _ = node.communicate(timeout=20)
    log = ''.join(lines) + rest
    assert 'coreg_node: warning: config file' in log and words in log, log
    assert log.index(words) < log.index('listening to')  # said before it starts

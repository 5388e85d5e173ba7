"""
The new user's faults of issue 25 (item 4) in coreg_node: each test failed before its fix.

A real coreg_node (in the test's process, or a subprocess where start-up or QoS across
processes is the point) on a private domain, real publishers and service clients.
"""

import math

from coreg_ros.cli.main import main
from coreg_ros.files.bag.posebag import write_pose_bag
from coreg_ros.ros.tools import call_trigger, play_streams, wait_for_result
from coreg_ros.sim import simulate_recording
import numpy as np
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

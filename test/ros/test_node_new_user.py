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
from coreg_ros.ros.buffer import SequenceCounter
from coreg_ros.ros.interface import SUB_DEPTH
from coreg_ros.ros.messages import make_pose_stamped
from coreg_ros.ros.node import PLAIN_ENV
from coreg_ros.ros.tools import (
    call_trigger,
    diagnostics_values,
    play_streams,
    wait_for_diagnostics,
    wait_for_result,
)
from coreg_ros.sim import simulate_recording
import numpy as np
import pytest
from rclpy.parameter import Parameter
from rosproc import publishers, wait_counts

A, B = '/device_a/pose', '/device_b/pose'
NODE = '/coreg_node'
CALIBRATE = f'{NODE}/calibrate'


def _quiet(_line):
    pass


def test_swapped_devices_are_not_published_unless_the_roles_are_confirmed(
        ros_session, start_node_here):
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


def test_the_nodes_own_result_is_not_a_prior_for_its_own_samples(
        ros_session, start_node_here, tmp_path, capfd):
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
def test_a_parameter_file_that_sets_nothing_is_said_at_start_up(
        ros_domain, tmp_path, text, words):
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


@pytest.mark.parametrize('plain', ['0', '1'])  # the raw intake, one message per callback
def test_messages_lost_on_the_way_are_counted_as_sent_whatever_the_stamps(
        ros_session, start_node_here, monkeypatch, plain):
    # A fresh node subscribed but not yet taking (still starting up) while a device with an
    # irregular rate pours messages in: the middleware keeps some (its history is bounded)
    # and drops the rest. The node must then say how many it lost, exactly: the holes in
    # irregular stamps cannot tell it (they count intervals, not messages).
    monkeypatch.setenv(PLAIN_ENV, plain)
    node = start_node_here(spin=False)
    pub = publishers(ros_session, (A,))[A]
    rng = np.random.default_rng(25)
    n = SUB_DEPTH + 4000
    stamps = 1_700_000_000 * 10**9 + np.cumsum(rng.integers(300_000, 2_500_000, n))
    for stamp in stamps[:-1].tolist():
        pub.publish(make_pose_stamped(stamp, 'device_a_base', (0, 0, 0), (1, 0, 0, 0)))
    time.sleep(0.5)
    node.spin()
    time.sleep(1.0)
    # the last one once the node takes them: nothing counts a loss after the last one taken
    pub.publish(make_pose_stamped(int(stamps[-1]), 'device_a_base', (0, 0, 0), (1, 0, 0, 0)))

    def settled(status):
        v = diagnostics_values(status)
        return int(v[f'{A} accepted']) + int(v[f'{A} lost']) >= n

    status = wait_for_diagnostics(ros_session, timeout=20, accept=settled)
    assert status is not None, 'the node never accounted for every message sent'
    v = diagnostics_values(status)
    accepted, lost = int(v[f'{A} accepted']), int(v[f'{A} lost'])
    print(f'{n} sent, {accepted} accepted, {lost} lost ({v[f"{A} lost counted from"]}); the '
          f'stamps say {v[f"{A} missing from stamps"]}, the middleware\'s events '
          f'{v[f"{A} lost in middleware"]}')
    assert accepted < n and accepted + lost == n, v
    assert 'publication sequence numbers' in v[f'{A} lost counted from'], v


def _infos(numbers, sources):
    return [{'publication_sequence_number': int(s), 'source_timestamp': int(t)}
            for s, t in zip(numbers, sources, strict=True)]


def test_sequence_counter_counts_holes_and_a_late_publishers_head_only():
    rng = np.random.default_rng(25)
    created = 10**18
    sent = np.arange(1, 5001)
    sources = created + 10**9 + sent * 1_000_000  # a 1 kHz publisher that began after us
    keep = rng.random(len(sent)) > 0.2
    keep[:300] = False  # lost before the first taken
    keep[-1] = True     # nothing counts what is lost after the last one taken
    counter = SequenceCounter(created)
    for chunk in np.array_split(np.flatnonzero(keep), 7):
        counter.update(_infos(sent[chunk], sources[chunk]))
    assert counter.counting and counter.lost == len(sent) - keep.sum()
    assert counter.head == 300
    one_by_one = SequenceCounter(created)  # the plain intake's way: the same count
    for info in _infos(sent[keep], sources[keep]):
        one_by_one.update_one(info)
    assert (one_by_one.between, one_by_one.head) == (counter.between, counter.head)
    # a publisher running since long before: its earlier messages were for nobody here
    running = SequenceCounter(created)
    running.update(_infos(sent[300:], created - 10**8 + (sent[300:] - 300) * 1_000_000))
    assert running.counting and running.lost == 0
    # two publishers on one topic: their numbers interleave; the count gives way to the stamps
    two = SequenceCounter(created)
    two.update(_infos([1, 2, 1, 3, 2], sources[:5]))
    assert not two.counting and 'several publishers' in two.why_not
    two_one_by_one = SequenceCounter(created)
    for info in _infos([1, 2, 1, 3, 2], sources[:5]):
        two_one_by_one.update_one(info)
    assert two_one_by_one.why_not == two.why_not

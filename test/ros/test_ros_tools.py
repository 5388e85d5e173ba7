"""Tests of the ROS stand-in tools (record, play errors) and the node's building blocks."""

import math
from pathlib import Path
import signal
import subprocess
import sys
import time

from coreg_ros.core.settings import settings_from_mapping
from coreg_ros.core.types import UncertainPose
from coreg_ros.files.bag.posebag import read_pose_bag, write_pose_bag
from coreg_ros.ros import persistence
from coreg_ros.ros.buffer import REASONS, StreamBuffer
from coreg_ros.ros.domain import reserve_domain_id
from coreg_ros.ros.messages import (
    make_pose_stamped,
    msg_to_uncertain_pose,
    pose_stamped_values,
    uncertain_pose_to_msg,
)
from coreg_ros.ros.node import CoregNode
from coreg_ros.ros.session import RosSession
from coreg_ros.ros.tools import play_streams
from coreg_ros.sim import simulate_recording
import numpy as np
import pytest
from rclpy.parameter import Parameter
from rosproc import PY, run_cli
import yaml

ROOT = Path(__file__).resolve().parents[2]


# --- building blocks (no subprocess) --------------------------------------------------------

def test_buffer_keeps_newest_and_counts_each_reason():
    buf = StreamBuffer(4)
    for k in range(6):
        assert buf.push(k + 1, 0, k, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 'f') is None
    assert buf.push(6, 0, 0, 0, 0, 1, 0, 0, 0, 'f') == 'duplicate_stamp'
    assert buf.push(2, 0, 0, 0, 0, 1, 0, 0, 0, 'f') == 'stamp_backwards'
    assert buf.push(7, 0, math.nan, 0, 0, 1, 0, 0, 0, 'f') == 'non_finite'
    assert buf.push(7, 0, 0, 0, 0, 0, 0, 0, 0, 'f') == 'non_unit_quaternion'
    assert buf.push(7, 0, 0, 0, 0, 1, 0, 0, 0, 'g') == 'frame_id_changed'
    snap = buf.snapshot()
    np.testing.assert_array_equal(snap.stamps, [3, 4, 5, 6])  # oldest dropped
    np.testing.assert_array_equal(snap.position[:, 0], [2, 3, 4, 5])
    assert buf.dropped == 2 and buf.accepted == 6 and buf.received == 11
    assert buf.rejected == dict.fromkeys(REASONS, 1)
    buf.clear()
    assert len(buf) == 0 and buf.push(1, 0, 0, 0, 0, 1, 0, 0, 0, 'g') is None


def test_conversion_flips_quaternion_order_once():
    msg = make_pose_stamped(12 * 10**9 + 5, 'base', (1, 2, 3), (0.5, 0.5, -0.5, 0.5))
    assert (msg.pose.orientation.x, msg.pose.orientation.w) == (0.5, 0.5)
    assert msg.pose.orientation.z == 0.5 and msg.pose.orientation.y == -0.5
    assert pose_stamped_values(msg) == (12 * 10**9 + 5, 1, 2, 3, 0.5, 0.5, -0.5, 0.5)
    cov = np.arange(36.0).reshape(6, 6)
    pose = UncertainPose(np.array([1.0, 2, 3]), np.array([0.0, 0, 1, 0]), cov)
    back = msg_to_uncertain_pose(uncertain_pose_to_msg(pose, 'f', msg.header.stamp))
    np.testing.assert_array_equal(back.quat_wxyz, pose.quat_wxyz)
    np.testing.assert_array_equal(back.covariance, cov)
    unknown = uncertain_pose_to_msg(UncertainPose(pose.position, pose.quat_wxyz), 'f',
                                    msg.header.stamp)
    assert list(np.diag(np.reshape(unknown.pose.covariance, (6, 6)))) == [-1.0] * 6


def test_result_file_is_replaced_atomically(tmp_path):
    pose = {'position': [1.0, 2.0, 3.0], 'orientation': {'w': 1.0, 'x': 0.0, 'y': 0.0,
                                                         'z': 0.0}, 'covariance': None}
    result = {'n_pairs': 3, 'base_to_base': pose, 'tool_to_marker': pose}
    persistence.save_result(str(tmp_path), result, {'tool': 't'}, {'model': 'full_pose'})
    persistence.save_result(str(tmp_path), dict(result, n_pairs=4), {}, {})
    assert sorted(p.name for p in tmp_path.iterdir()) == ['result.yaml']  # no temp left
    doc, base, _ = persistence.load_result(str(tmp_path))
    assert doc['result']['n_pairs'] == 4 and list(base.position) == [1, 2, 3]
    (tmp_path / 'result.yaml').write_text('result: [')
    with pytest.raises(ValueError, match='delete it and recalibrate'):
        persistence.load_result(str(tmp_path))
    assert persistence.load_result(str(tmp_path / 'none')) is None


def test_domain_ids_are_exclusive():
    held = [reserve_domain_id() for _ in range(5)]
    ids = [h.domain_id for h in held]
    assert len(set(ids)) == 5 and all(1 <= i <= 100 for i in ids)
    env = held[0].env()
    assert env['ROS_AUTOMATIC_DISCOVERY_RANGE'] == 'LOCALHOST'
    for h in held:
        h.release()


def test_node_reads_config_file_and_refuses_bad_changes(ros_domain, tmp_path):
    session = RosSession('unused', domain_id=ros_domain.domain_id, signals=False)
    try:
        node = CoregNode(context=session.context,
                         cli_args=['--ros-args', '--params-file', str(ROOT / 'config/coreg.yaml'),
                                   '-p', f'storage_dir:={tmp_path}'])
        config = yaml.safe_load((ROOT / 'config/coreg.yaml').read_text())
        expected = settings_from_mapping(config['coreg_node']['ros__parameters'])
        assert node.config.settings == expected
        assert node.config.buffer_capacity == 200000 and node.config.storage_dir == str(tmp_path)
        for name in ('max_gap', 'min_pairs', 'buffer_capacity'):
            assert node.describe_parameter(name).description
        assert node.describe_parameter('max_gap').floating_point_range[0].to_value == 10.0
        bad = node.set_parameters([Parameter('method', value='magic')])[0]
        assert not bad.successful and 'method' in bad.reason
        out_of_range = node.set_parameters([Parameter('max_gap', value=100.0)])[0]
        assert not out_of_range.successful
        assert node.set_parameters([Parameter('method', value='ols')])[0].successful
        assert node.params.settings().method == 'ols'
        read_only = node.set_parameters([Parameter('topic_a', value='/x')])[0]
        assert not read_only.successful
        # a choice no descriptor states (issue 22): refused in one line, a valid one taken
        limits = node.set_parameters([Parameter('motion_limits', value='scara')])[0]
        assert not limits.successful and 'free | auto | restricted' in limits.reason
        assert node.set_parameters([Parameter('motion_limits', value='restricted')])[0].successful
        tilt = node.set_parameters([Parameter('gravity_aligned_sigma', value=-1.0)])[0]
        assert not tilt.successful
        assert node.set_parameters([Parameter('gravity_aligned_sigma', value=0.01)])[0].successful
        assert node.calibrator._prior([]).gravity_sigma == 0.01
        node.destroy_node()
    finally:
        session.close()


# --- tools in subprocesses ------------------------------------------------------------------

def test_record_until_sigint_writes_what_was_published(ros_domain, ros_session, tmp_path):
    rec = simulate_recording(8, 1.0)
    out = tmp_path / 'recorded'
    topics = list(rec.streams)
    proc = subprocess.Popen([PY, '-m', 'coreg_ros.cli.ros_commands', 'record', str(out),
                             '--topics', *topics], env=ros_domain.env(), text=True,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        play_streams(ros_session, rec.streams, rate=4.0, wait_subscribers=20.0,
                     log=lambda s: None)
        time.sleep(1.0)  # let the recorder take the last messages off its queue
        proc.send_signal(signal.SIGINT)
        stdout, stderr = proc.communicate(timeout=20)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, stderr
    assert 'wrote' in stdout
    got = read_pose_bag(out, topics)
    for t in topics:
        np.testing.assert_array_equal(got[t].stamps, rec.streams[t].stamps)
        np.testing.assert_array_equal(got[t].quat_wxyz, rec.streams[t].quat_wxyz)
        assert np.all(np.diff(got[t].receive_stamps) >= 0)


def test_play_without_subscriber_and_call_without_node_fail_in_one_line(ros_domain, tmp_path):
    bag = tmp_path / 'bag'
    write_pose_bag(bag, simulate_recording(1, 0.2).streams)
    played = run_cli(ros_domain, 'play', bag, '--wait', 0.5)
    assert played.returncode == 1
    assert played.stderr.strip().count('\n') == 0 and 'no subscriber' in played.stderr
    missing = run_cli(ros_domain, 'play', tmp_path / 'nope')
    assert missing.returncode == 1 and 'Traceback' not in missing.stderr
    called = run_cli(ros_domain, 'call', 'reset', '--timeout', 1)
    assert called.returncode == 1 and 'Traceback' not in called.stderr


def test_subcommands_register_on_a_parser():
    import argparse

    from coreg_ros.cli.ros_commands import register
    parser = argparse.ArgumentParser()
    register(parser.add_subparsers(dest='command'))
    args = parser.parse_args(['call', 'calibrate', '--node', 'n'])
    assert callable(args.func) and args.node == 'n'
    # rclpy is imported lazily: registering did not need it.
    code = ('import sys, argparse; sys.modules["rclpy"] = None; '
            'from coreg_ros.cli.ros_commands import register; '
            'register(argparse.ArgumentParser().add_subparsers())')
    assert subprocess.run([sys.executable, '-c', code]).returncode == 0

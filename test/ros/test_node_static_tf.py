"""
coreg_node's calibration on /tf_static, received as a tf2 listener receives it.

The node runs in a subprocess; this process subscribes to /tf_static with tf2_msgs/TFMessage
(the type ``make venv`` builds from Jazzy's definitions; a ROS install's own where present)
and the QoS of tf2's static listener, and checks the transforms against ``~/base_to_base``
and ``~/tool_to_marker``, against the simulated truth (the direction), and the type's hash
against Jazzy's.
"""

import math
import sys

from coreg_ros.ros.messages import stamp_to_ns
from coreg_ros.ros.static_tf import MISSING_TYPE
from coreg_ros.ros.tools import call_trigger, play_streams, wait_for_message, wait_for_result
from coreg_ros.sim import simulate_recording
import numpy as np
import pytest
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rosproc import wait_counts

pytestmark = pytest.mark.ros

A, B = '/device_a/pose', '/device_b/pose'
CALIBRATE = '/coreg_node/calibrate'
#: tf2_ros's static listener QoS (tf2_ros.StaticListenerQoS).
LISTENER_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=100,
                          reliability=ReliabilityPolicy.RELIABLE,
                          durability=DurabilityPolicy.TRANSIENT_LOCAL)
FRAMES = {'frame_base_a': 'robot_base', 'frame_base_b': 'camera_base',
          'frame_tool': 'flange', 'frame_marker': 'target'}


@pytest.fixture
def tf_message():
    """tf2_msgs/msg/TFMessage: make venv builds it; without it these tests fail, saying so."""
    try:
        from tf2_msgs.msg import TFMessage
    except ImportError as e:
        pytest.fail(f'tf2_msgs cannot be imported ({e}): run `make venv`, which builds it '
                    f'(interfaces/build.sh)')
    return TFMessage


def _jazzy_hash() -> str:
    """RIHS01 hash of Jazzy's tf2_msgs/msg/TFMessage, computed by rosbags from its own store."""
    from rosbags.typesys import get_typestore, Stores
    return get_typestore(Stores.ROS2_JAZZY).hash_rihs01('tf2_msgs/msg/TFMessage')


def _tf_static(session, msg_type, timeout=20.0):
    return wait_for_message(session, msg_type, '/tf_static', LISTENER_QOS, timeout)


def _by_child(msg) -> dict:
    return {t.child_frame_id: t for t in msg.transforms}


def _assert_transform_is(t, result, parent: str) -> None:
    """Check that a TransformStamped carries the pose message's numbers, parent to child."""
    assert t.header.frame_id == parent == result.header.frame_id
    assert stamp_to_ns(t.header.stamp) == stamp_to_ns(result.header.stamp)
    p, q = result.pose.pose.position, result.pose.pose.orientation
    tr, rot = t.transform.translation, t.transform.rotation
    assert (tr.x, tr.y, tr.z) == (p.x, p.y, p.z)
    assert (rot.x, rot.y, rot.z, rot.w) == (q.x, q.y, q.z, q.w)


def _assert_matches_results(session, msg) -> dict:
    """Check a TFMessage against the node's ~/base_to_base and ~/tool_to_marker; return them."""
    base = wait_for_result(session, '/coreg_node/base_to_base', timeout=10)
    tool = wait_for_result(session, '/coreg_node/tool_to_marker', timeout=10)
    assert len(msg.transforms) == 2  # both in one message
    tf = _by_child(msg)
    assert set(tf) == {FRAMES['frame_base_a'], FRAMES['frame_marker']}
    _assert_transform_is(tf[FRAMES['frame_base_a']], base, FRAMES['frame_base_b'])
    _assert_transform_is(tf[FRAMES['frame_marker']], tool, FRAMES['frame_tool'])
    return {'base': base, 'tool': tool}


def _assert_near_truth(t, p_true, q_true_wxyz, covariance) -> None:
    """Check a transform against the truth's pose of child in parent (5 published sigmas)."""
    sd = np.sqrt(np.diag(np.array(covariance).reshape(6, 6)))
    tr, r = t.transform.translation, t.transform.rotation
    assert np.all(np.abs(np.array([tr.x, tr.y, tr.z]) - p_true) < 5 * sd[:3])
    angle = 2 * math.acos(min(1.0, abs(float(np.dot([r.w, r.x, r.y, r.z], q_true_wxyz)))))
    assert angle < 5 * math.sqrt(3) * sd[3:].max()


def _play_and_calibrate(session, rec):
    n = {t: len(s) for t, s in rec.streams.items()}
    play_streams(session, rec.streams, rate=5.0, wait_subscribers=20.0, log=lambda s: None)
    wait_counts(session, {f'{t} accepted': n[t] for t in (A, B)})
    ok, message = call_trigger(session, CALIBRATE, timeout=30)
    assert ok, message


def test_tf_static_carries_the_calibration_at_start_up_and_after_each(
        ros_session, start_node, tf_message):
    jazzy = _jazzy_hash()
    rec = simulate_recording(3, 3.0)
    node = start_node(FRAMES)
    _play_and_calibrate(ros_session, rec)
    msg = _tf_static(ros_session, tf_message)  # subscribed after the calibration: latched
    assert msg is not None, node.log()
    results = _assert_matches_results(ros_session, msg)
    (info,) = ros_session.node.get_publishers_info_by_topic('/tf_static')
    assert info.topic_type == 'tf2_msgs/msg/TFMessage'
    assert str(info.topic_type_hash) == jazzy  # what a Jazzy tf2 listener expects
    # The direction: parent B's base -> child A's base is T0 = T_bbase_abase of the truth,
    # parent tool -> child marker is T1 = T_atool_bmarker.
    tf, truth = _by_child(msg), rec.truth
    _assert_near_truth(tf[FRAMES['frame_base_a']], truth.p0, truth.q0,
                       results['base'].pose.covariance)
    _assert_near_truth(tf[FRAMES['frame_marker']], truth.p1, truth.q1,
                       results['tool'].pose.covariance)
    assert node.stop() == 0, node.log()

    # A node restarted on the stored result broadcasts it at start-up ...
    again = start_node({**FRAMES, 'storage_dir': str(node.storage)}, name='restart')
    stored = _tf_static(ros_session, tf_message)
    assert stored is not None, again.log()
    _assert_matches_results(ros_session, stored)
    assert _by_child(stored)[FRAMES['frame_base_a']].transform == \
        tf[FRAMES['frame_base_a']].transform
    # ... and a listener that stays gets the next calibration (another rig: another truth).
    heard = []
    sub = ros_session.node.create_subscription(tf_message, '/tf_static', heard.append,
                                               LISTENER_QOS)
    assert ros_session.spin_until(lambda: bool(heard), 10.0)
    other = simulate_recording(5, 3.0)
    _play_and_calibrate(ros_session, other)
    assert ros_session.spin_until(lambda: len(heard) >= 2, 10.0), again.log()
    new = _assert_matches_results(ros_session, heard[-1])
    _assert_near_truth(_by_child(heard[-1])[FRAMES['frame_base_a']], other.truth.p0,
                       other.truth.q0, new['base'].pose.covariance)
    ros_session.node.destroy_subscription(sub)
    assert again.stop() == 0, again.log()


def test_a_node_without_the_type_says_so_once_and_goes_on(ros_session, start_node, tmp_path):
    # A Python without tf2_ros and tf2_msgs: packages of those names that fail to import.
    shadow = tmp_path / 'no_tf'
    for name in ('tf2_ros', 'tf2_msgs'):
        (shadow / name).mkdir(parents=True)
        (shadow / name / '__init__.py').write_text(f'raise ImportError("no {name} here")\n')
    node = start_node(FRAMES, env={'PYTHONPATH': str(shadow)})
    _play_and_calibrate(ros_session, simulate_recording(3, 3.0))
    assert wait_for_result(ros_session, '/coreg_node/base_to_base', timeout=10) is not None
    assert ros_session.node.get_publishers_info_by_topic('/tf_static') == []
    assert node.stop() == 0, node.log()
    said = MISSING_TYPE.split('(')[0]
    assert node.log().count(said) == 1, node.log()

    # publish_tf:=false: no /tf_static and nothing said about it.
    quiet = start_node({**FRAMES, 'publish_tf': False, 'storage_dir': str(node.storage)},
                       name='quiet')
    assert wait_for_result(ros_session, '/coreg_node/base_to_base', timeout=20) is not None
    assert ros_session.node.get_publishers_info_by_topic('/tf_static') == []
    assert quiet.stop() == 0
    assert 'publish_tf' not in quiet.log()


def test_frame_ids_tf2_would_refuse_are_named(start_node_here):
    node = start_node_here({**FRAMES, 'frame_tool': 'target'})
    assert node.node.static_tf.via is None
    assert node.node.get_publishers_info_by_topic('/tf_static') == []
    assert "T1 would be a transform of 'target' to itself" in node.log(), node.log()


if __name__ == '__main__':
    sys.exit(pytest.main([__file__, '-q']))

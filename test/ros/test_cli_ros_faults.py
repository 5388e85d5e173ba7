"""
Faults of the ROS command-line tools found by trying them as a careless user (issue 12).

Real processes throughout: ``coreg play`` and ``coreg echo`` run as subprocesses on the test's
own ROS domain (discovery on localhost) and get a real SIGINT; the publishers ``coreg echo``
must show are real rclpy publishers in the test process, with the node's QoS, or coreg_node.
"""

import signal
import subprocess
import time

from coreg_ros.files.bag.posebag import write_pose_bag
from coreg_ros.ros.interface import LATCHED_QOS
from coreg_ros.ros.messages import make_pose_stamped
from coreg_ros.ros.uncertainty_outputs import FUSED_QOS, MARKER_QOS
from coreg_ros.sim import simulate_recording
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import PoseStamped, PoseWithCovarianceStamped
import pytest
from rclpy.qos import qos_profile_sensor_data
from rosproc import PY, run_cli
from visualization_msgs.msg import Marker, MarkerArray

pytestmark = pytest.mark.ros


def _interrupt(domain, args, delay: float, timeout: float = 20.0):
    """Start ``coreg <args>``, SIGINT it after ``delay`` s; return (code, stdout, stderr)."""
    proc = subprocess.Popen([PY, '-m', 'coreg_ros.cli.ros_commands', *map(str, args)],
                            env=domain.env(), text=True, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE)
    try:
        time.sleep(delay)
        proc.send_signal(signal.SIGINT)
        stdout, stderr = proc.communicate(timeout=timeout)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    return proc.returncode, stdout, stderr


def _one_line(stderr: str) -> bool:
    return 'Traceback' not in stderr and stderr.strip().count('\n') == 0


# --- item 8: Ctrl-C on play and echo ----------------------------------------------------------

@pytest.mark.parametrize('delay', [2.5, 4.0])  # after start-up: a Ctrl-C within the
# interpreter's own start-up (before any coreg code runs) is Python's to report
def test_ctrl_c_on_play_ends_without_traceback(ros_domain, tmp_path, delay):
    bag = tmp_path / 'bag'
    write_pose_bag(bag, simulate_recording(3, 30.0).streams)
    code, stdout, stderr = _interrupt(ros_domain, ['play', bag, '--wait', 0], delay)
    assert 'Traceback' not in stderr and 'RCLError' not in stderr, stderr
    assert code == 130, stderr
    assert 'interrupted' in stderr and _one_line(stderr)


@pytest.mark.parametrize('delay', [2.5, 4.0])  # after start-up: a Ctrl-C within the
# interpreter's own start-up (before any coreg code runs) is Python's to report
def test_ctrl_c_on_echo_before_a_message_ends_without_traceback(ros_domain, delay):
    code, _, stderr = _interrupt(ros_domain, ['echo', '/coreg_node/base_to_base'], delay)
    assert 'Traceback' not in stderr and 'TypeError' not in stderr, stderr
    assert code == 130 and 'interrupted' in stderr and _one_line(stderr)


def test_ctrl_c_on_play_while_waiting_for_subscribers(ros_domain, tmp_path):
    bag = tmp_path / 'bag'
    write_pose_bag(bag, simulate_recording(3, 1.0).streams)
    code, _, stderr = _interrupt(ros_domain, ['play', bag, '--wait', 30], 3.0)
    assert code == 130 and _one_line(stderr), stderr
    assert 'no subscriber' not in stderr  # not blamed on a missing node


# --- item 12: echo matches the publisher's type and QoS ----------------------------------------

class _Publisher:
    """A real rclpy publisher in the test's session, publishing every 0.1 s while spun."""

    def __init__(self, session, msg_type, topic, qos, make):
        self.session = session
        self.pub = session.node.create_publisher(msg_type, topic, qos)
        self.make = make
        self.timer = session.node.create_timer(0.1, lambda: self.pub.publish(make()))

    def run_cli(self, domain, *args, timeout=30.0):
        proc = subprocess.Popen([PY, '-m', 'coreg_ros.cli.ros_commands', *map(str, args)],
                                env=domain.env(), text=True, stdout=subprocess.PIPE,
                                stderr=subprocess.PIPE)
        end = time.monotonic() + timeout
        while proc.poll() is None and time.monotonic() < end:
            self.session.executor.spin_once(timeout_sec=0.05)
        if proc.poll() is None:
            proc.kill()
        stdout, stderr = proc.communicate()
        return proc.returncode, stdout, stderr


def _pose_cov():
    msg = PoseWithCovarianceStamped()
    msg.header.frame_id = 'device_b_base'
    msg.pose.pose.position.x = 0.25
    msg.pose.pose.orientation.w = 1.0
    msg.pose.covariance = [1e-8 if i % 7 == 0 else 0.0 for i in range(36)]
    return msg


def test_echo_shows_a_volatile_fused_pose(ros_domain, ros_session):
    pub = _Publisher(ros_session, PoseWithCovarianceStamped, '/coreg_node/fused_pose', FUSED_QOS,
                     _pose_cov)
    code, stdout, stderr = pub.run_cli(ros_domain, 'echo', 'fused_pose', '--once',
                                       '--timeout', 10)
    assert code == 0, stderr
    assert '/coreg_node/fused_pose (frame device_b_base' in stdout
    assert 'x  0.250000' in stdout and 'std position [m]  0.0001' in stdout


def test_echo_shows_a_best_effort_pose_stream(ros_domain, ros_session):
    pub = _Publisher(ros_session, PoseStamped, '/device_a/pose', qos_profile_sensor_data,
                     lambda: make_pose_stamped(5 * 10**9, 'device_a_base', (1.0, 2.0, 3.0),
                                               (1.0, 0.0, 0.0, 0.0)))
    code, stdout, stderr = pub.run_cli(ros_domain, 'echo', '/device_a/pose', '--once',
                                       '--timeout', 10)
    assert code == 0, stderr
    assert '(frame device_a_base, stamp 5.000)' in stdout and 'z  3.000000' in stdout


def test_echo_shows_a_latched_marker_array(ros_domain, ros_session):
    def markers():
        m = Marker(ns='base_to_base', id=3, type=Marker.SPHERE, action=Marker.ADD)
        m.header.frame_id = 'device_b_base'
        m.scale.x = m.scale.y = m.scale.z = 0.01
        return MarkerArray(markers=[m])
    pub = _Publisher(ros_session, MarkerArray, '/coreg_node/uncertainty_markers', MARKER_QOS,
                     markers)
    code, stdout, stderr = pub.run_cli(ros_domain, 'echo', 'uncertainty_markers', '--once',
                                       '--timeout', 10)
    assert code == 0, stderr
    assert '(1 markers)' in stdout and 'base_to_base/3 sphere add (frame device_b_base)' in stdout


def test_echo_prints_diagnostics_readably(ros_domain, ros_session):
    def diagnostics():
        status = DiagnosticStatus(level=DiagnosticStatus.WARN, name='coreg_node: streams',
                                  message='dropped 12 messages',
                                  values=[KeyValue(key='paired', value='3000')])
        return DiagnosticArray(status=[status])
    pub = _Publisher(ros_session, DiagnosticArray, '/diagnostics', 10, diagnostics)
    code, stdout, stderr = pub.run_cli(ros_domain, 'echo', '/diagnostics', '--once',
                                       '--timeout', 10)
    assert code == 0, stderr
    assert '[WARN] coreg_node: streams: dropped 12 messages' in stdout
    assert 'paired: 3000' in stdout


def test_echo_shows_the_nodes_diagnostics(ros_domain, start_node_here):
    node = start_node_here()
    result = run_cli(ros_domain, 'echo', '/diagnostics', '--once', '--timeout', 20)
    assert result.returncode == 0, result.stderr + node.log()
    assert '] coreg_node' in result.stdout and 'received: 0' in result.stdout


def test_echo_of_a_result_not_yet_published_says_why(ros_domain, ros_session):
    ros_session.node.create_publisher(PoseWithCovarianceStamped, '/coreg_node/base_to_base',
                                      LATCHED_QOS)
    pub = _Publisher(ros_session, DiagnosticArray, '/unused', 10, DiagnosticArray)
    code, _, stderr = pub.run_cli(ros_domain, 'echo', 'base_to_base', '--once', '--timeout', 3)
    assert code == 1 and _one_line(stderr)
    assert 'coreg call calibrate' in stderr


def test_echo_without_publisher_and_of_an_unknown_type_fail_in_one_line(ros_domain,
                                                                        ros_session):
    result = run_cli(ros_domain, 'echo', '/nobody', '--once', '--timeout', 1)
    assert result.returncode == 1 and _one_line(result.stderr)
    assert 'no publisher of /nobody' in result.stderr
    from std_msgs.msg import String
    pub = _Publisher(ros_session, String, '/chatter', 10, String)
    code, _, stderr = pub.run_cli(ros_domain, 'echo', '/chatter', '--once', '--timeout', 5)
    assert code == 1 and _one_line(stderr) and 'std_msgs/msg/String' in stderr


def test_matching_qos_takes_the_weakest_publisher():
    from coreg_ros.ros.interface import matching_qos

    class Info:

        def __init__(self, qos):
            self.qos_profile = qos
    assert matching_qos([Info(LATCHED_QOS)]).durability == LATCHED_QOS.durability
    mixed = matching_qos([Info(LATCHED_QOS), Info(qos_profile_sensor_data)])
    assert mixed.reliability == qos_profile_sensor_data.reliability
    assert mixed.durability == FUSED_QOS.durability

"""
coreg_node with a rig's devices list (issue 23): every device calibrated with A, each its own.

The node runs in a subprocess with a parameter file that names two devices (an optical
tracker and an EM sensor, position only, on their own clocks); this process plays the rig's
streams with real publishers, calls ``~/calibrate`` and reads each device's results, its
/diagnostics statuses and /tf_static, as a ROS system would.
"""

from dataclasses import replace
import math
import subprocess
import time

from coreg_ros.core.live import guidance as gd
from coreg_ros.core.live import watchdog as wd
from coreg_ros.ros.messages import stamp_to_ns
from coreg_ros.ros.tools import (
    call_trigger,
    diagnostics_values,
    play_streams,
    wait_for_diagnostics,
    wait_for_result,
)
from coreg_ros.sim.rig import SimDevice, simulate_rig
import numpy as np
import pytest
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rosproc import PY

pytestmark = pytest.mark.ros

A = '/robot/tool'
DEVICES = (SimDevice('optical', 'full_pose', 50.0, (3e-4, 1e-3), 0.004),
           SimDevice('em', 'position_only', 40.0, (5e-4, 2e-3), 0.020))
PARAMS = {'topic_a': A, 'sigma_a': [2e-4, 5e-4], 'qos_reliable': True,
          'devices': ['optical', 'em'],
          'device': {'optical': {'topic': ['/optical/pose'], 'sigma': [3e-4, 1e-3]},
                     'em': {'topic': ['/em/pose'], 'model': 'position_only',
                            'sigma': [5e-4, 2e-3]}}}
#: tf2_ros's static listener QoS (tf2_ros.StaticListenerQoS).
LISTENER_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=100,
                          reliability=ReliabilityPolicy.RELIABLE,
                          durability=DurabilityPolicy.TRANSIENT_LOCAL)


def _wait_accepted(session, device: str, expect: dict, timeout: float = 30.0) -> dict:
    """Wait until the device's main status shows ``topic accepted >= n`` for every topic."""
    end, values = time.monotonic() + timeout, {}
    while time.monotonic() < end:
        status = wait_for_diagnostics(session, f'coreg_node/{device}', timeout=3.0,
                                      accept=lambda s: s.name.endswith(': coregistration'))
        if status is not None:
            values = diagnostics_values(status)
        if all(int(values.get(f'{t} accepted', -1)) >= n for t, n in expect.items()):
            return values
    raise AssertionError(f'diagnostics of {device} never reached {expect}; last: {values}')


def _statuses(session, seconds: float) -> dict:
    """Collect the /diagnostics statuses for ``seconds``: name -> (message, values, level)."""
    from diagnostic_msgs.msg import DiagnosticArray
    got = {}

    def on_diag(msg):
        for s in msg.status:
            level = s.level[0] if isinstance(s.level, (bytes, bytearray)) else int(s.level)
            got[s.name] = (s.message, diagnostics_values(s), level)

    sub = session.node.create_subscription(DiagnosticArray, '/diagnostics', on_diag, 50)
    session.spin_until(lambda: False, seconds)
    session.node.destroy_subscription(sub)
    return got


def _static_transforms(session, seconds: float) -> dict:
    """Every transform latched on /tf_static (one message per device): child -> transform."""
    from tf2_msgs.msg import TFMessage
    got = {}

    def on_tf(msg):
        for t in msg.transforms:
            got[t.child_frame_id] = t

    sub = session.node.create_subscription(TFMessage, '/tf_static', on_tf, LISTENER_QOS)
    session.spin_until(lambda: len(got) >= 4, seconds)
    session.node.destroy_subscription(sub)
    return got


def test_a_rig_node_calibrates_guides_and_publishes_every_device(
        ros_domain, ros_session, start_node):
    rig = simulate_rig(21, 12.0, DEVICES, sigma_a=(2e-4, 5e-4))
    streams = {A: rig.stream_a, '/optical/pose': rig.streams[0][0],
               '/em/pose': rig.streams[1][0]}
    node = start_node(PARAMS)
    play_streams(ros_session, streams, rate=4.0, wait_subscribers=20.0, log=lambda s: None)
    _wait_accepted(ros_session, 'optical', {t: len(s) for t, s in streams.items()})

    # guidance per device, named by it, before any calibration
    statuses = _statuses(ros_session, 2.5)
    for name in ('optical', 'em'):
        assert f'coreg_node/{name}: {gd.STATUS_NAME}' in statuses, sorted(statuses)
    assert not [s for s in statuses if s.startswith('coreg_node:')], sorted(statuses)

    ok, message = call_trigger(ros_session, '/coreg_node/calibrate', timeout=60)
    assert ok, message + node.log()
    assert message.startswith('optical: ') and ' | em: ' in message

    for sim, truth in zip(DEVICES, rig.truths, strict=True):
        base = wait_for_result(ros_session, f'/coreg_node/{sim.name}/base_to_base', 10)
        tool = wait_for_result(ros_session, f'/coreg_node/{sim.name}/tool_to_marker', 10)
        assert base is not None and tool is not None, node.log()
        assert base.header.frame_id == f'{sim.name}_base'
        for msg, p_true in ((base, truth.p0), (tool, truth.p1)):
            p = msg.pose.pose.position
            sd = np.sqrt(np.diag(np.reshape(msg.pose.covariance, (6, 6)))[:3])
            assert np.all(np.abs(np.array([p.x, p.y, p.z]) - p_true) < 5 * sd), (sim.name, sd)

    # /tf_static: A's base is the parent of every device's base (tf2's one-parent rule),
    # A's tool the parent of every marker; T0 inverted, so B's base in A's base
    tf = _static_transforms(ros_session, 10.0)
    assert set(tf) >= {'optical_base', 'em_base', 'optical_marker', 'em_marker'}, sorted(tf)
    for sim, truth in zip(DEVICES, rig.truths, strict=True):
        t = tf[f'{sim.name}_base']
        assert t.header.frame_id == 'device_a_base'
        # T0 maps A's base into B's base: B's base origin in A's base is -R0ᵀ p0
        w, x, y, z = truth.q0
        r0 = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                       [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                       [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])
        tr = t.transform.translation
        assert np.allclose([tr.x, tr.y, tr.z], -r0.T @ truth.p0, atol=5e-3)
        assert tf[f'{sim.name}_marker'].header.frame_id == 'device_a_tool'
    stamps = {stamp_to_ns(t.header.stamp) for t in tf.values()}
    assert all(math.isfinite(s) for s in stamps)
    # the dashboard of one device
    watched = subprocess.run([PY, '-m', 'coreg_ros.cli.watch', '--once', '--node',
                              'coreg_node/em', '--timeout', '15'], env=ros_domain.env(),
                             capture_output=True, text=True, timeout=60)
    assert watched.returncode == 0, watched.stdout + watched.stderr
    assert 'coreg watch: coreg_node/em' in watched.stdout, watched.stdout
    assert node.stop() == 0, node.log()


def test_a_rig_parameter_file_with_a_device_on_as_topic_is_one_line(start_node):
    bad = {**PARAMS, 'device': {**PARAMS['device'], 'em': {'topic': [A]}}}
    node = start_node(bad)
    deadline = time.monotonic() + 30.0
    while node.alive() and time.monotonic() < deadline:
        time.sleep(0.2)
    assert not node.alive()
    log = node.log()
    assert node.stop() == 1, log
    (line,) = [ln for ln in log.splitlines() if ln.startswith('coreg_node:')]
    assert 'topic /robot/tool is given for device A and a device B' in line, log


def _moved_base(stream, shift_m):
    """B's samples after B's base moved by ``shift_m`` (m, along x): T0 changed."""
    return replace(stream, position=stream.position + np.array([shift_m, 0.0, 0.0]))


def _span(stream, lo_ns, hi_ns):
    keep = (stream.stamps >= lo_ns) & (stream.stamps < hi_ns)
    return replace(stream, stamps=stream.stamps[keep], position=stream.position[keep],
                   quat_wxyz=stream.quat_wxyz[keep])


def test_the_watchdog_of_the_device_that_moved_alone_goes_off(ros_session, start_node):
    # calibrated on the first 16 s; then the EM field generator is knocked 1 cm (20 σ) while
    # the optical tracker stays: only the EM device's watchdog may raise its alarm
    rig = simulate_rig(22, 26.0, DEVICES, sigma_a=(2e-4, 5e-4))
    topics = {A: rig.stream_a, '/optical/pose': rig.streams[0][0],
              '/em/pose': rig.streams[1][0]}
    cut = rig.stream_a.stamps[0] + 16 * 10**9
    first = {t: _span(s, 0, cut) for t, s in topics.items()}
    then = {t: _span(s, cut, np.iinfo(np.int64).max) for t, s in topics.items()}
    then['/em/pose'] = _moved_base(then['/em/pose'], 0.01)
    node = start_node(PARAMS)
    play_streams(ros_session, first, rate=4.0, wait_subscribers=20.0, log=lambda s: None)
    _wait_accepted(ros_session, 'em', {t: len(s) for t, s in first.items()})
    ok, message = call_trigger(ros_session, '/coreg_node/calibrate', timeout=60)
    assert ok, message + node.log()
    play_streams(ros_session, then, rate=1.0, wait_subscribers=5.0, log=lambda s: None)
    statuses = _statuses(ros_session, 3.0)
    em = statuses[f'coreg_node/em: {wd.STATUS_NAME}']
    optical = statuses[f'coreg_node/optical: {wd.STATUS_NAME}']
    assert em[2] == wd.ERROR, (em, node.log())
    # attributed to the EM device's T0, by the size it moved
    assert em[1][wd.KEY_CHANGE] == 't0', em
    size, sigma = (float(v) for v in em[1][wd.KEY_TRANSLATION].split(' ± '))
    assert abs(size - 10.0) < 3 * sigma, em
    assert optical[2] == wd.OK, optical
    assert node.alive(), node.log()

"""
Guidance and the watchdog in the live node, with real rclpy.

Recordings played (``coreg play``, a process) into coreg_node (in the test's process),
/diagnostics and ``~/fused_pose`` read as a user would.
"""

import shutil
import subprocess
import time

from coreg_ros.core.live import guidance as gd
from coreg_ros.core.live import watchdog as wd
from coreg_ros.core.types import PoseStream
from coreg_ros.files.bag.posebag import write_pose_bag
from coreg_ros.ros.domain import reserve_domain_id
from coreg_ros.ros.interface import LATCHED_QOS
from coreg_ros.ros.live_checks import STALE_QOS
from coreg_ros.ros.session import RosSession
from coreg_ros.ros.tools import wait_for_message, wait_for_result
from coreg_ros.ros.uncertainty_outputs import FUSED_QOS
from coreg_ros.sim import simulate_recording
from coreg_ros.sim.changes import apply_changes
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseWithCovarianceStamped
from innode import InProcessNode, Output
import numpy as np
import pytest
from rosproc import PY, run_cli
from std_msgs.msg import Bool

pytestmark = pytest.mark.ros

NODE = 'coreg_node'
# the noise of the sample recording (the simulator's default), pairs at 100 Hz
RATE = 100.0


def _slice(stream: PoseStream, lo_ns: int, hi_ns: int) -> PoseStream:
    keep = (stream.stamps >= lo_ns) & (stream.stamps < hi_ns)
    return PoseStream(stream.stamps[keep], stream.position[keep], stream.quat_wxyz[keep],
                      stream.frame_id)


def _bags(tmp_path, rec, cuts_s):
    """Write the recording's spans [cuts_s[k], cuts_s[k + 1]) as bags; return their paths."""
    paths = []
    for k in range(len(cuts_s) - 1):
        lo, hi = (rec.start_ns + int(c * 1e9) for c in cuts_s[k:k + 2])
        path = tmp_path / f'part{k}'
        write_pose_bag(path, {t: _slice(s, lo, hi) for t, s in rec.streams.items()})
        paths.append(path)
    return paths


class Collector:
    """Record the node's statuses by concern, the fused poses and the stale flag as they come."""

    def __init__(self, session):
        self.session = session
        self.statuses = {'coregistration': [], gd.STATUS_NAME: [], wd.STATUS_NAME: []}
        self.fused = []  # monotonic receipt times
        self.stale = []
        node = session.node
        node.create_subscription(DiagnosticArray, '/diagnostics', self._on_diag, 50)
        node.create_subscription(PoseWithCovarianceStamped, f'/{NODE}/fused_pose',
                                 lambda m: self.fused.append(time.monotonic()), FUSED_QOS)
        node.create_subscription(Bool, f'/{NODE}/calibration_stale',
                                 lambda m: self.stale.append(bool(m.data)), STALE_QOS)

    def _on_diag(self, msg) -> None:
        now = time.monotonic()
        for s in msg.status:
            concern = s.name.split(': ', 1)[-1]
            if s.name.startswith(f'{NODE}:') and concern in self.statuses:
                level = s.level[0] if isinstance(s.level, (bytes, bytearray)) else int(s.level)
                self.statuses[concern].append(
                    (now, level, s.message, {kv.key: kv.value for kv in s.values}))

    def last(self, concern):
        got = self.statuses[concern]
        return got[-1] if got else None

    def spin(self, seconds: float, done=lambda: False) -> bool:
        return self.session.spin_until(done, seconds)

    def play(self, domain, bag, rate: float, timeout: float = 90.0) -> None:
        """Play a bag into the node (``coreg play``) while collecting."""
        proc = subprocess.Popen([PY, '-m', 'coreg_ros.cli.ros_commands', 'play', str(bag),
                                 '--rate', str(rate), '--wait', '20'], env=domain.env(),
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        try:
            self.spin(timeout, lambda: proc.poll() is not None)
        finally:
            if proc.poll() is None:
                proc.kill()
        out, err = proc.communicate()
        assert proc.returncode == 0, out + err

    def settled_guidance(self, timeout: float = 15.0) -> dict:
        """Guidance values once its pair count stopped growing (the feed released all)."""
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            got = [v for _, _, _, v in self.statuses[gd.STATUS_NAME]]
            if (len(got) >= 3 and gd.KEY_WORST in got[-1]
                    and got[-1][gd.KEY_PAIRS] == got[-2][gd.KEY_PAIRS] == got[-3][gd.KEY_PAIRS]):
                return got[-1]
            self.spin(1.0)
        raise AssertionError(f'guidance never settled: {self.last(gd.STATUS_NAME)}')


def _sigmas(values, name):
    return np.array([float(v) for v in values[gd.KEY_SIGMA_PREFIX + name].split()])


def _cov_sd(msg):
    return np.sqrt(np.diag(np.reshape(msg.pose.covariance, (6, 6))))


def _calibrate(domain, node):
    called = run_cli(domain, 'call', 'calibrate', '--timeout', 60)
    assert called.returncode == 0 and 'success' in called.stdout, (
        called.stdout + called.stderr + node.log())
    return called.stdout


def test_guidance_sigma_is_the_calibrations_and_a_stable_recording_raises_no_alarm(
        ros_domain, ros_session, start_node_here, tmp_path):
    rec = simulate_recording(71, 90.0, rate_a=RATE, rate_b=RATE)
    collecting, stable = _bags(tmp_path, rec, [0.0, 30.0, 90.0])
    node = start_node_here({'qos_reliable': True})
    watch = Collector(ros_session)
    watch.play(ros_domain, collecting, rate=4.0)
    guidance = watch.settled_guidance()
    assert watch.last(wd.STATUS_NAME) is None  # no calibration yet: nothing to watch
    n_guided = int(guidance[gd.KEY_PAIRS])
    answer = _calibrate(ros_domain, node)
    n_pairs = int(answer.split(' pairs')[0].split()[-1])
    assert abs(n_guided - n_pairs) <= 0.01 * n_pairs, (n_guided, answer)
    base = wait_for_result(ros_session, f'/{NODE}/base_to_base', timeout=5)
    tool = wait_for_result(ros_session, f'/{NODE}/tool_to_marker', timeout=5)
    # the σ guidance showed before the calibration is the σ the calibration reports (10 %)
    reported = {'p0': _cov_sd(base)[:3], 'theta0': _cov_sd(base)[3:],
                'p1': _cov_sd(tool)[:3], 'theta1': _cov_sd(tool)[3:]}
    for name, sd in reported.items():
        ratio = _sigmas(guidance, name) / sd
        assert np.all(np.abs(ratio - 1.0) < 0.10), (name, ratio, answer)
    tau_sd = float(answer.split('time offset ')[1].split(' ± ')[1].split(' ms')[0]) * 1e-3
    ratio = _sigmas(guidance, 'time_offset')[0] / tau_sd
    assert abs(ratio - 1.0) < 0.10, (ratio, answer)

    # watched from now on: a stable recording (60 s at 100 Hz) raises no alarm
    watch.spin(2.0)
    before = len(watch.statuses[wd.STATUS_NAME])
    fused_before = len(watch.fused)
    watch.play(ros_domain, stable, rate=4.0)
    watch.spin(3.0)
    states = watch.statuses[wd.STATUS_NAME][before:]
    assert states and all(level == wd.OK for _, level, _, _ in states), [
        m for _, level, m, _ in states if level != wd.OK]
    values = states[-1][3]
    assert int(values[wd.KEY_CHECKED]) > 0.98 * 60 * RATE, values
    assert values[wd.KEY_STALE] == 'false' and values[wd.KEY_CHANGE] == 'none'
    assert 0.8 < float(values[wd.KEY_MEAN_D2]) < 1.25, values
    assert len(watch.fused) - fused_before > 100  # fusing goes on
    assert watch.stale and watch.stale[-1] is False
    assert node.alive(), node.log()


#: (change, attributed kind, /diagnostics key of its size, text in the message)
STEPS = [('t0_step=2mm', 't0', wd.KEY_TRANSLATION, 'T0 moved'),
         ('t0_step=0.5deg', 't0', wd.KEY_ROTATION, 'T0 moved'),
         ('t1_step=2mm', 't1', wd.KEY_TRANSLATION, 'T1 moved'),
         ('t1_step=0.5deg', 't1', wd.KEY_ROTATION, 'T1 moved'),
         ('clock_step=10ms', 'clock', wd.KEY_CLOCK, 'clock offset changed')]


def _true_size(change: dict, key: str) -> float:
    """Return the injected size in the unit of the /diagnostics key (mm, degrees, ms)."""
    if key == wd.KEY_TRANSLATION:
        return float(np.linalg.norm(change['translation_m'])) * 1e3
    if key == wd.KEY_ROTATION:
        return float(np.degrees(np.linalg.norm(change['rotation_rad'])))
    return abs(change['clock_s']) * 1e3


#: The steps' recording (seed, duration, s): the change comes at CHANGE_S, after BEFORE_S.
STEP_RECORDING, CHANGE_S, BEFORE_S = (72, 56.0), 43.0, 40.0


class _Uncaptured:
    """The output of a node made outside a test (no capfd): left to pytest's own capture."""

    @staticmethod
    def readouterr():
        return '', ''


@pytest.fixture(scope='module')
def calibrated_before(tmp_path_factory):
    """
    Return the storage of a node that calibrated the steps' first BEFORE_S seconds and stopped.

    Every step changes the same recording only after BEFORE_S (the test checks it), so the
    calibration before it is made once, in a domain of its own, by a real node and service call.
    """
    folder = tmp_path_factory.mktemp('before')
    rec = simulate_recording(*STEP_RECORDING, rate_a=RATE, rate_b=RATE)
    (before,) = _bags(folder, rec, [0.0, BEFORE_S])
    domain = reserve_domain_id()
    session = RosSession('coreg_test_before', domain_id=domain.domain_id, signals=False)
    try:
        first = InProcessNode(domain, folder, {'qos_reliable': True}, Output(_Uncaptured()),
                              name='first')
        try:
            watch = Collector(session)
            watch.play(domain, before, rate=4.0)
            watch.spin(2.0)
            _calibrate(domain, first)
        finally:
            code = first.stop()
        assert code == 0, first.log()
    finally:
        session.close()
        domain.release()
    return rec, first.storage


@pytest.mark.parametrize('spec, kind, key, text', STEPS)
def test_step_is_detected_attributed_and_stops_the_fused_pose(ros_domain, ros_session,
                                                              start_node_here, tmp_path,
                                                              calibrated_before, spec, kind,
                                                              key, text):
    unchanged, stored = calibrated_before
    rec = apply_changes(simulate_recording(*STEP_RECORDING, rate_a=RATE, rate_b=RATE),
                        [f'{spec}@{CHANGE_S}'], seed=72)
    change = rec.truth.effects[-1]
    # the change leaves the calibrated part as it was
    end = rec.start_ns + int(BEFORE_S * 1e9)
    for topic, s in rec.streams.items():
        was = unchanged.streams[topic]
        assert np.array_equal(s.stamps[s.stamps < end], was.stamps[was.stamps < end])
        assert np.array_equal(s.position[s.stamps < end], was.position[was.stamps < end])
        assert np.array_equal(s.quat_wxyz[s.stamps < end], was.quat_wxyz[was.stamps < end])
    (after,) = _bags(tmp_path, rec, [BEFORE_S, 56.0])
    watch = Collector(ros_session)
    # a restarted node watches the stored calibration it republishes
    storage = shutil.copytree(stored, tmp_path / 'store')
    node = start_node_here({'qos_reliable': True, 'storage_dir': str(storage)}, name='again')
    assert wait_for_result(ros_session, f'/{NODE}/base_to_base', timeout=20) is not None
    n0 = len(watch.statuses[wd.STATUS_NAME])
    watch.play(ros_domain, after, rate=1.0)  # real time: the node checks once a second
    watch.spin(2.0)
    states = watch.statuses[wd.STATUS_NAME][n0:]
    levels = [level for _, level, _, _ in states]
    assert wd.ERROR in levels, (states[-1], node.log())
    # OK while the calibration holds, then WARN (alarm) until ERROR (attributed), latched; the
    # status goes out once a second, so an attribution decided within that second shows no WARN
    first_bad = next(i for i, lv in enumerate(levels) if lv != wd.OK)
    first_error = levels.index(wd.ERROR)
    assert first_bad >= 2, levels
    assert all(lv == wd.WARN for lv in levels[first_bad:first_error]), levels
    assert all(lv == wd.ERROR for lv in levels[first_error:]), levels
    t_error, _, message, values = states[first_error]
    final = states[-1][3]
    assert final[wd.KEY_CHANGE] == kind, final
    assert text in message and final[wd.KEY_STALE] == 'true'
    assert '~/fused_pose stopped' in states[-1][2]
    alarm_s = (int(final[wd.KEY_ALARM_STAMP]) - change['start_ns']) * 1e-9
    assert 0.0 <= alarm_s < 5.0, final
    size, sigma = (abs(float(v)) for v in final[key].split(' ± '))
    assert abs(size - _true_size(change, key)) < 3.0 * sigma, final
    # ~/fused_pose fused until the change was found, and stopped then (data kept coming)
    assert any(t < t_error for t in watch.fused)
    assert not [t for t in watch.fused if t > t_error + 1.0], (t_error, watch.fused[-5:])
    assert watch.stale[-1] is True
    assert wait_for_message(ros_session, Bool, f'/{NODE}/calibration_stale', STALE_QOS,
                            5.0).data is True
    assert LATCHED_QOS.durability == STALE_QOS.durability
    assert node.alive(), node.log()


def test_auto_calibrate_then_auto_recalibrate_after_a_t0_step(ros_domain, ros_session,
                                                              start_node_here, tmp_path):
    rec = apply_changes(simulate_recording(73, 75.0, rate_a=RATE, rate_b=RATE),
                        ['t0_step=2mm@45'], seed=73)
    change = rec.truth.effects[-1]
    (bag,) = _bags(tmp_path, rec, [0.0, 75.0])
    node = start_node_here({'qos_reliable': True, 'auto_calibrate': True,
                            'auto_recalibrate': True})
    watch = Collector(ros_session)
    bases = []
    ros_session.node.create_subscription(PoseWithCovarianceStamped, f'/{NODE}/base_to_base',
                                         bases.append, LATCHED_QOS)
    watch.play(ros_domain, bag, rate=4.0)
    watch.spin(3.0)
    log = node.log()
    # calibrated once guidance said ready, long before the change; recalibrated after it
    assert log.count('calibrated (auto_calibrate)') == 1, log
    assert log.count('calibrated (auto_recalibrate)') == 1, log
    assert len(bases) == 2, log
    first, second = (np.array([m.pose.pose.position.x, m.pose.pose.position.y,
                               m.pose.pose.position.z]) for m in bases)
    sd = _cov_sd(bases[1])[:3]
    moved = second - first
    assert np.all(np.abs(moved - change['translation_m']) < 4 * sd + 1e-4), (moved, change)
    levels = [level for _, level, _, _ in watch.statuses[wd.STATUS_NAME]]
    assert wd.ERROR in levels
    # the new calibration is watched afresh: the pairs fit it, fusion goes on
    final = watch.last(wd.STATUS_NAME)
    assert final[1] == wd.OK and final[3][wd.KEY_CHANGE] == 'none', final
    assert watch.stale[-1] is False
    assert node.alive(), log

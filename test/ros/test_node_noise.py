"""
The node's noise (issue 24): measured while still, shown, used; a bad noise file refused.

Measured while the devices stand still, shown on /diagnostics and used with ``noise: auto``; a
``noise_file`` read at start-up, a bad one refused in one line.

A simulated recording whose tool stops twice (``sim.still.paused``) is played (``coreg play``,
a process) into coreg_node (in the test's process); /diagnostics and ``~/calibrate`` are read
as a user would.
"""

import time

from coreg_ros.core.noise_model import DeviceNoise
from coreg_ros.files.bag.posebag import write_pose_bag
from coreg_ros.files.noise_file import device_block, noise_document, write_noise_file
from coreg_ros.sim import make_motion, simulate_recording
from coreg_ros.sim.still import paused
import numpy as np
import pytest
from rosproc import run_cli
from test_node_guidance import Collector

pytestmark = pytest.mark.ros

NODE = 'coreg_node'
SIGMA_A, SIGMA_B = (2e-4, 1e-3), (6e-4, 3e-3)


def _recording(tmp_path):
    motion = paused(make_motion(np.random.default_rng(8), 'diverse'), [(4.0, 7.0), (20.0, 7.0)])
    rec = simulate_recording(8, 36.0, rate_a=100.0, rate_b=100.0, sigma_a=SIGMA_A,
                             sigma_b=SIGMA_B, motion=motion)
    bag = tmp_path / 'still'
    write_pose_bag(bag, rec.streams)
    return bag


def _noise_values(watch):
    got = [v for _, _, _, v in watch.statuses.get('noise', [])]
    return got[-1] if got else None


def _sigmas(values, key):
    return np.array([float(v) for v in values[key].split()])


def test_noise_measured_while_still_and_used_with_auto(ros_domain, ros_session,
                                                       start_node_here, tmp_path):
    bag = _recording(tmp_path)
    # the file states B at half its noise (and is for these topics)
    stated_b = DeviceNoise.isotropic((SIGMA_B[0] / 2, SIGMA_B[1] / 2))
    noise_file = write_noise_file(tmp_path / 'noise.yaml', noise_document(
        {'device_b': device_block(stated_b, '/device_b/pose')}, 'hand-written'))
    node = start_node_here({'qos_reliable': True, 'noise': 'auto',
                            'noise_file': str(noise_file)})
    watch = Collector(ros_session)
    watch.statuses['noise'] = []
    watch.play(ros_domain, bag, rate=3.0)
    watch.spin(3.0)
    values = _noise_values(watch)
    assert values is not None, node.log()
    for d, truth in (('A', SIGMA_A), ('B', SIGMA_B)):
        assert float(values[f'{d} still seconds']) > 8.0, values
        pos = _sigmas(values, f'{d} measured position sigma m')
        rot = _sigmas(values, f'{d} measured rotation sigma rad')
        assert np.all(np.abs(pos / truth[0] - 1) < 0.2), (d, pos)
        assert np.all(np.abs(rot / truth[1] - 1) < 0.2), (d, rot)
        assert values[f'{d} source'] == 'measured while still'
        # what is used now is what was measured, not the file's
        np.testing.assert_allclose(_sigmas(values, f'{d} used position sigma m'), pos,
                                   rtol=1e-2)
    assert np.allclose(_sigmas(values, 'B stated position sigma m'), SIGMA_B[0] / 2)
    # coreg watch shows it
    from coreg_ros.cli.dashboard import DashboardState, render_text, Status
    _, level, message, _ = watch.statuses['noise'][-1]
    state = DashboardState.from_statuses([Status(f'{NODE}: noise', level, message, values)])
    text = render_text(state, width=140)
    assert 'noise (auto)' in text and 'still σ' in text and 'measured while still' in text
    called = run_cli(ros_domain, 'call', 'calibrate', '--timeout', 60)
    assert called.returncode == 0 and 'success' in called.stdout, called.stdout + node.log()
    watch.spin(2.5)
    values = _noise_values(watch)
    assert values['B source'] == 'estimated with the last calibration', values
    assert node.alive(), node.log()


def test_noise_file_for_other_topics_is_refused_at_start(ros_domain, start_node, tmp_path):
    other = write_noise_file(tmp_path / 'other.yaml', noise_document(
        {'device_a': device_block(DeviceNoise.isotropic(SIGMA_A), '/robot/pose')}, 'measured'))
    node = start_node({'noise_file': str(other)})
    deadline = time.monotonic() + 30
    while node.alive() and time.monotonic() < deadline:
        time.sleep(0.2)
    assert not node.alive()
    log = node.log()
    assert 'device A noise is for topic /robot/pose' in log, log
    assert 'Traceback' not in log

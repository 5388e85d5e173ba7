"""
The live node and ``coreg calibrate`` give the same numbers from the same messages.

Clock offset and rejected pairs included; and the node refuses to publish an inconsistent fit.
"""

import json
import subprocess
import sys

from coreg_ros.files.bag.posebag import write_pose_bag
from coreg_ros.ros.tools import wait_for_diagnostics, wait_for_result
from coreg_ros.sim import parse_effect, simulate_recording
import numpy as np
import pytest
from rosproc import run_cli, wait_counts
from strategies import with_outliers

pytestmark = pytest.mark.ros

A, B = '/device_a/pose', '/device_b/pose'


def _recording(tmp_path, seed, outliers=0.0, effects=()):
    rec = simulate_recording(seed, 6.0, effects=[parse_effect(e) for e in effects])
    streams = dict(rec.streams)
    if outliers:
        streams[B] = with_outliers(streams[B], outliers, np.random.default_rng(seed))
    bag = tmp_path / f'rec{seed}'
    write_pose_bag(bag, streams)
    return bag, {t: len(s) for t, s in streams.items()}


def _cli_json(bag, tmp_path, *extra):
    out = tmp_path / 'offline.json'
    cli = subprocess.run([sys.executable, '-m', 'coreg_ros.cli.main', 'calibrate', str(bag),
                          '--json', str(out), *extra], capture_output=True, text=True,
                         timeout=120)
    return cli, json.loads(out.read_text())


def _feed(ros_domain, ros_session, start_node, bag, n, params=None):
    node = start_node({'qos_reliable': True, **(params or {})})
    played = run_cli(ros_domain, 'play', bag, '--rate', 4, '--wait', 20)
    assert played.returncode == 0, played.stderr + node.log()
    wait_counts(ros_session, {f'{A} accepted': n[A], f'{B} accepted': n[B]}, timeout=10)
    return node


def test_node_and_cli_agree_on_offset_and_rejected_pairs(ros_domain, ros_session,
                                                         start_node_here, tmp_path):
    bag, n = _recording(tmp_path, 61, outliers=0.02, effects=['time_offset=0.025'])
    node = _feed(ros_domain, ros_session, start_node_here, bag, n)
    called = run_cli(ros_domain, 'call', 'calibrate', '--timeout', 60)
    assert called.returncode == 0 and 'success' in called.stdout, called.stdout + node.log()
    cli, offline = _cli_json(bag, tmp_path)
    assert cli.returncode == 0, cli.stderr
    t = offline['time_offset']
    assert t['estimated'] and abs(t['value_s'] - 0.025) < 3 * t['sigma_s'] + 1e-6
    assert offline['rejected_pairs']['count'] > 0
    # the node's answer names the same offset and the same number of rejected pairs
    assert f"time offset {t['value_s'] * 1e3:.3f} ± {t['sigma_s'] * 1e3:.3f} ms" in \
        called.stdout, called.stdout
    assert f"{offline['rejected_pairs']['count']} rejected" in called.stdout
    base = wait_for_result(ros_session, '/coreg_node/base_to_base', timeout=5)
    p = base.pose.pose.position
    np.testing.assert_allclose([p.x, p.y, p.z], offline['base_to_base']['position'],
                               rtol=0, atol=1e-9)
    np.testing.assert_allclose(np.reshape(base.pose.covariance, 36),
                               offline['base_to_base']['covariance'], rtol=1e-7, atol=1e-18)
    status = wait_for_diagnostics(ros_session, timeout=5)
    values = {kv.key: kv.value for kv in status.values}
    # /diagnostics shows 6 significant digits
    assert float(values['last calibration time_offset_s']) == pytest.approx(t['value_s'],
                                                                            rel=1e-5)


def test_node_refuses_an_inconsistent_fit_unless_asked(ros_domain, ros_session,
                                                       start_node_here, tmp_path):
    # B's noise understated twofold: the fit contradicts the stated noise everywhere
    bag, n = _recording(tmp_path, 62)
    params = {'sigma_b': [0.00025, 0.001]}
    node = _feed(ros_domain, ros_session, start_node_here, bag, n, params)
    called = run_cli(ros_domain, 'call', 'calibrate', '--timeout', 60)
    assert 'not published' in called.stdout and 'does not match the stated noise' in \
        called.stdout, called.stdout + node.log()
    assert wait_for_result(ros_session, '/coreg_node/base_to_base', timeout=2) is None
    cli, offline = _cli_json(bag, tmp_path, '--sigma-b', '0.00025', '0.001')
    assert cli.returncode == 3 and offline['fit_consistent'] is False, cli.stderr
    assert offline['rescaled_covariance']['factor'] > 1.5
    node.stop()
    # with publish_inconsistent the same fit is published, flagged
    node = _feed(ros_domain, ros_session, start_node_here, bag, n,
                 {**params, 'publish_inconsistent': True})
    called = run_cli(ros_domain, 'call', 'calibrate', '--timeout', 60)
    assert 'PUBLISHED ALTHOUGH INCONSISTENT' in called.stdout, called.stdout + node.log()
    assert wait_for_result(ros_session, '/coreg_node/base_to_base', timeout=5) is not None

"""
A SCARA recording through the command line, as a user runs it (issue 22).

``coreg simulate --motion scara`` then ``coreg calibrate``: calibrated, not refused; the held
direction said in the text and in the JSON (12 numbers, by "held"), the published covariance
unknown along it; a partial prior on T1's position determines it (by "prior"); the gravity
preset's bad σ is one line.
"""

import json
from pathlib import Path
import subprocess
import sys

from coreg_ros.core.calibration.observability import UNKNOWN_VARIANCE
import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[2]


def coreg(*args, timeout=120):
    """Run ``coreg`` in a subprocess (what a user sees)."""
    return subprocess.run([sys.executable, '-m', 'coreg_ros.cli.main', *map(str, args)],
                          capture_output=True, text=True, timeout=timeout, cwd=ROOT)


@pytest.fixture(scope='module')
def scara_bag(tmp_path_factory):
    bag = tmp_path_factory.mktemp('scara') / 'bag'
    done = coreg('simulate', bag, '--motion', 'scara', '--duration', 30, '--seed', 3)
    assert done.returncode == 0, done.stderr
    return bag


def test_a_scara_recording_is_calibrated_with_the_lever_held(scara_bag, tmp_path):
    out = tmp_path / 'r.json'
    done = coreg('calibrate', scara_bag, '--json', out)
    assert done.returncode == 0, done.stderr
    assert 'unobservable: T1' in done.stdout and 'held at tool_to_marker' in done.stdout
    doc = json.loads(out.read_text())
    assert doc['success'] and len(doc['unobservable']) == 1
    held = doc['unobservable'][0]
    u = np.array(held['direction'])
    assert held['by'] == 'held' and u.shape == (12,) and abs(np.linalg.norm(u) - 1) < 1e-9
    cov = np.array(doc['cov_joint']).reshape(12, 12)
    determined = np.array(doc['cov_determined']).reshape(12, 12)
    assert u @ cov @ u > 0.5 * UNKNOWN_VARIANCE  # marked unknown along the held direction
    assert u @ determined @ u < 1e-12  # and the determined part says nothing along it
    truth = json.loads(Path(f'{scara_bag}.truth.json').read_text())
    assert truth  # the simulator's truth sits beside the bag


def test_a_partial_prior_on_the_lever_determines_it(scara_bag, tmp_path):
    first = tmp_path / 'first.json'
    assert coreg('calibrate', scara_bag, '--json', first).returncode == 0
    t1 = json.loads(first.read_text())['tool_to_marker']
    prior = tmp_path / 'prior.yaml'
    prior.write_text(json.dumps({'tool_to_marker': {
        'position': t1['position'], 'sigma': [0.005, 0.005, 0.005, None, None, None]}}))
    out = tmp_path / 'r.json'
    done = coreg('calibrate', scara_bag, '--prior', prior, '--json', out)
    assert done.returncode == 0, done.stderr
    doc = json.loads(out.read_text())
    assert doc['success'] and [u['by'] for u in doc['unobservable']] == ['prior']
    assert doc['prior_check']['consistent']
    u = np.array(doc['unobservable'][0]['direction'])
    sd = np.sqrt(u @ np.array(doc['cov_joint']).reshape(12, 12) @ u)
    assert 1e-3 < sd < 0.02  # the prior's 5 mm along the lever, not unknown


def test_the_gravity_preset_refuses_a_bad_sigma_in_one_line(scara_bag):
    done = coreg('calibrate', scara_bag, '--gravity-aligned', '-1')
    assert done.returncode != 0 and 'Traceback' not in done.stderr
    assert done.stderr.strip().count('\n') == 0 and 'gravity-aligned' in done.stderr

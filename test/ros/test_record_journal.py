"""`coreg record` writes as it goes: kill -9 loses at most about a second, --recover keeps it."""

import signal
import subprocess
import sys
import time

from coreg_ros.files.bag.posebag import read_pose_bag, write_pose_bag
from coreg_ros.sim import simulate_recording
import numpy as np
import pytest
from rosproc import run_cli

pytestmark = pytest.mark.ros

A, B = '/device_a/pose', '/device_b/pose'


def test_killed_record_keeps_what_it_had_and_recovers(ros_domain, tmp_path):
    rec = simulate_recording(81, 12.0)
    bag = tmp_path / 'source'
    write_pose_bag(bag, rec.streams)
    out = tmp_path / 'recorded'
    recorder = subprocess.Popen(
        [sys.executable, '-m', 'coreg_ros.cli.ros_commands', 'record', str(out), '--topics', A,
         B], env=ros_domain.env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        time.sleep(3.0)  # discovery
        player = subprocess.Popen(
            [sys.executable, '-m', 'coreg_ros.cli.ros_commands', 'play', str(bag), '--rate',
             '1', '--wait', '20'], env=ros_domain.env(), stdout=subprocess.PIPE,
            stderr=subprocess.PIPE, text=True)
        time.sleep(7.0)  # a few seconds of samples on the way
        recorder.send_signal(signal.SIGKILL)
        recorder.wait(timeout=10)
        player.wait(timeout=30)
    finally:
        for p in (recorder,):
            if p.poll() is None:
                p.kill()
    partial = tmp_path / 'recorded.partial'
    assert partial.is_dir() and not out.exists()
    again = run_cli(ros_domain, 'record', out, '--topics', A, B, timeout=60)
    assert again.returncode == 1 and '--recover' in again.stderr, again.stderr
    recovered = run_cli(ros_domain, 'record', out, '--topics', A, B, '--recover', timeout=60)
    assert recovered.returncode == 0, recovered.stderr
    assert not partial.exists()
    got = read_pose_bag(out, [A, B])
    sent = rec.streams
    for t in (A, B):
        n = len(got[t])
        # played at real time for ~4 s before the kill (after ~3 s of discovery and start-up),
        # at most the last second lost: a prefix of what was sent, in order
        assert n > 100, (t, n)
        np.testing.assert_array_equal(got[t].stamps, sent[t].stamps[:n])

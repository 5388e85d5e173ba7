"""
A's trajectory: the velocity written in a second thread (``velocity_arriving``) is the velocity.

The offset step reads its rows while they are made; these tests hold it to the numbers of the
velocity made at once, to the bit, and to the errors it raises.
"""

from coreg_ros.core.calibration.pipeline import calibrate_streams
from coreg_ros.core.clock import trajectory as trajectory_module
from coreg_ros.core.clock.trajectory import ARRIVING_CHUNKS, Trajectory, VELOCITY_CHUNK
from coreg_ros.core.settings import Settings
from coreg_ros.sim import parse_effect, simulate_recording
import numpy as np
import pytest


def _trajectory(rng, n):
    """Sample a random motion at n irregular times, with a few gaps of 0.2 s."""
    step = rng.uniform(0.5e-3, 1.5e-3, n)
    step[rng.integers(0, n, 5)] = 0.2
    t = np.cumsum(step)
    pos = np.cumsum(rng.normal(scale=1e-3, size=(n, 3)), axis=0)
    q = rng.normal(size=(n, 4)) * 0.02 + np.array([1.0, 0.0, 0.0, 0.0])
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return Trajectory(t, pos, q)


@pytest.mark.parametrize('seed', range(3))
def test_velocity_arriving_is_the_velocity_row_by_row(seed):
    rng = np.random.default_rng(seed)
    n = (ARRIVING_CHUNKS + 1) * VELOCITY_CHUNK + 17  # beyond the chunks written at once
    traj = _trajectory(rng, n + 84)
    t = np.sort(rng.uniform(traj.t[0] - 0.01, traj.t[-1] + 0.01, n))
    expected = np.empty((t.size, 6))
    traj.velocity(t, 0.004, max_gap=0.05, out=expected)
    got = np.full((t.size, 6), np.nan)
    ready = traj.velocity_arriving(t, 0.004, 0.05, got)
    assert isinstance(ready.__self__, trajectory_module._RowsWritten)  # a writer thread
    for stop in (1, VELOCITY_CHUNK, VELOCITY_CHUNK + 1, 2 * VELOCITY_CHUNK + 5, t.size):
        ready(stop)  # the rows before stop are final once it returns
        assert np.array_equal(got[:stop], expected[:stop])
    assert np.any(expected == 0.0) and np.any(expected != 0.0)  # gaps and motion both seen


def test_an_error_of_the_writer_is_raised_by_the_reader():
    rng = np.random.default_rng(7)
    traj = _trajectory(rng, 1000)
    t = np.linspace(traj.t[0], traj.t[-1], (ARRIVING_CHUNKS + 1) * VELOCITY_CHUNK)
    ready = traj.velocity_arriving(t, 0.004, None, np.empty((t.size, 2)))  # no room for v
    with pytest.raises(ValueError):
        ready(t.size)


def test_offset_estimate_is_the_same_with_the_velocity_arriving(monkeypatch):
    """The whole offset search with the velocity made in a thread gives the same numbers."""
    rec = simulate_recording(5, 40.0, 'full_pose', rate_a=200.0, rate_b=100.0,
                             effects=[parse_effect('time_offset=0.02')])
    a, bs = rec.streams[rec.topics_a], [rec.streams[t] for t in rec.topics_b]
    at_once, _ = calibrate_streams(a, bs, Settings())
    monkeypatch.setattr(trajectory_module, 'VELOCITY_CHUNK', 512)  # ~8 chunks: a thread
    threads = []
    arriving = Trajectory.velocity_arriving

    def counted(self, t, *args):
        threads.append(t.shape[0] > ARRIVING_CHUNKS * trajectory_module.VELOCITY_CHUNK)
        return arriving(self, t, *args)

    monkeypatch.setattr(Trajectory, 'velocity_arriving', counted)
    in_thread, _ = calibrate_streams(a, bs, Settings())
    assert any(threads)
    assert at_once.time_offset.estimated
    assert in_thread.time_offset.value_s == at_once.time_offset.value_s
    assert in_thread.time_offset.sigma_s == at_once.time_offset.sigma_s
    assert np.array_equal(in_thread.params, at_once.params)
    assert np.array_equal(in_thread.param_cov, at_once.param_cov)

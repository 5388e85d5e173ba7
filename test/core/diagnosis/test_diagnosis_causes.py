"""The cheap causes first (issue 26, item 1): a mistake a check names is the answer, no effect."""

import dataclasses

from coreg_ros.cli.main import main
from coreg_ros.core.diagnosis import diagnose_streams
from coreg_ros.core.errors import UnobservableError
from coreg_ros.core.settings import Settings
from coreg_ros.files.bag.posebag import write_pose_bag
from coreg_ros.sim import simulate_recording
import numpy as np
import pytest


def _answer(stream_a, streams_b, model='full_pose'):
    return diagnose_streams(stream_a, list(streams_b), Settings(model=model)).report


@pytest.mark.parametrize('seed', [1, 2])
def test_b_in_millimetres_is_named_units_and_never_sized_as_an_effect(seed):
    rec = simulate_recording(seed, 20.0)
    b = rec.streams_b[0]
    report = _answer(rec.stream_a, [dataclasses.replace(b, position=b.position * 1e3)])
    assert report.cause is not None and report.cause.check == 'units'
    assert 'mm' in report.cause.text
    assert not report.effects


def test_a_position_only_device_read_as_a_full_pose_is_named():
    rec = simulate_recording(3, 20.0, 'position_only')
    report = _answer(rec.stream_a, rec.streams_b, model='full_pose')
    assert report.cause is not None and report.cause.check == 'orientation_missing'
    assert '--model position_only' in report.cause.text
    assert not report.effects


def test_a_device_that_stops_moving_is_named_with_when():
    rng = np.random.default_rng(26)
    rec = simulate_recording(4, 30.0)
    b = rec.streams_b[0]
    # B repeats one sample for a random 2-5 s at a random time (it lost tracking)
    length = int(rng.integers(100, 250))
    k = int(rng.integers(50, len(b) - length - 50))
    p, q = b.position.copy(), b.quat_wxyz.copy()
    p[k:k + length], q[k:k + length] = p[k], q[k]
    report = _answer(rec.stream_a, [dataclasses.replace(b, position=p, quat_wxyz=q)])
    assert report.cause is not None and report.cause.check == 'frozen_device'
    start = (int(b.stamps[k]) - min(int(b.stamps[0]), int(rec.stream_a.stamps[0]))) * 1e-9
    assert f'from {start:.1f} s' in report.cause.text
    assert not report.effects


def test_nothing_moved_is_refused_as_calibrate_refuses_it():
    rec = simulate_recording(5, 15.0, motion='static')
    with pytest.raises(UnobservableError, match='did not move'):
        _answer(rec.stream_a, rec.streams_b)


def test_cli_names_the_cause_in_one_line_and_fails(tmp_path, capsys):
    rec = simulate_recording(6, 15.0)
    streams = dict(rec.streams)
    topic = rec.topics_b[0]
    streams[topic] = dataclasses.replace(streams[topic], position=streams[topic].position * 1e3)
    bag = tmp_path / 'mm'
    write_pose_bag(bag, streams)
    assert main(['diagnose', str(bag), '--quiet']) == 1
    err = capsys.readouterr().err
    assert err.startswith('coreg diagnose: error:') and err.count('\n') == 1
    assert 'mm' in err and 'Traceback' not in err

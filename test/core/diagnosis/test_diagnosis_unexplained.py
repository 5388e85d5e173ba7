"""Outside the library (issue 26, item 6): unexplained structure with its signature."""

import dataclasses

from coreg_ros.core.diagnosis import diagnose_streams
from coreg_ros.core.settings import Settings
from coreg_ros.report.html import write_report
from coreg_ros.sim import simulate_recording
import numpy as np


def test_a_vibrating_mount_is_unexplained_structure_in_its_channel_not_a_structured_name(
        tmp_path):
    # B's mount sways along one axis of B's base (a form no effect of the library has):
    # amplitude 2-4 mm, period 5-10 s, drawn
    rng = np.random.default_rng(2680)
    amplitude, period = rng.uniform(0.002, 0.004), rng.uniform(5.0, 10.0)
    axis = int(rng.integers(3))
    rec = simulate_recording(int(rng.integers(1000)), 30.0)
    b = rec.streams_b[0]
    t = (b.stamps - b.stamps[0]) * 1e-9
    p = b.position.copy()
    p[:, axis] += amplitude * np.sin(2 * np.pi * t / period)
    diag = diagnose_streams(rec.stream_a, [dataclasses.replace(b, position=p)], Settings())
    r = diag.report.as_dict()
    # no structured effect is forced onto it; at most its noise is described
    assert all(e['kind'] == 'noise' for e in r['effects'])
    u = r['unexplained']
    assert u is not None and u['channel'] == 'xyz'[axis]
    assert u['excess'] > 0.5 and u['not_white'] > 0.5
    assert 'unexplained structure' in u['text']
    html = write_report(diag, tmp_path / 'report').read_text()
    assert 'Unexplained structure' in html

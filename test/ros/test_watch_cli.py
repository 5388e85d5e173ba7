"""``coreg watch``: the dashboard's state and rendering (pure), and one frame from live ROS."""

import argparse
import subprocess
import sys
import time
from types import SimpleNamespace

import numpy as np
import pytest

pytest.importorskip('rich')

# After the importorskip: coreg_ros.cli.dashboard needs rich.
from coreg_ros.cli import dashboard, watch  # noqa: E402, I100
from coreg_ros.cli.dashboard import (  # noqa: E402
    bar,
    DashboardState,
    render_text,
    sigma_rows,
    Status,
)
from coreg_ros.core.calibration.pairing import pair_for  # noqa: E402
from coreg_ros.core.calibration.pipeline import calibrate_streams  # noqa: E402
from coreg_ros.core.live import guidance as g  # noqa: E402
from coreg_ros.core.live import watchdog as w  # noqa: E402
from coreg_ros.core.live.guidance import (  # noqa: E402
    batch_from_pairs,
    Estimate,
    GuidanceAccumulator,
)
from coreg_ros.core.live.watchdog import Watchdog  # noqa: E402
from coreg_ros.core.settings import Settings  # noqa: E402
from coreg_ros.sim import simulate_recording  # noqa: E402
from coreg_ros.sim.changes import apply_changes  # noqa: E402

SIGMA_A = (2e-4, 5e-4)
SIGMA_B = (5e-4, 2e-3)

CALIBRATION_VALUES = {
    '/device_a/pose received': '2000', '/device_a/pose accepted': '1998',
    '/device_a/pose rejected': '2', '/device_a/pose held': '1998',
    '/device_a/pose dropped oldest': '0', '/device_b/pose received': '1000',
    '/device_b/pose accepted': '1000', '/device_b/pose rejected': '0',
    '/device_b/pose held': '1000', '/device_b/pose dropped oldest': '0', 'paired': '999',
    'pairing rate': '0.999', 'last calibration n_pairs': '999',
    'last calibration success': 'True', 'last calibration chi2_dof': '0.991',
    'last calibration time_offset_s': '-0.000103', 'last calibration verdict': 'n/a'}


@pytest.fixture(scope='module')
def statuses():
    """Real guidance and watchdog values (a 2 mm T0 step after a calibration)."""
    rec = simulate_recording(61, 20.0, sigma_a=SIGMA_A, sigma_b=SIGMA_B)
    settings = Settings(sigma_a=SIGMA_A, sigma_b=SIGMA_B)
    result, _ = calibrate_streams(rec.stream_a, rec.streams_b, settings)
    pairs, _ = pair_for(rec.stream_a, rec.streams_b, settings, result.time_offset)
    acc = GuidanceAccumulator('full_pose', SIGMA_A, SIGMA_B, 5e-5, 1e-3)
    acc.set_estimate(Estimate.from_result(result))
    acc.add(batch_from_pairs(pairs))
    guid = acc.guidance()
    later = apply_changes(simulate_recording(62, 30.0, sigma_a=SIGMA_A, sigma_b=SIGMA_B,
                                             truth=rec.truth), ['t0_step=2mm@15'])
    p2, _ = pair_for(later.stream_a, later.streams_b, settings, result.time_offset)
    st = Watchdog(result, SIGMA_A, SIGMA_B).update(batch_from_pairs(p2))
    return [Status('coreg_node: coregistration', 0, 'last calibration: 999 pairs',
                   CALIBRATION_VALUES),
            Status('coreg_node: guidance', 0, guid.summary, dict(guid.diagnostic_values())),
            Status('coreg_node: watchdog', st.level, st.message, dict(st.diagnostic_values())),
            Status('other_node: watchdog', 0, 'not ours', {})], guid, st


def test_render_shows_counts_sigma_bars_next_motion_and_states(statuses):
    items, guid, st = statuses
    state = DashboardState.from_statuses(items)
    assert state.watchdog.message == st.message  # the other node's status is ignored
    text = render_text(state, width=120, now=state.received_at + 1.0)
    assert 'coreg watch: coreg_node' in text and 'last 1.0 s ago' in text
    assert '/device_a/pose' in text and '1998' in text and 'paired 999' in text
    assert 'success, 999 pairs, χ²/dof 0.991' in text
    for title in ('T0 position', 'T0 rotation', 'T1 position', 'T1 rotation', 'clock offset'):
        assert title in text
    assert guid.suggestion.description in text
    assert 'ERROR' in text and 'T0 moved (base bumped)' in text
    assert f'{guid.sigma["p0"][0] * 1e3:.3g}' in text


def test_render_before_anything_arrived():
    text = render_text(DashboardState(), width=100)
    assert 'waiting for /diagnostics' in text
    assert 'no guidance status' in text and 'no watchdog status' in text


def test_sigma_rows_and_bars(statuses):
    _, guid, _ = statuses
    rows = sigma_rows(dict(guid.diagnostic_values()))
    names = [r[0] for r in rows]
    assert names == ['p0', 'theta0', 'p1', 'theta1', 'time_offset']
    p0 = rows[0]
    assert np.allclose(p0[1], guid.sigma['p0'], rtol=1e-5) and p0[2] == 5e-5 and p0[3] == 'm'
    assert rows[-1][2] is None  # no target for the clock offset
    assert bar(None)[1] == 'dim'
    within, style = bar(0.5)
    assert style == 'green' and '┃' in within
    over, style = bar(2.0)
    assert style == 'yellow' and '╋' in over
    full, style = bar(1e6)
    assert full.count('█') == dashboard.BAR_WIDTH - 1 and '╋' in full and style == 'red'
    assert bar(1e-6)[0].count('█') == 0


def test_status_from_message_and_keys_match_the_core():
    msg = SimpleNamespace(name='coreg_node: watchdog', level=b'\x02', message='stale',
                          values=[SimpleNamespace(key=w.KEY_STATE, value='ERROR')])
    s = Status.from_msg(msg)
    assert s.level == 2 and s.values == {w.KEY_STATE: 'ERROR'}
    state = DashboardState()
    assert not state.update([Status('another: guidance', 0, '', {})])
    assert state.update([s]) and state.watchdog is s and state.messages == 1
    assert g.STATUS_NAME == 'guidance' and w.STATUS_NAME == 'watchdog'


def test_register_adds_the_subcommand():
    parser = argparse.ArgumentParser()
    watch.register(parser.add_subparsers(dest='command'))
    args = parser.parse_args(['watch', '--once', '--node', 'n', '--timeout', '3'])
    assert args.func is watch.cmd_watch and args.once and args.node == 'n'
    assert args.timeout == 3.0 and args.refresh == 4.0 and args.topic == '/diagnostics'


# --------------------------------------------------------------------------- live ROS


def test_once_prints_one_frame_from_live_diagnostics(ros_session, ros_domain, statuses):
    pytest.importorskip('diagnostic_msgs')
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
    items, guid, _ = statuses
    pub = ros_session.node.create_publisher(DiagnosticArray, '/diagnostics', 10)
    msg = DiagnosticArray()
    for s in items[:3]:
        msg.status.append(DiagnosticStatus(
            name=s.name, level=bytes([s.level]), message=s.message,
            values=[KeyValue(key=k, value=v) for k, v in s.values.items()]))
    proc = subprocess.Popen([sys.executable, '-m', 'coreg_ros.cli.watch', '--once', '--timeout',
                             '20'], env=ros_domain.env(), stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    end = time.monotonic() + 30
    while proc.poll() is None and time.monotonic() < end:
        pub.publish(msg)  # volatile: only what is published while it listens arrives
        time.sleep(0.1)
    out, err = proc.communicate(timeout=10)
    assert proc.returncode == 0, err
    assert 'coreg watch: coreg_node' in out and 'T1 rotation' in out
    assert guid.suggestion.name.split('_')[0] in out and 'ERROR' in out


def test_once_times_out_with_one_line(ros_domain):
    proc = subprocess.run([sys.executable, '-m', 'coreg_ros.cli.watch', '--once', '--timeout',
                           '1'], env=ros_domain.env(), capture_output=True, text=True,
                          timeout=60)
    assert proc.returncode == 1
    assert proc.stderr.strip().startswith('coreg watch: error: no status of coreg_node')
    assert len(proc.stderr.strip().splitlines()) == 1


@pytest.mark.parametrize('terminal', [False, True])
def test_ctrl_c_ends_watch_with_130_as_play_and_echo(ros_domain, ros_session, terminal):
    # Issue 25.4: the dashboard exited 0 on Ctrl-C (play and echo: 130); on a pipe, a Ctrl-C
    # before any status was a TypeError traceback.
    import os
    import pty
    import signal

    if terminal:  # the live dashboard: stdout is a terminal
        leader, follower = pty.openpty()
        out = follower
    else:
        out = subprocess.PIPE
    proc = subprocess.Popen([sys.executable, '-m', 'coreg_ros.cli.watch'], env=ros_domain.env(),
                            stdout=out, stderr=subprocess.PIPE, text=True)
    try:
        # waiting for statuses (nothing publishes them on this domain) once its node is up
        assert ros_session.spin_until(
            lambda: 'coreg_watch' in ros_session.node.get_node_names(), 60.0)
        time.sleep(0.5)
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=30)
    finally:
        proc.kill()
        if terminal:
            os.close(leader)
            os.close(follower)
    assert proc.returncode == 130, err
    assert err.strip() == 'coreg watch: interrupted', err

"""
Benchmark of coreg_node: messages lost and CPU at 2 x 2, 5 and 10 kHz; a TLS calibration.

Throughput (the default, ``run``): two PoseStamped topics at each rate into a fresh node, the
publisher in another process (``bench/node_flood.py``, pre-serialised messages), every case
with the node's raw path (raw takes, bulk decode: the default) and its plain path
(``COREG_NODE_PLAIN=1``: one deserialised message per callback) in the same run. Reports
messages lost (goal 0), the node's CPU in cores (goal < 1 at 2 x 5 kHz), the rate the publisher
achieved, the machine load, and a py-spy split of the node's CPU time per message (if py-spy
is installed: ``pip install py-spy``, or ``PY_SPY=/path/to/py-spy``).
Runnable alone (``python bench/bench_node.py``: prints ``table(run())`` and writes
bench/results/node.json).

``--calibrate`` runs the older benchmark (``run_calibrate``): two streams at ``--rate``, then a
``~/calibrate`` call (goal < 2 s at 60k pairs); bench/results/node_calibrate.json. The live checks
(``coreg_ros.ros.live_checks``): ``--guidance on|off`` and ``--watchdog on|off`` set the node's
two switches; ``--calibrated-first S`` streams S seconds of the same motion and calibrates before
the measured streaming, so the watchdog checks every measured pair against a published
calibration (and ``~/fused_pose`` runs, as in use). ``--compare-live`` runs that twice, with both
switches off and on, and reports the CPU ratio (goal < 1.3, 0 dropped).
"""

import argparse
import json
import os
from pathlib import Path
import re
import signal
import subprocess
import sys
import tempfile
import time

os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from coreg_ros.ros.domain import reserve_domain_id  # noqa: E402
from coreg_ros.ros.interface import service_name  # noqa: E402
from coreg_ros.ros.session import RosSession  # noqa: E402
from coreg_ros.ros.tools import (  # noqa: E402
    call_trigger,
    diagnostics_values,
    play_streams,
    wait_for_diagnostics,
)
from coreg_ros.sim import simulate_recording  # noqa: E402
import yaml  # noqa: E402

RESULTS = Path(__file__).resolve().parent / 'results' / 'node.json'
TICKS = os.sysconf('SC_CLK_TCK')


def _cpu_seconds(pid: int) -> float:
    """User + system CPU time of a process, s (from /proc)."""
    fields = Path(f'/proc/{pid}/stat').read_text().rsplit(')', 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / TICKS


def _wait_received(session, counts: dict, timeout: float):
    """Wait for a status whose ``<topic> received`` reaches ``counts[topic]`` (None on timeout)."""
    want = {f'{t} received': n for t, n in counts.items()}
    return wait_for_diagnostics(session, timeout=timeout, accept=lambda st: all(
        int(diagnostics_values(st)[k]) >= v for k, v in want.items()))


def _span(stream, lo_ns: int, hi_ns: int):
    from coreg_ros.core.types import PoseStream
    keep = (stream.stamps >= lo_ns) & (stream.stamps < hi_ns)
    return PoseStream(stream.stamps[keep], stream.position[keep], stream.quat_wxyz[keep],
                      stream.frame_id)


def _node_params(folder: Path, capacity: int, reliable: bool = False) -> Path:
    params = folder / 'params.yaml'
    params.write_text(yaml.safe_dump({'coreg_node': {'ros__parameters': {
        'storage_dir': str(folder / 'store'), 'qos_reliable': reliable,
        'buffer_capacity': int(capacity)}}}))
    return params


def run_case(rate_hz: float, duration: float, path: str = 'raw', profile: bool = False,
             seed: int = 1) -> dict:
    """
    Stream two topics at ``rate_hz`` each for ``duration`` s into a fresh coreg_node.

    The publisher is another process (``bench/node_flood.py``: pre-serialised messages, every
    due message at each ~1 ms wake). The node runs its default checks (guidance, watchdog, the
    journal every 0.5 s, diagnostics at 1 Hz).

    Parameters
    ----------
    rate_hz : float
        Messages per second on each topic.
    duration : float
        Seconds streamed.
    path : str
        ``raw`` (the node's default: raw takes, bulk decode) or ``plain`` (one deserialised
        message per callback; ``COREG_NODE_PLAIN=1``).
    profile : bool
        Also sample the node with py-spy (if installed) while it streams; the split is then
        in ``profile`` and the CPU figure includes py-spy's disturbance (run separately).
    seed : int
        Seed of the simulated recording that is streamed.

    Returns
    -------
    numbers : dict
        ``sent``, ``received``, ``accepted``, ``lost`` (sent - accepted + buffer drops; goal
        0), ``lost_in_middleware``, ``missing_from_stamps``, ``node_cpu_cores`` (CPU seconds
        of the node per wall second while streaming; goal < 1), ``publisher`` (achieved rate),
        ``load_avg`` (1 min, at the end), ``profile`` (shares of the node's busy time).

    """
    from bench.node_flood import profile_split, write_spec
    rec = simulate_recording(seed, duration, rate_a=rate_hz, rate_b=rate_hz)
    sent = {t: len(s) for t, s in rec.streams.items()}
    folder = Path(tempfile.mkdtemp(prefix='coreg_bench_'))
    params = _node_params(folder, int(rate_hz * duration * 1.2) + 1000)
    spec, pub_out = folder / 'spec.npz', folder / 'publisher.json'
    write_spec(spec, rec.streams)
    split = None
    with reserve_domain_id() as domain, open(folder / 'node.log', 'w') as log:
        env = domain.env()
        env.pop('COREG_NODE_PLAIN', None)
        if path == 'plain':
            env['COREG_NODE_PLAIN'] = '1'
        node = subprocess.Popen([sys.executable, '-m', 'coreg_ros.ros.node', '--ros-args',
                                 '--params-file', str(params)], env=env, stdout=log,
                                stderr=subprocess.STDOUT)
        publisher = None
        try:
            with RosSession('coreg_bench', domain_id=domain.domain_id, signals=False) as s:
                publisher = subprocess.Popen(
                    [sys.executable, str(Path(__file__).with_name('node_flood.py')),
                     str(spec), str(pub_out)], env=env, cwd=str(ROOT))
                while publisher.poll() is None and not (
                        pub_out.exists() and pub_out.read_text().strip()):
                    time.sleep(0.01)  # the publisher serialises, then waits for the node
                cpu0, t0 = _cpu_seconds(node.pid), time.monotonic()
                if profile:
                    split = profile_split(node.pid, max(1.0, duration - 2.0))
                publisher.wait(duration + 120)
                publisher_stats = json.loads(pub_out.read_text())
                status = _wait_received(s, sent, timeout=10.0)
                wall = time.monotonic() - t0
                cpu = _cpu_seconds(node.pid) - cpu0
                # the last diagnostics tick may lag the last message by up to 1 s
                wall_streaming = min(wall, publisher_stats.get('wall_s', wall) + 1.0)
                status = status or wait_for_diagnostics(s, timeout=3.0)
                if status is None:
                    tail = (folder / 'node.log').read_text().strip().splitlines()[-3:]
                    raise RuntimeError(f'no /diagnostics from coreg_node (exit code '
                                       f'{node.poll()}); its log ends: {" | ".join(tail)}')
                values = diagnostics_values(status)
        finally:
            if publisher is not None and publisher.poll() is None:
                publisher.kill()
                publisher.wait()
            node.send_signal(signal.SIGINT)
            node.wait(30)
    received = sum(int(values[f'{t} received']) for t in sent)
    accepted = sum(int(values[f'{t} accepted']) for t in sent)
    drops = sum(int(values[f'{t} dropped oldest']) for t in sent)
    return {
        'rate_hz': rate_hz, 'duration_s': duration, 'path': path,
        'sent': sum(sent.values()), 'received': received, 'accepted': accepted,
        'lost': sum(sent.values()) - accepted + drops,
        'node_says_lost': sum(int(values.get(f'{t} lost', -1)) for t in sent),
        'lost_in_middleware': sum(int(values[f'{t} lost in middleware']) for t in sent),
        'missing_from_stamps': sum(int(values[f'{t} missing from stamps']) for t in sent),
        'node_cpu_cores': cpu / wall_streaming, 'cpu_seconds': cpu,
        'cpu_us_per_message': cpu / max(1, received) * 1e6,
        'publisher': publisher_stats, 'load_avg': os.getloadavg()[0],
        'profile': split,
    }


def run(duration: float = 10.0, rates=(2000.0, 5000.0, 10000.0), paths=('raw', 'plain'),
        profile: bool = True) -> dict:
    """
    Measure the node's throughput: every rate with every path, all under the same load.

    Parameters
    ----------
    duration : float
        Seconds streamed per case.
    rates : sequence of float
        Messages per second on each of the two topics.
    paths : sequence of str
        ``raw`` (the default path of the node) and, as the baseline, ``plain``.
    profile : bool
        Add a py-spy split of the node's CPU time at 5 kHz (or the middle rate) per path,
        from a separate streaming run (py-spy disturbs the CPU figures).

    Returns
    -------
    result : dict
        ``cases`` (list of ``run_case`` dicts), ``profiles`` (path -> case with a split),
        ``goal`` and the machine's load before the run.

    """
    load0 = os.getloadavg()
    cases = [run_case(r, duration, p) for r in rates for p in paths]
    profiles = {}
    if profile:
        rate = 5000.0 if 5000.0 in rates else sorted(rates)[len(rates) // 2]
        profiles = {p: run_case(rate, duration, p, profile=True) for p in paths}
    return {'cases': cases, 'profiles': profiles, 'load_avg_before': load0,
            'cores': os.cpu_count(),
            'goal': {'lost': 0, 'node_cpu_cores': 1.0, 'rate_hz': 5000.0}}


def _per_message_us(case: dict) -> dict:
    """Return the profile's parts in us per message, and what py-spy does not see."""
    prof = case.get('profile') or {}
    shares = prof.get('shares') or {}
    if not shares:
        return {}
    # received while py-spy sampled (the plain path loses some)
    messages = 2 * case['rate_hz'] * prof['seconds'] * case['received'] / case['sent']
    python_us = prof['busy_python_seconds'] / messages * 1e6
    out = {k: v * python_us for k, v in shares.items()}
    out['not seen by py-spy (DDS threads, start and end of the run)'] = max(
        0.0, case['cpu_us_per_message'] - python_us)
    return out


def table(result: dict) -> str:
    """Markdown tables of ``run``: throughput per rate and path, then the CPU split."""
    lines = ['| streams | path | sent | lost (goal 0) | the node says lost (sequence numbers) '
             '| lost in middleware / missing from stamps | node CPU, cores (goal < 1) '
             '| CPU per received message (vs plain) | publisher achieved, Hz per topic '
             '| load (1 min) |',
             '|---|---|---|---|---|---|---|---|---|---|']
    plain = {c['rate_hz']: c for c in result['cases'] if c['path'] == 'plain'}
    for c in result['cases']:
        pub = c['publisher'].get('achieved_rate_hz_per_topic')
        base = plain.get(c['rate_hz'])
        ratio = (f' ({c["cpu_us_per_message"] / base["cpu_us_per_message"]:.2f}x)'
                 if base is not None and c is not base else '')
        lines.append(f'| 2 x {c["rate_hz"]:g} Hz, {c["duration_s"]:g} s | {c["path"]} '
                     f'| {c["sent"]:,} | {c["lost"]:,} ({100 * c["lost"] / c["sent"]:.1f} %) '
                     f'| {c.get("node_says_lost", "n/a")} '
                     f'| {c["lost_in_middleware"]:,} / {c["missing_from_stamps"]:,} '
                     f'| {c["node_cpu_cores"]:.2f} | {c["cpu_us_per_message"]:.0f} us{ratio} '
                     f'| {pub:.0f} | {c["load_avg"]:.2f} |'
                     if pub else f'| {c["rate_hz"]:g} | {c["path"]} | publisher failed |')
    for path, c in result.get('profiles', {}).items():
        us = _per_message_us(c)
        if not us:
            continue
        shares = c['profile']['shares']
        lines += ['', f'CPU per message at 2 x {c["rate_hz"]:g} Hz, {path} path: '
                  f'{c["cpu_us_per_message"]:.0f} us in all (py-spy, {c["profile"]["samples"]} '
                  f'samples of the Python threads; {c["node_cpu_cores"]:.2f} cores with py-spy '
                  f'attached):', '', '| part | share of the Python time | us per message |',
                  '|---|---|---|']
        lines += [f'| {k} | {f"{100 * shares[k]:.1f} %" if k in shares else "-"} | {v:.1f} |'
                  for k, v in us.items()]
    lines.append(f'\nmachine: {result["cores"]} cores, load {result["load_avg_before"][0]:.2f} '
                 f'at the start')
    return '\n'.join(lines)


def run_calibrate(duration: float = 60.0, rate_hz: float = 1000.0, reliable: bool = False,
                  guidance: bool = True, watchdog: bool = True,
                  calibrated_first: float = 0.0) -> dict:
    """
    Stream two topics at ``rate_hz`` for ``duration`` s into a fresh coreg_node; calibrate.

    With ``calibrated_first`` > 0, that many seconds of the same recording are streamed and
    calibrated first (not measured); ``guidance`` and ``watchdog`` are the node's switches.

    Returns
    -------
    numbers : dict
        ``sent``, ``received``, ``dropped`` (sent - accepted + buffer drops), ``node_cpu_percent``
        (of one core, while streaming), ``publish_seconds``, ``n_pairs``, ``calibrate_seconds``
        (service round trip) and ``estimator_seconds`` (as the node reports it), ``success``.

    """
    total = duration + calibrated_first
    rec = simulate_recording(1, total, rate_a=rate_hz, rate_b=rate_hz)
    cut = rec.start_ns + int(round(calibrated_first * 1e9))
    end = rec.start_ns + int(round(total * 1e9)) + 1
    first = {t: _span(s, rec.start_ns, cut) for t, s in rec.streams.items()}
    measured = {t: _span(s, cut, end) for t, s in rec.streams.items()}
    sent = {t: len(s) for t, s in rec.streams.items()}
    folder = Path(tempfile.mkdtemp(prefix='coreg_bench_'))
    params = folder / 'params.yaml'
    params.write_text(yaml.safe_dump({'coreg_node': {'ros__parameters': {
        'storage_dir': str(folder / 'store'), 'qos_reliable': reliable,
        'buffer_capacity': int(rate_hz * total * 1.2) + 1000,
        'guidance': bool(guidance), 'watchdog': bool(watchdog)}}}))
    first_calibration = None
    with reserve_domain_id() as domain, open(folder / 'node.log', 'w') as log:
        node = subprocess.Popen([sys.executable, '-m', 'coreg_ros.ros.node', '--ros-args',
                                 '--params-file', str(params)], env=domain.env(), stdout=log,
                                stderr=subprocess.STDOUT)
        try:
            with RosSession('coreg_bench', domain_id=domain.domain_id, signals=False) as s:
                cpu0, t0 = None, None
                if calibrated_first > 0:
                    play_streams(s, first, rate=1.0, wait_subscribers=30.0, log=lambda m: None)
                    _wait_received(s, {t: len(v) for t, v in first.items()}, timeout=10.0)
                    first_calibration = call_trigger(s, service_name('calibrate'),
                                                     timeout=120.0)
                    time.sleep(2.0)  # the watchdog starts on the next diagnostics tick

                def started(msg):  # play logs once before the first message, once after
                    nonlocal cpu0, t0
                    if t0 is None:
                        cpu0, t0 = _cpu_seconds(node.pid), time.monotonic()
                play_streams(s, measured, rate=1.0, wait_subscribers=30.0, log=started)
                status = _wait_received(s, sent, timeout=5.0)
                wall = time.monotonic() - t0
                cpu = _cpu_seconds(node.pid) - cpu0
                status = status or wait_for_diagnostics(s, timeout=3.0)
                values = diagnostics_values(status)
                live = _live_statuses(s)
                received = {t: int(values[f'{t} received']) for t in sent}
                accepted = {t: int(values[f'{t} accepted']) for t in sent}
                buffer_drops = sum(int(values[f'{t} dropped oldest']) for t in sent)
                c0 = time.monotonic()
                ok, message = call_trigger(s, service_name('calibrate'), timeout=120.0)
                calibrate_seconds = time.monotonic() - c0
        finally:
            node.send_signal(signal.SIGINT)
            node.wait(30)
    pairs = re.match(r'(\d+) pairs', message)
    estimator = re.search(r'iterations, ([\d.]+) s', message)
    return {
        'duration_s': duration, 'rate_hz': rate_hz,
        'guidance': bool(guidance), 'watchdog': bool(watchdog),
        'calibrated_first_s': calibrated_first,
        'first_calibration': None if first_calibration is None else list(first_calibration),
        'live': live,
        'qos': 'reliable' if reliable else 'sensor_data',
        'sent': sum(sent.values()), 'received': sum(received.values()),
        'dropped': sum(sent.values()) - sum(accepted.values()) + buffer_drops,
        'node_cpu_percent': 100.0 * cpu / wall, 'publish_seconds': wall,
        'success': ok, 'n_pairs': int(pairs.group(1)) if pairs else None,
        'calibrate_seconds': calibrate_seconds,
        'estimator_seconds': float(estimator.group(1)) if estimator else None,
        'message': message,
    }


def _live_statuses(session) -> dict:
    """Return the guidance and watchdog statuses of the next /diagnostics (level, message)."""
    from coreg_ros.ros.tools import wait_for_message
    from diagnostic_msgs.msg import DiagnosticArray
    msg = wait_for_message(session, DiagnosticArray, '/diagnostics', 10, 3.0)
    out = {}
    for st in [] if msg is None else msg.status:
        concern = st.name.split(': ', 1)[-1]
        if concern in ('guidance', 'watchdog'):
            out[concern] = {'level': st.level[0] if isinstance(st.level, bytes) else st.level,
                            'message': st.message}
    return out


def _on_off(text: str) -> bool:
    if text not in ('on', 'off'):
        raise argparse.ArgumentTypeError(f'expected on or off, got {text!r}')
    return text == 'on'


def _table(r: dict) -> list:
    return [('streams', f'2 x {r["rate_hz"]:g} Hz for {r["duration_s"]:g} s ({r["qos"]} QoS)'),
            ('guidance / watchdog', f'{"on" if r["guidance"] else "off"} / '
                                    f'{"on" if r["watchdog"] else "off"}'
                                    + (f' (calibrated on the first {r["calibrated_first_s"]:g} s)'
                                       if r['calibrated_first_s'] else '')),
            ('messages sent / received', f'{r["sent"]} / {r["received"]}'),
            ('dropped (goal 0)', str(r['dropped'])),
            ('node CPU while streaming', f'{r["node_cpu_percent"]:.0f} % of one core'),
            ('calibrate call (goal < 2 s)', f'{r["calibrate_seconds"]:.2f} s '
                                            f'({r["n_pairs"]} pairs, success {r["success"]})'),
            ('  of which in the estimator', f'{r["estimator_seconds"]} s')] + [
            (f'{k} status', f'{v["level"]}: {v["message"][:90]}') for k, v in r['live'].items()]


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[1])
    parser.add_argument('--duration', type=float, default=None,
                        help='seconds streamed per case (throughput: 10; --calibrate: 60)')
    parser.add_argument('--rates', type=float, nargs='+', default=[2000.0, 5000.0, 10000.0],
                        help='messages per second per topic, one case each (throughput)')
    parser.add_argument('--paths', nargs='+', default=['raw', 'plain'],
                        choices=['raw', 'plain'], help='node paths to compare (throughput)')
    parser.add_argument('--no-profile', action='store_true',
                        help='skip the py-spy split of the CPU time (throughput)')
    parser.add_argument('--calibrate', action='store_true',
                        help='the older benchmark instead: stream at --rate, then ~/calibrate')
    parser.add_argument('--rate', type=float, default=1000.0, help='with --calibrate')
    parser.add_argument('--reliable', action='store_true', help='reliable instead of sensor QoS')
    parser.add_argument('--guidance', type=_on_off, default=True, metavar='on|off',
                        help="the node's guidance switch (default on)")
    parser.add_argument('--watchdog', type=_on_off, default=True, metavar='on|off',
                        help="the node's watchdog switch (default on)")
    parser.add_argument('--calibrated-first', type=float, default=0.0, metavar='S',
                        help='stream S s and calibrate before the measured streaming (the '
                             'watchdog then checks every measured pair); default 0')
    parser.add_argument('--compare-live', action='store_true',
                        help='run with guidance and watchdog off, then on (calibrated first: '
                             '10 s unless --calibrated-first), and report the CPU ratio')
    args = parser.parse_args(argv)
    if args.compare_live:
        first = args.calibrated_first or 10.0
        runs = [run_calibrate(args.duration or 60.0, args.rate, args.reliable, on, on, first)
                for on in (False, True)]
        for r in runs:
            rows = _table(r)
            width = max(len(k) for k, _ in rows)
            print('\n'.join(f'{k:<{width}}  {v}' for k, v in rows) + '\n')
        off, on = runs
        ratio = on['node_cpu_percent'] / off['node_cpu_percent']
        print(f'CPU with guidance and watchdog on / off: {on["node_cpu_percent"]:.1f} % / '
              f'{off["node_cpu_percent"]:.1f} % = {ratio:.2f}x (goal < 1.3); dropped '
              f'{on["dropped"]} / {off["dropped"]} (goal 0)')
        out = {'off': off, 'on': on, 'cpu_ratio': ratio}
        path = RESULTS.with_name('node_live.json')
    elif args.calibrate:
        out = run_calibrate(args.duration or 60.0, args.rate, args.reliable, args.guidance,
                            args.watchdog, args.calibrated_first)
        rows = _table(out)
        width = max(len(k) for k, _ in rows)
        print('\n'.join(f'{k:<{width}}  {v}' for k, v in rows))
        path = RESULTS.with_name('node_calibrate.json')
    else:
        out = run(args.duration or 10.0, tuple(args.rates), tuple(args.paths),
                  profile=not args.no_profile)
        print(table(out))
        path = RESULTS
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(out, indent=2) + '\n')
    print(f'written to {path}')
    return 0


if __name__ == '__main__':
    sys.exit(main())

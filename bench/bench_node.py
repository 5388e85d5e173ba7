"""
Benchmark of coreg_node: two pose streams at 1 kHz, then a TLS calibration on all pairs.

Measures messages lost between the publisher and the buffer (goal 0), the CPU use of the node
process while streaming, and the time of a ``~/calibrate`` call (goal < 2 s at 60k pairs).
Runnable alone (``python bench/bench_node.py --duration 60``: prints a table and writes
bench/results/node.json); ``run(duration)`` returns the numbers as a dict.
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

import yaml

os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')

from coreg_ros.ros.domain import reserve_domain_id  # noqa: E402
from coreg_ros.ros.tools import (  # noqa: E402
    RosSession,
    call_trigger,
    diagnostics_values,
    play_streams,
    service_name,
    wait_for_diagnostics,
)
from coreg_ros.sim import simulate_recording  # noqa: E402

RESULTS = Path(__file__).resolve().parent / 'results' / 'node.json'
TICKS = os.sysconf('SC_CLK_TCK')


def _cpu_seconds(pid: int) -> float:
    """User + system CPU time of a process, s (from /proc)."""
    fields = Path(f'/proc/{pid}/stat').read_text().rsplit(')', 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / TICKS


def run(duration: float = 60.0, rate_hz: float = 1000.0, reliable: bool = False) -> dict:
    """
    Stream two topics at ``rate_hz`` for ``duration`` s into a fresh coreg_node; calibrate.

    Returns
    -------
    numbers : dict
        ``sent``, ``received``, ``dropped`` (sent - accepted + buffer drops), ``node_cpu_percent``
        (of one core, while streaming), ``publish_seconds``, ``n_pairs``, ``calibrate_seconds``
        (service round trip) and ``estimator_seconds`` (as the node reports it), ``success``.

    """
    rec = simulate_recording(1, duration, rate_a=rate_hz, rate_b=rate_hz)
    sent = {t: len(s) for t, s in rec.streams.items()}
    folder = Path(tempfile.mkdtemp(prefix='coreg_bench_'))
    params = folder / 'params.yaml'
    params.write_text(yaml.safe_dump({'coreg_node': {'ros__parameters': {
        'storage_dir': str(folder / 'store'), 'qos_reliable': reliable,
        'buffer_capacity': int(rate_hz * duration * 1.2) + 1000}}}))
    with reserve_domain_id() as domain, open(folder / 'node.log', 'w') as log:
        node = subprocess.Popen([sys.executable, '-m', 'coreg_ros.ros.node', '--ros-args',
                                 '--params-file', str(params)], env=domain.env(), stdout=log,
                                stderr=subprocess.STDOUT)
        try:
            with RosSession('coreg_bench', domain_id=domain.domain_id, signals=False) as s:
                cpu0, t0 = None, None

                def started(msg):  # play logs once before the first message, once after
                    nonlocal cpu0, t0
                    if t0 is None:
                        cpu0, t0 = _cpu_seconds(node.pid), time.monotonic()
                play_streams(s, rec.streams, rate=1.0, wait_subscribers=30.0, log=started)
                want = {f'{t} received': n for t, n in sent.items()}
                status = wait_for_diagnostics(
                    s, timeout=5.0, accept=lambda st: all(
                        int(diagnostics_values(st)[k]) >= v for k, v in want.items()))
                wall = time.monotonic() - t0
                cpu = _cpu_seconds(node.pid) - cpu0
                status = status or wait_for_diagnostics(s, timeout=3.0)
                values = diagnostics_values(status)
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
        'qos': 'reliable' if reliable else 'sensor_data',
        'sent': sum(sent.values()), 'received': sum(received.values()),
        'dropped': sum(sent.values()) - sum(accepted.values()) + buffer_drops,
        'node_cpu_percent': 100.0 * cpu / wall, 'publish_seconds': wall,
        'success': ok, 'n_pairs': int(pairs.group(1)) if pairs else None,
        'calibrate_seconds': calibrate_seconds,
        'estimator_seconds': float(estimator.group(1)) if estimator else None,
        'message': message,
    }


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[1])
    parser.add_argument('--duration', type=float, default=60.0)
    parser.add_argument('--rate', type=float, default=1000.0)
    parser.add_argument('--reliable', action='store_true', help='reliable instead of sensor QoS')
    args = parser.parse_args(argv)
    r = run(args.duration, args.rate, args.reliable)
    rows = [('streams', f'2 x {r["rate_hz"]:g} Hz for {r["duration_s"]:g} s ({r["qos"]} QoS)'),
            ('messages sent / received', f'{r["sent"]} / {r["received"]}'),
            ('dropped (goal 0)', str(r['dropped'])),
            ('node CPU while streaming', f'{r["node_cpu_percent"]:.0f} % of one core'),
            ('calibrate call (goal < 2 s)', f'{r["calibrate_seconds"]:.2f} s '
                                            f'({r["n_pairs"]} pairs, success {r["success"]})'),
            ('  of which in the estimator', f'{r["estimator_seconds"]} s')]
    width = max(len(k) for k, _ in rows)
    print('\n'.join(f'{k:<{width}}  {v}' for k, v in rows))
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    RESULTS.write_text(json.dumps(r, indent=2) + '\n')
    print(f'written to {RESULTS}')
    return 0


if __name__ == '__main__':
    sys.exit(main())

"""
Helpers of ``bench/bench_node.py``: a fast pose publisher process and a profile of the node.

Publisher
    ``python bench/node_flood.py SPEC.npz OUT.json`` publishes the streams of ``SPEC.npz``
    (per topic: stamps, positions, (w, x, y, z) quaternions, frame id) at their own timing.
    The messages are serialised before the clock starts and published as CDR bytes
    (``Publisher.publish(bytes)``), every message that is due at each wake (about 1 ms), so one
    Python process keeps up with 2 x 10 kHz; what it achieved (rate, lateness) goes to
    ``OUT.json``.
Profile
    ``profile_split`` runs py-spy (if installed) on the node process for a few seconds and
    splits the sampled CPU time of the node into the parts the benchmark reports (executor,
    take + deserialise, callback, validation + buffer, journal, live checks, diagnostics).
"""

from __future__ import annotations

from collections import Counter
import json
import os
from pathlib import Path
import shutil
import subprocess
import sys
import tempfile
import time

import numpy as np

os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')

#: Innermost frames listed in a profile.
TOP = 15
#: Seconds the publisher waits for a subscriber on every topic.
WAIT_SUBSCRIBERS = 30.0


def write_spec(path: Path, streams: dict) -> None:
    """Write topic -> PoseStream as the publisher's input (one npz)."""
    arrays = {}
    for k, (topic, s) in enumerate(streams.items()):
        arrays[f't{k}_name'] = np.array(topic)
        arrays[f't{k}_frame'] = np.array(s.frame_id)
        arrays[f't{k}_stamps'] = np.asarray(s.stamps, np.int64)
        arrays[f't{k}_pos'] = np.asarray(s.position, float)
        arrays[f't{k}_quat'] = np.asarray(s.quat_wxyz, float)
    np.savez(path, n=len(streams), **arrays)


def _serialised(spec) -> tuple[list, list, list]:
    """Return (topics, per-message topic index, per-message CDR bytes) in stamp order."""
    from coreg_ros.files.bag.cdr_pose import encode_pose_stamped
    topics, which, data, stamps = [], [], [], []
    for k in range(int(spec['n'])):
        topics.append(str(spec[f't{k}_name']))
        st = spec[f't{k}_stamps']
        data += encode_pose_stamped(st, str(spec[f't{k}_frame']), spec[f't{k}_pos'],
                                    spec[f't{k}_quat'])
        which += [k] * len(st)
        stamps += st.tolist()
    order = np.argsort(np.asarray(stamps, np.int64), kind='stable')
    t = np.asarray(stamps, np.int64)[order]
    return topics, [which[i] for i in order], [data[i] for i in order], ((t - t[0]) / 1e9).tolist()


def publish_main(spec_path: str, out_path: str) -> int:
    """Publish a spec (see the module docstring); write what was achieved to ``out_path``."""
    from coreg_ros.ros.interface import PLAY_QOS
    from coreg_ros.ros.session import RosSession
    from geometry_msgs.msg import PoseStamped
    spec = np.load(spec_path)
    topics, which, data, due = _serialised(spec)
    with RosSession('coreg_bench_publisher', signals=False) as s:
        pubs = [s.node.create_publisher(PoseStamped, t, PLAY_QOS) for t in topics]
        if not s.spin_until(lambda: all(p.get_subscription_count() > 0 for p in pubs),
                            WAIT_SUBSCRIBERS):
            Path(out_path).write_text(json.dumps({'error': 'no subscriber'}))
            return 1
        s.spin_until(lambda: False, 0.5)  # matched writers settle on both sides
        Path(out_path).write_text(json.dumps({'started': time.time()}))
        publish = [p.publish for p in pubs]
        n = len(data)
        i = 0
        late_max = 0.0
        start = time.perf_counter()
        while i < n:
            now = time.perf_counter() - start
            if due[i] > now:
                time.sleep(min(due[i] - now, 0.001))
                continue
            late_max = max(late_max, now - due[i])
            while i < n and due[i] <= now:
                publish[which[i]](data[i])
                i += 1
        wall = time.perf_counter() - start
        s.spin_until(lambda: False, 0.2)
    span = due[-1] if n else 0.0
    Path(out_path).write_text(json.dumps({
        'messages': n, 'wall_s': wall, 'span_s': span,
        'achieved_rate_hz_per_topic': n / len(topics) / wall if wall > 0 else None,
        'wanted_rate_hz_per_topic': n / len(topics) / span if span > 0 else None,
        'max_lateness_s': late_max}))
    return 0


# --- profile ---------------------------------------------------------------------------------

#: (part, test on one stack frame "function (file:line)"): a sample goes to the first part
#: (in this order) that matches any frame of its stack, so work called from the journal or the
#: live checks (numpy, rclpy's parameters) counts there, not as numpy's or rclpy's.
PARTS = (
    ('journal', lambda f: 'flush_journal' in f or 'persistence.py' in f),
    ('live checks', lambda f: 'live_checks.py' in f),
    ('diagnostics', lambda f: '_publish_diagnostics' in f or 'diagnostics (' in f),
    ('decode in bulk', lambda f: 'cdr_pose.py' in f),
    ('validation + buffer append', lambda f: 'buffer.py' in f),
    ('take (raw, every waiting message)', lambda f: '_take_all' in f),
    ('callback', lambda f: 'raw_intake.py' in f or 'node.py' in f and (
        'on_pose' in f or 'pose_stamped_values' in f)),
    ('take + deserialise', lambda f: '_take_subscription' in f),
    ('services thread: executor, timers, services', lambda f: '_spin_quietly' in f),
    ('stream thread: executor overhead', lambda f: 'executors.py' in f),
)


def split_stacks(stacks: Counter) -> dict:
    """Return {part: share of the samples} of sampled stacks (';'-joined frames)."""
    counts = Counter()
    for stack, n in stacks.items():
        frames = stack.split(';')
        if _idle(frames):
            continue
        part = next((name for name, test in PARTS if any(test(f) for f in frames)), 'other')
        counts[part] += n
    total = sum(counts.values()) or 1
    return {k: v / total for k, v in sorted(counts.items(), key=lambda kv: -kv[1])}


def _idle(frames: list) -> bool:
    """Tell a sample in the intake's pause (a sleep py-spy may not see as idle)."""
    return bool(frames) and frames[-1].startswith('_pause (')


def py_spy() -> str | None:
    """Path of py-spy (PATH, or PY_SPY), or None."""
    return os.environ.get('PY_SPY') or shutil.which('py-spy')


def profile_split(pid: int, seconds: float, rate: int = 200) -> dict | None:
    """
    Sample process ``pid`` with py-spy for ``seconds``; return the split of its busy samples.

    Returns None without py-spy. Idle samples (threads waiting in rcl) are not counted, so the
    shares are of the node's CPU time.
    """
    exe = py_spy()
    if exe is None:
        return None
    with tempfile.TemporaryDirectory() as d:
        out = Path(d) / 'stacks.txt'
        proc = subprocess.run([exe, 'record', '--pid', str(pid), '--duration',
                               str(max(1, int(seconds))), '--rate', str(rate), '--format',
                               'raw', '--output', str(out), '--nonblocking'],
                              capture_output=True, text=True)
        if proc.returncode != 0 or not out.exists():
            return {'error': (proc.stderr or proc.stdout).strip().splitlines()[-1:]}
        stacks = Counter()
        for line in out.read_text().splitlines():
            stack, _, n = line.rpartition(' ')
            if stack and not _idle(stack.split(';')):
                stacks[stack] += int(n)
        if os.environ.get('BENCH_NODE_STACKS'):  # keep the stacks for a closer look
            shutil.copy(out, os.environ['BENCH_NODE_STACKS'])
    leaves = Counter()
    for stack, n in stacks.items():
        leaves[stack.rsplit(';', 1)[-1]] += n
    total = sum(stacks.values()) or 1
    return {'samples': sum(stacks.values()), 'rate_hz': rate, 'seconds': max(1, int(seconds)),
            'busy_python_seconds': sum(stacks.values()) / rate,
            'shares': split_stacks(stacks),
            'top_frames': {f: n / total for f, n in leaves.most_common(TOP)}}


if __name__ == '__main__':
    sys.exit(publish_main(sys.argv[1], sys.argv[2]))

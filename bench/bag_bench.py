"""
PoseStamped bags at memory speed (issue 15): bulk path against rosbags' per-message path.

- **Read and write**: ``n`` messages per topic on ``topics`` topics (default 2 × 500k) with
  random poses, for sqlite3 and mcap: ``write_pose_bag`` and ``read_pose_bag`` with
  ``bulk=True`` and with ``bulk=False`` (rosbags message by message, the path before issue
  15), in the same run; messages/s, the ratio, and a check that both reads give identical
  arrays (stamps exactly, floats bit for bit). Goal: ≥ 1M messages/s read and ≥ 10×.
- **Whole command** (issue 25, item 5): ``coreg calibrate`` on a 2M-pair recording
  (``coreg simulate``, A and B at 1 kHz for 2000 s, 4M messages, written to a temporary
  directory and deleted), wall time, CPU time and peak memory of the child process: this
  tree with ``COREG_BAG_BULK=0`` (rosbags per message, issue 15's before), the code at
  ``BEFORE_COMMIT`` (a git worktree under /tmp: issue 25's before), the code at
  ``ROUND_COMMIT`` (the start of the round on item 5's memory and sqlite3 reading) and this
  tree, in the same run. The children get the user's environment (no BLAS pinning), as users
  call the command.
  Goals: within ``GOAL_CALIBRATE_S`` and ``GOAL_PEAK_BYTES``.

``python bench/bag_bench.py [--n N] [--seconds S] [--calibrate-storages sqlite3 mcap]
[--no-calibrate] [--repeat R] [--before-commit C]`` (reads alternate, best of R each) prints
the tables and writes ``bench/results/bag_bench.json``; ``run()`` returns the dict.
"""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path
import subprocess
import sys
import tempfile
import time
from typing import Optional

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from coreg_ros.core.types import PoseStream  # noqa: E402
from coreg_ros.files.bag.posebag import BULK_ENV, read_pose_bag, write_pose_bag  # noqa: E402
import numpy as np  # noqa: E402

#: Goals of issue 15 (read path).
GOAL_READ_MSG_PER_S = 1_000_000
GOAL_RATIO = 10.0
#: Goals of issue 25 (``coreg calibrate`` of the 4M-message recording): wall s, peak RSS.
GOAL_CALIBRATE_S = 6.0
GOAL_PEAK_BYTES = 1.2 * 2**30
#: The code before issue 25's long-recording work (the "before" of the whole command).
BEFORE_COMMIT = 'c1de503'
#: The code before the round that cut the fit's copies and the sqlite3 read's system time.
ROUND_COMMIT = 'fe84e92'
#: Runs of ``coreg calibrate`` now and at ``ROUND_COMMIT``, alternating: the median wall time
#: and the highest peak are reported (the two slow baselines run once).
CALIBRATE_RUNS = 3
#: BLAS pinning that bench/run.py sets for its own timings, not passed to the user's command.
_PINNING = ('OPENBLAS_NUM_THREADS', 'OMP_NUM_THREADS', 'MKL_NUM_THREADS')
STORAGES = ('sqlite3', 'mcap')
COREG = str(Path(sys.executable).with_name('coreg'))

#: Runs a command and prints its wall time and the child's peak RSS (a fresh parent per
#: measurement, so RUSAGE_CHILDREN holds that one child).
_MEASURE = (
    'import json, resource, subprocess, sys, time\n'
    't = time.perf_counter()\n'
    'p = subprocess.run(sys.argv[1:], capture_output=True, text=True)\n'
    'wall = time.perf_counter() - t\n'
    'use = resource.getrusage(resource.RUSAGE_CHILDREN)\n'
    'print(json.dumps({"wall_s": wall, "cpu_s": use.ru_utime + use.ru_stime,'
    ' "peak_rss_bytes": use.ru_maxrss * 1024, "returncode": p.returncode,'
    ' "stderr_tail": p.stderr[-300:]}))\n'
)


def _streams(n: int, topics: int, seed: int = 0) -> dict[str, PoseStream]:
    rng = np.random.default_rng(seed)
    out = {}
    for k in range(topics):
        stamps = 1_700_000_000 * 10**9 + np.arange(n, dtype=np.int64) * 1_000_000 + 37 * k
        q = rng.normal(size=(n, 4))
        q /= np.linalg.norm(q, axis=1, keepdims=True)
        out[f'/device_{k}/pose'] = PoseStream(
            stamps=stamps, position=rng.normal(size=(n, 3)), quat_wxyz=q,
            frame_id=['world', 'tracker_base', 'map'][k % 3],
            receive_stamps=stamps + rng.integers(100_000, 2_000_000, n))
    return out


def _timed(fn, *args, **kwargs):
    t = time.perf_counter()
    out = fn(*args, **kwargs)
    return time.perf_counter() - t, out


def _identical(a: dict, b: dict) -> bool:
    for topic in b:
        x, y = a[topic], b[topic]
        if x.frame_id != y.frame_id:
            return False
        for name in ('stamps', 'receive_stamps', 'position', 'quat_wxyz'):
            u, v = getattr(x, name), getattr(y, name)
            if u.dtype != v.dtype or u.shape != v.shape:
                return False
            if not np.array_equal(np.ascontiguousarray(u).view(np.int64),
                                  np.ascontiguousarray(v).view(np.int64)):
                return False
    return True


def _read_write(n: int, topics: int, storage: str, tmp: Path, repeat: int = 1) -> dict:
    streams = _streams(n, topics)
    total = n * topics
    names = list(streams)
    t_wb, _ = _timed(write_pose_bag, tmp / f'bulk_{storage}', streams, storage, bulk=True)
    t_wr, _ = _timed(write_pose_bag, tmp / f'ref_{storage}', streams, storage, bulk=False)
    # Reads alternate (bulk, rosbags, bulk, ...) so that both see the same load; best of
    # ``repeat`` each.
    bulk_s, ref_s = [], []
    for _ in range(repeat):
        t, got = _timed(read_pose_bag, tmp / f'bulk_{storage}', names, bulk=True)
        bulk_s.append(t)
        t, ref = _timed(read_pose_bag, tmp / f'bulk_{storage}', names, bulk=False)
        ref_s.append(t)
    t_rb, t_rr = min(bulk_s), min(ref_s)
    return {
        'storage': storage, 'messages': total, 'read_repeats': repeat,
        'read_bulk_runs_s': bulk_s, 'read_rosbags_runs_s': ref_s,
        'read_bulk_s': t_rb, 'read_rosbags_s': t_rr,
        'read_bulk_msg_per_s': total / t_rb, 'read_rosbags_msg_per_s': total / t_rr,
        'read_ratio': t_rr / t_rb,
        'write_bulk_s': t_wb, 'write_rosbags_s': t_wr,
        'write_bulk_msg_per_s': total / t_wb, 'write_rosbags_msg_per_s': total / t_wr,
        'write_ratio': t_wr / t_wb,
        'identical': _identical(got, ref),
        'read_goal_met': total / t_rb >= GOAL_READ_MSG_PER_S and t_rr / t_rb >= GOAL_RATIO,
    }


def _measure(cmd: list[str], env: dict, cwd: Optional[Path] = None) -> dict:
    out = subprocess.run([sys.executable, '-c', _MEASURE, *cmd], capture_output=True,
                         text=True, env=env, check=True, cwd=cwd)
    return json.loads(out.stdout)


def _median_run(runs: list) -> dict:
    """Return the run of median wall time, with every wall time and the highest peak."""
    for run in runs:
        if run['returncode']:
            return run
    middle = sorted(runs, key=lambda r: r['wall_s'])[len(runs) // 2]
    return {**middle, 'walls_s': [r['wall_s'] for r in runs],
            'peak_rss_bytes': max(r['peak_rss_bytes'] for r in runs)}


def _coreg_of(tree: Path, env: dict) -> tuple[list, dict]:
    """Return the ``coreg`` command of the code in ``tree`` and its environment."""
    env = {k: v for k, v in env.items() if k not in _PINNING}
    env['PYTHONPATH'] = os.pathsep.join([str(tree)] + (
        [env['PYTHONPATH']] if env.get('PYTHONPATH') else []))
    return [sys.executable, '-m', 'coreg_ros.cli.main'], env


def _calibrate(storage: str, seconds: float, rate: float, tmp: Path,
               before: Optional[tuple] = None, round_before: Optional[tuple] = None) -> dict:
    """
    Time ``coreg calibrate`` per message, at ``before`` and ``round_before`` and now.

    ``before`` and ``round_before`` are (commit, its tree), or None (not run).
    """
    bag = tmp / f'calib_{storage}'
    env = dict(os.environ)
    gen = _measure([COREG, 'simulate', '--seed', '15', '--duration', str(seconds),
                    '--rate-a', str(rate), '--rate-b', str(rate), '--storage', storage,
                    str(bag)], env)
    if gen['returncode']:
        raise RuntimeError(f'coreg simulate failed: {gen["stderr_tail"]}')
    size = sum(f.stat().st_size for f in bag.iterdir())
    t_read, streams = _timed(read_pose_bag, bag, ['/device_a/pose', '/device_b/pose'])
    messages = sum(len(s) for s in streams.values())
    del streams
    args = ['calibrate', str(bag), '--json', str(tmp / 'result.json')]
    now_cmd, now_env = _coreg_of(ROOT, env)
    runs = {'before': _measure(now_cmd + args, {**now_env, BULK_ENV: '0'}, ROOT)}
    if before is not None:
        old_cmd, old_env = _coreg_of(before[1], env)
        runs['commit'] = _measure(old_cmd + args, old_env, before[1])
    # the goal's runs, repeated and alternating: this machine's speed drifts by 10-30 % over
    # minutes, and one run each would compare moments rather than code
    repeated = {'after': (now_cmd, {**now_env, BULK_ENV: '1'}, ROOT)}
    if round_before is not None:
        old_cmd, old_env = _coreg_of(round_before[1], env)
        repeated['round'] = (old_cmd, old_env, round_before[1])
    samples: dict = {key: [] for key in repeated}
    for _ in range(CALIBRATE_RUNS):
        for key, (cmd, cmd_env, cwd) in repeated.items():
            samples[key].append(_measure(cmd + args, cmd_env, cwd))
    runs.update({key: _median_run(got) for key, got in samples.items()})
    for run in runs.values():
        if run['returncode']:
            raise RuntimeError(f'coreg calibrate failed: {run["stderr_tail"]}')
    after = runs['after']
    out = subprocess.run([sys.executable, str(ROOT / 'bench' / 'calibrate_phases.py'), *args[1:]],
                         capture_output=True, text=True, env=now_env, cwd=ROOT, check=True)
    phases = json.loads(out.stdout.strip().splitlines()[-1])
    row = {'storage': storage, 'seconds': seconds, 'rate_hz': rate, 'messages': messages,
           'bag_bytes': size, 'simulate_wall_s': gen['wall_s'], 'read_bulk_s': t_read,
           'load_average': os.getloadavg()[0],
           'goal_met': after['wall_s'] <= GOAL_CALIBRATE_S
           and after['peak_rss_bytes'] <= GOAL_PEAK_BYTES, 'profile': phases}
    for key, run in runs.items():
        row[f'calibrate_{key}_s'] = run['wall_s']
        row[f'calibrate_{key}_cpu_s'] = run['cpu_s']
        row[f'peak_rss_{key}_bytes'] = run['peak_rss_bytes']
        if 'walls_s' in run:
            row[f'calibrate_{key}_walls_s'] = run['walls_s']
    row['calibrate_ratio'] = runs['before']['wall_s'] / after['wall_s']
    if 'commit' in runs:
        row['before_commit'] = before[0]
        row['commit_ratio'] = runs['commit']['wall_s'] / after['wall_s']
    if 'round' in runs:
        row['round_commit'] = round_before[0]
    return row


def run(n: int = 500_000, topics: int = 2, storages=STORAGES, calibrate: bool = True,
        seconds: float = 2000.0, rate: float = 1000.0,
        calibrate_storages=('sqlite3',), repeat: int = 1,
        before_commit: Optional[str] = BEFORE_COMMIT,
        round_commit: Optional[str] = ROUND_COMMIT) -> dict:
    """
    Measure the bulk and per-message paths in one run.

    Parameters
    ----------
    n, topics : int
        Messages per topic and topics of the read/write benchmark.
    storages : sequence of str
        Storages of the read/write benchmark.
    repeat : int
        Reads of each path (alternating); the best of each is reported.
    calibrate : bool
        Also time ``coreg calibrate`` on a simulated recording of ``seconds`` s with A and B
        at ``rate`` Hz, before (``COREG_BAG_BULK=0``) and after, per ``calibrate_storages``.
    seconds : float
        Duration of the simulated recording of the calibrate benchmark, s.
    rate : float
        Rate of A and of B in that recording, Hz.
    calibrate_storages : sequence of str
        Storages the calibrate benchmark writes the recording in (one row each).
    before_commit : str, optional
        The commit whose ``coreg calibrate`` is the "before" of issue 25 (None: not run).
    round_commit : str, optional
        The commit before this round's work on item 5 (None: not run).

    Returns
    -------
    result : dict
        ``io`` (one row per storage), ``calibrate`` (one row per storage), the goals, and the
        machine's load average at the start.

    """
    result = {'goal_read_msg_per_s': GOAL_READ_MSG_PER_S, 'goal_ratio': GOAL_RATIO,
              'load_average': os.getloadavg(), 'cpus': os.cpu_count(), 'io': [],
              'calibrate': []}
    with tempfile.TemporaryDirectory(prefix='bag_bench_') as tmp:
        for storage in storages:
            result['io'].append(_read_write(n, topics, storage, Path(tmp), repeat))
        if calibrate:
            from bench.calibrate_speed_bench import before_worktree
            before, round_before = (None if not c else (c, before_worktree(c))
                                    for c in (before_commit, round_commit))
            for storage in calibrate_storages:
                result['calibrate'].append(_calibrate(storage, seconds, rate, Path(tmp), before,
                                                      round_before))
    return result


def table(result: dict) -> str:
    """Markdown tables of ``run()``'s result."""
    lines = [
        f'Bulk vs rosbags per-message path, same run (load average '
        f'{result["load_average"][0]:.1f} on {result["cpus"]} CPUs). Goal: read ≥ '
        f'{result["goal_read_msg_per_s"] / 1e6:.0f}M msg/s and ≥ {result["goal_ratio"]:.0f}×.',
        '',
        '| storage | messages | read bulk msg/s | read rosbags msg/s | read ratio | '
        'write bulk msg/s | write rosbags msg/s | write ratio | identical | read goal |',
        '|---|---:|---:|---:|---:|---:|---:|---:|---|---|',
    ]
    for r in result['io']:
        lines.append(
            f'| {r["storage"]} | {r["messages"]:,} | {r["read_bulk_msg_per_s"] / 1e6:.2f}M | '
            f'{r["read_rosbags_msg_per_s"] / 1e3:.0f}k | {r["read_ratio"]:.1f}× | '
            f'{r["write_bulk_msg_per_s"] / 1e6:.2f}M | {r["write_rosbags_msg_per_s"] / 1e3:.0f}k'
            f' | {r["write_ratio"]:.1f}× | {"yes" if r["identical"] else "NO"} | '
            f'{"met" if r["read_goal_met"] else "missed"} |')
    if result['calibrate']:
        lines += [
            '',
            f'`coreg calibrate` of the whole recording, wall / CPU s and peak RSS of the child, '
            f'same run: rosbags per message (`COREG_BAG_BULK=0`), the code at '
            f'{result["calibrate"][0].get("before_commit", "–")} (before issue 25), at '
            f'{result["calibrate"][0].get("round_commit", "–")} (before the round on its '
            f'memory and sqlite3 reading) and now; the last two the median of '
            f'{CALIBRATE_RUNS} alternating runs (wall times of all in the JSON) and the '
            f'highest peak. Goal (issue 25): ≤ {GOAL_CALIBRATE_S:g} s and ≤ '
            f'{GOAL_PEAK_BYTES / 2**30:g} GiB.',
            '',
            '| recording | messages | bag | read (bulk, in-process) | per message | before '
            '| round before | now | × before | peak RSS per message | before | round before '
            '| now | goal | load |',
            '|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|---:|',
        ]
        for r in result['calibrate']:
            def cell(key, r=r):
                return (f'{r[f"calibrate_{key}_s"]:.1f} / {r[f"calibrate_{key}_cpu_s"]:.1f} s'
                        if f'calibrate_{key}_s' in r else '–')

            def rss(key, r=r):
                v = r.get(f'peak_rss_{key}_bytes')
                return '–' if v is None else f'{v / 2**30:.2f} GiB'
            ratio = f'{r["commit_ratio"]:.1f}×' if 'commit_ratio' in r else '–'
            lines.append(
                f'| {r["storage"]}, {r["rate_hz"]:.0f} Hz × {r["seconds"]:.0f} s | '
                f'{r["messages"]:,} | {r["bag_bytes"] / 2**20:.0f} MiB | '
                f'{r["read_bulk_s"]:.1f} s | {cell("before")} | {cell("commit")} | '
                f'{cell("round")} | {cell("after")} | {ratio} | {rss("before")} | '
                f'{rss("commit")} | {rss("round")} | {rss("after")} | '
                f'{"met" if r.get("goal_met") else "missed"} | '
                f'{r.get("load_average", float("nan")):.1f} |')
        lines += ['', 'Where the time and memory go now (`python bench/calibrate_phases.py BAG`, '
                      'CPU s per phase, inner phases inside outer ones; peak RSS by phase):', '']
        for r in result['calibrate']:
            lines.append(f'- {r["storage"]}: ' + _profile_text(r.get('profile')))
    return '\n'.join(lines)


def _profile_text(profile: Optional[dict]) -> str:
    """One line of ``calibrate_phases``' result: CPU per phase, the three highest RSS peaks."""
    if not profile:
        return 'not measured'
    cpu = ', '.join(f'{name} {p["cpu_s"]:.2f} s ({p["calls"]}×)'
                    for name, p in profile['phases'].items())
    peaks = '; '.join(f'{v / 2**30:.2f} GiB in {k}'
                      for k, v in list(profile['peak_rss_by_phase'].items())[:3])
    return f'total {profile["total_cpu_s"]:.2f} s: {cpu}. Peaks: {peaks}'


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--n', type=int, default=500_000, help='messages per topic')
    parser.add_argument('--topics', type=int, default=2)
    parser.add_argument('--seconds', type=float, default=2000.0,
                        help='length of the calibrate recording, s')
    parser.add_argument('--rate', type=float, default=1000.0, help='A and B rate, Hz')
    parser.add_argument('--calibrate-storages', nargs='+', default=['sqlite3'],
                        choices=STORAGES)
    parser.add_argument('--no-calibrate', action='store_true')
    parser.add_argument('--before-commit', default=BEFORE_COMMIT,
                        help='the commit whose coreg calibrate is the "before" ("" skips it)')
    parser.add_argument('--round-commit', default=ROUND_COMMIT,
                        help='the commit before this round on item 5 ("" skips it)')
    parser.add_argument('--repeat', type=int, default=1,
                        help='reads of each path, alternating; the best of each counts')
    args = parser.parse_args()
    result = run(args.n, args.topics, calibrate=not args.no_calibrate, seconds=args.seconds,
                 rate=args.rate, calibrate_storages=args.calibrate_storages,
                 repeat=args.repeat, before_commit=args.before_commit or None,
                 round_commit=args.round_commit or None)
    print(table(result))
    out = ROOT / 'bench' / 'results' / 'bag_bench.json'
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=2) + '\n')


if __name__ == '__main__':
    main()

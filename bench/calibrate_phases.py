"""
Where ``coreg calibrate`` spends its time and memory: CPU seconds and peak RSS per phase.

``python bench/calibrate_phases.py BAG [coreg calibrate options]`` runs the command in this
process with the phases below wrapped (CPU time of each call, summed per phase, inner phases
included in outer ones; the process's resident memory sampled every 5 ms and the peak kept per
innermost phase) and prints one JSON line: ``total_cpu_s``, ``phases`` (name: calls,
CPU s), ``peak_rss_by_phase`` (phase path: bytes) and ``maxrss_bytes``. The sampling thread
costs a little CPU itself; the phases are what to optimise, the whole-command figures are
``bag_bench``'s.
"""

from __future__ import annotations

import functools
import importlib
import json
import os
from pathlib import Path
import resource
import sys
import threading
import time

ROOT = Path(__file__).resolve().parents[1]

#: (module, function, phase): the read, the offset search's parts, the fit's parts, the verdict.
PHASES = (
    ('coreg_ros.files.bag.posebag', 'read_pose_bag', 'read the bag'),
    ('coreg_ros.core.calibration.pairing', 'validate_stream', 'validate the streams'),
    ('coreg_ros.core.calibration.offset_search', '_candidates', 'coarse offset search'),
    ('coreg_ros.core.calibration.offset_search', 'pair_for', 'pairing'),
    ('coreg_ros.core.calibration.offset_search', 'calibrate', 'robust fit'),
    ('coreg_ros.core.calibration.offset_search', 'velocity_step', 'offset step'),
    ('coreg_ros.core.calibration.offset_search', '_round', 'offset round'),
    ('coreg_ros.core.calibration.pipeline', 'fit_with_offset_search', 'offset search'),
    ('coreg_ros.core.calibration.pipeline', 'fit_at_offset', 'fit at the given offset'),
    ('coreg_ros.core.calibration.pipeline', 'judge', 'verdict'),
    ('coreg_ros.core.calibration.pipeline', 'check_directions', 'direction check'),
    ('coreg_ros.core.clock.trajectory', 'Trajectory.velocity', 'velocity of A'),
)
_PAGE = os.sysconf('SC_PAGE_SIZE')


class _Recorder:
    """The CPU time per phase and the peak RSS per phase path (a sampling thread)."""

    def __init__(self):
        self.cpu, self.peak, self.stack = {}, {}, ['start-up']

    def _rss(self) -> int:
        with open('/proc/self/statm') as f:
            return int(f.read().split()[1]) * _PAGE

    def sample(self) -> None:
        while True:
            rss, path = self._rss(), ' / '.join(self.stack)
            if rss > self.peak.get(path, 0):
                self.peak[path] = rss
            time.sleep(0.005)

    def wrap(self, fn, phase: str):
        @functools.wraps(fn)
        def timed(*args, **kwargs):
            t = time.process_time()
            self.stack.append(phase)
            try:
                return fn(*args, **kwargs)
            finally:
                self.stack.pop()
                calls, s = self.cpu.get(phase, (0, 0.0))
                self.cpu[phase] = (calls + 1, s + time.process_time() - t)
        return timed


def main(argv: list) -> None:
    if str(ROOT) not in sys.path:
        sys.path.insert(0, str(ROOT))
    # as the command does at its start, before this tool's sampling thread exists: a thread
    # made before glibc is held at one arena keeps its own, and the arrays the command's
    # threads put there would count here (1.3 instead of 1.05 GiB) but not in the command
    from coreg_ros.allocator import keep_memory_for_reuse
    keep_memory_for_reuse()
    rec = _Recorder()
    threading.Thread(target=rec.sample, daemon=True).start()
    for module, name, phase in PHASES:
        owner = importlib.import_module(module)
        *cls, fn = name.split('.')
        if cls:
            owner = getattr(owner, cls[0])
        setattr(owner, fn, rec.wrap(getattr(owner, fn), phase))
    from coreg_ros.cli import main as cli
    rec.stack[:] = ['coreg calibrate']
    t = time.process_time()
    try:
        code = cli.main(['calibrate', *argv])
    except SystemExit as e:
        code = e.code
    total = time.process_time() - t
    time.sleep(0.02)
    print(json.dumps({
        'returncode': code, 'total_cpu_s': total,
        'phases': {k: {'calls': c, 'cpu_s': s} for k, (c, s) in rec.cpu.items()},
        'peak_rss_by_phase': dict(sorted(rec.peak.items(), key=lambda kv: -kv[1])),
        'maxrss_bytes': resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024}))


if __name__ == '__main__':
    main(sys.argv[1:])

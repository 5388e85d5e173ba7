"""
Fuzz of the command line's and the node's inputs (issue 12, "What must be shown").

Four kinds of inputs, each reproducible from ``(seed, kind, index)`` (numpy Generator seeded
with ``[seed, kind number, index]``):

``params``
    ROS parameter files (``coreg_node: ros__parameters:``) with random types, values, typos,
    deleted and unknown keys, and whole-file damage (unparseable YAML, empty, other sections).
    Each goes to ``coreg calibrate BAG --config FILE`` (``coreg_ros.cli.main.main`` in-process)
    and, with ROS, to ``coreg_node --ros-args --params-file FILE`` (a subprocess on its own
    domain, stopped with SIGINT once it has started). Whether the two accept or refuse the same
    file is counted (``disagreements``), not judged.
``csv``
    Two CSV exports built from ``simulate_recording`` with random units, quaternion orders,
    separators, headers, time units, sign flips and corruptions, sometimes with the units, the
    quaternion order or the time unit of one file misstated to ``coreg convert``; then
    ``coreg calibrate`` on the bag when the conversion succeeded.
``bag``
    rosbag2 directories (sqlite3 and mcap) truncated at random offsets, with random bytes
    overwritten, bits flipped, blocks zeroed or files deleted, given to ``coreg calibrate``.
``signals`` (with ROS)
    SIGINT or SIGTERM (sometimes twice) at a random moment of ``coreg play``, ``coreg record``,
    ``coreg echo`` or ``coreg_node``, sometimes with a partner process on the same domain.

Inputs are reproducible on the same source tree: the parameter files start from the keys of
``config/coreg.yaml`` and the recordings come from ``coreg_ros.sim``, so a failing parameter file
is also listed in full (``input_file``).

Every input ends as ``ok``, ``traceback`` (an exception escaping ``main()``, or ``Traceback`` in
a subprocess's output), ``hang`` (no exit within the time limit; 10 s after a signal) or
``wrong`` (a result the fuzzer knows is wrong: a misstated unit or quaternion order that
``convert`` + ``calibrate`` let through silently, a corrupt CSV converted without complaint,
an estimate more than 6 sigma from the simulated truth reported as a success, a refusal that is
not one line with exit code 1, ...).

``python bench/fuzz.py [--n N] [--seed S] [--no-ros] [--kinds ...] [--json OUT]`` prints the
table; ``run()`` returns it as a dict (``make bench`` and ``test/test_fuzz.py``).
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
import contextlib
from dataclasses import asdict, dataclass, field
import io
import json
import os
from pathlib import Path
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from typing import Optional

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')

import yaml  # noqa: E402

KINDS = ('params', 'csv', 'bag', 'signals')
VERDICTS = ('traceback', 'hang', 'wrong')
#: In-process command time limit, s (a ``coreg calibrate`` of a 4 s recording takes ~0.5 s).
CLI_TIMEOUT = 60.0
#: A signalled process must exit within this many seconds of the signal.
SIGNAL_EXIT_S = 10.0
#: A node must have refused its file or started within this many seconds (slow machines).
NODE_START_S = 40.0
#: The node runs this long after it has started before it is stopped (~3 s in all).
NODE_RUN_S = 1.0
#: Concurrent subprocess jobs (nodes, signalled commands), beside the in-process work.
WORKERS = 2
#: Failing inputs listed per kind.
SHOWN = 5
#: Simulated recordings: duration s, rates Hz.
SIM_DURATION = 4.0
#: An estimate further than this many posterior sigma from the truth (any axis) is wrong.
TRUTH_SIGMA = 6.0
#: Marker of a started node in its log.
NODE_STARTED = 'listening to'


def _bin(name: str) -> Optional[Path]:
    path = Path(sys.executable).parent / name
    return path if path.exists() else None


def _coreg_cmd() -> list:
    exe = _bin('coreg')
    return [str(exe)] if exe else [sys.executable, '-m', 'coreg_ros.cli.main']


def _node_cmd() -> list:
    exe = _bin('coreg_node')
    return [str(exe)] if exe else [sys.executable, '-m', 'coreg_ros.ros.node']


# ----------------------------------------------------------------------------------------------
# Outcomes
# ----------------------------------------------------------------------------------------------

@dataclass
class Outcome:
    """What one input gave: the verdict, and enough to reproduce and read it."""

    kind: str
    seed: int
    index: int
    desc: str
    verdict: str = 'ok'
    why: str = ''
    command: str = ''
    tail: str = ''
    info: dict = field(default_factory=dict)
    fault: str = ''

    def fail(self, verdict: str, why: str, command: str = '', output: str = '') -> None:
        """Record a failure; the first traceback, else hang, else wrong one is kept."""
        rank = {'ok': 3, 'wrong': 2, 'hang': 1, 'traceback': 0}
        if rank[verdict] < rank[self.verdict]:
            self.verdict, self.why, self.command = verdict, why, command
            self.tail = _tail(output)
            self.fault = fault_key(self.kind, verdict, why, output)


def _exception_name(output: str) -> str:
    """Class name of the exception a traceback in ``output`` ends with ('' if none)."""
    lines = output.splitlines()
    starts = [i for i, ln in enumerate(lines) if ln.startswith('Traceback (most recent')]
    for ln in lines[starts[-1] + 1:] if starts else ():
        if ln and not ln[0].isspace():
            return ln.split(':', 1)[0].rsplit('.', 1)[-1].strip()
    return ''


def fault_key(kind: str, verdict: str, why: str, output: str) -> str:
    """
    Return a short stable name of the fault behind a failure (groups them; tells known ones).

    E.g. ``signal-during-imports``, ``swapped-topics-unwarned``,
    ``node-traceback:InvalidParameterTypeException``, ``refusal-not-one-line:RuntimeWarning``.
    """
    if why.startswith(STARTUP_WHY):
        return 'signal-during-imports'
    if why.startswith('topics swapped'):
        return 'swapped-topics-unwarned'
    if why.startswith('node refusal'):
        return 'node-refusal-not-one-line'
    if 'not one line' in why:
        return 'refusal-not-one-line' + (':RuntimeWarning' if 'RuntimeWarning' in output
                                         else '')
    if verdict == 'traceback':
        who = 'node' if 'node' in why else kind
        return f'{who}-traceback:{_exception_name(output) or "?"}'
    return f'{kind}-{verdict}:' + ' '.join(w for w in why.split()[:4] if w.isalpha())


def _tail(text: str, lines: int = 8, chars: int = 1200) -> str:
    text = '\n'.join(str(text).rstrip().splitlines()[-lines:])
    return text[-chars:]


def _rng(seed: int, kind: str, index: int) -> np.random.Generator:
    return np.random.default_rng([seed, KINDS.index(kind), index])


def _pick(rng: np.random.Generator, items):
    items = list(items)
    return items[int(rng.integers(len(items)))]


# ----------------------------------------------------------------------------------------------
# Running the command line in-process, and subprocesses
# ----------------------------------------------------------------------------------------------

class _Hang(BaseException):
    """Raised by the watchdog alarm inside an in-process command."""


@dataclass
class CliRun:
    code: Optional[int]
    out: str
    err: str
    traceback: bool = False
    hang: bool = False
    seconds: float = 0.0

    @property
    def output(self) -> str:
        return self.out + self.err


def run_cli(argv: list, timeout: float = CLI_TIMEOUT) -> CliRun:
    """
    Run ``coreg_ros.cli.main.main(argv)`` in this process, capturing its output.

    An exception escaping ``main()`` (or ``Traceback`` in what it printed) is a traceback;
    running past ``timeout`` (a SIGALRM watchdog, main thread only) is a hang.
    """
    import traceback as tb

    from coreg_ros.cli.main import main

    out, err = io.StringIO(), io.StringIO()
    code, trace, hang = None, False, False
    use_alarm = threading.current_thread() is threading.main_thread()
    old = None
    if use_alarm:
        def _alarm(signum, frame):
            raise _Hang()
        old = signal.signal(signal.SIGALRM, _alarm)
        signal.setitimer(signal.ITIMER_REAL, timeout)
    t0 = time.perf_counter()
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            try:
                code = main([str(a) for a in argv])
            except SystemExit as e:  # argparse
                code = e.code if isinstance(e.code, int) else (0 if e.code is None else 1)
    except _Hang:
        hang = True
        err.write(f'\n[fuzz] no exit after {timeout:g} s\n')
    except BaseException:  # noqa: B036 - anything escaping main() is the finding
        trace = True
        err.write(tb.format_exc())
    finally:
        if use_alarm:
            signal.setitimer(signal.ITIMER_REAL, 0)
            signal.signal(signal.SIGALRM, old)
    run = CliRun(code, out.getvalue(), err.getvalue(), hang=hang,
                 seconds=time.perf_counter() - t0)
    run.traceback = trace or 'Traceback (most recent call last)' in run.output
    return run


def _default_sigint() -> None:
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def _cmdline(argv) -> str:
    return ' '.join(str(a) for a in argv)


class Proc:
    """A subprocess with its output in a file, on a given environment."""

    def __init__(self, argv: list, env: dict, log: Path, cwd: Path):
        self.argv = [str(a) for a in argv]
        self.log_path = log
        self._log = open(log, 'w')  # noqa: SIM115 - closed in finish()
        self.started = time.monotonic()
        # SIGINT as a user's terminal has it: a fuzz started in the background of a
        # non-interactive shell inherits it ignored, and so would every child
        self.proc = subprocess.Popen(self.argv, env=env, cwd=cwd, stdout=self._log,
                                     stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                     start_new_session=True, preexec_fn=_default_sigint)

    def alive(self) -> bool:
        return self.proc.poll() is None

    def output(self) -> str:
        if not self._log.closed:
            self._log.flush()
        try:
            return self.log_path.read_text(errors='replace')
        except OSError:
            return ''

    def signal(self, sig) -> None:
        if self.alive():
            with contextlib.suppress(ProcessLookupError):
                self.proc.send_signal(sig)

    def wait(self, timeout: float) -> bool:
        """Wait for the exit; False if still running after ``timeout``."""
        try:
            self.proc.wait(timeout)
            return True
        except subprocess.TimeoutExpired:
            return False

    def finish(self) -> None:
        """Kill it if it still runs (this process only) and close the log."""
        if self.alive():
            self.proc.kill()
            self.proc.wait()
        self._log.close()

    @property
    def code(self) -> Optional[int]:
        return self.proc.returncode

    def wait_for(self, text: str, timeout: float) -> bool:
        """Wait until ``text`` is in the output or the process ended; True if it is in it."""
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            if text in self.output():
                return True
            if not self.alive():
                return text in self.output()
            time.sleep(0.05)
        return False


def _has_traceback(text: str) -> bool:
    return 'Traceback' in text


def _startup_interrupt(text: str) -> bool:
    """
    Tell a KeyboardInterrupt traceback raised while the program was still importing.

    The signal came before ``main()`` had its handling in place: the traceback ends in
    ``KeyboardInterrupt`` and passes through module imports (``in <module>`` below the entry
    script) or ``build_parser`` (which imports the subcommands).
    """
    if _exception_name(text) not in ('KeyboardInterrupt', 'ImportError'):
        return False   # (a C extension interrupted while loading: 'initialization failed')
    lines = [ln.strip() for ln in text.strip().splitlines()]
    start = len(lines) - 1 - lines[::-1].index('Traceback (most recent call last):')
    frames = [ln for ln in lines[start:] if ln.startswith('File ')]
    return any(f.endswith(('in <module>', 'in build_parser', 'in _find_and_load'))
               for f in frames[1:])


def _ros_env(domain_id: int, home: Path) -> dict:
    env = dict(os.environ)
    env['ROS_DOMAIN_ID'] = str(domain_id)
    env['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    env.pop('ROS_LOCALHOST_ONLY', None)
    env['HOME'] = str(home)                       # ~/.ros/coreg of a mutated storage_dir
    env['ROS_LOG_DIR'] = str(home / 'ros_log')
    env['PYTHONUNBUFFERED'] = '1'
    return env


# ----------------------------------------------------------------------------------------------
# Shared material: a simulated recording, its bags and its truth
# ----------------------------------------------------------------------------------------------

@dataclass
class Material:
    root: Path
    bags: dict              # storage -> bag path
    truth: object           # coreg_ros.sim Truth of the bags
    params_text: str        # config/coreg.yaml
    good_params: Path       # a valid node file (storage in root)


def _material(root: Path, seed: int) -> Material:
    from coreg_ros.files.bag.posebag import write_pose_bag
    from coreg_ros.sim import simulate_recording

    rec = simulate_recording(int(seed) % 2**31, SIM_DURATION)
    bags = {}
    for storage in ('sqlite3', 'mcap'):
        bags[storage] = root / f'base_{storage}'
        write_pose_bag(bags[storage], rec.streams, storage=storage)
    text = (ROOT / 'config' / 'coreg.yaml').read_text()
    good = root / 'good_params.yaml'
    good.write_text(yaml.safe_dump({'coreg_node': {'ros__parameters': {
        'storage_dir': str(root / 'good_store')}}}))
    return Material(root, bags, rec.truth, text, good)


def _check_truth(outcome: Outcome, json_path: Path, truth, command: str, output: str) -> None:
    """Mark wrong a success whose T0 or T1 is beyond TRUTH_SIGMA posterior σ of the truth."""
    from coreg_ros.core import quaternion as quat

    try:
        data = json.loads(json_path.read_text())
    except (OSError, ValueError):
        outcome.fail('wrong', 'exit 0 but no --json result', command, output)
        return
    worst = 0.0
    for key, p_true, q_true in (('base_to_base', truth.p0, truth.q0),
                                ('tool_to_marker', truth.p1, truth.q1)):
        est = data[key]
        cov = np.asarray(est['covariance'], dtype=float).reshape(6, 6)
        sig = np.sqrt(np.abs(np.diag(cov)))
        dp = np.abs(np.asarray(est['position']) - np.asarray(p_true))
        worst = max(worst, float(np.max(dp / np.maximum(sig[:3], 1e-9))))
        if data.get('model', 'full_pose') == 'full_pose' or key == 'base_to_base':
            o = est['orientation']
            q = np.array([o['w'], o['x'], o['y'], o['z']])
            # R_true = Exp(dtheta) R_est: dtheta about the header frame's axes
            dq = quat.multiply(np.asarray(q_true)[None], quat.conjugate(q[None]))
            dth = np.abs(quat.log(quat.canonical(dq))[0])
            worst = max(worst, float(np.max(dth / np.maximum(sig[3:], 1e-9))))
    outcome.info['truth_sigma'] = round(worst, 2)
    if worst > TRUTH_SIGMA:
        outcome.fail('wrong', f'success, but {worst:.1f} sigma from the simulated truth',
                     command, output)


# ----------------------------------------------------------------------------------------------
# Kind 1: parameter files
# ----------------------------------------------------------------------------------------------

#: Values of any type, as YAML text.
WRONG_VALUES = (
    '1', '0', '-3', '2.5', '0.001', '1e-3', '1.0e+2', '"0.05"', "'abc'", 'abc', '12ms', 'true',
    'false', 'yes', 'off', 'null', '~', '', '[]', '[1, 2]', '[0.1, 0.2]', '[0.1, 2]',
    '["a", "b"]', '[/a, /b, /c]', '{a: 1}', '.nan', '.inf', '-.inf', '1e400', '0x10', '1_000',
    '2026-01-01', '!!binary aGVsbG8=', '[[1, 2], [3]]', '"/device_a/pose"', '/device_a/pose',
    'full_pose', 'ols', '9223372036854775808', '-0.0', '1e-300', '[true, false]', '"true"',
    '[0.0002, .nan]', '[1e-3, 5e-4]', '"[0.1, 0.2]"', '&anchor 0.05', "''",
)
#: Values of the right type but out of range or meaningless, per key.
BAD_VALUES = {
    'sigma_a': ('[-0.1, 0.5]', '[0.0, 0.0]', '[0.1]', '[0.1, 0.2, 0.3]', '[1.0e+300, 0.1]'),
    'sigma_b': ('[-0.1, 0.5]', '[0.0, 0.0]', '[0.1]', '[0.1, 0.2, 0.3]', '[5.0, 5.0]'),
    'max_gap': ('0.0', '-1.0', '1.0e+9', '1.0e-9'),
    'time_offset': ('1.0e+12', '-5.0', '0.3', '1.0e-300'),
    'min_pairs': ('0', '-1', '2', '1000000000', '100000'),
    'max_iterations': ('0', '-5', '1', '100000'),
    'model': ('fullpose', 'three_marker', 'position_only', "''", 'FULL_POSE'),
    'method': ('OLS', 'lm', "''", 'tls '),
    'topic_a': ("''", "'not a topic'", "'/a b'", '/device_b/pose', '~/x', '/device_a/pose/'),
    'topic_b': ('[]', '[/a, /b, /c]', '["/device_a/pose"]', "['']", '[/device_b/pose, /b2]'),
    'buffer_capacity': ('0', '-1', '5', '10', '100000001'),
    'storage_dir': ("''", '/proc/nope', 'rel/dir', '/dev/null'),
    'prior_file': ('/nonexistent/prior.yaml', 'bad', '/dev/null', '/etc'),
    'frame_base_a': ("''", "'a b'", 'device_b_base'),
    'frame_base_b': ("''", 'device_a_base'),
    'fused_rate_limit': ('-1.0', '1.0e+300', '0.0'),
    'marker_magnification': ('0.0', '-2.0', '1.0e+9'),
}
UNKNOWN_KEYS = (
    ('sigma_A', '[0.0002, 0.0005]'), ('methd', 'ols'), ('maxgap', '0.05'), ('foo', '1'),
    ('use_sim_time', 'true'), ('use_sim_time', '1'), ('use_sim_time', 'abc'),
    ('qos_overrides./device_a/pose.subscription.depth', '10'), ('Model', 'full_pose'),
    ('sigma_a.0', '0.1'), ('topic_b/0', '/x'),
)
WHOLE_FILE = ('unparseable', 'empty', 'comment_only', 'no_ros__parameters', 'other_node',
              'wildcard', 'slash_name', 'top_list', 'binary', 'parameters_not_mapping',
              'bom_crlf', 'tab_indent', 'anchors', 'two_documents', 'both_sections')


def _typo(rng, key: str) -> str:
    how = _pick(rng, ('case', 'drop', 'double', 'swap', 'suffix', 'dash'))
    i = int(rng.integers(len(key)))
    if how == 'case':
        return key[:i] + key[i].swapcase() + key[i + 1:] if key[i].isalpha() else key.upper()
    if how == 'drop' and len(key) > 2:
        return key[:i] + key[i + 1:]
    if how == 'double':
        return key[:i] + key[i] + key[i:]
    if how == 'swap' and i + 1 < len(key) and key[i] != key[i + 1]:
        return key[:i] + key[i + 1] + key[i] + key[i + 2:]
    if how == 'dash' and '_' in key:
        return key.replace('_', '-', 1)
    return key + 's'


def _base_entries(material: Material, store: Path) -> list:
    doc = yaml.safe_load(material.params_text)['coreg_node']['ros__parameters']
    entries = []
    for key, value in doc.items():
        if key == 'storage_dir':
            value = str(store)
        entries.append([key, _yaml_text(value)])
    return entries


def _yaml_text(value) -> str:
    if isinstance(value, bool):
        return 'true' if value else 'false'
    if value is None:
        return 'null'
    if isinstance(value, (int, float)):
        text = repr(value)
        return text if '.' in text or 'e' in text or isinstance(value, int) else text + '.0'
    if isinstance(value, list):
        return '[' + ', '.join(_yaml_text(v) for v in value) + ']'
    return json.dumps(value) if value == '' or not str(value)[:1].isalnum() \
        and not str(value).startswith('/') else str(value)


def _render(entries: list, node: str = 'coreg_node') -> str:
    lines = [f'{node}:', '  ros__parameters:']
    lines += [f'    {k}: {v}'.rstrip() for k, v in entries]
    return '\n'.join(lines) + '\n'


def make_params(rng, material: Material, workdir: Path) -> tuple:
    """Return a random parameter file: (text or bytes, one-line description, flags)."""
    store = workdir / 'store'
    entries = _base_entries(material, store)
    desc, flags = [], {}
    if rng.random() < 0.15:
        how = _pick(rng, WHOLE_FILE)
        desc.append(f'whole file: {how}')
        body = _render(entries)
        if how == 'unparseable':
            i = int(rng.integers(2, len(entries) + 2))
            lines = body.splitlines()
            lines.insert(i, _pick(rng, ('    max_gap: [0.05', '   bad indent: 1', 'x: : y',
                                        '    "unclosed: 1', '    - 1', '  : 0.05', '\t\tx: 1',
                                        '    key: {a: 1', '    sigma_a: [0.1, 0.2]]')))
            return '\n'.join(lines) + '\n', '; '.join(desc), flags
        if how == 'empty':
            return '', '; '.join(desc), flags
        if how == 'comment_only':
            return '# nothing here\n', '; '.join(desc), flags
        if how == 'no_ros__parameters':
            return body.replace('  ros__parameters:\n', '').replace('\n    ', '\n  '), \
                '; '.join(desc), flags
        if how == 'other_node':
            return _render(entries, 'other_node'), '; '.join(desc), flags
        if how == 'wildcard':
            return _render(entries, '/**'), '; '.join(desc), flags
        if how == 'slash_name':
            return _render(entries, '/coreg_node'), '; '.join(desc), flags
        if how == 'top_list':
            return '- coreg_node\n- max_gap: 0.05\n', '; '.join(desc), flags
        if how == 'binary':
            return bytes(rng.integers(0, 256, int(rng.integers(1, 400)), dtype=np.uint8)), \
                '; '.join(desc), flags
        if how == 'parameters_not_mapping':
            return 'coreg_node:\n  ros__parameters: 5\n', '; '.join(desc), flags
        if how == 'bom_crlf':
            return ('\ufeff' + body).replace('\n', '\r\n').encode(), '; '.join(desc), flags
        if how == 'tab_indent':
            return body.replace('    ', '\t'), '; '.join(desc), flags
        if how == 'anchors':
            return body.replace('sigma_b: [0.0005, 0.002]', 'sigma_b: &s [0.0005, 0.002]') \
                + '    sigma_a: *s\n', '; '.join(desc), flags
        if how == 'two_documents':
            return body + '---\n' + body, '; '.join(desc), flags
        # both_sections: a wildcard section and the node's, the node's overriding
        return _render([['max_gap', '"x"']], '/**') + body, '; '.join(desc), flags
    for _ in range(int(rng.integers(0, 4))):
        how = _pick(rng, ('wrong_type', 'wrong_type', 'bad_value', 'typo', 'delete', 'unknown',
                          'duplicate', 'swap_topics'))
        i = int(rng.integers(len(entries))) if entries else 0
        if how == 'wrong_type' and entries:
            entries[i][1] = _pick(rng, WRONG_VALUES)
            desc.append(f'{entries[i][0]}: {entries[i][1]}')
        elif how == 'bad_value':
            key = _pick(rng, BAD_VALUES)
            value = _pick(rng, BAD_VALUES[key])
            present = [e for e in entries if e[0] == key]
            if present:
                present[0][1] = value
            else:
                entries.append([key, value])
            desc.append(f'{key}: {value}')
        elif how == 'typo' and entries:
            new = _typo(rng, entries[i][0])
            desc.append(f'typo {entries[i][0]} -> {new}')
            entries[i][0] = new
        elif how == 'delete' and entries:
            desc.append(f'no {entries[i][0]}')
            del entries[i]
        elif how == 'unknown':
            key, value = UNKNOWN_KEYS[int(rng.integers(len(UNKNOWN_KEYS)))]
            entries.insert(int(rng.integers(len(entries) + 1)), [key, value])
            desc.append(f'extra {key}: {value}')
        elif how == 'duplicate' and entries:
            value = _pick(rng, WRONG_VALUES + ('0.05', '[0.0002, 0.0005]'))
            entries.append([entries[i][0], value])
            desc.append(f'{entries[i][0]} twice (then {value})')
        elif how == 'swap_topics':
            for entry in entries:
                if entry[0] == 'topic_a':
                    entry[1] = '/device_b/pose'
                elif entry[0] == 'topic_b':
                    entry[1] = '[/device_a/pose]'
            flags['swapped'] = True
            desc.append('topics swapped')
    return _render(entries), '; '.join(desc) or 'valid file', flags


def _node_params_job(path: Path, workdir: Path) -> dict:
    """Start coreg_node on a parameter file; refused, started, or a fault."""
    from coreg_ros.ros.domain import reserve_domain_id

    argv = [*_node_cmd(), '--ros-args', '--params-file', path]
    with reserve_domain_id() as domain:
        home = workdir / 'home'
        home.mkdir(exist_ok=True)
        proc = Proc(argv, _ros_env(domain.domain_id, home), workdir / 'node.log', workdir)
        try:
            started = proc.wait_for(NODE_STARTED, NODE_START_S)
            res = {'command': _cmdline(argv), 'hang': False, 'started': started}
            if started:
                time.sleep(NODE_RUN_S)
                exited_early = not proc.alive()
                proc.signal(signal.SIGINT)
                res['hang'] = not proc.wait(SIGNAL_EXIT_S)
                res['exited_early'] = exited_early
            elif proc.alive():
                res['hang'] = True   # neither refused nor started
            proc.finish()
            res['code'] = proc.code
            res['output'] = proc.output()
        finally:
            proc.finish()
    return res


def _error_lines(output: str) -> list:
    """Lines of a refusal that are not ROS log lines ([INFO] ...) or warnings."""
    return [ln for ln in output.splitlines()
            if ln.strip() and not ln.startswith('[') and 'warning:' not in ln]


def fuzz_params(n: int, seed: int, material: Material, work: Path, pool, with_ros: bool,
                log: Callable) -> list:
    outcomes, jobs = [], []
    missing = work / 'no_such_bag'
    for index in range(n):
        rng = _rng(seed, 'params', index)
        workdir = work / f'params_{index}'
        workdir.mkdir(parents=True)
        content, desc, flags = make_params(rng, material, workdir)
        path = workdir / 'params.yaml'
        if isinstance(content, bytes):
            path.write_bytes(content)
        else:
            path.write_text(content)
        outcome = Outcome('params', seed, index, desc)
        outcome.info['file'] = content if isinstance(content, str) else repr(content[:200])
        outcome.info['swapped'] = bool(flags.get('swapped'))
        outcomes.append(outcome)
        jobs.append(pool.submit(_node_params_job, path, workdir) if with_ros else None)
    for outcome, job in zip(outcomes, jobs, strict=True):
        workdir = work / f'params_{outcome.index}'
        path = workdir / 'params.yaml'
        # accepted: main() gets past the file to the (missing) bag
        argv = ['calibrate', missing, '--config', path]
        run = run_cli(argv)
        _judge_cli(outcome, run, argv)
        accepted = run.code == 1 and str(missing) in run.err
        outcome.info['cli_accepts'] = accepted
        if not accepted and run.code == 1 and len(_error_lines(run.err)) != 1:
            outcome.fail('wrong', 'a refused file is not one line', _cmdline(argv), run.err)
        if accepted:
            bag = material.bags['sqlite3']
            argv = ['calibrate', bag, '--config', path, '--json', workdir / 'result.json']
            run = run_cli(argv)
            _judge_cli(outcome, run, argv)
            outcome.info['cli_code'] = run.code
            if outcome.info['swapped'] and run.code == 0 and 'swap' not in run.output.lower():
                outcome.fail('wrong', 'topics swapped, yet exit 0 and no word of a swap',
                             _cmdline(argv), run.output)
        if job is not None:
            res = job.result()
            output = res['output']
            outcome.info['node_accepts'] = res['started']
            outcome.info['node_code'] = res['code']
            if _has_traceback(output):
                outcome.fail('traceback', 'Traceback in the node output', res['command'],
                             output)
            if res['hang']:
                outcome.fail('hang', 'node neither refused nor started' if not res['started']
                             else 'node did not exit after SIGINT', res['command'], output)
            elif not res['started']:
                lines = _error_lines(output)
                if res['code'] != 1 or len(lines) != 1:
                    outcome.fail('wrong', f'node refusal: exit {res["code"]}, {len(lines)} '
                                 f'error lines (expected exit 1, one line)', res['command'],
                                 output)
            elif res['code'] != 0:
                outcome.fail('wrong', f'started node exited {res["code"]} after SIGINT',
                             res['command'], output)
            outcome.info['disagree'] = outcome.info['cli_accepts'] != res['started']
        _log_outcome(log, outcome)
    return outcomes


def _judge_cli(outcome: Outcome, run: CliRun, argv: list) -> None:
    command = 'coreg ' + _cmdline(argv)
    if run.traceback:
        outcome.fail('traceback', 'exception escaped main()', command, run.output)
    if run.hang:
        outcome.fail('hang', f'no exit within {CLI_TIMEOUT:g} s', command, run.output)


# ----------------------------------------------------------------------------------------------
# Kind 2: CSV exports through coreg convert and coreg calibrate
# ----------------------------------------------------------------------------------------------

SEPARATORS = (',', ', ', ' ', '\t', ' , ', ';')
TIME_UNITS = {'s': 10**9, 'ms': 10**6, 'ns': 1}
#: Corruptions convert must refuse (exit 1), unless noted.
MUST_REFUSE = ('truncated_line', 'nan', 'text', 'empty', 'extra_column')
CORRUPTIONS = MUST_REFUSE + ('duplicate', 'reverse', 'blank_and_comments', 'crlf_bom',
                             'cut_end', 'huge_value', 'latin1', 'semicolon_line')


def _format_time(ns: int, unit: str) -> str:
    size = TIME_UNITS[unit]
    sign, ns = ('-', -ns) if ns < 0 else ('', ns)
    if size == 1:
        return f'{sign}{ns}'
    digits = len(str(size)) - 1
    return f'{sign}{ns // size}.{ns % size:0{digits}d}'


def _csv_rows(stream, fmt: dict, start_ns: int, rng) -> list:
    scale = 1000.0 if fmt['units'] == 'mm' else 1.0
    q = np.asarray(stream.quat_wxyz, dtype=float).copy()
    if fmt['sign_flips']:
        q[rng.random(len(q)) < 0.5] *= -1
    if fmt['order'] == 'xyzw':
        q = q[:, [1, 2, 3, 0]]
    rows = []
    for i in range(len(stream)):
        t = _format_time(int(stream.stamps[i]) - start_ns, fmt['time'])
        fields = [t] + [f'{v * scale:.9g}' for v in stream.position[i]]
        if fmt['columns'] == 8:
            fields += [f'{v:.9f}' for v in q[i]]
        rows.append(fields)
    return rows


def _options(side: str, fmt: dict, told: dict) -> list:
    out = []
    if told['units'] != 'm' or fmt['explicit']:
        out += [f'--units-{side}', told['units']]
    if fmt['columns'] == 8 and (told['order'] != 'xyzw' or fmt['explicit']):
        out += [f'--quaternion-order-{side}', told['order']]
    if told['time'] != 's' or fmt['explicit']:
        out += [f'--time-unit-{side}', told['time']]
    return out


def make_csv(rng, workdir: Path) -> dict:
    """Two random CSV exports of one simulated recording, the options told, what was done."""
    from coreg_ros.sim import simulate_recording

    model = 'position_only' if rng.random() < 0.15 else 'full_pose'
    sim_seed = int(rng.integers(2**31))
    rate_a = float(_pick(rng, (50.0, 100.0, 200.0)))
    rate_b = float(_pick(rng, (30.0, 50.0, 100.0)))
    rec = simulate_recording(sim_seed, SIM_DURATION, model, rate_a=rate_a, rate_b=rate_b)
    streams = [rec.streams[rec.topics_a], rec.streams[rec.topics_b[0]]]
    relative = rng.random() < 0.3
    start_ns = min(int(s.stamps[0]) for s in streams) if relative else 0
    fmts, told = [], []
    for side in range(2):
        fmt = {'units': _pick(rng, ('m', 'm', 'mm')), 'order': _pick(rng, ('xyzw', 'wxyz')),
               'sep': _pick(rng, SEPARATORS[:-1]) if rng.random() < 0.95 else ';',
               'header': bool(rng.random() < 0.5), 'time': _pick(rng, ('s', 's', 'ms', 'ns')),
               'sign_flips': bool(rng.random() < 0.3), 'explicit': bool(rng.random() < 0.3),
               'columns': 4 if (side == 1 and model == 'position_only') else 8}
        fmts.append(fmt)
        told.append({k: fmt[k] for k in ('units', 'order', 'time')})
    desc = [f'{model}, sim seed {sim_seed}, {rate_a:g}/{rate_b:g} Hz'
            + (', relative times' if relative else '')]
    for side, fmt in zip('AB', fmts, strict=True):
        desc.append(f'{side}: {fmt["units"]} {fmt["order"] if fmt["columns"] == 8 else "xyz"} '
                    f'sep {fmt["sep"]!r} t[{fmt["time"]}]{" header" if fmt["header"] else ""}'
                    f'{" sign-flips" if fmt["sign_flips"] else ""}')
    lie = None
    if rng.random() < 0.35:
        side = int(rng.integers(2))
        what = _pick(rng, ('units', 'order', 'time') if fmts[side]['columns'] == 8
                     else ('units', 'time'))
        other = {'units': {'m': 'mm', 'mm': 'm'}, 'order': {'xyzw': 'wxyz', 'wxyz': 'xyzw'},
                 'time': {'s': _pick(rng, ('ms', 'ns')), 'ms': 's', 'ns': 's'}}
        told[side][what] = other[what][fmts[side][what]]
        lie = (side, what)
        desc.append(f'{"AB"[side]} {what} told {told[side][what]}')
    corruption = None
    sort = False
    if rng.random() < 0.4:
        corruption = _pick(rng, CORRUPTIONS)
        sort = corruption in ('duplicate', 'reverse') and bool(rng.random() < 0.5)
        desc.append(f'corruption {corruption}{" (--sort)" if sort else ""}')
    hit = int(rng.integers(2)) if corruption is not None else None
    if hit is not None:
        desc.append(f'in {"AB"[hit]}')
    paths = []
    for side, (stream, fmt) in enumerate(zip(streams, fmts, strict=True)):
        rows = _csv_rows(stream, fmt, start_ns, rng)
        text = _write_csv(rng, rows, fmt, corruption if side == hit else None)
        path = workdir / f'{"ab"[side]}.csv'
        path.write_bytes(text)
        paths.append(path)
    args = ['convert', *paths, workdir / 'bag', *_options('a', fmts[0], told[0]),
            *_options('b', fmts[1], told[1])]
    if sort:
        args.append('--sort')
    if rng.random() < 0.3:
        args += ['--storage', 'mcap']
    return {'args': args, 'desc': '; '.join(desc), 'lie': lie, 'corruption': corruption,
            'sort': sort, 'model': model, 'truth': rec.truth, 'fmts': fmts,
            'honest': lie is None and corruption in (None, 'blank_and_comments', 'crlf_bom')
            and all(f['sep'] != ';' for f in fmts)}


def _write_csv(rng, rows: list, fmt: dict, corruption: Optional[str]) -> bytes:
    sep = fmt['sep']
    header = []
    if fmt['header']:
        names = ['t', 'x', 'y', 'z'] + (list(fmt['order']) if fmt['columns'] == 8 else [])
        header = [sep.join(names if fmt['order'] == 'xyzw' or fmt['columns'] == 4
                           else ['time'] + names[1:])]
    lines = [sep.join(r) for r in rows]
    n = len(lines)
    i = int(rng.integers(1, n))   # never the first data row (a text row there is a header)
    if corruption == 'truncated_line':
        lines[i] = sep.join(rows[i][:int(rng.integers(1, len(rows[i])))])
    elif corruption == 'nan':
        fields = list(rows[i])
        fields[int(rng.integers(len(fields)))] = _pick(rng, ('nan', 'NaN', 'inf', '-inf'))
        lines[i] = sep.join(fields)
    elif corruption == 'text':
        fields = list(rows[i])
        fields[int(rng.integers(len(fields)))] = _pick(rng, ('abc', '1.2.3', 'n/a', '?', '--',
                                                             '0x1F', 'None'))
        lines[i] = sep.join(fields)
    elif corruption == 'empty':
        lines = _pick(rng, ([], ['   '], ['', '']))
        header = header if rng.random() < 0.5 else []
    elif corruption == 'extra_column':
        lines[i] = sep.join([*rows[i], '0.5'])
    elif corruption == 'duplicate':
        lines.insert(i, lines[i])
    elif corruption == 'reverse':
        j = int(rng.integers(i, min(n, i + 20) + 1))
        lines[i - 1:j] = lines[i - 1:j][::-1] if j - i >= 1 else lines[i - 1:j]
        if j - i < 1:
            lines[i - 1], lines[i] = lines[i], lines[i - 1]
    elif corruption == 'blank_and_comments':
        lines.insert(i, '# tracking resumed')
        lines.insert(int(rng.integers(n)), '')
        lines.append('')
    elif corruption == 'huge_value':
        fields = list(rows[i])
        fields[int(rng.integers(1, 4))] = _pick(rng, ('1e300', '-1e308', '1e-320', '123456789'))
        lines[i] = sep.join(fields)
    elif corruption == 'semicolon_line':
        lines[i] = ';'.join(rows[i])
    text = '\n'.join(header + lines) + ('\n' if lines or header else '')
    data = text.encode()
    if corruption == 'crlf_bom':
        data = b'\xef\xbb\xbf' + text.replace('\n', '\r\n').encode()
    elif corruption == 'cut_end':
        data = data[:int(rng.integers(len(data) // 2, len(data)))]
    elif corruption == 'latin1':
        data = data.replace(b'\n', b'\n# caf\xe9\n', 1)
    return data


_FIX_WORDS = ('--units', '--quaternion-order', '--time-unit', '--invert')


def fuzz_csv(n: int, seed: int, material: Material, work: Path, log: Callable) -> list:
    outcomes = []
    for index in range(n):
        rng = _rng(seed, 'csv', index)
        workdir = work / f'csv_{index}'
        workdir.mkdir(parents=True)
        case = make_csv(rng, workdir)
        outcome = Outcome('csv', seed, index, case['desc'])
        outcomes.append(outcome)
        argv = case['args']
        conv = run_cli(argv)
        _judge_cli(outcome, conv, argv)
        outcome.info['convert_code'] = conv.code
        warned = any(w in line for line in conv.err.splitlines() if 'warning' in line
                     for w in _FIX_WORDS)
        outcome.info['convert_warned'] = warned
        corruption = case['corruption']
        if conv.code == 0 and corruption in MUST_REFUSE:
            outcome.fail('wrong', f'convert accepted a file with corruption {corruption}',
                         'coreg ' + _cmdline(argv), conv.output)
        if conv.code == 0 and corruption in ('duplicate', 'reverse') and not case['sort']:
            outcome.fail('wrong', f'convert accepted {corruption} rows without --sort',
                         'coreg ' + _cmdline(argv), conv.output)
        if conv.code == 1 and len(_error_lines(conv.err)) != 1:
            outcome.fail('wrong', 'convert refusal is not one line', 'coreg ' + _cmdline(argv),
                         conv.output)
        if conv.code == 0:
            cal = ['calibrate', workdir / 'bag', '--json', workdir / 'result.json']
            if case['model'] != 'full_pose':
                cal += ['--model', case['model']]
            run = run_cli(cal)
            _judge_cli(outcome, run, cal)
            outcome.info['calibrate_code'] = run.code
            output = conv.output + run.output
            if case['lie'] and run.code == 0 and not warned:
                side, what = case['lie']
                outcome.fail('wrong', f'{"AB"[side]} {what} misstated, yet convert gave no '
                             f'warning and calibrate exit 0', 'coreg ' + _cmdline(argv)
                             + ' && coreg ' + _cmdline(cal), output)
            if case['honest'] and run.code == 0:
                _check_truth(outcome, workdir / 'result.json', case['truth'],
                             'coreg ' + _cmdline(cal), output)
            if case['honest'] and run.code != 0:
                outcome.info['false_refusal'] = True
            if case['honest'] and warned:
                outcome.info['false_warning'] = True
        _log_outcome(log, outcome)
        if outcome.verdict == 'ok':
            shutil.rmtree(workdir, ignore_errors=True)
    return outcomes


# ----------------------------------------------------------------------------------------------
# Kind 3: damaged bags
# ----------------------------------------------------------------------------------------------

def make_bag(rng, material: Material, workdir: Path) -> tuple:
    storage = _pick(rng, ('sqlite3', 'mcap'))
    bag = workdir / 'bag'
    shutil.copytree(material.bags[storage], bag)
    files = sorted(p for p in bag.iterdir() if p.is_file())
    data = [p for p in files if p.suffix in ('.db3', '.mcap')]
    target = _pick(rng, data) if rng.random() < 0.8 or not data else _pick(rng, files)
    size = target.stat().st_size
    how = _pick(rng, ('truncate', 'truncate', 'overwrite', 'overwrite', 'flip_bits', 'zero',
                      'delete', 'append'))
    raw = bytearray(target.read_bytes())
    # offsets drawn over the whole file, or near its ends where headers and indexes live
    region = _pick(rng, ('any', 'any', 'head', 'tail'))
    lo, hi = {'any': (0, size), 'head': (0, min(size, 4096)),
              'tail': (max(0, size - 4096), size)}[region]
    offset = int(rng.integers(lo, max(lo + 1, hi)))
    if how == 'truncate':
        raw = raw[:offset]
        what = f'truncated at byte {offset} of {size}'
    elif how == 'overwrite':
        k = int(rng.integers(1, 257))
        raw[offset:offset + k] = rng.integers(0, 256, len(raw[offset:offset + k]),
                                              dtype=np.uint8).tobytes()
        what = f'{k} random bytes at {offset} of {size}'
    elif how == 'flip_bits':
        k = int(rng.integers(1, 17))
        where = rng.integers(lo, max(lo + 1, hi), k)
        for w in where:
            if w < len(raw):
                raw[int(w)] ^= 1 << int(rng.integers(8))
        what = f'{k} bits flipped ({region})'
    elif how == 'zero':
        k = int(rng.integers(1, 4097))
        raw[offset:offset + k] = bytes(len(raw[offset:offset + k]))
        what = f'{k} bytes zeroed at {offset} of {size}'
    elif how == 'append':
        raw += rng.integers(0, 256, int(rng.integers(1, 2000)), dtype=np.uint8).tobytes()
        what = 'garbage appended'
    else:
        what = 'deleted'
    if how == 'delete':
        target.unlink()
    else:
        target.write_bytes(bytes(raw))
    return bag, f'{storage} {target.name}: {what}'


def fuzz_bag(n: int, seed: int, material: Material, work: Path, log: Callable) -> list:
    outcomes = []
    for index in range(n):
        rng = _rng(seed, 'bag', index)
        workdir = work / f'bag_{index}'
        workdir.mkdir(parents=True)
        bag, desc = make_bag(rng, material, workdir)
        outcome = Outcome('bag', seed, index, desc)
        outcomes.append(outcome)
        argv = ['calibrate', bag, '--json', workdir / 'result.json']
        run = run_cli(argv)
        _judge_cli(outcome, run, argv)
        outcome.info['calibrate_code'] = run.code
        if run.code == 1 and len(_error_lines(run.err)) != 1:
            outcome.fail('wrong', 'refusal is not one line', 'coreg ' + _cmdline(argv),
                         run.output)
        if run.code == 0:
            _check_truth(outcome, workdir / 'result.json', material.truth,
                         'coreg ' + _cmdline(argv), run.output)
        _log_outcome(log, outcome)
        if outcome.verdict == 'ok':
            shutil.rmtree(workdir, ignore_errors=True)
    return outcomes


# ----------------------------------------------------------------------------------------------
# Kind 4: signals at random moments of the ROS commands and the node
# ----------------------------------------------------------------------------------------------

def make_signal_case(rng, material: Material, workdir: Path) -> dict:
    target = _pick(rng, ('play', 'record', 'echo', 'node'))
    bag = material.bags['sqlite3']
    coreg = _coreg_cmd()
    node_argv = [*_node_cmd(), '--ros-args', '--params-file', material.good_params,
                 '-p', f'storage_dir:={workdir / "store"}']
    play_argv = [*coreg, 'play', bag, '--rate', _pick(rng, ('1', '2', 'inf')), '--wait',
                 _pick(rng, ('0', '1', '10'))]
    if target == 'play':
        argv = play_argv
        partner = _pick(rng, (None, None, 'echo', 'node', 'record'))
    elif target == 'record':
        argv = [*coreg, 'record', workdir / 'rec', '--topics', '/device_a/pose',
                '/device_b/pose']
        if rng.random() < 0.3:
            argv += ['--duration', _pick(rng, ('1', '3', '30'))]
        if rng.random() < 0.3:
            argv += ['--storage', 'mcap']
        partner = _pick(rng, (None, 'play', 'play'))
    elif target == 'echo':
        argv = [*coreg, 'echo', _pick(rng, ('/device_a/pose', '/diagnostics', 'base_to_base',
                                            'fused_pose', '/nothing'))]
        if rng.random() < 0.3:
            argv.append('--once')
        if rng.random() < 0.2:
            argv += ['--timeout', _pick(rng, ('1', '5'))]
        partner = _pick(rng, (None, 'play', 'node'))
    else:
        argv = node_argv
        partner = _pick(rng, (None, 'play', 'play'))
    partner_argv = {None: None, 'node': node_argv,
                    'echo': [*coreg, 'echo', '/device_a/pose'],
                    'record': [*coreg, 'record', workdir / 'partner_rec', '--topics',
                               '/device_a/pose'],
                    'play': [*coreg, 'play', bag, '--rate', '1', '--wait', '10']}[partner]
    sig = signal.SIGINT if rng.random() < 0.7 else signal.SIGTERM
    delay = float(rng.uniform(0.0, 6.0))
    second = float(rng.uniform(0.0, 1.0)) if rng.random() < 0.2 else None
    desc = (f'{target}{" + " + partner if partner else ""}: {sig.name} at {delay:.2f} s'
            + (f', again {second:.2f} s later' if second is not None else '')
            + f' ({_cmdline(argv[len(coreg) if target != "node" else 1:])})')
    return {'target': target, 'argv': argv, 'partner': partner, 'partner_argv': partner_argv,
            'signal': sig, 'delay': delay, 'second': second, 'desc': desc}


def _signal_job(case: dict, workdir: Path) -> dict:
    from coreg_ros.ros.domain import reserve_domain_id

    res = {'traceback': [], 'hang': [], 'wrong': []}
    home = workdir / 'home'
    home.mkdir(parents=True, exist_ok=True)
    with reserve_domain_id() as domain:
        env = _ros_env(domain.domain_id, home)
        partner = None
        procs = []
        try:
            if case['partner_argv']:
                partner = Proc(case['partner_argv'], env, workdir / 'partner.log', workdir)
                procs.append(partner)
                time.sleep(0.5)
            proc = Proc(case['argv'], env, workdir / 'target.log', workdir)
            procs.append(proc)
            time.sleep(case['delay'])
            exited_before = not proc.alive()
            proc.signal(case['signal'])
            sent = time.monotonic()
            if case['second'] is not None:
                time.sleep(case['second'])
                proc.signal(case['signal'])
            if not proc.wait(max(0.0, SIGNAL_EXIT_S - (time.monotonic() - sent))):
                res['hang'].append(f'{case["target"]} did not exit within {SIGNAL_EXIT_S:g} s '
                                   f'of {case["signal"].name}')
            proc.finish()
            out = proc.output()
            res['code'] = proc.code
            res['exited_before'] = exited_before
            res['output'] = out
            if _has_traceback(out):
                res['traceback'].append(_traceback_why(case['target'], out))
            if partner is not None:
                _wait_ready(partner, case['partner'])
                partner.signal(signal.SIGINT)
                if not partner.wait(SIGNAL_EXIT_S):
                    res['hang'].append(f'partner {case["partner"]} did not exit within '
                                       f'{SIGNAL_EXIT_S:g} s of SIGINT')
                partner.finish()
                pout = partner.output()
                res['partner_output'] = pout
                if _has_traceback(pout):
                    res['traceback'].append(_traceback_why(f'partner {case["partner"]}', pout))
            _judge_signal_result(case, res, workdir)
        finally:
            for p in procs:
                p.finish()
    return res


#: Start of the reason given for a traceback on a signal during the imports.
STARTUP_WHY = 'traceback of a signal during the start-up imports'


def _traceback_why(who: str, output: str) -> str:
    if _startup_interrupt(output):
        return f'{STARTUP_WHY} of {who} (the signal came before main() handles it)'
    return f'Traceback from {who}'


#: What a partner prints once it runs (past its imports); none for echo.
READY = {'node': NODE_STARTED, 'record': 'recording', 'play': 'playing'}
#: Age of a partner without a marker before it is stopped, s.
READY_AGE = 8.0


def _wait_ready(proc: Proc, what: str, timeout: float = 30.0) -> None:
    """Let a partner finish starting before it is stopped (its start-up is not the input)."""
    marker = READY.get(what)
    if marker is not None:
        proc.wait_for(marker, timeout)
    else:
        time.sleep(max(0.0, READY_AGE - (time.monotonic() - proc.started)))


def _judge_signal_result(case: dict, res: dict, workdir: Path) -> None:
    """Results the fuzzer knows are wrong: a bag said written that is not, a node losing data."""
    code, out = res.get('code'), res.get('output', '')
    if case['target'] == 'record' and 'wrote ' in out:
        from coreg_ros.files.bag.posebag import read_pose_bag
        try:
            got = read_pose_bag(workdir / 'rec', ['/device_a/pose', '/device_b/pose'])
            res['recorded'] = {t: len(s) for t, s in got.items()}
        except Exception as e:  # noqa: BLE001 - any failure to read it back is the finding
            res['wrong'].append(f'record said it wrote {workdir / "rec"} but it cannot be read '
                                f'({type(e).__name__}: {e})')
    if case['target'] == 'node' and code not in (0, 130, 143, -2, -15, None) \
            and not res['exited_before'] and not res['traceback']:
        res['wrong'].append(f'node exit code {code} after {case["signal"].name}')
    if case['target'] in ('play', 'record', 'echo') and code not in (0, 1, 130, 143, -2, -15) \
            and not res['traceback']:
        res['wrong'].append(f'{case["target"]} exit code {code} after {case["signal"].name}')


def fuzz_signals(n: int, seed: int, material: Material, work: Path, pool) -> list:
    """Submit the signal inputs to ``pool``; return (outcome, future) pairs."""
    jobs = []
    for index in range(n):
        rng = _rng(seed, 'signals', index)
        workdir = work / f'signals_{index}'
        workdir.mkdir(parents=True)
        case = make_signal_case(rng, material, workdir)
        outcome = Outcome('signals', seed, index, case['desc'])
        outcome.command = _cmdline(case['argv'])
        jobs.append((outcome, case, pool.submit(_signal_job, case, workdir)))
    return jobs


def _collect_signals(jobs: list, log: Callable) -> list:
    outcomes = []
    for outcome, case, job in jobs:
        res = job.result()
        output = res.get('output', '')
        if res.get('partner_output'):
            output += '\n--- partner ---\n' + res['partner_output']
        partner = (f'  (partner: {_cmdline(case["partner_argv"])})' if case['partner_argv']
                   else '')
        cmd = _cmdline(case['argv']) + partner
        for why in res['traceback']:
            outcome.fail('traceback', why, cmd, output)
        for why in res['hang']:
            outcome.fail('hang', why, cmd, output)
        for why in res['wrong']:
            outcome.fail('wrong', why, cmd, output)
        outcome.info['code'] = res.get('code')
        outcome.info['startup_interrupt'] = bool(res['traceback']) and all(
            why.startswith(STARTUP_WHY) for why in res['traceback'])
        outcomes.append(outcome)
        _log_outcome(log, outcome)
    return outcomes


# ----------------------------------------------------------------------------------------------
# The run and its table
# ----------------------------------------------------------------------------------------------

def _log_outcome(log: Callable, outcome: Outcome) -> None:
    if outcome.verdict != 'ok':
        log(f'fuzz {outcome.kind} #{outcome.index}: {outcome.verdict.upper()}: {outcome.why} '
            f'[{outcome.desc}]')


def run(n_per_kind: int, seed: int, *, with_ros: bool = True, log=print,
        kinds=KINDS, keep: Optional[Path] = None) -> dict:
    """
    Run the fuzz: ``n_per_kind`` inputs of each kind, all drawn from ``seed``.

    Parameters
    ----------
    n_per_kind : int
        Inputs per kind.
    seed : int
        Input ``i`` of a kind is drawn from ``np.random.default_rng([seed, kind, i])``.
    with_ros : bool
        Also start ``coreg_node`` on the parameter files and run the signal inputs.
    log : callable
        Gets one line per failing input and per finished kind.
    kinds : sequence of str
        Subset of ``KINDS`` to run.
    keep : path, optional
        Work directory to keep (default: a temporary one, removed at the end).

    Returns
    -------
    dict
        ``kinds``: per kind ``tried``, ``traceback``, ``hang``, ``wrong``, ``seconds`` (and
        ``disagreements`` for params with ROS, ``false_refusals`` for csv); ``failures``: the
        first ``SHOWN`` failing inputs per kind (kind, seed, index, description, why, command,
        tail of the output); ``totals``; ``seed``, ``n_per_kind``, ``with_ros``.

    """
    from concurrent.futures import ThreadPoolExecutor

    kinds = [k for k in KINDS if k in kinds and (with_ros or k != 'signals')]
    t_start = time.perf_counter()
    tmp = None
    if keep is None:
        tmp = tempfile.TemporaryDirectory(prefix='coreg_fuzz_')
        work = Path(tmp.name)
    else:
        work = Path(keep)
        work.mkdir(parents=True, exist_ok=True)
    results = {'seed': seed, 'n_per_kind': n_per_kind, 'with_ros': with_ros, 'kinds': {},
               'failures': []}
    try:
        material = _material(work, seed)
        by_kind, seconds = {}, {}
        with ThreadPoolExecutor(max_workers=WORKERS) as pool:
            signal_jobs = None
            t_sig = time.perf_counter()
            if 'signals' in kinds:
                signal_jobs = fuzz_signals(n_per_kind, seed, material, work, pool)
            if 'params' in kinds:
                t = time.perf_counter()
                by_kind['params'] = fuzz_params(n_per_kind, seed, material, work, pool,
                                                with_ros, log)
                seconds['params'] = time.perf_counter() - t
                log(f'fuzz params: {n_per_kind} done in {seconds["params"]:.1f} s')
            if 'csv' in kinds:
                t = time.perf_counter()
                by_kind['csv'] = fuzz_csv(n_per_kind, seed, material, work, log)
                seconds['csv'] = time.perf_counter() - t
                log(f'fuzz csv: {n_per_kind} done in {seconds["csv"]:.1f} s')
            if 'bag' in kinds:
                t = time.perf_counter()
                by_kind['bag'] = fuzz_bag(n_per_kind, seed, material, work, log)
                seconds['bag'] = time.perf_counter() - t
                log(f'fuzz bag: {n_per_kind} done in {seconds["bag"]:.1f} s')
            if signal_jobs is not None:
                by_kind['signals'] = _collect_signals(signal_jobs, log)
                seconds['signals'] = time.perf_counter() - t_sig
                log(f'fuzz signals: {n_per_kind} done ({seconds["signals"]:.1f} s since the '
                    f'start, run beside the others)')
        for kind in kinds:
            outs = by_kind[kind]
            row = {'tried': len(outs), 'seconds': round(seconds[kind], 1)}
            for verdict in VERDICTS:
                row[verdict] = sum(o.verdict == verdict for o in outs)
            if kind == 'params' and with_ros:
                row['disagreements'] = sum(bool(o.info.get('disagree')) for o in outs)
                row['disagreeing'] = [o.index for o in outs if o.info.get('disagree')]
            if kind == 'signals':
                row['startup_tracebacks'] = sum(bool(o.info.get('startup_interrupt'))
                                                for o in outs)
            if kind == 'csv':
                row['false_refusals'] = sum(bool(o.info.get('false_refusal')) for o in outs)
                row['false_warnings'] = sum(bool(o.info.get('false_warning')) for o in outs)
                row['caught_misstatements'] = sum(
                    1 for o in outs if ' told ' in o.desc and o.verdict != 'wrong')
            faults = {}
            for o in outs:
                if o.verdict != 'ok':
                    faults[o.fault] = faults.get(o.fault, 0) + 1
            row['faults'] = faults
            results['kinds'][kind] = row
            failing = [o for o in outs if o.verdict != 'ok']
            first = {}
            for o in failing:           # the first input of each fault, then the others
                first.setdefault(o.fault, o)
            shown = list(first.values()) + [o for o in failing if o not in first.values()]
            results['failures'] += [_public(o) for o in shown[:SHOWN]]
        results['disagreement_examples'] = [
            {'index': o.index, 'desc': o.desc, 'cli_accepts': o.info.get('cli_accepts'),
             'node_accepts': o.info.get('node_accepts'), 'file': o.info.get('file')}
            for o in by_kind.get('params', []) if o.info.get('disagree')][:SHOWN]
        results['totals'] = {v: sum(r[v] for r in results['kinds'].values())
                             for v in ('tried',) + VERDICTS}
        results['seconds'] = round(time.perf_counter() - t_start, 1)
    finally:
        if tmp is not None:
            tmp.cleanup()
    return results


def _public(o: Outcome) -> dict:
    d = asdict(o)
    d['info'] = {k: v for k, v in d['info'].items() if k != 'file'}
    if 'file' in o.info:   # the parameter file itself: its keys follow config/coreg.yaml
        d['input_file'] = o.info['file']
    return d


def table(results: dict) -> str:
    """Return the markdown fuzz table and the failing inputs, for a person."""
    lines = ['| kind | tried | tracebacks | hangs | known-wrong | notes | time |',
             '|---|---|---|---|---|---|---|']
    for kind, r in results['kinds'].items():
        notes = []
        if 'disagreements' in r:
            notes.append(f'CLI/node disagree on {r["disagreements"]} files')
        if r.get('startup_tracebacks'):
            notes.append(f'{r["startup_tracebacks"]} of the tracebacks: a signal during the '
                         f'start-up imports')
        if 'false_refusals' in r:
            notes.append(f'{r["caught_misstatements"]} misstatements caught, '
                         f'{r["false_refusals"]} honest inputs refused, '
                         f'{r["false_warnings"]} falsely warned')
        lines.append(f'| {kind} | {r["tried"]} | {r["traceback"]} | {r["hang"]} '
                     f'| {r["wrong"]} | {"; ".join(notes) or "–"} | {r["seconds"]:.0f} s |')
    t = results['totals']
    lines.append(f'| **all** | {t["tried"]} | {t["traceback"]} | {t["hang"]} | {t["wrong"]} '
                 f'| seed {results["seed"]} | {results["seconds"]:.0f} s |')
    if any(r.get('faults') for r in results['kinds'].values()):
        lines += ['', 'faults (inputs):']
    for kind, r in results['kinds'].items():
        for key, count in sorted(r.get('faults', {}).items()):
            lines.append(f'- {kind}: {key}: {count} input(s)')
    for f in results['failures']:
        lines += ['', f'- {f["kind"]} seed {f["seed"]} index {f["index"]}: **{f["verdict"]}** '
                      f'({f["fault"]}): {f["why"]}', f'  input: {f["desc"]}',
                  f'  command: {f["command"]}']
        if f.get('input_file'):
            lines.append(f'  file: {len(f["input_file"].splitlines())} lines (input_file in '
                         f'the JSON results)')
        lines += ['  output (tail):'] + ['    ' + ln for ln in f['tail'].splitlines()]
    for d in results.get('disagreement_examples', []):
        lines += ['', f'- params index {d["index"]} ({d["desc"]}): CLI '
                      f'{"accepts" if d["cli_accepts"] else "refuses"}, node '
                      f'{"accepts" if d["node_accepts"] else "refuses"}']
    return '\n'.join(lines)


def main(argv=None) -> int:
    """Run the fuzz and print its table; exit 1 if any input failed."""
    p = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    p.add_argument('--n', type=int, default=60, help='inputs per kind (default 60)')
    p.add_argument('--seed', type=int, default=12)
    p.add_argument('--no-ros', action='store_true', help='no node, no signals')
    p.add_argument('--kinds', nargs='+', choices=KINDS, default=list(KINDS))
    p.add_argument('--json', help='also write the results as JSON')
    p.add_argument('--keep', help='keep the work directory here')
    args = p.parse_args(argv)
    results = run(args.n, args.seed, with_ros=not args.no_ros, kinds=args.kinds,
                  log=lambda m: print(m, file=sys.stderr, flush=True),
                  keep=Path(args.keep) if args.keep else None)
    print(table(results))
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=2, default=str) + '\n')
    return 0 if not any(results['totals'][v] for v in VERDICTS) else 1


if __name__ == '__main__':
    sys.exit(main())

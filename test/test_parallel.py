"""
Many cases in parallel (coreg_ros.parallel, issue 15): local processes and a Dask cluster.

The same cases give the same results whatever the workers (each case carries its own seed); a
case that raises is a record with its seed and does not stop the others; ``coreg batch`` runs
the single-bag commands over a folder; a scheduler that cannot be used is a one-line error.
The Dask test starts its own LocalCluster (2 worker processes, 1 thread each) on this machine.
"""

import json
import os
from pathlib import Path
import sys

from bench import montecarlo as mc
from coreg_ros import parallel
from coreg_ros.cli.main import build_parser, main
from coreg_ros.files.bag.posebag import write_pose_bag
from coreg_ros.parallel import CaseFailure, run_cases, SchedulerError
from coreg_ros.sim import simulate_recording
from coreg_ros.sim.injected import parse_effect
from coreg_ros.sim.validation import validate
import numpy as np
import pytest

SHORT = (15.0, 20.0)
#: Nothing listens on the discard port of this machine: the connection is refused.
NO_SCHEDULER = 'tcp://127.0.0.1:9'


def unlucky_square(case: dict) -> int:
    """Square a case's seed, failing for seed 13 (module level: the workers import it)."""
    if case['seed'] == 13:
        raise RuntimeError('seed 13 is unlucky\nsecond line of the message')
    return case['seed'] ** 2


def _without_timing(results: list) -> list:
    return [{k: v for k, v in r.items() if k != 'seconds'} for r in results]


def test_validate_same_results_for_one_and_two_workers():
    one = validate(3, seed=21, duration=SHORT, workers=1)
    two = validate(3, seed=21, duration=SHORT, workers=2)
    assert [r['seed'] for r in one['results']] == [r['seed'] for r in two['results']]
    assert _without_timing(one['results']) == _without_timing(two['results'])
    assert one['summary']['confusion_matrix'] == two['summary']['confusion_matrix']


def test_montecarlo_same_results_for_one_and_two_workers():
    scenario = mc.SCENARIOS[1]
    one = mc.run_trials(scenario, 24, workers=1)
    two = mc.run_trials(scenario, 24, workers=2)
    assert one['failed'] == two['failed'] == []
    for key in mc.TRIAL_KEYS:
        np.testing.assert_array_equal(one['tls'][key], two['tls'][key])
    # the trials differ from each other (each has its own noise), so equality means something
    assert len(np.unique(one['tls']['chi2'])) == 24


def test_failing_case_does_not_stop_the_others():
    cases = [{'seed': s} for s in (3, 13, 5, 7)]
    seen = []
    results = run_cases(unlucky_square, cases, workers=2,
                        progress=lambda f, text: seen.append((f, text)))
    assert results[0] == 9 and results[2] == 25 and results[3] == 49
    failure = results[1]
    assert isinstance(failure, CaseFailure)
    assert failure.seed == 13 and failure.index == 1
    assert failure.error.startswith('RuntimeError: seed 13 is unlucky')
    assert '\n' not in failure.error
    assert 'seed 13' in str(failure)
    assert parallel.failures(results) == [failure]
    # the plain callback saw every case finish, and the failure counted
    assert seen[0][0] == 0.0 and seen[-1] == (1.0, '4/4 cases, 1 failed')


def _bag(path: Path, seed: int, effect=None) -> None:
    rec = simulate_recording(seed, 15.0, effects=[parse_effect(effect)] if effect else [])
    path.parent.mkdir(parents=True, exist_ok=True)
    write_pose_bag(path, rec.streams)


def test_batch_over_a_folder_with_a_broken_bag(tmp_path, capsys):
    folder = tmp_path / 'recordings'
    _bag(folder / 'day1', 1)
    _bag(folder / 'more' / 'day2', 2, 'outliers=0.03')
    broken = folder / 'broken'
    broken.mkdir(parents=True)
    (broken / 'metadata.yaml').write_text('rosbag2_bagfile_information: [not closed\n')
    out = tmp_path / 'out'

    code = main(['batch', 'calibrate', str(folder), '--out', str(out), '--workers', '2',
                 '--quiet'])
    captured = capsys.readouterr()
    assert code == 1  # one bag failed; the other two ran
    lines = captured.out.splitlines()
    assert lines[1].split()[:3] == ['bag', 'pairs', 'chi2/dof']
    rows = {line.split()[0]: line for line in lines[2:]}
    assert set(rows) == {'broken', 'day1', 'more/day2'}
    assert 'consistent' in rows['day1'] and 'BagError' in rows['broken']
    summary = json.loads((out / 'summary.json').read_text())
    by_bag = {r['bag']: r for r in summary['bags']}
    assert by_bag['broken']['error'].startswith('BagError:')
    assert by_bag['day1']['error'] is None and by_bag['day1']['pairs'] > 500
    # each bag's JSON is what `coreg calibrate --json` writes for it
    single = tmp_path / 'single.json'
    assert main(['calibrate', str(folder / 'more' / 'day2'), '--json', str(single)]) == 0
    capsys.readouterr()
    assert json.loads((out / 'more__day2.json').read_text()) == json.loads(single.read_text())
    assert 'error' in json.loads((out / 'broken.json').read_text())

    code = main(['batch', 'diagnose', str(folder), '--out', str(tmp_path / 'diag'),
                 '--workers', '1', '--quiet'])
    assert code == 1
    rows = {line.split()[0]: line for line in capsys.readouterr().out.splitlines()[2:]}
    assert 'outliers' in rows['more/day2'] and 'BagError' in rows['broken']
    report = json.loads((tmp_path / 'diag' / 'more__day2.json').read_text())
    assert report['effects'][0]['name'] == 'outliers'


def test_validate_on_a_dask_local_cluster_matches_local():
    distributed = pytest.importorskip('distributed')
    local = validate(3, seed=5, duration=SHORT, workers=1)
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                  dashboard_address=None) as cluster:
        remote = validate(3, seed=5, duration=SHORT, scheduler=cluster.scheduler_address)
        failing = run_cases(unlucky_square, [{'seed': 13}, {'seed': 4}],
                            scheduler=cluster.scheduler_address)
    assert _without_timing(remote['results']) == _without_timing(local['results'])
    assert isinstance(failing[0], CaseFailure) and failing[0].seed == 13
    assert failing[1] == 16


def test_unusable_scheduler_is_one_line(monkeypatch, capsys):
    monkeypatch.setattr(parallel, 'CONNECT_TIMEOUT_S', 2.0)
    with pytest.raises(SchedulerError) as e:
        run_cases(unlucky_square, [{'seed': 1}], scheduler=NO_SCHEDULER)
    assert NO_SCHEDULER in str(e.value) and '\n' not in str(e.value)
    assert main(['validate-diagnosis', '--cases', '1', '--scheduler', NO_SCHEDULER,
                 '--quiet']) == 1
    err = capsys.readouterr().err
    assert err.startswith('coreg validate-diagnosis: error: cannot reach the Dask scheduler')
    assert err.count('\n') == 1
    # without dask installed: the extra to install, in one line
    monkeypatch.setitem(sys.modules, 'distributed', None)
    with pytest.raises(SchedulerError, match=r"pip install 'coreg_ros\[dask\]'") as e:
        run_cases(unlucky_square, [{'seed': 1}], scheduler=NO_SCHEDULER)
    assert '\n' not in str(e.value)


def test_workers_options():
    parser = build_parser()
    args = parser.parse_args(['validate-diagnosis'])
    assert args.workers == parallel.default_workers() and args.scheduler is None
    assert parser.parse_args(['validate-diagnosis', '--jobs', '3']).workers == 3
    assert parser.parse_args(['validate-diagnosis', '--workers', '2']).workers == 2
    args = parser.parse_args(['batch', 'diagnose', 'f', '--out', 'o', '--scheduler', 'tcp://h:1'])
    assert args.scheduler == 'tcp://h:1' and args.what == 'diagnose'


def test_validate_scores_the_cases_that_ran_and_lists_the_one_that_raised(monkeypatch):
    from coreg_ros.sim import validation

    real = validation.run_case
    drawn = []

    def flaky(case, options=None):
        drawn.append(case['seed'])
        if len(drawn) == 2:  # the second case hits a fault of the harness's making
            raise RuntimeError('injected fault')
        return real(case, options)

    monkeypatch.setattr(validation, 'run_case', flaky)
    out = validation.validate(3, seed=11, workers=1, duration=(15.0, 20.0))
    assert [f['seed'] for f in out['failed']] == [drawn[1]]
    assert 'injected fault' in out['failed'][0]['error']
    assert out['summary']['cases'] == 2  # the failure is not scored
    assert len(out['results']) == 3


def test_an_address_where_something_else_answers_is_one_line_at_once():
    # Issue 25.4: a port that accepts but is no Dask scheduler (a web server, a proxy that
    # accepts any port) gave the one-line error, then a Client.__del__ traceback and a 20 s
    # stall while the half-made client closed itself.
    import socket
    import subprocess
    import threading
    import time

    server = socket.create_server(('127.0.0.1', 0))
    port = server.getsockname()[1]

    def answer_like_a_web_server():
        while True:
            try:
                conn, _ = server.accept()
            except OSError:  # closed: the test is over
                return
            with conn:
                conn.sendall(b'HTTP/1.1 400 Bad Request\r\nContent-Length: 0\r\n\r\n')

    threading.Thread(target=answer_like_a_web_server, daemon=True).start()
    try:
        cases = [('garbage:::', 'is not a Dask address'),
                 ('http://127.0.0.1:8787', 'http:// is not a Dask protocol'),
                 (f'tcp://127.0.0.1:{port}', "does not speak Dask's protocol")]
        for address, said in cases:
            start = time.monotonic()
            proc = subprocess.run([sys.executable, '-m', 'coreg_ros.cli.main',
                                   'validate-diagnosis', '--cases', '1', '--quiet',
                                   '--scheduler', address],
                                  capture_output=True, text=True, timeout=120)
            took = time.monotonic() - start
            assert proc.returncode == 1, proc.stderr
            assert said in proc.stderr and proc.stderr.count('\n') == 1, proc.stderr
            assert 'Traceback' not in proc.stderr
            # the stall was twice the connect timeout after it: far beyond start-up and one try
            assert took < 2 * parallel.CONNECT_TIMEOUT_S, (address, took)
    finally:
        server.close()


def _children(pid: int) -> list:
    path = Path(f'/proc/{pid}/task/{pid}/children')
    return [int(c) for c in path.read_text().split()] if path.exists() else []


def _alive(pid: int) -> bool:
    stat = Path(f'/proc/{pid}/stat')
    return stat.exists() and stat.read_text().split(')')[-1].split()[0] != 'Z'


def test_sigterm_stops_the_local_workers_and_their_resource_tracker(tmp_path):
    # Issue 25.4: SIGTERM to `validate-diagnosis --workers 2` ended the command at once and
    # left both workers and the resource tracker running (orphaned, still computing).
    import signal
    import subprocess
    import time

    err_path = tmp_path / 'stderr'
    children = []
    with open(err_path, 'w') as err:  # a file, not a pipe: orphans would hold a pipe open
        proc = subprocess.Popen([sys.executable, '-m', 'coreg_ros.cli.main',
                                 'validate-diagnosis', '--cases', '8', '--workers', '2',
                                 '--quiet'], stdout=subprocess.DEVNULL, stderr=err)
    try:
        end = time.monotonic() + 60
        while len(_children(proc.pid)) < 3 and time.monotonic() < end:  # 2 workers, tracker
            time.sleep(0.1)
        children = _children(proc.pid)
        assert len(children) == 3, 'the workers never started'
        proc.send_signal(signal.SIGTERM)
        proc.wait(timeout=30)
        end = time.monotonic() + 10
        while any(map(_alive, children)) and time.monotonic() < end:
            time.sleep(0.1)
        left = [c for c in children if _alive(c)]
    finally:
        proc.kill()
        for pid in children:  # never leave them to the next test
            if _alive(pid):
                os.kill(pid, signal.SIGKILL)
    err = err_path.read_text()
    assert not left, f'processes left running after SIGTERM: {left}'
    assert proc.returncode == 143, err
    assert err.strip() == 'coreg validate-diagnosis: SIGTERM: stopped (its workers too)', err

"""
The fuzz of issue 12 (bench/fuzz.py) at a reduced size.

No input may give a traceback, a hang or a result the fuzzer knows is wrong. ``make bench`` runs
it at full size.

The size is chosen to keep this module well under two minutes on a loaded 2-core machine.
"""

from pathlib import Path

from bench import fuzz
import pytest

ROOT = Path(__file__).resolve().parents[1]

#: Inputs per kind, and the seed (fixed: a failure here is reproducible from the table).
N_PER_KIND = 8
SEED = 2024


def _report(results, kind):
    return fuzz.table({**results, 'kinds': {kind: results['kinds'][kind]},
                       'failures': [f for f in results['failures'] if f['kind'] == kind],
                       'disagreement_examples': []})


@pytest.fixture(scope='module')
def results():
    # with_ros: coreg_node is started on the parameter files and signals are sent: every test
    # that uses these results is a ROS test (``make test-fast`` runs none of them)
    return fuzz.run(N_PER_KIND, SEED, with_ros=True, log=lambda line: None)


@pytest.mark.ros
def test_every_kind_was_tried(results):
    for kind in fuzz.KINDS:
        assert results['kinds'][kind]['tried'] == N_PER_KIND


#: Faults the fuzz found that other files must fix (bench/fuzz.py fault_key -> the fault).
#: Faults the fuzz found that are not fixed yet (name: description). The ones it found in its
#: first full run (signals during start-up imports, swapped topics unwarned, use_sim_time of
#: a wrong type, YAML anchors, record's RCLError on a signal, a 1e300 position, a warning
#: before a refusal) are fixed; any fault now fails this test.
KNOWN_FAULTS: dict = {}


def _check(results, kind, verdicts=fuzz.VERDICTS):
    row = results['kinds'][kind]
    failures = [f for f in results['failures'] if f['kind'] == kind]
    unknown = {k: n for k, n in row['faults'].items() if k not in KNOWN_FAULTS}
    counted = sum(row[v] for v in verdicts)
    assert not unknown, _report(results, kind)
    assert counted == sum(row['faults'].values()), _report(results, kind)
    if row['faults']:
        pytest.xfail('known faults: ' + '; '.join(
            f'{KNOWN_FAULTS[k]} ({n} input(s), e.g. index '
            f'{next((f["index"] for f in failures if f["fault"] == k), "?")})'
            for k, n in sorted(row['faults'].items())))


@pytest.mark.ros
@pytest.mark.parametrize('kind', ['params', 'csv', 'bag'])
def test_no_traceback_hang_or_wrong_result(results, kind):
    _check(results, kind)


@pytest.mark.ros
def test_signals_end_cleanly(results):
    _check(results, 'signals')


def test_inputs_are_reproducible_from_seed_and_index(tmp_path):
    a = [fuzz.make_params(fuzz._rng(SEED, 'params', i), _material_stub(), tmp_path)[:2]
         for i in range(20)]
    b = [fuzz.make_params(fuzz._rng(SEED, 'params', i), _material_stub(), tmp_path)[:2]
         for i in range(20)]
    assert a == b
    assert len({desc for _, desc in a}) > 10


def _material_stub():
    return fuzz.Material(root=ROOT, bags={}, truth=None,
                         params_text=(ROOT / 'config' / 'coreg.yaml').read_text(),
                         good_params=ROOT / 'config' / 'coreg.yaml')


def test_the_fuzzer_flags_a_known_wrong_result(tmp_path):
    """A success far from the truth is flagged (the oracle itself is checked)."""
    import json

    from coreg_ros.sim import simulate_recording
    import numpy as np

    truth = simulate_recording(3, 1.0).truth
    cov = list(np.diag([1e-8] * 6).ravel())
    pose = {'position': [float(v) + 0.01 for v in truth.p0],
            'orientation': dict(zip('wxyz', map(float, truth.q0), strict=True)),
            'covariance': cov}
    t1 = {'position': [float(v) for v in truth.p1],
          'orientation': dict(zip('wxyz', map(float, truth.q1), strict=True)),
          'covariance': cov}
    path = tmp_path / 'r.json'
    path.write_text(json.dumps({'model': 'full_pose', 'base_to_base': pose,
                                'tool_to_marker': t1}))
    outcome = fuzz.Outcome('bag', 0, 0, 'oracle check')
    fuzz._check_truth(outcome, path, truth, 'cmd', 'output')
    assert outcome.verdict == 'wrong'
    pose['position'] = [float(v) for v in truth.p0]
    path.write_text(json.dumps({'model': 'full_pose', 'base_to_base': pose,
                                'tool_to_marker': t1}))
    outcome = fuzz.Outcome('bag', 0, 0, 'oracle check')
    fuzz._check_truth(outcome, path, truth, 'cmd', 'output')
    assert outcome.verdict == 'ok'


def test_startup_interrupt_is_told_apart():
    startup = ('Traceback (most recent call last):\n'
               '  File "/x/.venv/bin/coreg", line 6, in <module>\n'
               '  File "/x/coreg_ros/cli/main.py", line 266, in main\n'
               '  File "/x/coreg_ros/cli/main.py", line 258, in build_parser\n'
               '  File "/x/coreg_ros/cli/convert.py", line 27, in <module>\n'
               'KeyboardInterrupt\n')
    later = ('Traceback (most recent call last):\n'
             '  File "/x/.venv/bin/coreg", line 6, in <module>\n'
             '  File "/x/coreg_ros/ros/tools.py", line 200, in play_streams\n'
             "rclpy._rclpy_pybind11.RCLError: publisher's context is invalid\n")
    assert fuzz._startup_interrupt(startup)
    assert not fuzz._startup_interrupt(later)

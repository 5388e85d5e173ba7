"""
The new user's faults of issue 25 (item 4) in the offline commands: each test failed before.

Tried as a new user would: swapped devices, huge plans, output paths that cannot be written,
a position-only B calibrated with the default model, mis-scaled positions, a prior from the
same recording, clock options that contradict each other. The node's faults are in
test/ros/test_node_new_user.py, the Python front door's in test/test_front_door.py.
"""

from pathlib import Path
import subprocess
import sys

from coreg_ros.cli.main import main
from coreg_ros.files.bag.posebag import write_pose_bag
from coreg_ros.sim import simulate_recording
import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[2]
A, B = '/device_a/pose', '/device_b/pose'


def coreg(*args, timeout=120, **kwargs):
    """Run the ``coreg`` command in a subprocess (what a user sees, tracebacks included)."""
    return subprocess.run([sys.executable, '-m', 'coreg_ros.cli.main', *map(str, args)],
                          capture_output=True, text=True, timeout=timeout, cwd=ROOT, **kwargs)


def one_line_error(result) -> bool:
    return (result.returncode == 1 and 'Traceback' not in result.stderr
            and result.stderr.strip().count('\n') == 0 and 'error:' in result.stderr)


@pytest.fixture(scope='module')
def rec():
    return simulate_recording(25, 20.0)


@pytest.fixture(scope='module')
def bag(rec, tmp_path_factory):
    path = tmp_path_factory.mktemp('bags') / 'rec'
    write_pose_bag(path, rec.streams)
    return path


# --- a confident swap of the devices is not a success ------------------------------------------

def test_swapped_devices_exit_3_unless_the_roles_are_confirmed(rec, tmp_path, capsys):
    a, b = rec.stream_a, rec.streams_b[0]
    write_pose_bag(tmp_path / 'swapped', {A: b, B: a})  # each device on the other's topic
    noise = ['--sigma-a', *map(str, rec.truth.sigma_b), '--sigma-b', *map(str, rec.truth.sigma_a)]
    assert main(['calibrate', str(tmp_path / 'swapped'), *noise]) == 3
    out = capsys.readouterr().out
    assert 'REFUSED' in out and 'swapped (exchange topic_a and topic_b)' in out
    assert '--roles-confirmed' in out
    assert main(['calibrate', str(tmp_path / 'swapped'), *noise, '--roles-confirmed']) == 0
    # the same through the node's parameter file
    config = tmp_path / 'coreg.yaml'
    config.write_text('coreg_node:\n  ros__parameters:\n    roles_confirmed: true\n')
    assert main(['calibrate', str(tmp_path / 'swapped'), *noise, '--config', str(config)]) == 0
    capsys.readouterr()


# --- every command guards memory like `coreg simulate` ----------------------------------------

def _capped():
    """Cap the address space of the subprocess at 3 GB: a job that ignores its size fails."""
    import resource
    resource.setrlimit(resource.RLIMIT_AS, (3 * 2**30, 3 * 2**30))


@pytest.mark.parametrize('args', [
    ('plan', '--duration', '1e7', '--sigma-a', '2e-4', '5e-4', '--sigma-b', '5e-4', '2e-3'),
    ('plan', '--duration', '60', '--rate-b', '1e7', '--sigma-a', '2e-4', '5e-4', '--sigma-b',
     '5e-4', '2e-3'),
    ('plan', '--duration', '600', '--extra', '1e6', '--sigma-a', '2e-4', '5e-4', '--sigma-b',
     '5e-4', '2e-3'),
    ('validate-diagnosis', '--cases', '1000000000', '--workers', '1'),
])
def test_a_huge_size_is_refused_before_the_work(args, tmp_path):
    result = coreg(*args, '--json', tmp_path / 'out.json', timeout=60, preexec_fn=_capped)
    assert one_line_error(result), result.stderr[-2000:]
    assert 'memory' in result.stderr and 'lower' in result.stderr
    assert ('--duration' in result.stderr or '--extra' in result.stderr
            or '--cases' in result.stderr)
    assert not (tmp_path / 'out.json').exists()


# --- output paths are checked before the work starts -------------------------------------------

@pytest.fixture
def a_file(tmp_path):
    path = tmp_path / 'a_file'
    path.write_text('an existing file\n')
    return path


@pytest.mark.parametrize('command, option', [
    ('calibrate', '--report'), ('diagnose', '--report'), ('calibrate', '--json'),
    ('diagnose', '--json')])
def test_calibrate_and_diagnose_outputs_are_checked_first(bag, a_file, command, option):
    # a directory where a file is meant, a file where a directory is, a place nobody can write
    target = a_file.parent if option == '--json' else a_file
    for path, words in ((target, 'a directory' if option == '--json' else 'is a file'),
                        (a_file / 'below', 'is a file, not a directory'),
                        ('/proc/coreg_test/out', 'cannot write in /proc')):
        result = coreg(command, bag, option, path)
        assert one_line_error(result), result.stderr[-2000:]
        assert f'{option} {path}' in result.stderr and words in result.stderr, result.stderr
        assert result.stdout == ''  # nothing was calibrated first
    assert a_file.read_text() == 'an existing file\n'


def test_batch_out_and_new_bags_are_checked_first(bag, a_file, tmp_path):
    result = coreg('batch', 'calibrate', bag.parent, '--out', a_file, '--workers', 1)
    assert one_line_error(result) and '--out' in result.stderr and 'is a file' in result.stderr
    result = coreg('plan', '--duration', 10, '--sigma-a', 2e-4, 5e-4, '--sigma-b', 5e-4, 2e-3,
                   '--json', tmp_path)
    assert one_line_error(result) and 'is a directory' in result.stderr
    for args in (('simulate', bag, '--seed', 1, '--duration', 1),
                 ('convert', a_file, a_file, bag), ('fix-bag', bag, bag)):
        result = coreg(*args)
        assert one_line_error(result), result.stderr
        assert 'exists already' in result.stderr and result.stdout == ''


# --- a position-only B and mis-scaled positions get the fix that exists -------------------------

def _csvs(tmp_path, rec, scale_a=1.0, scale_b=1.0, b_orientation=True):
    from strategies import write_csv
    a = write_csv(tmp_path / 'a.csv', rec.stream_a, scale=scale_a)
    b = rec.streams_b[0]
    if b_orientation:
        return a, write_csv(tmp_path / 'b.csv', b, scale=scale_b)
    path = tmp_path / 'b.csv'  # t, x, y, z: a position-only tracker's export
    path.write_text(''.join(f'{int(t) / 1e9:.9f}, {float(x) * scale_b!r}, '
                            f'{float(y) * scale_b!r}, {float(z) * scale_b!r}\n'
                            for t, (x, y, z) in zip(b.stamps, b.position, strict=True)))
    return a, str(path)


def test_a_position_only_b_with_the_default_model_names_the_model(tmp_path, capsys):
    rec = simulate_recording(31, 20.0, 'position_only')
    a, b = _csvs(tmp_path, rec, b_orientation=False)
    assert main(['convert', a, b, str(tmp_path / 'bag')]) == 0
    assert 'position only' in capsys.readouterr().out
    code = main(['calibrate', str(tmp_path / 'bag')])
    out = capsys.readouterr().out
    assert code == 3 and '--model position_only' in out, out
    assert main(['calibrate', str(tmp_path / 'bag'), '--model', 'position_only']) == 0
    capsys.readouterr()


def test_unit_advice_blames_the_mis_scaled_device_with_an_option_that_exists(tmp_path, rec,
                                                                             capsys):
    # A exported in metres but converted as mm: A is 1000x too small, B is right
    a, b = _csvs(tmp_path, rec)
    assert main(['convert', a, b, str(tmp_path / 'small_a'), '--units-a', 'mm']) == 0
    err = capsys.readouterr().err
    assert '--units-a m' in err and '--units-b' not in err, err
    assert main(['calibrate', str(tmp_path / 'small_a')]) != 0
    out = capsys.readouterr()
    text = out.out + out.err
    assert '--units-a m' in text and '--units-b' not in text, text
    # B exported in cm: the advice names --units-b cm, which convert accepts and which fixes it
    a, b = _csvs(tmp_path, rec, scale_b=100.0)
    assert main(['convert', a, b, str(tmp_path / 'cm_b')]) == 0
    capsys.readouterr()
    assert main(['calibrate', str(tmp_path / 'cm_b')]) != 0
    out = capsys.readouterr()
    assert '--units-b cm' in out.out + out.err
    assert main(['convert', a, b, str(tmp_path / 'fixed'), '--units-b', 'cm']) == 0
    assert main(['calibrate', str(tmp_path / 'fixed')]) == 0
    capsys.readouterr()


# --- the clock: options that contradict each other, and verdicts that name the fix -----------

def test_a_drift_with_a_fixed_offset_is_refused(bag):
    result = coreg('calibrate', bag, '--time-offset', '0.01', '--clock-drift', 'auto')
    assert one_line_error(result), result.stderr
    assert '--clock-drift' in result.stderr and '--time-offset auto' in result.stderr


def _simulated(tmp_path, name, effects=(), changes=()):
    from coreg_ros.sim import parse_effect
    from coreg_ros.sim.changes import apply_changes, parse_change
    rec = simulate_recording(41, 40.0, effects=[parse_effect(e) for e in effects])
    rec = apply_changes(rec, [parse_change(c) for c in changes], seed=41)
    write_pose_bag(tmp_path / name, rec.streams)
    return tmp_path / name


@pytest.mark.parametrize('name, effects, changes, args, fix', [
    ('offset', ['time_offset=0.02'], [], ['--time-offset', '0'], '--time-offset auto'),
    ('drift', ['clock_drift=300'], [], [], '--clock-drift auto'),
    ('step', [], ['clock_step=0.05@20'], [], '--split-at-jump'),
])
def test_clock_problems_get_a_verdict_naming_the_fix(tmp_path, capsys, name, effects, changes,
                                                     args, fix):
    bag = _simulated(tmp_path, name, effects, changes)
    assert main(['calibrate', str(bag), *args]) == 3
    out = capsys.readouterr().out
    verdict = next(line for line in out.splitlines() if line.startswith('verdict:'))
    assert fix in verdict, verdict
    if name != 'step':
        return
    # the advice works: the split parts each calibrate
    import re
    threshold = re.search(r'--split-at-jump ([0-9.e-]+)', verdict).group(1)
    assert main(['fix-bag', str(bag), str(tmp_path / 'parts'), '--split-at-jump',
                 threshold]) == 0
    parts = sorted(tmp_path.glob('parts_*'))
    assert len(parts) == 2
    assert [main(['calibrate', str(p)]) for p in parts] == [0, 0]
    capsys.readouterr()


# --- a prior from the same recording is refused, not counted twice -----------------------------

def test_a_prior_from_the_same_samples_is_refused(rec, bag, tmp_path, capsys):
    first = tmp_path / 'first.json'
    assert main(['calibrate', str(bag), '--json', str(first)]) == 0
    capsys.readouterr()
    assert main(['calibrate', str(bag), '--prior', str(first)]) == 1
    err = capsys.readouterr().err
    assert 'same samples' in err and 'count them twice' in err and '--prior' in err, err
    # a part of the recording is the same data too
    half = {t: s.take(np.arange(len(s)) < len(s) // 2) for t, s in rec.streams.items()}
    write_pose_bag(tmp_path / 'half', half)
    assert main(['calibrate', str(tmp_path / 'half'), '--prior', str(first)]) == 1
    assert 'same samples (about 100% of this' in capsys.readouterr().err
    # a prior from another recording of the same rig is taken
    other = simulate_recording(25, 20.0, start_ns=rec.start_ns + 100 * 10**9)
    write_pose_bag(tmp_path / 'other', other.streams)
    assert main(['calibrate', str(tmp_path / 'other'), '--prior', str(first)]) == 0
    assert 'prior: chi2' in capsys.readouterr().out


def _options_without_help(parser, path):
    import argparse

    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                yield from _options_without_help(sub, f'{path} {name}')
        elif action.help is None and not isinstance(action, argparse._HelpAction):
            yield f'{path} {"/".join(action.option_strings) or action.dest}'


def test_every_option_of_every_command_says_what_it_is():
    # `coreg simulate --help` had five options without a word (and convert, fix-bag, plan,
    # record and call one each)
    from coreg_ros.cli.main import build_parser

    assert list(_options_without_help(build_parser(), 'coreg')) == []


@pytest.mark.parametrize('command', [['calibrate'], ['diagnose'], ['batch', 'calibrate'],
                                     ['batch', 'diagnose'], ['validate-diagnosis']])
def test_help_says_what_the_exit_codes_mean(command, capsys):
    # the exit codes of diagnose and batch were documented nowhere
    with pytest.raises(SystemExit):
        main([*command, '--help'])
    text = ' '.join(capsys.readouterr().out.split())
    assert 'exit codes: 0 ' in text and '1 ' in text and '130 Ctrl-C' in text
    if command[0] in ('calibrate', 'batch'):
        assert '3 ' in text

"""
``coreg export``: round trips of every format, held directions kept, bad input in one line.

The results are real: ``coreg calibrate --json`` of simulated recordings (a free rig, a SCARA
arm whose motion leaves a direction held, a position-only B) and the node's stored YAML
written by the node's own writer. Numbers must come back to 1e-12: through ``--prior`` (the
YAML and JSON exports), through the shell line, the launch file (parsed with ast) and the URDF
(rpy back to a rotation by scipy).
"""

import ast
import json
from pathlib import Path
import shlex
import subprocess
import sys
import xml.etree.ElementTree as ET

from coreg_ros.cli.main import main
from coreg_ros.core.so3 import invert_poses
from coreg_ros.files.bag.posebag import write_pose_bag
from coreg_ros.files.export import load_export
from coreg_ros.files.results import load_prior
from coreg_ros.files.tf_snippets import launch, static_tf, urdf
from coreg_ros.ros.persistence import save_result
from coreg_ros.sim import simulate_recording
import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from strategies import random_quat
import yaml

ROOT = Path(__file__).resolve().parents[2]
TOL = 1e-12
FRAMES = {'base_a': 'robot_base', 'base_b': 'camera_base', 'tool': 'flange',
          'marker': 'target'}


def coreg_here(*args) -> int:
    """Run ``coreg`` in this process; argparse's refusals (SystemExit) give their code."""
    try:
        return main([str(a) for a in args])
    except SystemExit as e:
        return int(e.code)


def one_line_error(capsys, code: int) -> str:
    err = capsys.readouterr().err
    assert code == 1 and 'Traceback' not in err and err.strip().count('\n') == 0, err
    return err


@pytest.fixture(scope='module')
def results(tmp_path_factory):
    """``coreg calibrate --json`` results of three rigs, and the node's YAML of the first."""
    folder = tmp_path_factory.mktemp('results')
    out = {}
    for name, seed, model, motion in (('free', 4, 'full_pose', 'diverse'),
                                      ('scara', 3, 'full_pose', 'scara'),
                                      ('position_only', 5, 'position_only', 'diverse')):
        rec = simulate_recording(seed, 12.0, model, motion=motion)
        bag = folder / name
        write_pose_bag(bag, rec.streams)
        out[name] = folder / f'{name}.json'
        assert main(['calibrate', str(bag), '--model', model, '--json', str(out[name])]) == 0
    doc = json.loads(out['free'].read_text())
    node = save_result(folder / 'store', doc, FRAMES, doc['settings'],
                       name='result_coreg_node_0123456789.yaml',
                       extra={'node': '/coreg_node', 'stamp_ns': 1_700_000_000_000_000_000})
    out['node'] = node
    return out


def _prior_numbers(path) -> dict:
    prior = load_prior(path)
    out = {}
    for key in ('base_to_base', 'tool_to_marker'):
        pose = getattr(prior, key)
        out[key] = np.concatenate([pose.position, pose.quat_wxyz, pose.covariance.ravel()])
    out['joint'] = prior.joint_cov
    return out


def _assert_same_prior(a, b) -> None:
    for key in ('base_to_base', 'tool_to_marker'):
        np.testing.assert_allclose(a[key], b[key], rtol=0, atol=TOL)  # inf stays inf
    np.testing.assert_allclose(a['joint'], b['joint'], rtol=0, atol=TOL)


@pytest.mark.parametrize('name', ['free', 'scara', 'position_only', 'node'])
@pytest.mark.parametrize('fmt', ['yaml', 'json'])
def test_export_then_prior_gives_the_same_numbers(results, tmp_path, name, fmt, capsys):
    out = tmp_path / f'cal.{fmt}'
    assert coreg_here('export', results[name], '--format', fmt, '--out', out) == 0
    _assert_same_prior(_prior_numbers(out), _prior_numbers(results[name]))
    doc = yaml.safe_load(out.read_text())
    original = load_export(results[name])
    # what the YAML keeps besides the numbers: verdict, clock offset, date, configuration
    for key in ('fit', 'time_offset', 'date', 'settings', 'frames', 'unobservable'):
        assert doc[key] == original[key]
    assert doc['fit']['success'] is True and 'verdict' in doc['fit']
    assert doc['settings']['model'] == doc['fit']['model']
    assert doc['time_offset']['estimated'] is True
    if name == 'node':  # the node's frames and the date it stored
        assert doc['frames'] == FRAMES
        assert doc['date'] == yaml.safe_load(results['node'].read_text())['saved_at']
    if name == 'scara':  # a restricted rig: the held direction and the determined part
        assert any(u['by'] == 'held' for u in doc['unobservable'])
        assert len(doc['cov_determined']) == 144
    # an export is a result for export too: the same document again
    again = load_export(out)
    assert {k: v for k, v in again.items() if k != 'source'} == \
        {k: v for k, v in doc.items() if k != 'source'}


def test_exported_prior_is_read_by_calibrate(results, tmp_path, capsys):
    rec = simulate_recording(4, 12.0)  # the recording of results['free']
    write_pose_bag(tmp_path / 'bag', rec.streams)
    assert coreg_here('export', results['free'], '--format', 'yaml', '--out',
                      tmp_path / 'cal.yaml') == 0
    code = coreg_here('calibrate', tmp_path / 'bag', '--prior', tmp_path / 'cal.yaml',
                      '--json', tmp_path / 'again.json')
    assert code in (0, 3), capsys.readouterr().err
    assert 'prior_check' in json.loads((tmp_path / 'again.json').read_text())


def _poses(doc, base_parent='b'):
    """Return the doc's T0 and T1 as (parent, child, position, quat_wxyz), tf2's direction."""
    out = []
    for key, parent, child in (('base_to_base', 'base_b', 'base_a'),
                               ('tool_to_marker', 'tool', 'marker')):
        o = doc[key]['orientation']
        p, q = np.array(doc[key]['position']), np.array([o[k] for k in 'wxyz'])
        frames = (doc['frames'][parent], doc['frames'][child])
        if key == 'base_to_base' and base_parent == 'a':
            frames = frames[::-1]
            # independent of tf_snippets: the inverse by rotation matrices
            R = Rotation.from_quat(np.r_[q[1:], q[0]]).as_matrix()
            p, q = -R.T @ p, np.r_[q[0], -q[1:]]
        out.append((*frames, p, q))
    return out


def _same_rotation(q, q_ref) -> bool:
    return min(np.abs(q - q_ref).max(), np.abs(q + q_ref).max()) < TOL


def _random_doc(rng, results) -> dict:
    doc = load_export(results['free'], FRAMES)
    for key in ('base_to_base', 'tool_to_marker'):
        doc[key]['position'] = [float(v) for v in rng.uniform(-3, 3, 3)]
        doc[key]['orientation'] = dict(zip('wxyz', (float(v) for v in random_quat(rng)),
                                           strict=True))
    return doc


@pytest.mark.parametrize('seed', range(6))
@pytest.mark.parametrize('base_parent', ['b', 'a'])
def test_text_formats_give_back_the_numbers(results, seed, base_parent):
    rng = np.random.default_rng(seed)
    doc = _random_doc(rng, results)
    want = _poses(doc, base_parent)

    # static-tf: the shell words after each flag
    lines = [line for line in static_tf(doc, base_parent).splitlines()
             if not line.startswith('#')]
    assert len(lines) == 2
    for line, (parent, child, p, q) in zip(lines, want, strict=True):
        words = shlex.split(line)
        assert words[:4] == ['ros2', 'run', 'tf2_ros', 'static_transform_publisher']
        args = dict(zip(words[4::2], words[5::2], strict=True))
        assert (args['--frame-id'], args['--child-frame-id']) == (parent, child)
        got_p = np.array([float(args[k]) for k in ('--x', '--y', '--z')])
        got_q = np.array([float(args[k]) for k in ('--qw', '--qx', '--qy', '--qz')])
        assert np.abs(got_p - p).max() < TOL and _same_rotation(got_q, q)

    # launch: a Python module whose Node(...) arguments are the same words
    tree = ast.parse(launch(doc, base_parent))
    calls = [n for n in ast.walk(tree) if isinstance(n, ast.Call)
             and getattr(n.func, 'id', '') == 'Node']
    assert len(calls) == 2
    for call, (parent, child, p, q) in zip(calls, want, strict=True):
        kw = {k.arg: ast.literal_eval(k.value) for k in call.keywords}
        assert (kw['package'], kw['executable']) == ('tf2_ros', 'static_transform_publisher')
        args = dict(zip(kw['arguments'][::2], kw['arguments'][1::2], strict=True))
        assert (args['--frame-id'], args['--child-frame-id']) == (parent, child)
        assert np.abs(np.array([float(args[k]) for k in ('--x', '--y', '--z')]) - p).max() < TOL
        got_q = np.array([float(args[k]) for k in ('--qw', '--qx', '--qy', '--qz')])
        assert _same_rotation(got_q, q)
    assert len({kw.value.value for c in calls for kw in c.keywords if kw.arg == 'name'}) == 2

    # urdf: fixed joints whose origin rpy turn back into the rotation
    robot = ET.fromstring(f'<robot name="r">{urdf(doc, base_parent)}</robot>')
    joints = robot.findall('joint')
    assert [j.get('type') for j in joints] == ['fixed', 'fixed']
    # the links device B adds (A's description has its base and tool)
    assert {link.get('name') for link in robot.findall('link')} == {'camera_base', 'target'}
    for joint, (parent, child, p, q) in zip(joints, want, strict=True):
        assert joint.find('parent').get('link') == parent
        assert joint.find('child').get('link') == child
        origin = joint.find('origin')
        xyz = np.array(origin.get('xyz').split(), dtype=float)
        x, y, z, w = Rotation.from_euler('xyz', np.array(origin.get('rpy').split(),
                                                         dtype=float)).as_quat()
        assert np.abs(xyz - p).max() < TOL and _same_rotation(np.array([w, x, y, z]), q)


def test_inverse_base_composes_to_identity(results):
    doc = _random_doc(np.random.default_rng(9), results)
    (_, _, p, q), _ = _poses(doc)
    (_, _, pi, qi), _ = _poses(yaml.safe_load(json.dumps(doc)), 'a')
    p2, q2 = invert_poses(pi, qi)
    assert np.abs(p2 - p).max() < TOL and _same_rotation(q2, q)


def test_held_directions_and_unestimated_rotation_are_comments(results):
    scara, po = load_export(results['scara']), load_export(results['position_only'])
    for render in (static_tf, launch, urdf):
        assert 'held, not measured' in render(scara)
        assert 'held' not in render(load_export(results['free']))
        assert "T1's rotation is not estimated by model position_only" in render(po)
    ast.parse(launch(scara))  # comments stay comments
    ET.fromstring(f'<robot name="r">{urdf(scara)}</robot>')


def test_bad_input_is_one_line(results, tmp_path, capsys):
    # missing file, a folder, not a result (a partial prior, text, a bag's metadata)
    assert 'cannot read' in one_line_error(capsys, coreg_here('export', tmp_path / 'none.json'))
    assert 'is a directory' in one_line_error(capsys, coreg_here('export', tmp_path))
    partial = tmp_path / 'partial.yaml'
    partial.write_text(yaml.safe_dump({'tool_to_marker': {'position': [0, 0, 0.1],
                                                          'sigma': [1e-3] * 3 + [None] * 3}}))
    assert 'partial prior' in one_line_error(capsys, coreg_here('export', partial))
    text = tmp_path / 'notes.txt'
    text.write_text('calibration went fine\n')
    assert 'not a calibration result' in one_line_error(capsys, coreg_here('export', text))
    binary = tmp_path / 'metadata.db3'
    binary.write_bytes(bytes(range(256)) * 4)
    assert 'neither JSON nor YAML' in one_line_error(capsys, coreg_here('export', binary))
    # an edited result: a quaternion that is no rotation
    doc = json.loads(results['free'].read_text())
    doc['base_to_base']['orientation']['w'] += 0.5
    edited = tmp_path / 'edited.json'
    edited.write_text(json.dumps(doc))
    assert 'no unit quaternion' in one_line_error(capsys, coreg_here('export', edited))
    # unknown format, output path that cannot be written, frame ids tf2 refuses
    one_line_error(capsys, coreg_here('export', results['free'], '--format', 'sdf'))
    blocker = tmp_path / 'file'
    blocker.write_text('x')
    err = one_line_error(capsys, coreg_here('export', results['free'], '--out',
                                            blocker / 'cal.sh'))
    assert 'cannot write' in err
    assert 'cannot write' in one_line_error(capsys, coreg_here('export', results['free'],
                                                               '--out', tmp_path))
    err = one_line_error(capsys, coreg_here('export', results['free'], '--frame-tool', '/x'))
    assert '--frame-tool' in err
    err = one_line_error(capsys, coreg_here('export', results['free'], '--frame-marker',
                                            'device_a_tool'))
    assert 'T1 would be a transform' in err


def test_a_failed_calibration_needs_force(results, tmp_path, capsys):
    doc = json.loads(results['free'].read_text())
    doc.update(success=False, fit_consistent=False, verdict='chi2/dof 9.1: the data contradict '
               'the stated noise')
    failed = tmp_path / 'failed.json'
    failed.write_text(json.dumps(doc))
    err = one_line_error(capsys, coreg_here('export', failed))
    assert 'no successful calibration' in err and '--force' in err
    assert coreg_here('export', failed, '--force') == 0
    out = capsys.readouterr().out
    assert 'NOT A SUCCESS: chi2/dof 9.1' in out and 'static_transform_publisher' in out


def test_the_command_as_a_user_runs_it(results):
    """What a person sees: the lines on stdout, nothing on stderr, exit 0."""
    run = subprocess.run([sys.executable, '-m', 'coreg_ros.cli.main', 'export',
                          str(results['node'])], capture_output=True, text=True, cwd=ROOT,
                         timeout=60)
    assert run.returncode == 0 and run.stderr == '', run.stderr
    assert run.stdout.count('ros2 run tf2_ros static_transform_publisher') == 2
    assert '--frame-id camera_base --child-frame-id robot_base' in run.stdout

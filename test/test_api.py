"""The front door ``import coreg_ros as cr``: the README's snippet, models from shapes, stamps."""

from pathlib import Path
import re

import coreg_ros as cr
from coreg_ros.core import quaternion as quat
from coreg_ros.sim import simulate_pairs
import numpy as np
import pytest

README = Path(__file__).resolve().parents[1] / 'README.md'
SIGMA_A, SIGMA_B = (2e-4, 5e-4), (5e-4, 2e-3)


def _python_section() -> str:
    text = README.read_text()
    section = text[text.index('\n## Python\n'):]
    section = section[:section.index('\n## ', 1)]
    return re.search(r'```python\n(.*?)```', section, re.S).group(1)


def test_readme_snippet_runs_and_prints_what_it_says(capsys):
    exec(compile(_python_section(), 'README.md', 'exec'), {})
    out = capsys.readouterr().out
    assert out.startswith('model full_pose, method TLS: success')
    assert 'True 1 converged' in out


def test_every_public_name_resolves():
    for name in cr.__all__:
        assert getattr(cr, name) is not None, name
    with pytest.raises(AttributeError):
        cr.no_such_name  # noqa: B018


def _pairs(model, seed=3, n=1500):
    pairs, _, truth = simulate_pairs(np.random.default_rng(seed), n, model, sigma_a=SIGMA_A,
                                     sigma_b=SIGMA_B)
    return pairs, truth


@pytest.mark.parametrize('model', ['full_pose', 'position_only', 'three_marker'])
def test_model_follows_from_the_shapes_and_matches_the_truth(model):
    pairs, truth = _pairs(model)
    res = cr.calibrate(pairs.pos_a, pairs.quat_a, pairs.pos_b, pairs.quat_b,
                       sigma_a=SIGMA_A, sigma_b=SIGMA_B)
    assert res.model == model and res.success
    cov = res.base_to_base.covariance[:3, :3]
    err = res.base_to_base.position - truth.p0
    assert float(err @ np.linalg.solve(cov, err)) < 16.3  # χ²₃ at 0.1 %
    assert res.reduced_chi2 == pytest.approx(res.chi2 / res.dof)
    assert res.summary().startswith(f'model {model}, method TLS: success')


def test_stamps_pair_by_time_and_estimate_the_offset():
    pairs, truth = _pairs('full_pose', seed=5, n=4000)
    stamps = np.asarray(pairs.stamps, dtype=np.int64)
    shift = 12_000_000  # B's clock 12 ms ahead of A's
    # A at 2× the rate of B: every B sample has A samples around it
    ta = np.sort(np.concatenate([stamps, stamps[:-1] + np.diff(stamps) // 2]))
    pa = np.stack([np.interp(ta, stamps, pairs.pos_a[:, k]) for k in range(3)], 1)
    idx = np.clip(np.searchsorted(stamps, ta), 1, len(stamps) - 1)
    frac = (ta - stamps[idx - 1]) / (stamps[idx] - stamps[idx - 1])
    qa = quat.slerp(pairs.quat_a[idx - 1], pairs.quat_a[idx], frac)
    res = cr.calibrate(pa, qa, pairs.pos_b, pairs.quat_b, stamps_a=ta, stamps_b=stamps + shift,
                       sigma_a=SIGMA_A, sigma_b=SIGMA_B)
    assert res.time_offset.estimated
    assert abs(res.time_offset.value_s - 0.012) < 4 * res.time_offset.sigma_s + 1e-4


@pytest.mark.parametrize('kwargs, words', [
    ({'pos_b': np.zeros((10, 4))}, 'pos_b must have shape'),
    ({'pos_b': np.zeros((9, 3))}, 'as many samples'),
    ({'stamps_a': np.arange(10)}, 'both stamps_a and stamps_b'),
    ({'stamps_a': np.arange(10.0), 'stamps_b': np.arange(10.0)}, 'integer nanoseconds'),
])
def test_bad_arrays_get_one_line_errors_that_name_the_fix(kwargs, words):
    args = {'pos_a': np.zeros((10, 3)), 'quat_a_wxyz': np.tile([1.0, 0, 0, 0], (10, 1)),
            'pos_b': np.zeros((10, 3)), 'quat_b_wxyz': None}
    args.update(kwargs)
    with pytest.raises(cr.InputError, match=words) as e:
        cr.calibrate(**args)
    assert '\n' not in str(e.value)


def test_a_rig_of_arrays_and_one_device_is_the_pair():
    from coreg_ros.sim.rig import SimDevice, simulate_rig
    devices = (SimDevice('cam', 'full_pose', 40.0, (5e-4, 2e-3), 300.0),
               SimDevice('pen', 'position_only', 40.0, (5e-4, 2e-3), -0.02))
    rig = simulate_rig(4, 20.0, devices)
    a = rig.stream_a

    def device(k, name):
        s = rig.streams[k][0]
        return cr.Device(name, s.position, s.quat_wxyz if k == 0 else None, stamps=s.stamps,
                         sigma=devices[k].sigma)

    both = cr.calibrate(a.position, a.quat_wxyz, devices=[device(0, 'cam'), device(1, 'pen')],
                        stamps_a=a.stamps)
    assert isinstance(both, cr.RigResult) and both.success
    assert [d.result.model for d in both.devices] == ['full_pose', 'position_only']
    assert abs(both.devices[0].result.time_offset.value_s - 300.0) < 1e-3
    pose = cr.relative_base(both, 0, 1)  # the camera's base in the pen's
    truth = rig.truths
    expected = truth[1].p0 - quat.to_matrix(quat.multiply(truth[1].q0, quat.conjugate(
        truth[0].q0))) @ truth[0].p0
    assert np.all(np.abs(pose.position - expected) < 4 * np.sqrt(np.diag(pose.covariance)[:3]))
    one = cr.calibrate(a.position, a.quat_wxyz, devices=[device(0, 'cam')], stamps_a=a.stamps)
    s = rig.streams[0][0]
    pair = cr.calibrate(a.position, a.quat_wxyz, s.position, s.quat_wxyz, stamps_a=a.stamps,
                        stamps_b=s.stamps, sigma_b=devices[0].sigma)
    assert np.array_equal(one.devices[0].result.params, pair.params)
    assert np.array_equal(one.devices[0].result.cov_joint, pair.cov_joint)
    with pytest.raises(cr.InputError, match='not both'):
        cr.calibrate(a.position, a.quat_wxyz, s.position, devices=[device(0, 'cam')])

"""
Tests of coreg_ros.report.calibration_report.

The page and figures are written and say what the uncertainty module computes; point errors
follow Hoff's ΔP = d Δθ.
"""

from pathlib import Path
import re

import numpy as np
import pytest

pytest.importorskip('matplotlib')

from coreg_ros.core import uncertainty as unc  # noqa: E402, I100 (after the importorskip)
from coreg_ros.core.calibration.calibrate import calibrate  # noqa: E402
from coreg_ros.core.settings import Settings  # noqa: E402
from coreg_ros.report.calibration_report import (  # noqa: E402
    point_errors,
    write_calibration_report,
)
from coreg_ros.sim import simulate_pairs  # noqa: E402

PNG_MAGIC = b'\x89PNG\r\n\x1a\n'


def result_for(model, method='tls', n=400, seed=11):
    pairs, _, _ = simulate_pairs(np.random.default_rng(seed), n, model)
    return calibrate(pairs, Settings(model=model, method=method))


@pytest.fixture(scope='module')
def full_pose():
    return result_for('full_pose')


def test_report_full_pose_with_points(full_pose, tmp_path):
    points = [[0.0, 0.0, 0.4], [0.3, -0.2, 0.5]]
    path = write_calibration_report(full_pose, tmp_path / 'rep', points=points)
    assert path == tmp_path / 'rep' / 'index.html'
    page = path.read_text(encoding='utf-8')
    for name in ('pose_uncertainty.png', 'residuals.png'):
        assert (tmp_path / 'rep' / name).read_bytes()[:8] == PNG_MAGIC
    assert page.count('data:image/png;base64,') == 2
    assert 'axis cone' in page and 'ellipsoid semi-axes' in page
    # the table carries the ellipsoid of T0 as computed by the core
    ell = unc.ellipsoid_axes(full_pose.base_to_base.covariance[0:3, 0:3], 3.0)
    assert f'{ell.semi_axes[0] * 1e3:.3f}' in page
    # one table row per point
    assert len(re.findall(r'<tr><td>\[0\.', page)) == 2
    assert not (tmp_path / 'rep' / '.index.html.tmp').exists()


def test_point_errors_grow_with_distance_as_hoff_says(full_pose):
    near, far = point_errors(full_pose, [[0, 0, 0], [2.0, 0, 0]])
    assert far['rms'] > near['rms']
    y, cov = unc.propagate_point(full_pose.base_to_base, [2.0, 0, 0])
    np.testing.assert_allclose(far['mapped'], y)
    assert far['rms'] == pytest.approx(np.sqrt(np.trace(cov)))
    # tool-frame points are located in B's marker frame by T1⁻¹
    tip = point_errors(full_pose, [[0, 0, 0.15]], frame='a_tool')[0]
    inv = unc.invert(full_pose.tool_to_marker)
    np.testing.assert_allclose(tip['mapped'], unc.propagate_point(inv, [0, 0, 0.15])[0])
    with pytest.raises(ValueError):
        point_errors(full_pose, [[0, 0, 0]], frame='b_base')


def test_report_position_only_ols_has_no_cones_for_t1(tmp_path):
    result = result_for('position_only', method='ols')
    path = write_calibration_report(result, tmp_path, points=[[0.1, 0.1, 0.1]],
                                    points_frame='a_tool', title='po')
    page = Path(path).read_text(encoding='utf-8')
    assert 'not estimated by this model' in page
    # a tool point's location in B's marker frame needs T1's orientation: not determined
    assert 'not determined by this model' in page
    assert '<title>po</title>' in page


SAMPLE_BAG = Path(__file__).resolve().parents[2] / 'bags' / 'sample_full_pose'


@pytest.mark.skipif(not SAMPLE_BAG.exists(), reason='sample bag not shipped')
def test_cli_calibrate_report(tmp_path, capsys):
    from coreg_ros.cli.main import main

    out = tmp_path / 'report'
    assert main(['calibrate', str(SAMPLE_BAG), '--report', str(out), '--points', '0', '0',
                 '0.4', '0.3', '-0.2', '0.5']) == 0
    assert f'report written to {out / "index.html"}' in capsys.readouterr().out
    page = (out / 'index.html').read_text(encoding='utf-8')
    assert "A's base frame, mapped into B's base frame by T0" in page
    assert main(['calibrate', str(SAMPLE_BAG), '--report', str(out), '--points', '1', '2']) == 1
    assert 'X Y Z triples' in capsys.readouterr().err
    assert main(['calibrate', str(SAMPLE_BAG), '--points', '1', '2', '3']) == 1
    assert '--report DIR' in capsys.readouterr().err

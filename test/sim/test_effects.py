"""Tests of the unmodelled effects of coreg_ros.sim.injected and their CLI."""

import json

from coreg_ros.cli.main import main
from coreg_ros.core import quaternion as quat
from coreg_ros.core.errors import ConfigError
from coreg_ros.core.rigid import rigid_part
from coreg_ros.sim import simulate_recording
from coreg_ros.sim.injected import (
    ALL_EFFECT_NAMES as EFFECT_NAMES,
)
from coreg_ros.sim.injected import (
    Backlash,
    EFFECT_UNITS,
    FieldDistortion,
    LinkFlex,
    make_effect,
    NonStationary,
    parse_effect,
    play_operator,
    Scale,
    SharedClock,
    TimeOffset,
    TimestampJitter,
)
import numpy as np
import pytest

SEED = 11
DURATION = 60.0
A = '/device_a/pose'
B = '/device_b/pose'
EXAMPLES = {
    'time_offset': '0.02', 'clock_drift': '300', 'timestamp_jitter': '0.01',
    'field_distortion': '5', 'distance_noise': '4', 'scale': '0.01', 'link_flex': '2',
    'outliers': '0.02', 'backlash': '0.5', 'noise_scale': '2', 'non_stationary': '3',
    'shared_clock': '0.02', 'outlier_bursts': '0.05', 'clock_step': '0.03',
    'anisotropic_noise': '3', 't0_step': '2', 't1_step': '1', 'noise_step': '2',
}


@pytest.fixture(scope='module')
def base():
    return simulate_recording(SEED, DURATION)


@pytest.fixture(scope='module')
def clean():
    """Return the same recording without any noise (noise draws are separate from the rest)."""
    return simulate_recording(SEED, DURATION, sigma_a=(0.0, 0.0), sigma_b=(0.0, 0.0))


def rec_with(text, **kwargs):
    return simulate_recording(SEED, DURATION, effects=[parse_effect(text)], **kwargs)


def same_stream(s, t):
    return (np.array_equal(s.stamps, t.stamps) and np.array_equal(s.position, t.position)
            and np.array_equal(s.quat_wxyz, t.quat_wxyz))


def rot_angle(q_from, q_to):
    return quat.angle_between(q_from, q_to)


# ------------------------------------------------------------------------------ parsing

def test_every_name_parses_and_describes_itself():
    assert set(EFFECT_NAMES) == set(EFFECT_UNITS) == set(EXAMPLES)
    for name in EFFECT_NAMES:
        e = parse_effect(f'{name}={EXAMPLES[name]}')
        d = e.as_dict()
        assert d['name'] == name and d['unit'] == EFFECT_UNITS[name]
        assert d['stage'] in ('clean', 'noise', 'measured')
        json.dumps(d)


@pytest.mark.parametrize('text, needle', [
    ('warp=3', 'unknown'), ('time_offset', 'NAME=VALUE'), ('time_offset=', 'NAME=VALUE'),
    ('time_offset=abc', 'not a number'), ('outliers=1.5', 'out of range'),
    ('noise_scale=0', 'out of range'), ('noise_scale=nan', 'out of range'),
    ('scale=0.1,0.2', 'three comma-separated'), ('backlash=-1', 'out of range'),
    ('clock_drift=1,2,3', 'out of range'),
])
def test_parse_errors_are_one_line_config_errors(text, needle):
    with pytest.raises(ConfigError) as info:
        parse_effect(text)
    message = str(info.value)
    assert '\n' not in message and needle in message
    if needle == 'unknown' or needle == 'NAME=VALUE':
        assert all(name in message for name in EFFECT_NAMES)
        assert 'ppm' in message and 'mm' in message


def test_scale_accepts_one_or_three_values():
    assert parse_effect('scale=0.01').s == (0.01, 0.01, 0.01)
    assert parse_effect('scale=0.01, 0, -0.002').s == (0.01, 0.0, -0.002)
    assert make_effect('scale', (0.01, 0.0, 0.0)).as_dict()['value'] == [0.01, 0.0, 0.0]


# ------------------------------------------------------------------------------ clocks

def test_time_offset_shifts_b_stamps_exactly(base):
    rec = rec_with('time_offset=0.0123')
    b, b0 = rec.streams[B], base.streams[B]
    assert np.array_equal(b.stamps - b0.stamps, np.full(len(b0), 12_300_000))
    assert np.array_equal(b.position, b0.position) and np.array_equal(b.quat_wxyz, b0.quat_wxyz)
    assert same_stream(rec.streams[A], base.streams[A])
    assert rec.truth.effects == (TimeOffset(0.0123).as_dict(),)


def test_negative_time_offset():
    rec = simulate_recording(SEED, 5.0, effects=[TimeOffset(-0.004)])
    base = simulate_recording(SEED, 5.0)
    assert np.all(rec.streams[B].stamps - base.streams[B].stamps == -4_000_000)


def test_clock_drift_grows_linearly_from_the_start(base):
    rec = rec_with('clock_drift=250')
    b, b0 = rec.streams[B], base.streams[B]
    elapsed = (b0.stamps - base.start_ns).astype(float)
    assert np.array_equal(b.stamps - b0.stamps, np.round(250e-6 * elapsed).astype(np.int64))
    assert abs(rec.truth.effects[0]['offset_at_end_s'] - 250e-6 * DURATION) < 1e-4
    assert np.array_equal(b.position, b0.position)
    assert same_stream(rec.streams[A], base.streams[A])


def test_timestamp_jitter_perturbs_and_drops_b_only(base):
    rec = rec_with('timestamp_jitter=0.005')
    b, b0 = rec.streams[B], base.streams[B]
    assert np.all(np.diff(b.stamps) > 0)
    n_dropped = len(b0) - len(b)
    assert n_dropped == rec.truth.effects[0]['n_dropped']
    assert 0.01 * len(b0) <= n_dropped <= 0.04 * len(b0)
    # every kept sample is an original sample (pose unchanged) with a wrong stamp
    index = {tuple(p): i for i, p in enumerate(b0.position)}
    original = np.array([index[tuple(p)] for p in b.position])
    error = (b.stamps - b0.stamps[original]) * 1e-9
    assert abs(np.std(error) - 0.005) < 0.0006 and abs(np.mean(error)) < 0.0006
    assert np.array_equal(b.quat_wxyz, b0.quat_wxyz[original])
    assert same_stream(rec.streams[A], base.streams[A])


def test_large_jitter_is_sorted_and_deduplicated():
    rec = simulate_recording(SEED, 10.0, effects=[parse_effect('timestamp_jitter=0.05')])
    assert np.all(np.diff(rec.streams[B].stamps) > 0)


# ------------------------------------------------------------------------------ space

@pytest.mark.parametrize('shape', ['harmonic', 'dipole'])
def test_field_distortion_nonrigid_part_reaches_value_and_is_smooth(base, clean, shape):
    rec = simulate_recording(SEED, DURATION, effects=[FieldDistortion(5.0, shape=shape)])
    b, b0 = rec.streams[B], base.streams[B]
    d = b.position - b0.position                     # the noise draws are the same
    p = clean.streams[B].position
    nonrigid = np.linalg.norm(d - rigid_part(p, d), axis=1)
    # the size is what a rigid registration cannot absorb; the whole field is larger
    assert nonrigid.max() == pytest.approx(0.005, rel=1e-6)
    found = rec.truth.effects[0]
    assert found['shape'] == shape
    assert found['whole_field_max_mm'] >= 5.0 - 1e-9
    assert found['whole_field_max_mm'] == pytest.approx(np.linalg.norm(d, axis=1).max() * 1e3)
    # smooth: neighbouring samples get nearly the same error
    dp = np.linalg.norm(np.diff(p, axis=0), axis=1)
    dd = np.linalg.norm(np.diff(d, axis=0), axis=1)
    assert np.all(dd <= 200.0 * found['whole_field_max_mm'] * 1e-3 * dp + 1e-12)
    assert np.std(d, axis=0).max() > 1e-4
    angle = rot_angle(b0.quat_wxyz, b.quat_wxyz)
    assert 1e-3 < angle.max() <= 0.005 + 1e-6
    assert np.array_equal(b.stamps, b0.stamps)
    assert same_stream(rec.streams[A], base.streams[A])


def test_dipole_field_is_steep_near_its_source(base, clean):
    rec = simulate_recording(SEED, DURATION, effects=[FieldDistortion(5.0, shape='dipole')])
    d = np.linalg.norm(rec.streams[B].position - base.streams[B].position, axis=1)
    src = np.array(rec.truth.effects[0]['source_m'])
    r = np.linalg.norm(clean.streams[B].position - src, axis=1)
    near, far = r < np.quantile(r, 0.1), r > np.quantile(r, 0.9)
    # an inverse-cube field: the near tenth carries far more than the far tenth
    assert d[near].mean() > 2.5 * d[far].mean()


def test_field_distortion_is_a_function_of_position():
    """Two samples at (nearly) the same place get (nearly) the same error."""
    rng = np.random.default_rng(0)
    from coreg_ros.sim.injected.field import _harmonic_field
    g = _harmonic_field(rng)
    u = rng.uniform(-1, 1, (100, 3))
    assert np.allclose(g(u), g(u + 1e-9), atol=1e-8)
    assert np.allclose(g(2 * u), 4 * g(u))            # quadratic about the source
    # divergence-free (harmonic gradient): numerical divergence vanishes
    h = 1e-5
    div = sum((g(u + h * e)[:, i] - g(u - h * e)[:, i]) / (2 * h)
              for i, e in enumerate(np.eye(3)))
    assert np.allclose(div, 0.0, atol=1e-6)


def test_field_distortion_three_marker():
    model = 'three_marker'
    rec = simulate_recording(SEED, 10.0, model, effects=[FieldDistortion(3.0)])
    base = simulate_recording(SEED, 10.0, model)
    d = np.concatenate([rec.streams[t].position - base.streams[t].position
                        for t in rec.topics_b])
    clean = simulate_recording(SEED, 10.0, model, sigma_a=(0, 0), sigma_b=(0, 0))
    p = np.concatenate([clean.streams[t].position for t in rec.topics_b])
    assert np.linalg.norm(d - rigid_part(p, d), axis=1).max() == pytest.approx(0.003, rel=1e-6)


def test_distance_noise_grows_with_range(clean):
    rec = rec_with('distance_noise=6')
    noise = rec.streams[B].position - clean.streams[B].position
    r = np.linalg.norm(clean.streams[B].position, axis=1)
    r0 = rec.truth.effects[0]['r0_m']
    assert r0 == pytest.approx(np.median(r))
    factor = (r / r0) ** 6
    sigma = rec.truth.sigma_b[0]
    # normalising by the factor restores the stated noise
    assert np.std(noise / factor[:, None]) == pytest.approx(sigma, rel=0.05)
    near, far = r < np.quantile(r, 0.25), r > np.quantile(r, 0.75)
    expected = np.sqrt(np.mean(factor[far] ** 2) / np.mean(factor[near] ** 2))
    ratio = np.std(noise[far]) / np.std(noise[near])
    assert ratio == pytest.approx(expected, rel=0.15) and ratio > 1.5
    d = rec.truth.effects[0]
    assert d['edge_to_centre'] == pytest.approx(factor.max())
    rot = quat.log(quat.multiply(rec.streams[B].quat_wxyz,
                                 quat.conjugate(clean.streams[B].quat_wxyz)))
    assert np.std(rot / factor[:, None]) == pytest.approx(rec.truth.sigma_b[1], rel=0.05)
    assert np.array_equal(rec.streams[A].position, simulate_recording(SEED, DURATION)
                          .streams[A].position)


def test_scale_scales_b_positions_about_its_base(base, clean):
    s = (0.01, -0.005, 0.002)
    rec = simulate_recording(SEED, DURATION, effects=[Scale(s)])
    b, b0 = rec.streams[B], base.streams[B]
    assert np.allclose(b.position - b0.position, clean.streams[B].position * np.array(s),
                       rtol=0, atol=1e-15)
    assert np.array_equal(b.quat_wxyz, b0.quat_wxyz)
    assert same_stream(rec.streams[A], base.streams[A])
    exact = simulate_recording(SEED, DURATION, sigma_a=(0, 0), sigma_b=(0, 0),
                               effects=[parse_effect('scale=0.01')])
    assert np.allclose(exact.streams[B].position, 1.01 * clean.streams[B].position,
                       rtol=1e-14, atol=0)


def test_link_flex_pivots_under_gravity_of_any_direction(base, clean):
    g = np.array([0.6, -0.48, -0.64])
    rec = simulate_recording(SEED, DURATION, effects=[LinkFlex(2.0, gravity=tuple(g),
                                                               pivot_share=0.4)])
    d = rec.streams[B].position - base.streams[B].position
    truth = rec.truth
    R0 = quat.to_matrix(truth.q0)
    d_a = d @ R0                                        # back in A's base frame
    _, q_a = rec.motion.pose((clean.streams[B].stamps - rec.start_ns) * 1e-9)
    ell = quat.to_matrix(q_a) @ (truth.p1 / np.linalg.norm(truth.p1))
    g_perp = g - np.sum(ell * g, axis=1, keepdims=True) * ell
    # the marker moves along gravity's part across the link, 2 mm when the link is level
    assert np.allclose(d_a, 0.002 * g_perp, atol=2e-5)
    assert np.linalg.norm(d_a, axis=1).max() <= 0.002 + 1e-9
    # and the marker tilts about ℓ × ĝ by up to sag / lever
    tilt = rot_angle(base.streams[B].quat_wxyz, rec.streams[B].quat_wxyz)
    lever = 0.6 * np.linalg.norm(truth.p1)
    expected = 0.002 / lever * np.linalg.norm(np.cross(ell, g), axis=1)
    assert np.allclose(tilt, expected, atol=1e-6)
    found = rec.truth.effects[0]
    assert found['gravity_in_a_base'] == pytest.approx(g.tolist())
    assert found['tilt_max_rad'] == pytest.approx(0.002 / lever)
    assert same_stream(rec.streams[A], base.streams[A])
    # a random gravity direction when none is given
    dirs = [np.array(simulate_recording(s, 5.0, effects=[LinkFlex(1.0)]).truth.effects[0][
        'gravity_in_a_base']) for s in range(6)]
    assert np.std([v[2] for v in dirs]) > 0.1


def test_non_stationary_distortion_acts_in_its_window_only(base):
    rec = simulate_recording(SEED, DURATION, effects=[NonStationary(3.0, window=(0.4, 0.6))])
    d = np.linalg.norm(rec.streams[B].position - base.streams[B].position, axis=1)
    t = (base.streams[B].stamps - base.streams[B].stamps[0]) * 1e-9
    assert d.max() == pytest.approx(0.003, rel=1e-6)
    assert np.all(d[(t < 0.4 * t[-1] - 1e-6) | (t > 0.6 * t[-1] + 1e-6)] == 0)
    inside = (t > 0.42 * t[-1]) & (t < 0.58 * t[-1])
    assert np.median(d[inside]) > 1e-4


def test_shared_clock_restamps_both_devices_without_drift(base):
    rec = simulate_recording(SEED, DURATION, effects=[SharedClock(0.02)])
    a, b = rec.streams[A], rec.streams[B]
    lat_a = rec.truth.effects[0]['latency_a_s']
    da = (a.stamps - base.streams[A].stamps[:len(a)]) * 1e-9
    db = (b.stamps - base.streams[B].stamps[:len(b)]) * 1e-9
    assert np.median(da) == pytest.approx(lat_a, abs=1e-4)
    assert np.median(db) == pytest.approx(lat_a + 0.02, abs=1e-4)
    # constant: no trend over the recording
    half = len(db) // 2
    assert abs(np.median(db[:half]) - np.median(db[half:])) < 1e-5
    lag = (b.receive_stamps - b.stamps) * 1e-9
    assert np.all(lag >= 0) and np.median(lag) == pytest.approx(0.3e-3 * np.log(2), rel=0.2)


def test_jitter_with_gaps_of_seconds(base):
    rec = simulate_recording(SEED, DURATION, effects=[TimestampJitter(0.001, 0.05, gaps=2,
                                                                      gap_s=2.0)])
    s = rec.streams[B].stamps
    steps = np.diff(s) * 1e-9
    assert np.sum(steps > 1.5) >= 1
    assert rec.truth.effects[0]['n_dropped'] > 0.05 * len(base.streams[B])


def test_outliers_replace_that_fraction_with_gross_errors(base):
    rec = rec_with('outliers=0.03')
    b, b0 = rec.streams[B], base.streams[B]
    jump = np.linalg.norm(b.position - b0.position, axis=1)
    hit = jump > 0
    count = rec.truth.effects[0]['count']
    assert count == round(0.03 * len(b0)) == hit.sum()
    assert np.all((jump[hit] >= 0.02 - 1e-12) & (jump[hit] <= 0.10 + 1e-12))
    angle = rot_angle(b0.quat_wxyz, b.quat_wxyz)
    assert np.all(angle[hit] >= np.deg2rad(10) - 1e-9) and np.all(angle[~hit] < 1e-6)
    assert np.array_equal(b.stamps, b0.stamps)
    assert same_stream(rec.streams[A], base.streams[A])


# ------------------------------------------------------------------------------ A and noise

def test_play_operator_on_a_triangle_wave():
    t = np.linspace(0, 4, 401)
    x = (2 * np.abs((t % 2) - 1) - 1)[:, None] * 0.01       # ±1 cm triangle, starts falling
    y = play_operator(x, 0.002)
    off = (y - x)[:, 0]
    assert np.all(np.abs(off) <= 0.001 + 1e-15)
    v = np.gradient(x[:, 0])
    steady = np.abs(np.abs(x[:, 0]) - 0.01) > 0.0025          # away from the reversals
    assert np.allclose(off[steady], -0.001 * np.sign(v[steady]), atol=1e-12)
    # held still through the reversal: y constant right after the turning point
    k = np.argmin(x[:, 0])
    assert np.allclose(y[k:k + 5, 0], y[k, 0])


def test_backlash_lags_a_and_flips_at_reversals(base, clean):
    rec = simulate_recording(SEED, DURATION, effects=[Backlash(0.4)])
    off = rec.streams[A].position - base.streams[A].position
    x = clean.streams[A].position
    assert np.all(np.abs(off) <= 0.0002 + 1e-12)
    v = np.diff(x, axis=0, prepend=x[:1])           # backward difference: the last step
    moving = (np.abs(off) > 0.0002 - 1e-9) & (v != 0)
    # where it is fully engaged, the offset opposes the velocity
    assert np.all(np.sign(off[moving]) == -np.sign(v[moving]))
    assert moving.mean() > 0.7
    for axis in range(3):
        flips = np.count_nonzero(np.diff(np.sign(off[moving[:, axis], axis])) != 0)
        reversals = np.count_nonzero(np.diff(np.sign(v[:, axis])) != 0)
        assert flips >= 1 and flips <= reversals
    assert np.array_equal(rec.streams[A].quat_wxyz, base.streams[A].quat_wxyz)
    assert same_stream(rec.streams[B], base.streams[B])


def test_noise_scale_scales_true_noise_but_not_the_stated(clean):
    rec = rec_with('noise_scale=2.5')
    assert rec.truth.sigma_a == (0.0002, 0.0005) and rec.truth.sigma_b == (0.0005, 0.002)
    for topic, sigma in ((A, rec.truth.sigma_a), (B, rec.truth.sigma_b)):
        s, c = rec.streams[topic], clean.streams[topic]
        assert np.std(s.position - c.position) == pytest.approx(2.5 * sigma[0], rel=0.03)
        rot = quat.log(quat.multiply(s.quat_wxyz, quat.conjugate(c.quat_wxyz)))
        assert np.std(rot) == pytest.approx(2.5 * sigma[1], rel=0.03)
        assert np.array_equal(s.stamps, c.stamps)


# ------------------------------------------------------------------------------ together

def test_deterministic_by_seed_and_stage_order():
    texts = ['outliers=0.02', 'time_offset=0.01', 'noise_scale=2', 'field_distortion=4',
             'timestamp_jitter=0.003']
    one = simulate_recording(5, 20.0, effects=[parse_effect(t) for t in texts])
    two = simulate_recording(5, 20.0, effects=[parse_effect(t) for t in texts])
    for topic in one.streams:
        assert same_stream(one.streams[topic], two.streams[topic])
    assert one.truth.effects == two.truth.effects
    # applied stage by stage: clean, noise, measured (given order kept within a stage)
    assert [e['name'] for e in one.truth.effects] == [
        'field_distortion', 'noise_scale', 'outliers', 'time_offset', 'timestamp_jitter']
    other = simulate_recording(6, 20.0, effects=[parse_effect(t) for t in texts])
    assert not np.array_equal(other.streams[B].position[:10], one.streams[B].position[:10])


def test_every_effect_on_every_model():
    for model in ('full_pose', 'position_only', 'three_marker'):
        effects = [parse_effect(f'{n}={EXAMPLES[n]}') for n in EFFECT_NAMES]
        rec = simulate_recording(2, 10.0, model, effects=effects)
        assert len(rec.truth.effects) == len(EFFECT_NAMES)
        for topic in rec.topics_b:
            s = rec.streams[topic]
            assert np.all(np.diff(s.stamps) > 0) and np.isfinite(s.position).all()
        stamps = [rec.streams[t].stamps for t in rec.topics_b]
        assert all(np.array_equal(stamps[0], s) for s in stamps)


# ------------------------------------------------------------------------------ CLI

def test_cli_simulate_with_effects(tmp_path, capsys):
    out = tmp_path / 'rec'
    code = main(['simulate', str(out), '--seed', '3', '--duration', '5',
                 '--effect', 'time_offset=0.015', '--effect', 'scale=0.002'])
    assert code == 0
    truth = json.loads((tmp_path / 'rec.truth.json').read_text())
    names = [e['name'] for e in truth['effects']]
    assert sorted(names) == ['scale', 'time_offset']
    assert truth['sigma_b'] == [0.0005, 0.002]


def test_cli_simulate_bad_effect_is_one_line(tmp_path, capsys):
    code = main(['simulate', str(tmp_path / 'rec'), '--seed', '3', '--duration', '5',
                 '--effect', 'warp=2'])
    err = capsys.readouterr().err
    assert code == 1 and err.count('\n') == 1 and 'time_offset' in err
    assert not (tmp_path / 'rec').exists()

"""
Verdicts a new user needs (issue 25, item 4): each test failed before its fix.

A confident swap of the devices refuses the fit unless the roles are confirmed.
"""

from dataclasses import replace

from coreg_ros.core.calibration.pipeline import calibrate_streams
from coreg_ros.core.settings import Settings
from coreg_ros.sim import simulate_recording
import pytest

FRAMES = ('device_a_base', 'device_b_base')


@pytest.fixture(scope='module')
def swapped():
    """Each device's stream on the other's topic, frame ids as the devices send them."""
    rec = simulate_recording(10, 20.0, 'full_pose')
    a, b = rec.stream_a, rec.streams_b[0]
    assert (a.frame_id, b.frame_id) == FRAMES
    # the noise of each device stated for the topic it arrives on: the swap fits well
    settings = Settings(sigma_a=rec.truth.sigma_b, sigma_b=rec.truth.sigma_a)
    return b, a, settings


def test_a_confident_swap_is_not_a_success(swapped):
    on_a, on_b, settings = swapped
    result, _ = calibrate_streams(on_a, [on_b], settings, frames=FRAMES)
    assert result.fit_consistent  # the inverse calibration fits the noise...
    assert not result.success and result.flagged  # ...but is not used
    assert result.refusals == ('devices_swapped',)
    assert 'swapped (exchange topic_a and topic_b)' in result.verdict
    assert '`roles_confirmed`' in result.verdict


def test_confirmed_roles_lift_the_refusal(swapped):
    on_a, on_b, settings = swapped
    result, _ = calibrate_streams(on_a, [on_b], settings, frames=FRAMES, roles_confirmed=True)
    assert result.success and not result.flagged and result.refusals == ()
    assert 'swapped' not in result.verdict


def test_devices_as_configured_are_not_refused(swapped):
    on_a, on_b, settings = swapped
    right = replace(settings, sigma_a=settings.sigma_b, sigma_b=settings.sigma_a)
    result, _ = calibrate_streams(on_b, [on_a], right, frames=FRAMES)
    assert result.success and result.refusals == ()


# --- after a bad fit: is it the clock? (random draws, not the cases it was tuned on) --------

CLOCK_STORIES = {
    # kind: (effects or changes drawn from the rng, settings, the fix named; None: no claim)
    'wrong_fixed_offset': (lambda r: ([f'time_offset={r.uniform(0.005, 0.05):.4f}'], []),
                           {'estimate_time_offset': False}, '--time-offset auto'),
    'drift': (lambda r: ([f'clock_drift={r.uniform(150, 500):.0f}'], []), {},
              '--clock-drift auto'),
    'step': (lambda r: ([], [f'clock_step={r.uniform(0.01, 0.1):.3f}@{r.uniform(12, 28):.1f}']),
             {}, '--split-at-jump'),
    'noise_understated': (lambda r: ([f'noise_scale={r.uniform(2, 4):.2f}'], []), {}, None),
    'field_distortion': (lambda r: ([f'field_distortion={r.uniform(3, 8):.1f}'], []), {}, None),
    'ols_without_a_noise': (lambda r: ([], []), {'method': 'ols'}, None),
}


@pytest.mark.parametrize('kind', list(CLOCK_STORIES))
def test_a_bad_fit_names_the_clock_story_only_when_it_is_one(kind):
    from coreg_ros.core.calibration.clock_check import clock_problem
    from coreg_ros.sim import parse_effect
    from coreg_ros.sim.changes import apply_changes, parse_change
    import numpy as np

    draw, settings, fix = CLOCK_STORIES[kind]
    rng = np.random.default_rng(2500 + list(CLOCK_STORIES).index(kind))
    for seed in rng.integers(10_000, 20_000, size=2):
        effects, changes = draw(rng)
        rec = simulate_recording(int(seed), 40.0, effects=[parse_effect(e) for e in effects])
        rec = apply_changes(rec, [parse_change(c) for c in changes], seed=int(seed))
        found = clock_problem(rec.stream_a, list(rec.streams_b), Settings(**settings))
        if fix is None:
            assert found is None, (kind, effects, found)
        else:
            assert found is not None and fix in found, (kind, effects, changes, found)

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

"""
Seeded synthetic devices, with a place for unmodelled effects (docs/design.md §2, §5).

``simulate_recording`` makes unsynchronised streams of two devices as a bag would hold them;
``simulate_pairs`` makes synchronised pairs for Monte Carlo checks of the estimator;
``random_truth`` and ``make_motion`` draw the calibration and A's tool motion;
``parse_effect`` builds the unmodelled effects of ``coreg_ros.sim.injected``.
"""

from coreg_ros.sim.devices import (
    add_pose_noise,
    check_allocation,
    DEFAULT_SIGMA_A,
    DEFAULT_SIGMA_B,
    DEFAULT_START_NS,
    FRAME_A,
    FRAME_B,
    SimRecording,
    simulate_pairs,
    simulate_recording,
)
from coreg_ros.sim.injected import EFFECT_NAMES, EFFECT_UNITS, make_effect, parse_effect
from coreg_ros.sim.injection import apply_effects, Effect, EffectContext
from coreg_ros.sim.motion import (
    make_motion,
    Motion,
    MOTION_PRESETS,
    random_rotation,
    RESTRICTED_PRESETS,
)
from coreg_ros.sim.truth import random_truth, Truth, validate_sigma

__all__ = [
    'DEFAULT_SIGMA_A', 'DEFAULT_SIGMA_B', 'DEFAULT_START_NS', 'EFFECT_NAMES', 'EFFECT_UNITS',
    'Effect', 'EffectContext', 'FRAME_A', 'FRAME_B', 'MOTION_PRESETS', 'Motion',
    'RESTRICTED_PRESETS', 'SimRecording',
    'Truth', 'add_pose_noise', 'apply_effects', 'check_allocation', 'make_effect',
    'make_motion', 'parse_effect', 'random_rotation', 'random_truth', 'simulate_pairs',
    'simulate_recording', 'validate_sigma',
]

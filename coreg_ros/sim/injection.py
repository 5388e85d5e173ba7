"""
Extension point for unmodelled effects applied to simulated recordings (docs/design.md §5).

An effect is any callable ``effect(streams, context, rng) -> streams`` that returns new
``PoseStream`` objects (never modifies its input) for some of the topics: a time offset or
clock drift changes B's stamps, jitter perturbs stamps, a field distortion or a scale error
changes B's positions as a function of the true ones, outliers replace a few samples, and so
on. ``simulate_recording(..., effects=[...])`` applies them in order after the Gaussian device
noise, each with its own random generator (so adding an effect changes neither the base
recording nor the draws of the effects before it), and records ``effect.as_dict()`` in
``Truth.effects`` so that a diagnosis can be scored against what was really done.

Stages: an effect may carry an attribute ``stage`` (``STAGES``) saying where it acts.
``'clean'`` effects change the noise-free poses before the device noise is added (a field
distortion, a scale error, a bending link, backlash: physics, not measurement) and must keep
every stamp; ``'noise'`` effects change the device noise itself (see
``EffectContext.clean_streams``) and must keep every stamp too; ``'measured'`` effects (the
default, e.g. a time offset, jitter, outliers) act on the noisy streams as recorded.
``simulate_recording`` applies the effects stage by stage in that order, keeping the given
order within a stage. The implemented effects are in ``coreg_ros.sim.injected``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Protocol, runtime_checkable

from coreg_ros.core.errors import ConfigError
from coreg_ros.core.types import PoseStream
from coreg_ros.sim.motion import Motion
from coreg_ros.sim.truth import Truth
import numpy as np


@dataclass(frozen=True, eq=False)
class EffectContext:
    """
    What an effect may know about the simulation besides the streams it changes.

    Attributes
    ----------
    truth : Truth
        The true calibration (``effects`` still empty).
    motion : Motion
        A's tool motion in A's base frame; ``motion.pose((stamps - start_ns) * 1e-9)``
        evaluates the true pose at any instant (e.g. for a time offset).
    start_ns : int
        Origin of the motion's time, nanoseconds on the common clock.
    topic_a : str
        Topic of device A.
    topics_b : tuple of str
        Topic(s) of device B.
    true_streams : dict of str to PoseStream
        Noise-free streams at the same stamps as the noisy ones.
    sigma_a, sigma_b : tuple of float
        Device noise (position m, rotation rad).
    clean_streams : dict of str to PoseStream, optional
        For ``'noise'`` and ``'measured'`` effects: the noise-free streams after the
        ``'clean'`` effects, i.e. the noisy streams minus their noise (before any
        ``'measured'`` effect); None while the ``'clean'`` stage runs.

    """

    truth: Truth
    motion: Optional[Motion]
    start_ns: int
    topic_a: str
    topics_b: tuple
    true_streams: dict
    sigma_a: tuple
    sigma_b: tuple
    clean_streams: Optional[dict] = None


#: Where an effect acts, in the order ``simulate_recording`` applies them.
STAGES = ('clean', 'noise', 'measured')


def effect_stage(effect) -> str:
    """``effect.stage`` (one of ``STAGES``), ``'measured'`` if it has none."""
    stage = getattr(effect, 'stage', 'measured')
    if stage not in STAGES:
        raise ConfigError(f'effect stage {stage!r} is unknown; use one of {STAGES}')
    return stage


@runtime_checkable
class Effect(Protocol):
    """
    An unmodelled effect: a callable on the streams of a recording.

    ``__call__(streams, context, rng)`` takes the dict of topic to ``PoseStream`` after the
    device noise, the ``EffectContext`` and a ``numpy.random.Generator`` of its own, and returns
    a new dict of topic to ``PoseStream`` (stamps int64 ns, quaternions (w, x, y, z), w >= 0).
    ``as_dict()`` describes the effect and its true size, JSON-friendly, e.g.
    ``{'name': 'time_offset', 'tau_s': 0.012}``.
    """

    def __call__(self, streams: dict[str, PoseStream], context: EffectContext,
                 rng: np.random.Generator) -> dict[str, PoseStream]:
        """Return the streams with the effect applied."""
        ...  # pragma: no cover

    def as_dict(self) -> dict:
        """Describe the effect and its size."""
        ...  # pragma: no cover


def describe(effect) -> dict:
    """``effect.as_dict()``, or ``{'name': <its class or function name>}`` if it has none."""
    if hasattr(effect, 'as_dict'):
        return dict(effect.as_dict())
    return {'name': getattr(effect, '__name__', type(effect).__name__)}


def apply_effects(streams: dict[str, PoseStream], effects, context: EffectContext,
                  seed_sequence: np.random.SeedSequence) -> tuple[dict, tuple]:
    """
    Apply effects in order, each with its own generator spawned from ``seed_sequence``.

    Returns
    -------
    streams : dict of str to PoseStream
    descriptions : tuple of dict
        ``describe(effect)`` for each effect, in order.

    """
    effects = tuple(effects)
    children = seed_sequence.spawn(len(effects)) if effects else []
    out = dict(streams)
    for effect, child in zip(effects, children, strict=True):
        out = dict(effect(out, context, np.random.default_rng(child)))
    return out, tuple(describe(e) for e in effects)

"""
Errors of the samples themselves: noise larger than stated or growing with distance, outliers.

``distance_noise`` and ``noise_scale`` change the device noise (stage ``'noise'``);
``outliers`` replace recorded samples by gross errors (stage ``'measured'``).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Optional

from coreg_ros.core import quaternion as quat
from coreg_ros.sim.injected.common import EFFECT_UNITS, full_pose, scale_noise
from coreg_ros.sim.injection import EffectContext
import numpy as np

#: Range of an outlier's position jump, m, and of its rotation, rad.
OUTLIER_JUMP = (0.02, 0.10)
OUTLIER_ANGLE = (np.deg2rad(10.0), np.deg2rad(90.0))


@dataclass(frozen=True)
class DistanceNoise:
    """
    B's noise grows with the distance r from B's base (the source): σ(r) = σ (r / r0)^k.

    r0 is the median distance of B's (true) marker positions, so the stated σ holds in the
    middle of the workspace. Both the position and the rotation noise of B are scaled; for
    three markers each marker by its own distance.
    """

    exponent: float
    stage = 'noise'
    _found: dict = field(default_factory=dict, init=False, repr=False, compare=False)

    def __call__(self, streams: dict, context: EffectContext, rng) -> dict:
        """Scale each B sample's noise by (r / r0)^k."""
        clean = context.clean_streams
        r = np.stack([np.linalg.norm(clean[t].position, axis=1) for t in context.topics_b])
        r0 = float(np.median(r))
        out = dict(streams)
        for j, t in enumerate(context.topics_b):
            out[t] = scale_noise(streams[t], clean[t], (r[j] / r0) ** self.exponent)
        self._found.update(r0_m=r0, edge_to_centre=float((r.max() / r0) ** self.exponent),
                           near_to_centre=float((r.min() / r0) ** self.exponent))
        return out

    def as_dict(self) -> dict:
        """Describe the effect: ``exponent``, r0 and the σ ratios edge/centre, near/centre."""
        return {'name': 'distance_noise', 'value': self.exponent,
                'unit': EFFECT_UNITS['distance_noise'], 'stage': self.stage,
                'exponent': self.exponent, **self._found}


@dataclass(frozen=True)
class AnisotropicNoise:
    """
    B's position noise ``factor`` × larger along one direction of B's base frame.

    The noise of each B sample (and marker) about its clean value is stretched along
    ``axis`` (a unit vector in B's base frame; drawn when None: one of B's axes in two cases
    of three, a random direction in the third): n ↦ n + (factor - 1)(n·a)a. B's rotation
    noise and A's noise stay as stated (an optical tracker's depth, an EM field axis).
    """

    factor: float
    axis: Optional[tuple] = None
    stage = 'noise'
    _found: dict = field(default_factory=dict, init=False, repr=False, compare=False)

    def __call__(self, streams: dict, context: EffectContext, rng) -> dict:
        """Stretch the position noise of every B topic along the axis."""
        if self.axis is not None:
            a = np.asarray(self.axis, dtype=float)
        elif rng.random() < 2.0 / 3.0:
            a = np.eye(3)[int(rng.integers(3))]
        else:
            a = rng.standard_normal(3)
        a = a / np.linalg.norm(a)
        out = dict(streams)
        for t in context.topics_b:
            clean, noisy = context.clean_streams[t], streams[t]
            n = noisy.position - clean.position
            out[t] = replace(noisy, position=clean.position + n
                             + (self.factor - 1.0) * (n @ a)[:, None] * a)
        self._found['axis'] = a.tolist()
        return out

    def as_dict(self) -> dict:
        """Describe the effect: ``factor`` and the axis in B's base frame."""
        return {'name': 'anisotropic_noise', 'value': self.factor,
                'unit': EFFECT_UNITS['anisotropic_noise'], 'stage': self.stage,
                'factor': self.factor, **self._found}


@dataclass(frozen=True)
class NoiseScale:
    """
    The true noise of both devices is ``factor`` × the stated one (position and rotation).

    ``Truth.sigma_a`` / ``sigma_b`` keep the stated values: a wrong noise model.
    """

    factor: float
    stage = 'noise'

    def __call__(self, streams: dict, context: EffectContext, rng) -> dict:
        """Scale the noise of A and every B topic by ``factor``."""
        out = dict(streams)
        for t in (context.topic_a, *context.topics_b):
            out[t] = scale_noise(streams[t], context.clean_streams[t], self.factor)
        return out

    def as_dict(self) -> dict:
        """Describe the effect: ``factor`` and the true sigmas."""
        return {'name': 'noise_scale', 'value': self.factor,
                'unit': EFFECT_UNITS['noise_scale'], 'stage': self.stage, 'factor': self.factor}


@dataclass(frozen=True)
class Outliers:
    """
    A ``fraction`` of B's samples replaced by gross errors (glitches, mistracked markers).

    Exactly ``round(fraction · N)`` samples, chosen at random, jump by 2-10 cm in a random
    direction and (full_pose) rotate by 10-90° about a random axis. The three marker topics
    glitch at the same samples, each marker by its own jump.
    """

    fraction: float
    stage = 'measured'
    _found: dict = field(default_factory=dict, init=False, repr=False, compare=False)
    name = 'outliers'

    def _chosen(self, n: int, count: int, rng) -> np.ndarray:
        """Return the samples to corrupt (``count`` of ``n``, at random)."""
        return np.sort(rng.choice(n, size=count, replace=False)) if count else np.array([], int)

    def __call__(self, streams: dict, context: EffectContext, rng) -> dict:
        """Corrupt the chosen B samples."""
        n = len(streams[context.topics_b[0]])
        count = int(round(self.fraction * n))
        idx = self._chosen(n, count, rng)
        count = len(idx)
        out = dict(streams)
        for j, t in enumerate(context.topics_b):
            s = streams[t]
            direction = rng.standard_normal((count, 3))
            direction /= np.linalg.norm(direction, axis=1, keepdims=True)
            position = s.position.copy()
            position[idx] += rng.uniform(*OUTLIER_JUMP, size=(count, 1)) * direction
            q = s.quat_wxyz.copy()
            if full_pose(context) and j == 0:
                axis = rng.standard_normal((count, 3))
                axis /= np.linalg.norm(axis, axis=1, keepdims=True)
                angle = rng.uniform(*OUTLIER_ANGLE, size=(count, 1))
                q[idx] = quat.canonical(quat.multiply(quat.exp(angle * axis), q[idx]))
            out[t] = replace(s, position=position, quat_wxyz=q)
        self._found['count'] = count
        return out

    def as_dict(self) -> dict:
        """Describe the effect: ``fraction``, the count and the jump sizes."""
        return {'name': self.name, 'value': self.fraction, 'unit': EFFECT_UNITS[self.name],
                'stage': self.stage, 'fraction': self.fraction, 'jump_m': list(OUTLIER_JUMP),
                'angle_rad': [float(a) for a in OUTLIER_ANGLE], **self._found}


@dataclass(frozen=True)
class OutlierBursts(Outliers):
    """
    Outliers that come in bursts: ``fraction`` of B's samples, in runs of ``runs`` samples.

    Each run (its length drawn uniformly from ``runs``, inclusive) starts at a random sample,
    runs apart (a tracker losing a marker for a few frames, a reflection crossing the view);
    every sample of a run jumps as ``Outliers``' do, each by its own jump.
    """

    runs: tuple = (2, 6)
    name = 'outlier_bursts'

    def _chosen(self, n: int, count: int, rng) -> np.ndarray:
        """Return ``count`` samples in runs at random, not overlapping nor touching."""
        lo, hi = int(self.runs[0]), int(self.runs[1])
        taken = np.zeros(n, dtype=bool)
        lengths = []
        for _ in range(100 * max(count, 1)):
            if taken.sum() >= count:
                break
            length = min(int(rng.integers(lo, hi + 1)), count - int(taken.sum()))
            start = int(rng.integers(0, max(n - length, 1)))
            if taken[max(start - 1, 0):start + length + 1].any():
                continue
            taken[start:start + length] = True
            lengths.append(length)
        self._found['run_lengths'] = [int(v) for v in (min(lengths), max(lengths))] if (
            lengths) else []
        return np.flatnonzero(taken)

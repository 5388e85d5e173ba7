"""
Mechanical errors between the devices: a link that bends under gravity, backlash in A.

Applied to the noise-free poses (stage ``'clean'``).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Optional

from coreg_ros.core import quaternion as quat
from coreg_ros.sim.injected.common import EFFECT_UNITS, full_pose
from coreg_ros.sim.injection import EffectContext
from coreg_ros.sim.motion import random_unit
import numpy as np


def _a_orientation_at_b(context: EffectContext) -> np.ndarray:
    """A's true tool orientation at B's stamps (exact from the motion, else nearest sample)."""
    qa = context.true_streams[context.topic_a]
    b0 = context.true_streams[context.topics_b[0]]
    if context.motion is not None:
        _, q = context.motion.pose((b0.stamps - np.int64(context.start_ns)) * 1e-9)
        return q
    i = np.clip(np.searchsorted(qa.stamps, b0.stamps), 0, len(qa) - 1)
    return qa.quat_wxyz[i]


@dataclass(frozen=True)
class LinkFlex:
    """
    A non-rigid link that pivots under gravity: the marker sags **and tilts**.

    The link from A's tool to B's marker bends at a pivot on it (at ``pivot_share`` of the
    way from the tool origin to the marker, drawn in [0, 0.7] when None) as a spring hinge
    loaded by the weight beyond it: the part beyond the pivot turns about ``ℓ × ĝ`` (ℓ the
    link direction R_A p1 / |p1|, ĝ gravity in A's base frame, a random direction when None)
    by an angle ``θ_max |ℓ × ĝ|`` (the torque of the weight), exactly (a finite rotation, not
    its first order). ``sag_mm`` is the marker's displacement when the link is horizontal:
    ``θ_max = sag / |p1 - pivot|``. Every marker turns about the pivot; B's orientation turns
    with it (full_pose).
    """

    sag_mm: float
    gravity: Optional[tuple] = None
    pivot_share: Optional[float] = None
    stage = 'clean'
    _found: dict = field(default_factory=dict, init=False, repr=False, compare=False)

    def __call__(self, streams: dict, context: EffectContext, rng) -> dict:
        """Turn B's noise-free markers (and orientation) about the pivot."""
        truth = context.truth
        g = (np.asarray(self.gravity, dtype=float) if self.gravity is not None
             else random_unit(rng))
        g = g / np.linalg.norm(g)
        share = float(rng.uniform(0.0, 0.7) if self.pivot_share is None else self.pivot_share)
        p1 = np.asarray(truth.p1, dtype=float)
        pivot = share * p1
        lever = np.linalg.norm(p1 - pivot)
        theta_max = self.sag_mm * 1e-3 / max(lever, 1e-9)
        q_a = _a_orientation_at_b(context)
        Ra = quat.to_matrix(q_a)
        ell = Ra @ (p1 / np.linalg.norm(p1))
        axis = np.cross(ell, g)                        # |axis| = sin of the link's tilt
        rotvec = theta_max * axis                      # angle θ_max |ℓ × ĝ| about ℓ × ĝ
        Rf = quat.to_matrix(quat.exp(rotvec))
        R0 = quat.to_matrix(truth.q0)
        out = dict(streams)
        for j, t in enumerate(context.topics_b):
            arm = Ra @ (truth.markers[j] - pivot)      # pivot to marker, A's base frame
            moved = np.einsum('nij,nj->ni', Rf, arm) - arm
            s = streams[t]
            changes = {'position': s.position + moved @ R0.T}
            if j == 0 and full_pose(context):
                changes['quat_wxyz'] = quat.canonical(quat.multiply(
                    quat.exp(rotvec @ R0.T), s.quat_wxyz))
            out[t] = replace(s, **changes)
        self._found.update(gravity_in_a_base=g.tolist(), pivot_share=share,
                           tilt_max_rad=float(theta_max), lever_m=float(lever))
        return out

    def as_dict(self) -> dict:
        """Describe the effect: ``sag_mm``, gravity in A's base frame, pivot, largest tilt."""
        return {'name': 'link_flex', 'value': self.sag_mm, 'unit': EFFECT_UNITS['link_flex'],
                'stage': self.stage, 'sag_mm': self.sag_mm, **self._found}


def play_operator(x: np.ndarray, width: float) -> np.ndarray:
    """
    Backlash (play) of width ``width`` per column of ``x``, shape (N, d) -> (N, d).

    The output follows the input at distance ``width / 2`` behind the motion and stays put
    after a reversal until the input has travelled ``width`` back: ``y_i = clip(y_{i-1},
    x_i - w/2, x_i + w/2)``. It starts as if it had been moving the way the input first moves.
    """
    x = np.asarray(x, dtype=float)
    y = np.empty_like(x)
    if x.shape[0] == 0:
        return y
    half = 0.5 * width
    first = x[1] - x[0] if x.shape[0] > 1 else np.zeros(x.shape[1])
    prev = x[0] - half * np.sign(first)
    lo, hi = x - half, x + half
    for i in range(x.shape[0]):
        prev = np.minimum(np.maximum(prev, lo[i]), hi[i])
        y[i] = prev
    return y


@dataclass(frozen=True)
class Backlash:
    """
    Backlash in device A (a haptic arm's cables and gears).

    A reports its tool position ``width_mm / 2`` behind the true one along each axis of A's
    base frame, the sign flipping at each velocity reversal of that axis (a play operator,
    ``play_operator``). A's orientation is unaffected. Applied to A's noise-free positions,
    before the noise.
    """

    width_mm: float
    stage = 'clean'

    def __call__(self, streams: dict, context: EffectContext, rng) -> dict:
        """Pass A's noise-free positions through the play operator."""
        a = streams[context.topic_a]
        out = dict(streams)
        out[context.topic_a] = replace(
            a, position=play_operator(a.position, self.width_mm * 1e-3))
        return out

    def as_dict(self) -> dict:
        """Describe the effect: ``width_mm`` and the frame."""
        return {'name': 'backlash', 'value': self.width_mm, 'unit': EFFECT_UNITS['backlash'],
                'stage': self.stage, 'width_mm': self.width_mm, 'frame': 'per axis of A base'}

"""
Spatial errors of device B: a field distortion, one that comes and goes, a scale error.

They change B's noise-free positions (and orientation, full pose) as a function of where B
is (stage ``'clean'``, before the device noise).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Optional

from coreg_ros.core import quaternion as quat
from coreg_ros.core.rigid import rigid_part
from coreg_ros.sim.injected.common import EFFECT_UNITS, full_pose
from coreg_ros.sim.injection import EffectContext
from coreg_ros.sim.motion import random_unit
import numpy as np

#: Rotation error of a ``field_distortion`` at the workspace edge per mm of position error,
#: rad/mm (EM trackers: about 0.5° beside 10 mm).
DISTORTION_ROTATION_PER_MM = 1e-3


def _null_vectors(rng: np.random.Generator, k: int) -> np.ndarray:
    """K complex vectors z = e1 + i e2 (e1 ⟂ e2 unit): z·z = 0, so (z·u)^n is harmonic."""
    g = rng.standard_normal((k, 2, 3))
    e1 = g[:, 0] / np.linalg.norm(g[:, 0], axis=1, keepdims=True)
    e2 = g[:, 1] - np.sum(g[:, 1] * e1, axis=1, keepdims=True) * e1
    e2 /= np.linalg.norm(e2, axis=1, keepdims=True)
    return e1 + 1j * e2


def _harmonic_field(rng: np.random.Generator, n_terms: int = 3):
    """
    Draw a random quadratic field g = ∇h, h a harmonic cubic; return g: (N, 3) -> (N, 3).

    Being a harmonic gradient it is curl- and divergence-free, like a static magnetic
    disturbance.
    """
    z = _null_vectors(rng, n_terms)
    c = rng.standard_normal(n_terms) + 1j * rng.standard_normal(n_terms)

    def g(u: np.ndarray) -> np.ndarray:
        zu = u @ z.T                                            # (N, K)
        return np.real((c * zu ** 2) @ z)                       # ∝ ∇ Re Σ c (z·u)³

    return g


def _dipole(rng: np.random.Generator, centre: np.ndarray, r_edge: float):
    """Draw a dipole disturbance: a random moment at a source just outside the workspace."""
    direction = random_unit(rng)
    source = centre + rng.uniform(1.2, 2.0) * r_edge * direction
    moment = random_unit(rng)

    def g(p: np.ndarray) -> np.ndarray:
        r = p - source
        dist = np.linalg.norm(r, axis=1, keepdims=True)
        rh = r / dist
        return (3.0 * np.sum(rh * moment, axis=1, keepdims=True) * rh - moment) / dist ** 3

    return g, source


@dataclass(frozen=True)
class FieldDistortion:
    """
    A smooth position-dependent error of B (an EM tracker's field distortion).

    ``shape`` ``'harmonic'``: a random quadratic field around B's base (the gradient of a
    harmonic cubic, zero at the source, growing as r²); ``'dipole'``: the field of a dipole
    disturbance (a metal part) at a random point just outside the workspace, growing as the
    inverse cube of the distance to it, steep on the near side; None draws either. The size
    ``max_mm`` is the largest error a rigid registration **cannot** absorb (the field minus
    its best translation and small rotation over the recording's samples); the whole field's
    largest value is recorded beside it. The orientation (full_pose) gets a rotation error
    ``Exp(δθ(p)) ⊗ q`` from a second field of the same shape, largest
    ``max_mm · rotation_per_mm`` rad. Applied to the noise-free poses, before the noise.
    """

    max_mm: float
    rotation_per_mm: float = DISTORTION_ROTATION_PER_MM
    shape: Optional[str] = None
    stage = 'clean'
    _found: dict = field(default_factory=dict, init=False, repr=False, compare=False)

    def __call__(self, streams: dict, context: EffectContext, rng) -> dict:
        """Add the error field to B's positions (every marker) and orientation."""
        shape = self.shape or ('dipole' if rng.random() < 0.5 else 'harmonic')
        topics = context.topics_b
        p = np.stack([streams[t].position for t in topics], axis=1)   # (N, k, 3)
        flat = p.reshape(-1, 3)
        r_edge = float(np.max(np.linalg.norm(flat, axis=1))) if flat.size else 1.0
        found = {'shape': shape, 'r_edge_m': r_edge}
        if shape == 'dipole':
            centre = flat.mean(axis=0)
            spread = float(np.max(np.linalg.norm(flat - centre, axis=1)))
            g_pos, source = _dipole(rng, centre, spread)
            g_rot, _ = _dipole(rng, centre, spread)
            found['source_m'] = source.tolist()
        else:
            hp, hr = _harmonic_field(rng), _harmonic_field(rng)

            def g_pos(x, hp=hp):
                return hp(x / r_edge)

            def g_rot(x, hr=hr):
                return hr(x / r_edge)
        d = g_pos(flat)
        nonrigid = d - rigid_part(flat, d)
        peak = float(np.max(np.linalg.norm(nonrigid, axis=1))) if flat.size else 1.0
        d = (self.max_mm * 1e-3 / peak) * d
        found['whole_field_max_mm'] = float(np.max(np.linalg.norm(d, axis=1)) * 1e3)
        out = dict(streams)
        d = d.reshape(p.shape)
        for j, t in enumerate(topics):
            out[t] = replace(streams[t], position=streams[t].position + d[:, j])
        rot_max = self.max_mm * self.rotation_per_mm
        if full_pose(context) and len(p):
            w = g_rot(p[:, 0])
            w = (rot_max / float(np.max(np.linalg.norm(w, axis=1)))) * w
            s = out[topics[0]]
            q = quat.canonical(quat.multiply(quat.exp(w), s.quat_wxyz))
            out[topics[0]] = replace(s, quat_wxyz=q)
        found['rotation_max_rad'] = rot_max if full_pose(context) else 0.0
        self._found.update(found)
        return out

    def as_dict(self) -> dict:
        """Describe the effect: ``max_mm`` (non-rigid part), the shape and what was found."""
        return {'name': 'field_distortion', 'value': self.max_mm,
                'unit': EFFECT_UNITS['field_distortion'], 'stage': self.stage,
                'max_mm': self.max_mm, 'rotation_per_mm': self.rotation_per_mm, **self._found}


@dataclass(frozen=True)
class NonStationary:
    """
    A distortion that comes and goes: a metal object brought near an EM sensor for a while.

    A dipole disturbance at a random point just outside the workspace acts during one window
    of the recording (``window`` = (start, end) as shares of the duration, drawn when None:
    15-35 % of it), switched on and off over half a second each. ``max_mm`` is the largest
    position error it causes (rotation ``max_mm · rotation_per_mm`` rad): over the samples
    recorded while it acts, not over places the sensor visits only while it is away. Applied
    to B's noise-free poses.
    """

    max_mm: float
    window: Optional[tuple] = None
    rotation_per_mm: float = DISTORTION_ROTATION_PER_MM
    stage = 'clean'
    _found: dict = field(default_factory=dict, init=False, repr=False, compare=False)

    def __call__(self, streams: dict, context: EffectContext, rng) -> dict:
        """Add the switched disturbance to B's positions and orientation."""
        topics = context.topics_b
        b0 = streams[topics[0]]
        t = (b0.stamps - b0.stamps[0]).astype(float) * 1e-9
        T = max(float(t[-1]), 1e-9) if len(t) else 1.0
        if self.window is None:
            length = rng.uniform(0.15, 0.35)
            start = rng.uniform(0.05, 0.95 - length)
            window = (start, start + length)
        else:
            window = tuple(self.window)
        t1, t2 = window[0] * T, window[1] * T
        on = np.clip((t - t1) / 0.5, 0, 1) * np.clip((t2 - t) / 0.5, 0, 1)
        p = np.stack([streams[x].position for x in topics], axis=1)
        flat = p.reshape(-1, 3)
        centre = flat.mean(axis=0)
        spread = float(np.max(np.linalg.norm(flat - centre, axis=1)))
        g_pos, source = _dipole(rng, centre, 0.7 * spread)
        g_rot, _ = _dipole(rng, centre, 0.7 * spread)
        d = g_pos(flat).reshape(p.shape) * on[:, None, None]
        # sized by the largest error it does cause: while it acts, where the sensor then is
        # (not where the sensor is only while the object is away)
        peak = float(np.max(np.linalg.norm(d, axis=2))) if d.size else 0.0
        d = (self.max_mm * 1e-3 / peak) * d if peak > 0 else d
        out = dict(streams)
        for j, x in enumerate(topics):
            out[x] = replace(streams[x], position=streams[x].position + d[:, j])
        if full_pose(context):
            w = g_rot(p[:, 0]) * on[:, None]
            peak_w = float(np.max(np.linalg.norm(w, axis=1))) if len(w) else 0.0
            w = (self.max_mm * self.rotation_per_mm / peak_w) * w if peak_w > 0 else w
            s = out[topics[0]]
            out[topics[0]] = replace(s, quat_wxyz=quat.canonical(
                quat.multiply(quat.exp(w), s.quat_wxyz)))
        self._found.update(window_s=[float(t1), float(t2)], source_m=source.tolist())
        return out

    def as_dict(self) -> dict:
        """Describe the effect: ``max_mm``, the window (s) and the source."""
        return {'name': 'non_stationary', 'value': self.max_mm,
                'unit': EFFECT_UNITS['non_stationary'], 'stage': self.stage,
                'max_mm': self.max_mm, **self._found}


@dataclass(frozen=True)
class Scale:
    """B's positions scaled by (1 + s) per axis of B's base frame, about its origin."""

    s: tuple
    stage = 'clean'

    def __post_init__(self):
        s = tuple(float(v) for v in np.broadcast_to(np.asarray(self.s, dtype=float), (3,)))
        object.__setattr__(self, 's', s)

    def __call__(self, streams: dict, context: EffectContext, rng) -> dict:
        """Multiply B's noise-free positions by (1 + s)."""
        f = 1.0 + np.asarray(self.s)
        out = dict(streams)
        for t in context.topics_b:
            out[t] = replace(streams[t], position=streams[t].position * f)
        return out

    def as_dict(self) -> dict:
        """Describe the effect: ``scale`` per axis (fractions)."""
        value = self.s[0] if len(set(self.s)) == 1 else list(self.s)
        return {'name': 'scale', 'value': value, 'unit': EFFECT_UNITS['scale'],
                'stage': self.stage, 'scale': list(self.s)}

"""
Unmodelled effects to inject into simulated recordings (DESIGN.md §5, issue 4).

Each effect is a small frozen dataclass implementing the ``Effect`` protocol of
``coreg_ros.sim.effects`` (``__call__(streams, context, rng) -> streams``, ``as_dict()``) and
a ``stage`` saying where it acts (``coreg_ros.sim.effects.STAGES``): ``'clean'`` effects change
the noise-free poses before the device noise is added (physics: distortion, scale, a bending
link, backlash), ``'noise'`` effects change the device noise itself, ``'measured'`` effects act
on the recorded samples (stamps, dropped samples, outliers). ``parse_effect('name=value')``
builds one from the command line (``coreg simulate --effect NAME=VALUE``).

=================== ========== ========= ====================================================
name                VALUE unit stage     what it does
=================== ========== ========= ====================================================
time_offset         s          measured  B's header stamps = true time + τ (B stamped late)
clock_drift         ppm        measured  B's stamps + κ (t - t_start), κ = VALUE·1e-6
timestamp_jitter    s          measured  B's stamps + N(0, VALUE²), 2 % of B dropped (more,
                                         and gaps of seconds, through the class)
field_distortion    mm         clean     a harmonic quadratic field around B's base or a
                                         dipole disturbance just outside the workspace; its
                                         part a rigid registration cannot absorb reaches
                                         VALUE; a rotation error (1 mrad per mm) beside it
distance_noise      exponent k noise     B's noise σ × (r / r0)^k, r = distance from B's base
scale               fraction   clean     B's positions × (1 + s) per axis about B's base
link_flex           mm         clean     the link pivots under gravity (a random direction in
                                         A's base): the marker sags VALUE when the link is
                                         level, and tilts with it
outliers            fraction   measured  that fraction of B's samples jump 2-10 cm, 10-90°
backlash            mm         clean     A's position lags VALUE/2 per axis behind the
                                         motion, flipping at each reversal (play operator)
noise_scale         factor     noise     the true noise of A and B is VALUE × the stated
non_stationary      mm         clean     a dipole disturbance during one window of the
                                         recording (a metal object brought near), VALUE at
                                         most
shared_clock        s          measured  A and B stamped on receipt by one host clock: B's
                                         latency exceeds A's by VALUE, no drift
=================== ========== ========= ====================================================

``as_dict()`` gives ``name``, ``value`` (as parsed), ``unit``, ``stage`` and the effect's
parameters; effects whose size depends on the recording (e.g. the workspace edge of a field
distortion) add what they found on the recording they were last applied to.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional, Union

import numpy as np

from coreg_ros.core import quaternion as quat
from coreg_ros.core.errors import ConfigError
from coreg_ros.core.types import PoseStream
from coreg_ros.sim.effects import EffectContext

#: The ten effects of DESIGN.md §5 that the diagnosis models one by one, in its order.
EFFECT_NAMES = ('time_offset', 'clock_drift', 'timestamp_jitter', 'field_distortion',
                'distance_noise', 'scale', 'link_flex', 'outliers', 'backlash', 'noise_scale')
#: Further cases real rigs show (issue 11): a distortion that comes and goes, and both
#: devices stamped by one host clock (a constant offset, no drift).
EXTRA_EFFECT_NAMES = ('non_stationary', 'shared_clock')
#: Every name ``parse_effect`` accepts.
ALL_EFFECT_NAMES = EFFECT_NAMES + EXTRA_EFFECT_NAMES

#: Unit of each effect's VALUE, as shown in error messages and ``as_dict()['unit']``.
EFFECT_UNITS = {
    'time_offset': 's', 'clock_drift': 'ppm', 'timestamp_jitter': 's std',
    'field_distortion': 'mm at the workspace edge', 'distance_noise': 'exponent k',
    'scale': 'fraction, one or three comma-separated', 'link_flex': 'mm of sag',
    'outliers': 'fraction of B samples', 'backlash': 'mm', 'noise_scale': 'factor',
    'non_stationary': 'mm at most, during a window', 'shared_clock': 's of B latency over A',
}

#: Share of B's samples a ``timestamp_jitter`` drops.
JITTER_DROP_FRACTION = 0.02
#: Rotation error of a ``field_distortion`` at the workspace edge per mm of position error,
#: rad/mm (EM trackers: about 0.5° beside 10 mm).
DISTORTION_ROTATION_PER_MM = 1e-3
#: Range of an outlier's position jump, m, and of its rotation, rad.
OUTLIER_JUMP = (0.02, 0.10)
OUTLIER_ANGLE = (np.deg2rad(10.0), np.deg2rad(90.0))
#: Direction of gravity in A's base frame used by ``link_flex`` (A stands upright: z up).
GRAVITY_IN_A_BASE = np.array([0.0, 0.0, -1.0])


def _replace_stream(s: PoseStream, **changes) -> PoseStream:
    values = {'stamps': s.stamps, 'position': s.position, 'quat_wxyz': s.quat_wxyz,
              'frame_id': s.frame_id, 'receive_stamps': s.receive_stamps}
    values.update(changes)
    return PoseStream(**values)


def _select(s: PoseStream, keep: np.ndarray) -> PoseStream:
    return PoseStream(stamps=s.stamps[keep], position=s.position[keep],
                      quat_wxyz=s.quat_wxyz[keep], frame_id=s.frame_id,
                      receive_stamps=None if s.receive_stamps is None else s.receive_stamps[keep])


def _full_pose(context: EffectContext) -> bool:
    return context.truth.model == 'full_pose'


def _scale_noise(noisy: PoseStream, clean: PoseStream, factor) -> PoseStream:
    """Scale the noise of ``noisy`` about ``clean`` (same stamps) by ``factor``, scalar or (N,)."""
    if not np.array_equal(noisy.stamps, clean.stamps):
        raise ConfigError('noise effects need the noisy and the clean stream at the same '
                          'stamps; apply them before effects that change stamps')
    f = np.broadcast_to(np.asarray(factor, dtype=float), (len(noisy),))
    position = clean.position + f[:, None] * (noisy.position - clean.position)
    dtheta = quat.log(quat.multiply(noisy.quat_wxyz, quat.conjugate(clean.quat_wxyz)))
    q = quat.canonical(quat.multiply(quat.exp(f[:, None] * dtheta), clean.quat_wxyz))
    return _replace_stream(noisy, position=position, quat_wxyz=q)


# ------------------------------------------------------------------------------ clock effects

@dataclass(frozen=True)
class TimeOffset:
    """
    Device B stamped τ late: B's header stamps are the true time plus ``tau_s``.

    Calibrating with ``time_offset = tau_s`` (``Settings.time_offset``, B's clock minus A's)
    undoes it exactly.
    """

    tau_s: float
    stage = 'measured'

    def __call__(self, streams: dict, context: EffectContext, rng) -> dict:
        """Shift the stamps of every B topic by τ (rounded to ns)."""
        shift = np.int64(round(self.tau_s * 1e9))
        out = dict(streams)
        for t in context.topics_b:
            out[t] = _replace_stream(streams[t], stamps=streams[t].stamps + shift)
        return out

    def as_dict(self) -> dict:
        """Describe the effect: ``tau_s``."""
        return {'name': 'time_offset', 'value': self.tau_s, 'unit': EFFECT_UNITS['time_offset'],
                'stage': self.stage, 'tau_s': self.tau_s}


@dataclass(frozen=True)
class ClockDrift:
    """
    B's clock runs fast by ``ppm``: stamps + κ (t - t_start), κ = ppm · 1e-6.

    The offset is zero at the recording's start (``EffectContext.start_ns``) and grows
    linearly: 100 ppm give 6 ms after a minute.
    """

    ppm: float
    stage = 'measured'
    _found: dict = field(default_factory=dict, init=False, repr=False, compare=False)

    def __call__(self, streams: dict, context: EffectContext, rng) -> dict:
        """Add κ (t - t_start) to the stamps of every B topic."""
        kappa = self.ppm * 1e-6
        out = dict(streams)
        last = 0
        for t in context.topics_b:
            s = streams[t]
            elapsed = (s.stamps - np.int64(context.start_ns)).astype(float)
            shift = np.round(kappa * elapsed).astype(np.int64)
            out[t] = _replace_stream(s, stamps=s.stamps + shift)
            last = int(shift[-1]) if len(s) else 0
        self._found['offset_at_end_s'] = last * 1e-9
        return out

    def as_dict(self) -> dict:
        """Describe the effect: ``ppm``, ``kappa`` and the offset reached at the end, s."""
        return {'name': 'clock_drift', 'value': self.ppm, 'unit': EFFECT_UNITS['clock_drift'],
                'stage': self.stage, 'ppm': self.ppm, 'kappa': self.ppm * 1e-6, **self._found}


@dataclass(frozen=True)
class TimestampJitter:
    """
    Random stamp errors on B, N(0, ``sigma_s``²) each, and ``drop_fraction`` of B's samples lost.

    The three marker topics of a three-marker tracker share their stamp errors and drops (one
    device). Jittered stamps that come out of order are sorted (a sample keeps its pose and
    wrong stamp); a stamp that repeats another is dropped too.
    """

    sigma_s: float
    drop_fraction: float = JITTER_DROP_FRACTION
    gaps: int = 0
    gap_s: float = 2.0
    stage = 'measured'
    _found: dict = field(default_factory=dict, init=False, repr=False, compare=False)

    def __call__(self, streams: dict, context: EffectContext, rng) -> dict:
        """Jitter, drop, cut gaps, sort and de-duplicate B's samples."""
        first = streams[context.topics_b[0]]
        n = len(first)
        error = np.round(rng.standard_normal(n) * self.sigma_s * 1e9).astype(np.int64)
        n_drop = int(round(self.drop_fraction * n))
        dropped = rng.choice(n, size=n_drop, replace=False) if n_drop else np.array([], int)
        keep = np.ones(n, dtype=bool)
        keep[dropped] = False
        t = (first.stamps - first.stamps[0]).astype(float) * 1e-9
        gap_list = []
        for _ in range(self.gaps):
            # a stretch of gap_s seconds with no sample at all (a lost connection)
            start = rng.uniform(0.1, 0.9) * max(float(t[-1]) - self.gap_s, 0.0) if n else 0.0
            keep[(t >= start) & (t < start + self.gap_s)] = False
            gap_list.append([float(start), float(self.gap_s)])
        stamps = first.stamps + error
        idx = np.flatnonzero(keep)
        idx = idx[np.argsort(stamps[idx], kind='stable')]
        unique = np.ones(idx.size, dtype=bool)
        unique[1:] = np.diff(stamps[idx]) > 0
        idx = idx[unique]
        out = dict(streams)
        for t in context.topics_b:
            s = streams[t]
            out[t] = _select(_replace_stream(s, stamps=s.stamps + error), idx)
        self._found.update(n_dropped=int(n - idx.size), gaps_s=gap_list,
                           empirical_sigma_s=float(np.std(error[idx]) * 1e-9) if idx.size else 0.0)
        return out

    def as_dict(self) -> dict:
        """Describe the effect: ``sigma_s``, ``drop_fraction`` and the samples dropped."""
        return {'name': 'timestamp_jitter', 'value': self.sigma_s,
                'unit': EFFECT_UNITS['timestamp_jitter'], 'stage': self.stage,
                'sigma_s': self.sigma_s, 'drop_fraction': self.drop_fraction, **self._found}


# --------------------------------------------------------------------------- spatial effects

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


def rigid_part(points: np.ndarray, d: np.ndarray) -> np.ndarray:
    """
    Return the part of a displacement field a rigid registration absorbs, ``t + ω × p``.

    Shape (N, 3), like ``points`` and ``d``.

    Least squares over the points (first order in ω: the fields are millimetres on metres).
    """
    c = points.mean(axis=0)
    q = points - c
    n = len(points)
    A = np.zeros((3 * n, 6))
    A[:, 0:3] = np.tile(np.eye(3), (n, 1))
    skew = np.zeros((n, 3, 3))
    skew[:, 0, 1], skew[:, 0, 2] = q[:, 2], -q[:, 1]
    skew[:, 1, 0], skew[:, 1, 2] = -q[:, 2], q[:, 0]
    skew[:, 2, 0], skew[:, 2, 1] = q[:, 1], -q[:, 0]
    A[:, 3:6] = skew.reshape(3 * n, 3)                 # ω × q = -q × ω
    x, *_ = np.linalg.lstsq(A, d.reshape(-1), rcond=None)
    return (A @ x).reshape(n, 3)


def _dipole(rng: np.random.Generator, centre: np.ndarray, r_edge: float):
    """Draw a dipole disturbance: a random moment at a source just outside the workspace."""
    direction = _random_direction(rng)
    source = centre + rng.uniform(1.2, 2.0) * r_edge * direction
    moment = _random_direction(rng)

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
            out[t] = _replace_stream(streams[t], position=streams[t].position + d[:, j])
        rot_max = self.max_mm * self.rotation_per_mm
        if _full_pose(context) and len(p):
            w = g_rot(p[:, 0])
            w = (rot_max / float(np.max(np.linalg.norm(w, axis=1)))) * w
            s = out[topics[0]]
            q = quat.canonical(quat.multiply(quat.exp(w), s.quat_wxyz))
            out[topics[0]] = _replace_stream(s, quat_wxyz=q)
        found['rotation_max_rad'] = rot_max if _full_pose(context) else 0.0
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
            out[x] = _replace_stream(streams[x], position=streams[x].position + d[:, j])
        if _full_pose(context):
            w = g_rot(p[:, 0]) * on[:, None]
            peak_w = float(np.max(np.linalg.norm(w, axis=1))) if len(w) else 0.0
            w = (self.max_mm * self.rotation_per_mm / peak_w) * w if peak_w > 0 else w
            s = out[topics[0]]
            out[topics[0]] = _replace_stream(s, quat_wxyz=quat.canonical(
                quat.multiply(quat.exp(w), s.quat_wxyz)))
        self._found.update(window_s=[float(t1), float(t2)], source_m=source.tolist())
        return out

    def as_dict(self) -> dict:
        """Describe the effect: ``max_mm``, the window (s) and the source."""
        return {'name': 'non_stationary', 'value': self.max_mm,
                'unit': EFFECT_UNITS['non_stationary'], 'stage': self.stage,
                'max_mm': self.max_mm, **self._found}


@dataclass(frozen=True)
class SharedClock:
    """
    Both devices stamped on receipt by one host clock: a constant offset, never a drift.

    Header stamps = true sample time + the device's transport latency + a small positive
    host scheduling delay (exponential, mean ``host_jitter_s``); the recorder's receive stamps
    follow by an exponential 0.3 ms on average. ``latency_s`` is B's latency minus A's (A's
    is drawn in 1-5 ms): the offset the diagnosis should find (B stamped late by it), with no
    drift at all.
    """

    latency_s: float
    host_jitter_s: float = 3e-5
    stage = 'measured'
    _found: dict = field(default_factory=dict, init=False, repr=False, compare=False)

    def __call__(self, streams: dict, context: EffectContext, rng) -> dict:
        """Restamp A and B with host receive times."""
        lat_a = rng.uniform(0.001, 0.005)
        out = dict(streams)
        first = streams[context.topics_b[0]]
        delay_b = rng.exponential(self.host_jitter_s, len(first))
        for topic, lat, delay in (
                [(context.topic_a, lat_a, rng.exponential(self.host_jitter_s,
                                                          len(streams[context.topic_a])))]
                + [(t, lat_a + self.latency_s, delay_b) for t in context.topics_b]):
            s = streams[topic]
            stamps = s.stamps + np.round((lat + delay) * 1e9).astype(np.int64)
            order = np.argsort(stamps, kind='stable')
            keep = np.ones(len(order), dtype=bool)
            keep[1:] = np.diff(stamps[order]) > 0
            idx = order[keep]
            # the recorder receives each message a little after the driver stamped it
            receive = stamps + np.round(rng.exponential(3e-4, len(stamps)) * 1e9).astype(
                np.int64)
            out[topic] = _select(_replace_stream(s, stamps=stamps, receive_stamps=receive),
                                 idx)
        self._found.update(latency_a_s=float(lat_a))
        return out

    def as_dict(self) -> dict:
        """Describe the effect: ``latency_s`` (B's minus A's) and A's latency."""
        return {'name': 'shared_clock', 'value': self.latency_s,
                'unit': EFFECT_UNITS['shared_clock'], 'stage': self.stage,
                'latency_s': self.latency_s, 'host_jitter_s': self.host_jitter_s,
                **self._found}


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
            out[t] = _scale_noise(streams[t], clean[t], (r[j] / r0) ** self.exponent)
        self._found.update(r0_m=r0, edge_to_centre=float((r.max() / r0) ** self.exponent),
                           near_to_centre=float((r.min() / r0) ** self.exponent))
        return out

    def as_dict(self) -> dict:
        """Describe the effect: ``exponent``, r0 and the σ ratios edge/centre, near/centre."""
        return {'name': 'distance_noise', 'value': self.exponent,
                'unit': EFFECT_UNITS['distance_noise'], 'stage': self.stage,
                'exponent': self.exponent, **self._found}


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
            out[t] = _replace_stream(streams[t], position=streams[t].position * f)
        return out

    def as_dict(self) -> dict:
        """Describe the effect: ``scale`` per axis (fractions)."""
        value = self.s[0] if len(set(self.s)) == 1 else list(self.s)
        return {'name': 'scale', 'value': value, 'unit': EFFECT_UNITS['scale'],
                'stage': self.stage, 'scale': list(self.s)}


def _a_orientation_at_b(context: EffectContext) -> np.ndarray:
    """A's true tool orientation at B's stamps (exact from the motion, else nearest sample)."""
    qa = context.true_streams[context.topic_a]
    b0 = context.true_streams[context.topics_b[0]]
    if context.motion is not None:
        _, q = context.motion.pose((b0.stamps - np.int64(context.start_ns)) * 1e-9)
        return q
    i = np.clip(np.searchsorted(qa.stamps, b0.stamps), 0, len(qa) - 1)
    return qa.quat_wxyz[i]


def _random_direction(rng) -> np.ndarray:
    g = rng.standard_normal(3)
    return g / np.linalg.norm(g)


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
             else _random_direction(rng))
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
            if j == 0 and _full_pose(context):
                changes['quat_wxyz'] = quat.canonical(quat.multiply(
                    quat.exp(rotvec @ R0.T), s.quat_wxyz))
            out[t] = _replace_stream(s, **changes)
        self._found.update(gravity_in_a_base=g.tolist(), pivot_share=share,
                           tilt_max_rad=float(theta_max), lever_m=float(lever))
        return out

    def as_dict(self) -> dict:
        """Describe the effect: ``sag_mm``, gravity in A's base frame, pivot, largest tilt."""
        return {'name': 'link_flex', 'value': self.sag_mm, 'unit': EFFECT_UNITS['link_flex'],
                'stage': self.stage, 'sag_mm': self.sag_mm, **self._found}


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

    def __call__(self, streams: dict, context: EffectContext, rng) -> dict:
        """Corrupt the chosen B samples."""
        n = len(streams[context.topics_b[0]])
        count = int(round(self.fraction * n))
        idx = np.sort(rng.choice(n, size=count, replace=False)) if count else np.array([], int)
        out = dict(streams)
        for j, t in enumerate(context.topics_b):
            s = streams[t]
            direction = rng.standard_normal((count, 3))
            direction /= np.linalg.norm(direction, axis=1, keepdims=True)
            position = s.position.copy()
            position[idx] += rng.uniform(*OUTLIER_JUMP, size=(count, 1)) * direction
            q = s.quat_wxyz.copy()
            if _full_pose(context) and j == 0:
                axis = rng.standard_normal((count, 3))
                axis /= np.linalg.norm(axis, axis=1, keepdims=True)
                angle = rng.uniform(*OUTLIER_ANGLE, size=(count, 1))
                q[idx] = quat.canonical(quat.multiply(quat.exp(angle * axis), q[idx]))
            out[t] = _replace_stream(s, position=position, quat_wxyz=q)
        self._found['count'] = count
        return out

    def as_dict(self) -> dict:
        """Describe the effect: ``fraction``, the count and the jump sizes."""
        return {'name': 'outliers', 'value': self.fraction, 'unit': EFFECT_UNITS['outliers'],
                'stage': self.stage, 'fraction': self.fraction, 'jump_m': list(OUTLIER_JUMP),
                'angle_rad': [float(a) for a in OUTLIER_ANGLE], **self._found}


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
        out[context.topic_a] = _replace_stream(
            a, position=play_operator(a.position, self.width_mm * 1e-3))
        return out

    def as_dict(self) -> dict:
        """Describe the effect: ``width_mm`` and the frame."""
        return {'name': 'backlash', 'value': self.width_mm, 'unit': EFFECT_UNITS['backlash'],
                'stage': self.stage, 'width_mm': self.width_mm, 'frame': 'per axis of A base'}


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
            out[t] = _scale_noise(streams[t], context.clean_streams[t], self.factor)
        return out

    def as_dict(self) -> dict:
        """Describe the effect: ``factor`` and the true sigmas."""
        return {'name': 'noise_scale', 'value': self.factor,
                'unit': EFFECT_UNITS['noise_scale'], 'stage': self.stage, 'factor': self.factor}


# ------------------------------------------------------------------------------------ parsing

_CLASSES = {
    'time_offset': TimeOffset, 'clock_drift': ClockDrift, 'timestamp_jitter': TimestampJitter,
    'field_distortion': FieldDistortion, 'distance_noise': DistanceNoise, 'scale': Scale,
    'link_flex': LinkFlex, 'outliers': Outliers, 'backlash': Backlash,
    'noise_scale': NoiseScale, 'non_stationary': NonStationary, 'shared_clock': SharedClock,
}

# accepted range of VALUE per effect: (low, high, low inclusive), for the error message
_RANGES = {
    'time_offset': (-10.0, 10.0, True), 'clock_drift': (-1e5, 1e5, True),
    'timestamp_jitter': (0.0, 1.0, True), 'field_distortion': (0.0, 1000.0, True),
    'distance_noise': (-10.0, 10.0, True), 'scale': (-0.5, 0.5, True),
    'link_flex': (0.0, 100.0, True), 'outliers': (0.0, 1.0, True),
    'backlash': (0.0, 100.0, True), 'noise_scale': (0.0, 100.0, False),
    'non_stationary': (0.0, 1000.0, True), 'shared_clock': (-10.0, 10.0, True),
}


def _accepted() -> str:
    return ', '.join(f'{n}=<{EFFECT_UNITS[n].split(",")[0]}>' for n in ALL_EFFECT_NAMES)


def make_effect(name: str, value: Union[float, tuple]):
    """
    Build the effect ``name`` of size ``value`` (unit ``EFFECT_UNITS[name]``).

    Raises
    ------
    ConfigError
        For an unknown name or a value out of its range.

    """
    if name not in _CLASSES:
        raise ConfigError(f'effect {name!r} is unknown; use NAME=VALUE with one of '
                          f'{_accepted()}')
    low, high, inclusive = _RANGES[name]
    values = np.atleast_1d(np.asarray(value, dtype=float))
    ok = np.isfinite(values).all() and (values <= high).all() and (
        (values >= low).all() if inclusive else (values > low).all())
    if not ok or (name != 'scale' and values.size != 1) or (name == 'scale'
                                                             and values.size not in (1, 3)):
        bracket = '[' if inclusive else '('
        raise ConfigError(f'effect {name}: value {value!r} is out of range; give one number'
                          f'{" or three comma-separated" if name == "scale" else ""} in '
                          f'{bracket}{low:g}, {high:g}] ({EFFECT_UNITS[name]})')
    if name == 'scale':
        return Scale(tuple(values.tolist()) if values.size == 3 else float(values[0]))
    return _CLASSES[name](float(values[0]))


def parse_effect(text: str):
    """
    Parse ``'NAME=VALUE'`` (e.g. ``'time_offset=0.012'``, ``'scale=0.01,0,-0.005'``) to an effect.

    Parameters
    ----------
    text : str
        NAME one of ``EFFECT_NAMES``; VALUE a number in the unit of ``EFFECT_UNITS[NAME]``
        (for ``scale`` one number for all axes or three comma-separated).

    Returns
    -------
    Effect

    Raises
    ------
    ConfigError
        One line naming the accepted names and units.

    """
    name, sep, raw = str(text).partition('=')
    name = name.strip()
    if not sep or not raw.strip():
        raise ConfigError(f'effect {text!r}: expected NAME=VALUE, one of {_accepted()}')
    if name not in _CLASSES:
        raise ConfigError(f'effect {name!r} is unknown; use NAME=VALUE with one of '
                          f'{_accepted()}')
    try:
        values = tuple(float(v) for v in raw.replace(' ', '').split(','))
    except ValueError:
        raise ConfigError(f'effect {name}: {raw.strip()!r} is not a number; give VALUE in '
                          f'{EFFECT_UNITS[name]}, e.g. {name}={_EXAMPLES[name]}') from None
    return make_effect(name, values if len(values) > 1 else values[0])


_EXAMPLES = {
    'time_offset': '0.012', 'clock_drift': '100', 'timestamp_jitter': '0.005',
    'field_distortion': '5', 'distance_noise': '2', 'scale': '0.005', 'link_flex': '1',
    'outliers': '0.02', 'backlash': '0.3', 'noise_scale': '2', 'non_stationary': '3',
    'shared_clock': '0.02',
}

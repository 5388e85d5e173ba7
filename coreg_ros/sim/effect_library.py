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
timestamp_jitter    s          measured  B's stamps + N(0, VALUE²), and 2 % of B dropped
field_distortion    mm         clean     smooth error field around B's base (the source),
                                         |error| reaching VALUE at the workspace edge, and a
                                         position-dependent rotation error (1 mrad per mm)
distance_noise      exponent k noise     B's noise σ × (r / r0)^k, r = distance from B's base
scale               fraction   clean     B's positions × (1 + s) per axis about B's base
link_flex           mm         clean     the marker sags VALUE along gravity (-z of A's base)
                                         when the tool-to-marker link is horizontal
outliers            fraction   measured  that fraction of B's samples jump 2-10 cm, 10-90°
backlash            mm         clean     A's position lags VALUE/2 per axis behind the
                                         motion, flipping at each reversal (play operator)
noise_scale         factor     noise     the true noise of A and B is VALUE × the stated
=================== ========== ========= ====================================================

``as_dict()`` gives ``name``, ``value`` (as parsed), ``unit``, ``stage`` and the effect's
parameters; effects whose size depends on the recording (e.g. the workspace edge of a field
distortion) add what they found on the recording they were last applied to.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Union

import numpy as np

from coreg_ros.core import quaternion as quat
from coreg_ros.core.errors import ConfigError
from coreg_ros.core.types import PoseStream
from coreg_ros.sim.effects import EffectContext

#: Names accepted by ``parse_effect``, in the order of DESIGN.md §5.
EFFECT_NAMES = ('time_offset', 'clock_drift', 'timestamp_jitter', 'field_distortion',
                'distance_noise', 'scale', 'link_flex', 'outliers', 'backlash', 'noise_scale')

#: Unit of each effect's VALUE, as shown in error messages and ``as_dict()['unit']``.
EFFECT_UNITS = {
    'time_offset': 's', 'clock_drift': 'ppm', 'timestamp_jitter': 's std',
    'field_distortion': 'mm at the workspace edge', 'distance_noise': 'exponent k',
    'scale': 'fraction, one or three comma-separated', 'link_flex': 'mm of sag',
    'outliers': 'fraction of B samples', 'backlash': 'mm', 'noise_scale': 'factor',
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
    stage = 'measured'
    _found: dict = field(default_factory=dict, init=False, repr=False, compare=False)

    def __call__(self, streams: dict, context: EffectContext, rng) -> dict:
        """Jitter, drop, sort and de-duplicate B's samples."""
        first = streams[context.topics_b[0]]
        n = len(first)
        error = np.round(rng.standard_normal(n) * self.sigma_s * 1e9).astype(np.int64)
        n_drop = int(round(self.drop_fraction * n))
        dropped = rng.choice(n, size=n_drop, replace=False) if n_drop else np.array([], int)
        keep = np.ones(n, dtype=bool)
        keep[dropped] = False
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
        self._found.update(n_dropped=int(n - idx.size),
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


@dataclass(frozen=True)
class FieldDistortion:
    """
    A smooth position-dependent error of B (an EM tracker's field distortion).

    The error is a random quadratic field around B's base (the field source), the gradient of
    a harmonic cubic: zero at the source, growing as r² with the distance r. Its size is set
    on the recording: at the workspace edge r_edge (the largest distance of a true marker
    position from B's base) it reaches ``max_mm`` — exactly, ``max_mm`` is the largest error
    over the recording's samples. The orientation (full_pose) gets a rotation error
    ``Exp(δθ(p)) ⊗ q`` from a second such field, largest ``max_mm · rotation_per_mm`` rad.
    Applied to the noise-free poses, before the noise.
    """

    max_mm: float
    rotation_per_mm: float = DISTORTION_ROTATION_PER_MM
    stage = 'clean'
    _found: dict = field(default_factory=dict, init=False, repr=False, compare=False)

    def __call__(self, streams: dict, context: EffectContext, rng) -> dict:
        """Add the error field to B's positions (every marker) and orientation."""
        g_pos, g_rot = _harmonic_field(rng), _harmonic_field(rng)
        topics = context.topics_b
        p = np.stack([streams[t].position for t in topics], axis=1)   # (N, k, 3)
        flat = p.reshape(-1, 3)
        r_edge = float(np.max(np.linalg.norm(flat, axis=1))) if flat.size else 1.0
        u = flat / r_edge
        d = g_pos(u)
        peak = float(np.max(np.linalg.norm(d, axis=1))) if flat.size else 1.0
        d = (self.max_mm * 1e-3 / peak) * d
        out = dict(streams)
        d = d.reshape(p.shape)
        for j, t in enumerate(topics):
            out[t] = _replace_stream(streams[t], position=streams[t].position + d[:, j])
        rot_max = self.max_mm * self.rotation_per_mm
        if _full_pose(context) and len(p):
            w = g_rot(p[:, 0] / r_edge)
            w = (rot_max / float(np.max(np.linalg.norm(w, axis=1)))) * w
            s = out[topics[0]]
            q = quat.canonical(quat.multiply(quat.exp(w), s.quat_wxyz))
            out[topics[0]] = _replace_stream(s, quat_wxyz=q)
        self._found.update(r_edge_m=r_edge, rotation_max_rad=rot_max if _full_pose(context)
                           else 0.0)
        return out

    def as_dict(self) -> dict:
        """Describe the effect: ``max_mm``, the rotation's size and the edge distance found."""
        return {'name': 'field_distortion', 'value': self.max_mm,
                'unit': EFFECT_UNITS['field_distortion'], 'stage': self.stage,
                'max_mm': self.max_mm, 'rotation_per_mm': self.rotation_per_mm, **self._found}


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


@dataclass(frozen=True)
class LinkFlex:
    """
    A non-rigid link: the marker sags along gravity as a cantilever would.

    Gravity is -z of A's base frame (``GRAVITY_IN_A_BASE``: A, a robot or a haptic arm, stands
    upright). The link is the tool-to-marker offset p1; the sag is ``sag_mm · h`` along
    gravity, with h = |ℓ × ĝ| ∈ [0, 1] how horizontal the link direction ℓ = R_A p1 / |p1| is
    (1 when horizontal, 0 when vertical). In the tool frame the sag direction R_Aᵀ ĝ depends
    on the tool's orientation: the signature of a bending link. Every marker moves by the
    same sag; the marker's orientation is kept (its small tilt is not modelled).
    """

    sag_mm: float
    stage = 'clean'

    def __call__(self, streams: dict, context: EffectContext, rng) -> dict:
        """Move B's noise-free marker positions by R0 · sag(R_A)."""
        truth = context.truth
        qa = context.true_streams[context.topic_a]
        b0 = context.true_streams[context.topics_b[0]]
        # A's orientation at B's stamps from the motion (exact), else nearest A sample
        if context.motion is not None:
            _, q_at_b = context.motion.pose((b0.stamps - np.int64(context.start_ns)) * 1e-9)
        else:
            i = np.clip(np.searchsorted(qa.stamps, b0.stamps), 0, len(qa) - 1)
            q_at_b = qa.quat_wxyz[i]
        p1 = np.asarray(truth.p1, dtype=float)
        ell = quat.to_matrix(q_at_b) @ (p1 / np.linalg.norm(p1))
        ell = ell.reshape(-1, 3)
        h = np.linalg.norm(np.cross(ell, GRAVITY_IN_A_BASE), axis=1)
        sag_a = (self.sag_mm * 1e-3) * h[:, None] * GRAVITY_IN_A_BASE
        sag_b = sag_a @ quat.to_matrix(truth.q0).T
        out = dict(streams)
        for t in context.topics_b:
            out[t] = _replace_stream(streams[t], position=streams[t].position + sag_b)
        return out

    def as_dict(self) -> dict:
        """Describe the effect: ``sag_mm`` and the gravity direction in A's base frame."""
        return {'name': 'link_flex', 'value': self.sag_mm, 'unit': EFFECT_UNITS['link_flex'],
                'stage': self.stage, 'sag_mm': self.sag_mm,
                'gravity_in_a_base': GRAVITY_IN_A_BASE.tolist()}


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
    'noise_scale': NoiseScale,
}

# accepted range of VALUE per effect: (low, high, low inclusive), for the error message
_RANGES = {
    'time_offset': (-10.0, 10.0, True), 'clock_drift': (-1e5, 1e5, True),
    'timestamp_jitter': (0.0, 1.0, True), 'field_distortion': (0.0, 1000.0, True),
    'distance_noise': (-10.0, 10.0, True), 'scale': (-0.5, 0.5, True),
    'link_flex': (0.0, 100.0, True), 'outliers': (0.0, 1.0, True),
    'backlash': (0.0, 100.0, True), 'noise_scale': (0.0, 100.0, False),
}


def _accepted() -> str:
    return ', '.join(f'{n}=<{EFFECT_UNITS[n].split(",")[0]}>' for n in EFFECT_NAMES)


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
    'outliers': '0.02', 'backlash': '0.3', 'noise_scale': '2',
}

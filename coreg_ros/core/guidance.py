r"""
Guidance while collecting: how accurate a calibration would be now, and which motion helps most.

From the pairs accumulated so far, the posterior σ each parameter would have is the inverse of
the information of the accumulated motion at the current estimate, in the errors-in-variables
("effective variance") form of ``crlb``:

.. math::

    \mathcal{I} = \sum_i F_i^T (Σ_b + s_i F_{x,i} Σ_a F_{x,i}^T)^{-1} F_i,

with ``F_i = [F_ψ, c]`` the Jacobian of B's measurement with respect to ψ (T0 and T1 in the ROS
tangents of ``crlb.model_jacobians``) and, when the clock offset is estimated, the offset's
column ``c = -F_x ẋ_A`` (A's interpolated pose moves with its velocity: ``linearized``). This
is the covariance ``calibrate_streams`` reports for TLS (the φ block of the inverse with τ
marginalised), evaluated at the measured inputs.

The sum is accumulated incrementally: each new pair adds its own term once, so an update at
1 Hz with 2 × 1 kHz streams costs about a millisecond. The Jacobians depend on the estimate
only through T0's rotation and the marker positions; when a new estimate moves those by more
than ``RELINEARISE_ROTATION`` / ``RELINEARISE_MARKER``, the sum is rebuilt from a bounded,
evenly decimated store of the pairs (an unbiased estimate of the full sum).

Candidate motions added to the recording (``CANDIDATE_SECONDS`` at the current pair rate,
from the tool's current pose): rotate the tool back and forth about one of its own axes, move
it back and forth along one of A's base axes, or hold it still (a pose that adds information
without coupling to the clock offset). The suggestion is the candidate whose added information
most reduces the worst ratio σ / target over the parameters.

Units SI (m, rad, s); quaternions (w, x, y, z).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional

import numpy as np

from coreg_ros.core import quaternion as quat
from coreg_ros.core.calibrate import noise_covariance
from coreg_ros.core.crlb import CRLB_DIMENSION, model_jacobians
from coreg_ros.core.errors import InputError, UnobservableError
from coreg_ros.core.initialize import initialize
from coreg_ros.core.models import SPECS, Parameters
from coreg_ros.core.observability import check_motion
from coreg_ros.core.trajectory import VELOCITY_HALF_WINDOW, Trajectory
from coreg_ros.core.types import MODELS, CalibrationResult, Pairs

#: Re-linearise (rebuild the information) when T0's rotation estimate moves by more (rad).
RELINEARISE_ROTATION = np.deg2rad(2.0)
#: ... or a marker position estimate moves by more (m).
RELINEARISE_MARKER = 0.005
#: Pairs kept for re-linearising (evenly decimated beyond this).
MAX_STORED_PAIRS = 50_000
#: Weak prior that keeps the information invertible before the motion determines everything:
#: σ of a position (m), a rotation (rad) and the clock offset (s). A σ near these is "not yet
#: determined".
WEAK_PRIOR = (1.0, 1.0, 1.0)
#: Recording time each candidate motion adds, s.
CANDIDATE_SECONDS = 10.0
#: Amplitude (rad) and frequency (Hz) of a candidate rotation about a tool axis.
CANDIDATE_ROTATION = (np.deg2rad(30.0), 0.2)
#: Amplitude (m) and frequency (Hz) of a candidate translation along a base axis.
CANDIDATE_TRANSLATION = (0.10, 0.2)
#: Samples that represent a candidate's added motion (its information is scaled to its pairs).
CANDIDATE_SAMPLES = 100
#: Pairs linearised at once.
CHUNK = 4096

#: Name of the guidance status in /diagnostics (``<node>: guidance``).
STATUS_NAME = 'guidance'
#: /diagnostics keys of the guidance status (the node publishes exactly
#: ``Guidance.diagnostic_values()``; ``coreg watch`` reads these).
KEY_PAIRS = 'pairs'
KEY_DURATION = 'duration s'
KEY_READY = 'ready'
KEY_TARGET_POSITION = 'target sigma position m'
KEY_TARGET_ROTATION = 'target sigma rotation rad'
KEY_TARGET_TIME = 'target sigma time s'
KEY_SIGMA_PREFIX = 'sigma '  # + group name (p0, theta0, p1, theta1, p2, p3, time_offset)
KEY_WORST = 'worst'
KEY_WORST_RATIO = 'worst ratio'
KEY_NEXT = 'next motion'
KEY_NEXT_TEXT = 'next motion text'
KEY_NEXT_RATIO = 'next motion worst ratio'
KEY_SUMMARY = 'summary'

#: Parameter groups of ψ per model (3 axes each), in the order of ``crlb``.
GROUPS = {'full_pose': ('p0', 'theta0', 'p1', 'theta1'),
          'position_only': ('p0', 'theta0', 'p1'),
          'three_marker': ('p0', 'theta0', 'p1', 'p2', 'p3')}
#: Group names for people.
GROUP_TITLES = {'p0': 'T0 position', 'theta0': 'T0 rotation', 'p1': 'T1 position',
                'theta1': 'T1 rotation', 'p2': 'marker 2', 'p3': 'marker 3',
                'time_offset': 'clock offset'}
AXES = 'xyz'


def is_rotation_group(name: str) -> bool:
    """Whether a group of ψ is a rotation (rad) rather than a position (m)."""
    return name.startswith('theta')


# --------------------------------------------------------------------------- pairs and velocity


@dataclass(frozen=True)
class PairBatch:
    """
    Pairs with device A's velocity at each pair instant: what guidance and the watchdog take.

    Attributes
    ----------
    stamps : ndarray of int64, shape (N,)
        B's stamps, ns.
    pos_a : ndarray, shape (N, 3)
        A's tool position (interpolated at B's stamps), A's base frame, m.
    quat_a : ndarray, shape (N, 4)
        A's tool orientation, (w, x, y, z).
    pos_b : ndarray, shape (N, 3) or (N, 3, 3)
        B's marker position(s), B's base frame, m.
    quat_b : ndarray, shape (N, 4) or None
        B's marker orientation (full pose only).
    a_var_scale : ndarray, shape (N,) or None
        Factor on A's noise variance per pair (interpolation).
    velocity : ndarray, shape (N, 6)
        A's linear (m/s) and angular velocity (rad/s, A's base frame, left perturbation).

    """

    stamps: np.ndarray
    pos_a: np.ndarray
    quat_a: np.ndarray
    pos_b: np.ndarray
    quat_b: Optional[np.ndarray]
    a_var_scale: Optional[np.ndarray]
    velocity: np.ndarray

    def __len__(self) -> int:
        return int(self.stamps.shape[0])

    def take(self, index) -> PairBatch:
        """Return the pairs at ``index`` (a slice, mask or integer array)."""
        def sub(x):
            return None if x is None else x[index]
        return PairBatch(self.stamps[index], self.pos_a[index], self.quat_a[index],
                         self.pos_b[index], sub(self.quat_b), sub(self.a_var_scale),
                         self.velocity[index])

    @staticmethod
    def concatenate(batches) -> Optional[PairBatch]:
        """One batch from several (None when there is none)."""
        batches = [b for b in batches if b is not None and len(b)]
        if not batches:
            return None
        if len(batches) == 1:
            return batches[0]

        def cat(name):
            parts = [getattr(b, name) for b in batches]
            return None if any(p is None for p in parts) else np.concatenate(parts)
        return PairBatch(cat('stamps'), cat('pos_a'), cat('quat_a'), cat('pos_b'),
                         cat('quat_b'), cat('a_var_scale'), cat('velocity'))


def _pairs_arrays(pairs: Pairs) -> dict:
    return {'stamps': np.asarray(pairs.stamps, dtype=np.int64),
            'pos_a': np.asarray(pairs.pos_a, dtype=float),
            'quat_a': np.asarray(pairs.quat_a, dtype=float),
            'pos_b': np.asarray(pairs.pos_b, dtype=float),
            'quat_b': None if pairs.quat_b is None else np.asarray(pairs.quat_b, dtype=float),
            'a_var_scale': None if pairs.a_var_scale is None
            else np.asarray(pairs.a_var_scale, dtype=float)}


class PairFeed:
    """
    Turn pairs arriving in batches into ``PairBatch`` es with A's velocity.

    The velocity of a pair is the central difference of A's interpolated poses over
    ±``half`` s along the pair sequence (``Trajectory.velocity``, as the clock-offset estimate
    uses), so a pair is released once the pairs up to ``half`` after it have arrived. Pairs
    whose stamp is not after the last one seen are ignored, so the caller may re-pair an
    overlapping span of its buffers each time.

    Parameters
    ----------
    half : float
        Half-width of the difference window, s.
    max_gap : float, optional
        A window spanning a gap between pairs longer than this (s; at least 2.5 pair
        intervals), or reaching before the first pair, gives zero velocity
        (``Trajectory.velocity``): none is known across a tracking dropout. The settings'
        ``max_gap``, as the clock-offset estimate uses; None: differences across any gap.

    """

    def __init__(self, half: float = VELOCITY_HALF_WINDOW, max_gap: Optional[float] = None):
        self.half = float(half)
        self.max_gap = None if max_gap is None else float(max_gap)
        self._last_stamp: Optional[int] = None
        self._held: Optional[dict] = None  # released context + pending pairs
        self._n_context = 0  # leading pairs of _held already released
        self._origin: Optional[int] = None

    def push(self, pairs: Optional[Pairs], final: bool = False) -> Optional[PairBatch]:
        """
        Add pairs (B stamps increasing); return the pairs now released, or None.

        Parameters
        ----------
        pairs : Pairs or None
        final : bool
            Release everything held (end of the data, or before a gap).

        """
        if pairs is not None and len(pairs):
            new = _pairs_arrays(pairs)
            keep = np.ones(len(new['stamps']), dtype=bool)
            if self._last_stamp is not None:
                keep = new['stamps'] > self._last_stamp
            if keep.any():
                new = {k: None if v is None else v[keep] for k, v in new.items()}
                self._last_stamp = int(new['stamps'][-1])
                if self._origin is None:
                    self._origin = int(new['stamps'][0])
                self._held = new if self._held is None else {
                    k: None if v is None or new[k] is None else np.concatenate([v, new[k]])
                    for k, v in self._held.items()}
        held = self._held
        if held is None or len(held['stamps']) <= self._n_context:
            return None
        t = (held['stamps'] - np.int64(self._origin)).astype(float) * 1e-9
        if final:
            end = len(t)
        else:
            end = int(np.searchsorted(t, t[-1] - self.half, side='right'))
        if end <= self._n_context:
            return None
        release = slice(self._n_context, end)
        if len(t) > 1:
            traj = Trajectory(t, held['pos_a'], held['quat_a'])
            gap = None
            if self.max_gap is not None:
                gap = max(self.max_gap, 2.5 * float(np.median(np.diff(t))))
            v, w = traj.velocity(t[release], self.half, max_gap=gap)
        else:
            v = w = np.zeros((end - self._n_context, 3))
        out = PairBatch(held['stamps'][release], held['pos_a'][release], held['quat_a'][release],
                        held['pos_b'][release],
                        None if held['quat_b'] is None else held['quat_b'][release],
                        None if held['a_var_scale'] is None else held['a_var_scale'][release],
                        np.hstack([v, w]))
        if final:
            self._held, self._n_context = None, 0
        else:
            # keep the released pairs within 3 half-windows as context for later differences
            first = int(np.searchsorted(t, t[end - 1] - 3.0 * self.half, side='left'))
            first = min(first, end)
            self._held = {k: None if v_ is None else v_[first:] for k, v_ in held.items()}
            self._n_context = end - first
        return out


def batch_from_pairs(pairs: Pairs, half: float = VELOCITY_HALF_WINDOW,
                     max_gap: Optional[float] = None) -> PairBatch:
    """All of ``pairs`` with A's velocity (``PairFeed`` at once)."""
    out = PairFeed(half, max_gap).push(pairs, final=True)
    if out is None:
        raise InputError('no pairs')
    return out


# --------------------------------------------------------------------------- the estimate


@dataclass(frozen=True)
class Estimate:
    """
    The calibration the information is evaluated at.

    Attributes
    ----------
    model : str
    p0 : ndarray, shape (3,)
        T0 position (A's base in B's base), m.
    q0 : ndarray, shape (4,)
        T0 orientation (w, x, y, z).
    markers : ndarray, shape (k, 3)
        Marker position(s) in A's tool frame, m (k = 3 for three markers).
    q1 : ndarray, shape (4,)
        T1 orientation (w, x, y, z); the identity where the model does not estimate it.

    """

    model: str
    p0: np.ndarray
    q0: np.ndarray
    markers: np.ndarray
    q1: np.ndarray = field(default_factory=lambda: np.array([1.0, 0.0, 0.0, 0.0]))

    @classmethod
    def from_parameters(cls, params: Parameters) -> Estimate:
        """From the estimator's parameters."""
        return cls(params.spec.name, params.p0.copy(), quat.canonical(params.q0),
                   params.markers.copy(), quat.canonical(params.q1))

    @classmethod
    def from_result(cls, result: CalibrationResult) -> Estimate:
        """From a calibration result."""
        return cls(result.model, np.asarray(result.base_to_base.position, dtype=float),
                   np.asarray(result.base_to_base.quat_wxyz, dtype=float),
                   np.atleast_2d(np.asarray(result.markers, dtype=float)),
                   np.asarray(result.tool_to_marker.quat_wxyz, dtype=float))

    @classmethod
    def from_pairs(cls, model: str, pairs) -> Estimate:
        """
        Closed-form estimate from pairs (``initialize``: no guess needed).

        Parameters
        ----------
        model : str
        pairs : Pairs or PairBatch

        """
        spec = SPECS[model]
        params = initialize(spec, np.asarray(pairs.pos_a, dtype=float),
                            np.asarray(pairs.quat_a, dtype=float),
                            np.asarray(pairs.pos_b, dtype=float),
                            None if pairs.quat_b is None or not spec.has_q1
                            else np.asarray(pairs.quat_b, dtype=float))
        return cls.from_parameters(params)

    def moved_from(self, other: Estimate) -> bool:
        """Whether the Jacobians at ``self`` differ enough from those at ``other``."""
        angle = float(quat.angle_between(self.q0, other.q0))
        shift = float(np.max(np.linalg.norm(self.markers - other.markers, axis=1)))
        return angle > RELINEARISE_ROTATION or shift > RELINEARISE_MARKER


# --------------------------------------------------------------------------- information


def device_covariances(model: str, sigma_a, sigma_b) -> tuple[np.ndarray, np.ndarray]:
    """
    Noise covariances in the ``crlb`` tangents: A (6×6) and B's measurement (m×m).

    Parameters
    ----------
    model : str
    sigma_a, sigma_b : (float, float)
        Noise standard deviations (position m, rotation rad).

    """
    cov_a = noise_covariance(sigma_a)
    cov_b6 = noise_covariance(sigma_b)
    if model == 'full_pose':
        return cov_a, cov_b6
    k = 3 if model == 'three_marker' else 1
    return cov_a, np.kron(np.eye(k), cov_b6[0:3, 0:3])


def jacobians(estimate: Estimate, pos_a: np.ndarray, quat_a: np.ndarray,
              velocity: Optional[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """
    B's measurement Jacobians with respect to (ψ[, τ]) and to A's pose.

    Parameters
    ----------
    estimate : Estimate
    pos_a, quat_a : ndarray, shapes (n, 3), (n, 4)
        A's tool poses.
    velocity : ndarray, shape (n, 6), optional
        A's velocity; when given, the offset's column ``c = -F_x ẋ_A`` is appended (τ: B's
        clock minus A's; the measurement at B stamp t is A's pose at t - τ).

    Returns
    -------
    f : ndarray, shape (n, m, d) or (n, m, d + 1)
    f_x : ndarray, shape (n, m, 6)

    """
    f_psi, f_x = model_jacobians(estimate.model, estimate.p0, estimate.q0, estimate.markers,
                                 pos_a, quat_a)
    if velocity is None:
        return f_psi, f_x
    c = -np.einsum('nmk,nk->nm', f_x, velocity)
    return np.concatenate([f_psi, c[:, :, None]], axis=2), f_x


def effective_covariance(f_x: np.ndarray, cov_a: np.ndarray, cov_b: np.ndarray,
                         scale: Optional[np.ndarray], tls: bool) -> np.ndarray:
    """Σ_b + s F_x Σ_a F_xᵀ per pair, shape (n, m, m) (Σ_b alone, broadcast, without TLS)."""
    n = f_x.shape[0]
    if not tls:
        return np.broadcast_to(cov_b, (n,) + cov_b.shape)
    m = f_x @ cov_a @ np.swapaxes(f_x, 1, 2)
    if scale is not None:
        m = m * np.asarray(scale, dtype=float)[:, None, None]
    return m + cov_b


def information(estimate: Estimate, pos_a, quat_a, velocity, cov_a, cov_b,
                scale: Optional[np.ndarray] = None, tls: bool = True) -> np.ndarray:
    """
    Information of ψ (and τ when ``velocity`` is given) carried by pairs, (D, D).

    Parameters
    ----------
    estimate : Estimate
    pos_a, quat_a : ndarray, shapes (N, 3), (N, 4)
    velocity : ndarray, shape (N, 6) or None
    cov_a, cov_b : ndarray
        ``device_covariances``.
    scale : ndarray, shape (N,), optional
        ``a_var_scale``.
    tls : bool
        A's noise enters (errors in both devices); False: B's noise only (OLS).

    """
    d = CRLB_DIMENSION[estimate.model] + (0 if velocity is None else 1)
    out = np.zeros((d, d))
    n = len(pos_a)
    for start in range(0, n, CHUNK):
        sl = slice(start, min(n, start + CHUNK))
        f, f_x = jacobians(estimate, pos_a[sl], quat_a[sl],
                           None if velocity is None else velocity[sl])
        m = effective_covariance(f_x, cov_a, cov_b, None if scale is None else scale[sl], tls)
        out += np.einsum('nmi,nmj->ij', f, np.linalg.solve(m, f))
    return 0.5 * (out + out.T)


def _weak_prior(model: str, with_time: bool) -> np.ndarray:
    groups = GROUPS[model]
    diag = []
    for g in groups:
        s = WEAK_PRIOR[1] if is_rotation_group(g) else WEAK_PRIOR[0]
        diag += [s ** -2] * 3
    if with_time:
        diag.append(WEAK_PRIOR[2] ** -2)
    return np.diag(diag)


def sigma_groups(model: str, cov: np.ndarray, with_time: bool) -> dict:
    """
    σ per group from a covariance over (ψ[, τ]).

    Returns
    -------
    dict of str to ndarray
        Each group of ``GROUPS[model]`` → σ per axis, shape (3,) (m or rad); ``time_offset``
        → shape (1,) (s) when ``with_time``.

    """
    sd = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    out = {g: sd[3 * i:3 * i + 3].copy() for i, g in enumerate(GROUPS[model])}
    if with_time:
        out['time_offset'] = sd[-1:].copy()
    return out


# --------------------------------------------------------------------------- candidates


@dataclass(frozen=True)
class CandidateMotion:
    """
    A motion that could be added to the recording.

    Attributes
    ----------
    name : str
        ``rotate_x`` .. ``rotate_z`` (about the tool's own axis), ``move_x`` .. ``move_z``
        (along A's base axis) or ``hold_still``.
    description : str
        One line for a person.
    pos_a : ndarray, shape (n, 3)
    quat_a : ndarray, shape (n, 4)
    velocity : ndarray, shape (n, 6)
    n_pairs : int
        Pairs it adds at the current pair rate (each of the n samples stands for
        ``n_pairs / n`` of them).

    """

    name: str
    description: str
    pos_a: np.ndarray
    quat_a: np.ndarray
    velocity: np.ndarray
    n_pairs: int


def candidate_motions(position: np.ndarray, orientation: np.ndarray, rate: float,
                      seconds: float = CANDIDATE_SECONDS,
                      samples: int = CANDIDATE_SAMPLES) -> list:
    """
    Build the candidate additions, each from the tool's current pose.

    Parameters
    ----------
    position : ndarray, shape (3,)
        The tool's current position, A's base frame, m.
    orientation : ndarray, shape (4,)
        The tool's current orientation, (w, x, y, z).
    rate : float
        Pairs per second, Hz.
    seconds : float
        Time each candidate adds, s.
    samples : int
        Samples per candidate at which the information is evaluated.

    Returns
    -------
    list of CandidateMotion

    """
    n_pairs = max(1, int(round(rate * seconds)))
    n = max(8, min(samples, n_pairs))
    t = (np.arange(n) + 0.5) * (seconds / n)
    position = np.asarray(position, dtype=float)
    orientation = quat.canonical(np.asarray(orientation, dtype=float))
    out = []
    amp, freq = CANDIDATE_ROTATION
    phase = 2.0 * np.pi * freq * t
    for k, axis in enumerate(AXES):
        e = np.eye(3)[k]
        q = quat.multiply(np.broadcast_to(orientation, (n, 4)),
                          quat.exp(e[None, :] * (amp * np.sin(phase))[:, None]))
        # body rate about e, expressed in A's base frame (the left perturbation's axes)
        w_body = e[None, :] * (amp * 2.0 * np.pi * freq * np.cos(phase))[:, None]
        w = np.einsum('nij,nj->ni', quat.to_matrix(q), w_body)
        vel = np.hstack([np.zeros((n, 3)), w])
        out.append(CandidateMotion(
            f'rotate_{axis}', f'rotate the tool ±{np.degrees(amp):.0f}° about its own {axis} '
                              f'axis, back and forth, for {seconds:.0f} s',
            np.broadcast_to(position, (n, 3)).copy(), q, vel, n_pairs))
    amp, freq = CANDIDATE_TRANSLATION
    for k, axis in enumerate(AXES):
        e = np.eye(3)[k]
        p = position + e[None, :] * (amp * np.sin(phase))[:, None]
        v = e[None, :] * (amp * 2.0 * np.pi * freq * np.cos(phase))[:, None]
        out.append(CandidateMotion(
            f'move_{axis}', f"move the tool ±{amp * 100:.0f} cm along A's base {axis} axis, "
                            f'back and forth, for {seconds:.0f} s',
            p, np.broadcast_to(orientation, (n, 4)).copy(), np.hstack([v, np.zeros((n, 3))]),
            n_pairs))
    out.append(CandidateMotion(
        'hold_still', f'hold the tool still for {seconds:.0f} s (a pose free of the clock '
                      f'offset)', np.broadcast_to(position, (n, 3)).copy(),
        np.broadcast_to(orientation, (n, 4)).copy(), np.zeros((n, 6)), n_pairs))
    return out


# --------------------------------------------------------------------------- result


@dataclass(frozen=True)
class MotionOption:
    """
    A candidate motion and the worst σ / target it would leave.

    Attributes
    ----------
    name : str
    description : str
    worst_ratio : float
        Largest σ / target over the parameters after adding it.
    worst : str
        Which parameter that is (``p0 z``).

    """

    name: str
    description: str
    worst_ratio: float
    worst: str


@dataclass(frozen=True)
class Guidance:
    """
    How accurate a calibration of the pairs so far would be, and what to do next.

    Attributes
    ----------
    model : str
    n_pairs : int
    duration_s : float
        Time the pairs span, s.
    sigma : dict of str to ndarray
        σ per group and axis: ``p0`` (m, B's base axes), ``theta0`` (rad, B's base axes),
        ``p1`` (m, A's tool axes), ``theta1`` (rad, A's tool axes; full pose), ``p2``,
        ``p3`` (three markers); ``time_offset`` (s, shape (1,)) when τ is estimated. The
        covariance of T0/T1 is marginal over τ (as ``calibrate_streams`` reports it).
    covariance : ndarray, shape (D, D)
        Posterior covariance over (ψ[, τ]) in the ``crlb`` coordinates.
    targets : (float, float, float or None)
        Target σ of positions (m), rotations (rad) and the clock offset (s; None: no target).
    worst : str
        The parameter with the largest σ / target (``theta1 z``).
    worst_ratio : float
        Its σ / target (≤ 1 for every parameter means ready).
    ready : bool
        Every σ is within its target.
    determined : bool
        The motion determines every parameter: it rotates the tool about two axes at least
        (``observability.check_motion`` on the pairs so far) and no σ is near the weak
        prior's.
    reason : str
        Why not determined (empty when determined).
    options : tuple of MotionOption
        The candidate motions, best first.
    summary : str
        One line for a person.

    """

    model: str
    n_pairs: int
    duration_s: float
    sigma: dict
    covariance: np.ndarray
    targets: tuple
    worst: str
    worst_ratio: float
    ready: bool
    determined: bool
    options: tuple
    summary: str
    reason: str = ''

    @property
    def suggestion(self) -> Optional[MotionOption]:
        """The motion that would reduce the worst σ / target most (None when ready)."""
        return None if self.ready or not self.options else self.options[0]

    def diagnostic_values(self) -> list:
        """
        (key, value) string pairs for the guidance status of /diagnostics.

        σ values are three numbers ``x y z`` (one for the clock offset), in SI units, in the
        keys ``sigma <group>`` (``KEY_SIGMA_PREFIX``).
        """
        pos, rot, tim = self.targets
        out = [(KEY_PAIRS, str(self.n_pairs)), (KEY_DURATION, f'{self.duration_s:.3f}'),
               (KEY_READY, 'true' if self.ready else 'false'),
               (KEY_TARGET_POSITION, f'{pos:.6g}'), (KEY_TARGET_ROTATION, f'{rot:.6g}'),
               (KEY_TARGET_TIME, 'n/a' if tim is None else f'{tim:.6g}')]
        for name, sd in self.sigma.items():
            out.append((KEY_SIGMA_PREFIX + name, ' '.join(f'{v:.6g}' for v in sd)))
        out += [(KEY_WORST, self.worst), (KEY_WORST_RATIO, f'{self.worst_ratio:.4g}')]
        best = self.suggestion
        out += [(KEY_NEXT, 'none' if best is None else best.name),
                (KEY_NEXT_TEXT, 'ready: calibrate now' if best is None else best.description),
                (KEY_NEXT_RATIO, 'n/a' if best is None else f'{best.worst_ratio:.4g}'),
                (KEY_SUMMARY, self.summary)]
        return out


def _format_sigma(name: str, value: float) -> str:
    if name == 'time_offset':
        return f'{value * 1e3:.3g} ms'
    if is_rotation_group(name):
        return f'{np.degrees(value):.3g}°'
    return f'{value * 1e3:.3g} mm'


def _ratios(sigma: dict, targets: tuple) -> dict:
    pos, rot, tim = targets
    out = {}
    for name, sd in sigma.items():
        if name == 'time_offset':
            if tim is not None:
                out[name] = sd / tim
            continue
        out[name] = sd / (rot if is_rotation_group(name) else pos)
    return out


def _worst(ratios: dict) -> tuple[str, float]:
    name = max(ratios, key=lambda k: float(np.max(ratios[k])))
    axis = int(np.argmax(ratios[name]))
    label = name if name == 'time_offset' else f'{name} {AXES[axis]}'
    return label, float(ratios[name][axis])


# --------------------------------------------------------------------------- accumulator


class GuidanceAccumulator:
    """
    Incremental guidance from pairs as they arrive.

    Parameters
    ----------
    model : str
    sigma_a, sigma_b : (float, float)
        Device noise (position m, rotation rad), as the calibration states it.
    target_sigma_position : float
        Target σ of every position component, m.
    target_sigma_rotation : float
        Target σ of every rotation component, rad.
    target_sigma_time : float, optional
        Target σ of the clock offset, s (None: no target; τ still enters the marginals).
    estimate_time_offset : bool
        Whether the calibration estimates τ (adds τ's column: the marginals then carry its
        uncertainty).
    tls : bool
        Errors in both devices (the calibration's ``method == 'tls'``).

    Notes
    -----
    Call ``add(batch)`` with each new ``PairBatch`` and ``set_estimate`` when a better
    estimate exists (the first one may come from ``Estimate.from_pairs``); pairs added before
    any estimate are kept until one is set. ``guidance()`` then costs one D×D inverse per
    candidate.

    """

    def __init__(self, model: str, sigma_a, sigma_b, target_sigma_position: float,
                 target_sigma_rotation: float, target_sigma_time: Optional[float] = None,
                 estimate_time_offset: bool = True, tls: bool = True,
                 max_stored: int = MAX_STORED_PAIRS):
        if model not in MODELS:
            raise InputError(f'model {model!r} is unknown; use one of {", ".join(MODELS)}')
        if not (target_sigma_position > 0 and target_sigma_rotation > 0):
            raise InputError('target_sigma_position and target_sigma_rotation must be > 0')
        if target_sigma_time is not None and not target_sigma_time > 0:
            raise InputError('target_sigma_time must be > 0 (or None)')
        self.model = model
        self.cov_a, self.cov_b = device_covariances(model, sigma_a, sigma_b)
        self.sigma_rot_a = float(sigma_a[1])
        self.targets = (float(target_sigma_position), float(target_sigma_rotation),
                        None if target_sigma_time is None else float(target_sigma_time))
        self.with_time = bool(estimate_time_offset)
        self.tls = bool(tls)
        self.max_stored = int(max_stored)
        d = CRLB_DIMENSION[model] + (1 if self.with_time else 0)
        self.info = np.zeros((d, d))
        self.estimate: Optional[Estimate] = None
        self.n_pairs = 0
        self.first_stamp: Optional[int] = None
        self.last_stamp: Optional[int] = None
        self.last_pose: Optional[tuple] = None
        # evenly decimated store (every `_stride`-th pair) for re-linearising
        self._stride = 1
        self._seen = 0
        self._store: list = []
        self._n_store = 0
        # once the motion rotated about two axes, more pairs cannot undo it: checked until then
        self._motion_ok = False

    # -- input

    def add(self, batch: Optional[PairBatch]) -> None:
        """Add new pairs (their information at the current estimate, if any)."""
        if batch is None or not len(batch):
            return
        pos_a = np.asarray(batch.pos_a, dtype=float)
        quat_a = np.asarray(batch.quat_a, dtype=float)
        vel = np.asarray(batch.velocity, dtype=float)
        scale = None if batch.a_var_scale is None else np.asarray(batch.a_var_scale, float)
        if self.estimate is not None:
            self.info += information(self.estimate, pos_a, quat_a,
                                     vel if self.with_time else None, self.cov_a, self.cov_b,
                                     scale, self.tls)
        n = len(pos_a)
        self.n_pairs += n
        if self.first_stamp is None:
            self.first_stamp = int(batch.stamps[0])
        self.last_stamp = int(batch.stamps[-1])
        self.last_pose = (pos_a[-1].copy(), quat_a[-1].copy())
        self._keep(pos_a, quat_a, vel, np.ones(n) if scale is None else scale)

    def _keep(self, pos_a, quat_a, vel, scale) -> None:
        idx = np.arange(self._seen, self._seen + len(pos_a))
        take = idx % self._stride == 0
        self._seen += len(pos_a)
        if take.any():
            self._store.append(np.hstack([pos_a[take], quat_a[take], vel[take],
                                          scale[take, None]]))
            self._n_store += int(take.sum())
        while self._n_store > self.max_stored:
            # double the stride: keep every other stored pair (still evenly spread)
            stored = np.concatenate(self._store)
            self._store = [stored[::2]]
            self._n_store = len(self._store[0])
            self._stride *= 2

    def set_estimate(self, estimate: Estimate, force: bool = False) -> bool:
        """
        Evaluate the information at ``estimate`` from now on.

        Rebuilds the sum from the stored pairs when the Jacobians there differ enough from
        those at the current estimate (or ``force``); returns whether it rebuilt.
        """
        if estimate.model != self.model:
            raise InputError(f'estimate is for model {estimate.model}, guidance for '
                             f'{self.model}')
        if self.estimate is not None and not force and not estimate.moved_from(self.estimate):
            return False
        self.estimate = estimate
        self.info[:] = 0.0
        if self._n_store:
            s = np.concatenate(self._store)
            info = information(estimate, s[:, 0:3], s[:, 3:7],
                               s[:, 7:13] if self.with_time else None, self.cov_a, self.cov_b,
                               s[:, 13], self.tls)
            # the store is an even sample of the pairs: scale its sum up to all of them
            self.info = info * (self.n_pairs / self._n_store)
        return True

    # -- output

    def _covariance(self, info: np.ndarray) -> np.ndarray:
        return np.linalg.inv(info + _weak_prior(self.model, self.with_time))

    def rate(self) -> float:
        """Pairs per second so far (Hz; 0 before two pairs)."""
        if self.n_pairs < 2 or self.last_stamp == self.first_stamp:
            return 0.0
        return (self.n_pairs - 1) / ((self.last_stamp - self.first_stamp) * 1e-9)

    def guidance(self, rate: Optional[float] = None) -> Guidance:
        """
        Return the σ now, whether the targets are met, and the candidate motions ranked.

        Parameters
        ----------
        rate : float, optional
            Pairs per second the candidates add (default: the rate so far, else 100 Hz).

        Raises
        ------
        InputError
            Before any estimate was set.

        """
        if self.estimate is None:
            raise InputError('no estimate yet: set_estimate first (Estimate.from_pairs)')
        cov = self._covariance(self.info)
        sigma = sigma_groups(self.model, cov, self.with_time)
        ratios = _ratios(sigma, self.targets)
        worst, worst_ratio = _worst(ratios)
        ready = worst_ratio <= 1.0
        prior_sd = np.sqrt(np.diag(np.linalg.inv(_weak_prior(self.model, self.with_time))))
        determined = bool(np.all(np.sqrt(np.diag(cov)) < 0.1 * prior_sd))
        reason = '' if determined else 'some σ are still at the weak prior'
        if self._n_store and not self._motion_ok:
            try:
                # the store is an even sample of the motion: enough to judge its rotations
                check_motion(np.concatenate(self._store)[:, 3:7], SPECS[self.model],
                             self.sigma_rot_a)
                self._motion_ok = True
            except UnobservableError as e:
                determined, reason = False, str(e).split(':')[0]
        ready = ready and determined
        options = []
        if self.last_pose is not None:
            rate = rate or self.rate() or 100.0
            for cand in candidate_motions(*self.last_pose, rate):
                add = information(self.estimate, cand.pos_a, cand.quat_a,
                                  cand.velocity if self.with_time else None, self.cov_a,
                                  self.cov_b, None, self.tls)
                add *= cand.n_pairs / len(cand.pos_a)
                c_sigma = sigma_groups(self.model, self._covariance(self.info + add),
                                       self.with_time)
                c_worst, c_ratio = _worst(_ratios(c_sigma, self.targets))
                options.append(MotionOption(cand.name, cand.description, c_ratio, c_worst))
            options.sort(key=lambda o: o.worst_ratio)
        duration = 0.0 if self.first_stamp is None else (
            (self.last_stamp - self.first_stamp) * 1e-9)
        name = worst.split()[0]
        axis = worst.split()[1] if ' ' in worst else ''
        sd = sigma[name][AXES.index(axis) if axis else 0]
        target = (self.targets[2] if name == 'time_offset' else
                  self.targets[1] if is_rotation_group(name) else self.targets[0])
        what = f'{GROUP_TITLES[name]}{" " + axis if axis else ""}'
        if ready:
            summary = (f'ready: {self.n_pairs} pairs, every σ within target (worst {what} '
                       f'{_format_sigma(name, sd)} of {_format_sigma(name, target)})')
        else:
            head = 'collecting' if determined else f'collecting (not yet determined: {reason})'
            summary = (f'{head}: {self.n_pairs} pairs; worst {what} σ {_format_sigma(name, sd)}'
                       f' (target {_format_sigma(name, target)})')
            if options:
                summary += f'; next: {options[0].description}'
        return Guidance(self.model, self.n_pairs, duration, sigma, cov, self.targets, worst,
                        worst_ratio, ready, determined, tuple(options), summary, reason)

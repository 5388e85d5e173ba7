"""
Plan a calibration recording: predict its accuracy and which added motion would improve it most.

The prediction is the Cramér-Rao bound of the calibration in the errors-in-variables model
(``crlb.cramer_rao_bound``: the inverse Fisher information of ψ with A's true
poses as nuisance parameters, Ikits 2000 appendix B.2), evaluated at device A's tool motion and
a calibration (an estimate, or a random truth before any data exist). It is the covariance an
efficient estimator (TLS) reaches; it needs only the motion, not B's data.

Besides the σ of T0 = T_bbase_abase and T1 = T_atool_bmarker (ROS layout of docs/design.md §3), the
plan reports what the calibration is for: the RMS error, over the recorded workspace (the
poses of the given motion, for every candidate), of B's marker pose predicted from A through
the calibration (calibration error only; Hoff & Vincent eq. 6 with the CRLB as the parameter
covariance). Candidates are ranked by that position RMS.

PlannedAddition additions all add the same recording time, so they compare fairly:

- ``longer``: more of the same motion;
- ``rotate_weakest_axis``: the tool rotated back and forth about the axis of its frame about
  which the recorded motion rotates least (principal axes of the rotation vectors about the
  mean orientation);
- ``wider_translation``: the same motion with the position excursions doubled.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

from coreg_ros.core import quaternion as quat
from coreg_ros.core.calibration import observability
from coreg_ros.core.errors import InputError, UnobservableError
from coreg_ros.core.memory import check_memory
from coreg_ros.core.models import SPECS
from coreg_ros.core.planning.crlb import CRLB_DIMENSION, fisher_information, model_jacobians
from coreg_ros.core.types import MODELS
import numpy as np

#: Amplitude (rad) and frequency (Hz) of the added back-and-forth rotation about the weakest axis.
ADDED_ROTATION = (0.8, 0.1)
#: Factor on the position excursions of the ``wider_translation`` candidate.
WIDER_FACTOR = 2.0
#: Peak bytes of a plan per pair of its largest motion (the recording plus ``extra``):
#: measured 2.1-2.2 kB (``coreg plan --duration 1000``, 50 Hz, extra 0.1 to 2), rounded up.
BYTES_PER_PAIR = 2500


def check_plan_memory(n_pairs: float, extra: float, what: str, fix: str) -> None:
    """
    Refuse a plan whose motions would not fit in memory, before anything is simulated.

    Parameters
    ----------
    n_pairs : float
        Pairs of the recording (a float: ``duration × rate`` may be astronomically large).
    extra : float
        Time each candidate adds, as a fraction of the recording.
    what, fix : str
        The recording and the options to lower, for the message (``core.memory``).

    Raises
    ------
    InputError
        One line with the estimate and the limit.

    """
    check_memory(float(n_pairs) * (1.0 + float(extra)), BYTES_PER_PAIR, what, fix,
                 unit='pairs (with the candidates)')


@dataclass(frozen=True)
class AccuracyPrediction:
    """
    Predicted 1σ accuracy of a calibration (Cramér-Rao bound) for one motion.

    Attributes
    ----------
    model : str
    n_pairs : int
    duration : float
        Recording time the pairs span, s.
    crlb : ndarray, shape (d, d)
        Bound on the covariance of ψ (``crlb`` module table: δp0, δθ0, δp1, [δθ1 | δp2, δp3]).
    sigma : dict of str to ndarray, shape (3,)
        σ per axis: ``p0`` (m, B's base axes), ``theta0`` (rad, B's base axes), ``p1`` (m,
        A's tool axes), ``theta1`` (rad, A's tool axes; full_pose), ``p2``, ``p3``
        (three_marker).
    registration_rms : ndarray, shape (2,)
        RMS over the workspace (default: the motion) of the error of B's marker pose predicted
        from A through the calibration (calibration error only): position m, rotation rad
        (NaN unless full_pose).
    unobservable : tuple of (ndarray (12,), str, str)
        What the motion leaves undetermined (a restricted rig): each direction in the (T0, T1)
        layout, in words, and what would determine it. ``crlb`` and ``sigma`` are then those
        of the part it determines (the calibration holds the rest and says so).

    """

    model: str
    n_pairs: int
    duration: float
    crlb: np.ndarray
    sigma: dict
    registration_rms: np.ndarray
    unobservable: tuple = ()

    def worst(self) -> tuple[str, int, float]:
        """Return the position component with the largest σ: (name, axis 0-2, σ in m)."""
        names = [k for k in self.sigma if k.startswith('p')]
        name = max(names, key=lambda k: float(np.max(self.sigma[k])))
        axis = int(np.argmax(self.sigma[name]))
        return name, axis, float(self.sigma[name][axis])


@dataclass(frozen=True)
class PlannedAddition:
    """
    A candidate addition to the recording and its predicted accuracy.

    Attributes
    ----------
    name : str
        ``baseline``, ``longer``, ``rotate_weakest_axis`` or ``wider_translation``.
    description : str
        One line for a person.
    prediction : AccuracyPrediction or None
        None where the motion leaves the calibration unobservable.
    gain : float
        Baseline registration position RMS divided by this one's (> 1 is better; inf when
        the baseline is unobservable and this one is not; 0 when this one is unobservable).

    """

    name: str
    description: str
    prediction: Optional[AccuracyPrediction]
    gain: float


@dataclass(frozen=True)
class Plan:
    """
    Result of ``plan_recording``.

    Attributes
    ----------
    baseline : PlannedAddition
    candidates : tuple of PlannedAddition
        The additions, best first.
    weakest_axis : ndarray, shape (3,)
        Unit axis of A's tool frame about which the motion rotates least.
    rotation_spread : ndarray, shape (3,)
        RMS rotation (rad) about the principal axes of the motion, smallest first.

    """

    baseline: PlannedAddition
    candidates: tuple
    weakest_axis: np.ndarray
    rotation_spread: np.ndarray

    @property
    def best(self) -> PlannedAddition:
        """Return the candidate with the largest gain."""
        return self.candidates[0]


def _sigma_blocks(model: str, crlb: np.ndarray) -> dict:
    sd = np.sqrt(np.clip(np.diag(crlb), 0.0, None))
    names = {'full_pose': ('p0', 'theta0', 'p1', 'theta1'),
             'position_only': ('p0', 'theta0', 'p1'),
             'three_marker': ('p0', 'theta0', 'p1', 'p2', 'p3')}[model]
    return {n: sd[3 * i:3 * i + 3] for i, n in enumerate(names)}


def predict_accuracy(model: str, p0, q0, markers, pos_a, quat_a, cov_a, cov_b,
                     duration: Optional[float] = None, workspace=None) -> AccuracyPrediction:
    """
    Predict the 1σ accuracy of a calibration from A's motion alone (Cramér-Rao bound).

    Parameters
    ----------
    model : str
        ``full_pose``, ``position_only`` or ``three_marker``.
    p0 : array_like, shape (3,)
        T0 position (A's base in B's base), m.
    q0 : array_like, shape (4,)
        T0 orientation (w, x, y, z).
    markers : array_like, shape (k, 3)
        Marker position(s) in A's tool frame, m.
    pos_a : ndarray, shape (N, 3)
        A's tool positions at the pair instants, in A's base frame, m.
    quat_a : ndarray, shape (N, 4)
        A's tool orientations (w, x, y, z).
    cov_a, cov_b : ndarray, shape (6, 6)
        Device noise, ROS layout (m², rad²).
    duration : float, optional
        Time the pairs span, s (reported only).
    workspace : tuple of ndarray (positions (M, 3), quaternions (M, 4)), optional
        A's tool poses over which the registration error is averaged; default the motion
        itself. (Averaged over the very samples it was fitted to, the error hardly depends on
        the motion's geometry, only on the number of pairs; averaged over a fixed workspace it
        shows what a better motion buys.)

    Returns
    -------
    AccuracyPrediction

    Raises
    ------
    InputError
        If the motion determines nothing (the tool does not move).

    """
    if model not in MODELS:
        raise InputError(f'model {model!r} is unknown; use one of {", ".join(MODELS)}')
    pos_a = np.asarray(pos_a, dtype=float)
    quat_a = np.asarray(quat_a, dtype=float)
    if len(pos_a) * (6 if model == 'full_pose' else 3) < CRLB_DIMENSION[model]:
        raise InputError(f'{len(pos_a)} pairs cannot determine {CRLB_DIMENSION[model]} '
                         'parameters; record longer')
    cov_a6 = np.asarray(cov_a, dtype=float).reshape(6, 6)
    try:  # the calibration's own refusal: a tool that never moved determines nothing
        observability.refuse_if_nothing_moved(
            pos_a, quat_a, np.sqrt(np.max(np.diag(cov_a6).reshape(2, 3), axis=1)))
    except UnobservableError as e:
        raise InputError(str(e)) from e
    info = fisher_information(model, p0, q0, markers, pos_a, quat_a, cov_a, cov_b)
    # what the motion leaves undetermined (a restricted rig): the bound of the rest, as the
    # calibration holds those directions and determines the others
    found = observability.undetermined_in_tangent(info, None,
                                                  float(np.sqrt(cov_a6[3:6, 3:6].max())))
    held = found.held
    if held.shape[1]:
        proj = np.eye(len(info)) - held @ held.T
        crlb = np.linalg.pinv(proj @ info @ proj, rcond=1e-12, hermitian=True)
    else:
        crlb = np.linalg.inv(info)
    spec = SPECS[model]
    unobservable = []
    for k in range(held.shape[1]):
        u12, _ = observability.pose_layout(held[:, k], spec)
        u12 /= np.linalg.norm(u12) or 1.0
        unobservable.append((u12, *observability.describe_direction(u12)))
    ws_p, ws_q = (pos_a, quat_a) if workspace is None else workspace
    f_psi, _ = model_jacobians(model, p0, q0, markers, np.asarray(ws_p, dtype=float),
                               np.asarray(ws_q, dtype=float))
    # B's prediction error per pair from the calibration alone: F_ψ C F_ψᵀ (Hoff eq. 6)
    var = np.einsum('nmi,ij,nmj->nm', f_psi, crlb, f_psi)
    rms_pos = float(np.sqrt(np.mean(np.sum(var[:, 0:3], axis=1))))
    rms_rot = (float(np.sqrt(np.mean(np.sum(var[:, 3:6], axis=1)))) if model == 'full_pose'
               else float('nan'))
    return AccuracyPrediction(model=model, n_pairs=len(pos_a),
                              duration=float('nan') if duration is None else float(duration),
                              crlb=crlb, sigma=_sigma_blocks(model, crlb),
                              registration_rms=np.array([rms_pos, rms_rot]),
                              unobservable=tuple(unobservable))


def _resample(pos_a, quat_a, n: int):
    """First n samples of the motion repeated cyclically (more of the same motion)."""
    idx = np.arange(n) % len(pos_a)
    return pos_a[idx], quat_a[idx]


def planned_motions(pos_a, quat_a, rate: float, extra: float = 0.5) -> dict:
    """
    Build the candidate additions' motions: the recording plus ``extra`` of its length each.

    Parameters
    ----------
    pos_a : ndarray, shape (N, 3)
        A's tool positions at the pair instants (rate ``rate``), m.
    quat_a : ndarray, shape (N, 4)
        A's tool orientations.
    rate : float
        Pairs per second, Hz.
    extra : float
        Added recording time as a fraction of the recording (> 0).

    Returns
    -------
    dict of str to (description, pos (M, 3), quat (M, 4))
        Keys ``longer``, ``rotate_weakest_axis``, ``wider_translation``.

    """
    pos_a = np.asarray(pos_a, dtype=float)
    quat_a = np.asarray(quat_a, dtype=float)
    n_add = max(1, int(round(extra * len(pos_a))))
    seconds = n_add / rate
    add_p, add_q = _resample(pos_a, quat_a, n_add)
    weak = observability.rotation_spread(quat_a)[1][-1]  # rows, least excited last
    amp, freq = ADDED_ROTATION
    t = np.arange(n_add) / rate
    wobble = quat.exp(weak[None, :] * (amp * np.sin(2.0 * np.pi * freq * t))[:, None])
    centre = np.mean(pos_a, axis=0)
    axis_txt = f'[{weak[0]:+.2f} {weak[1]:+.2f} {weak[2]:+.2f}]'
    return {
        'longer': (f'record {seconds:.0f} s more of the same motion',
                   np.concatenate([pos_a, add_p]), np.concatenate([quat_a, add_q])),
        'rotate_weakest_axis': (
            f'add {seconds:.0f} s rotating the tool ±{np.degrees(amp):.0f}° about its least '
            f'excited axis {axis_txt} (tool frame)',
            np.concatenate([pos_a, add_p]),
            np.concatenate([quat_a, quat.multiply(add_q, wobble)])),
        'wider_translation': (
            f'add {seconds:.0f} s of the same motion with {WIDER_FACTOR:g}× wider translation',
            np.concatenate([pos_a, centre + WIDER_FACTOR * (add_p - centre)]),
            np.concatenate([quat_a, add_q])),
    }


def plan_recording(model: str, p0, q0, markers, pos_a, quat_a, cov_a, cov_b, rate: float,
                   extra: float = 0.5) -> Plan:
    """
    Predict a recording's calibration accuracy and rank additions to its motion.

    Parameters
    ----------
    model : str
        Measurement model name.
    p0, q0, markers :
        The calibration the bound is evaluated at (an estimate, or a random truth).
    pos_a, quat_a : ndarray, shapes (N, 3), (N, 4)
        A's tool poses at the pair instants, A's base frame.
    cov_a, cov_b : ndarray, shape (6, 6)
        Device noise, ROS layout.
    rate : float
        Pairs per second (B's rate), Hz.
    extra : float
        Time each candidate adds, as a fraction of the recording.

    Returns
    -------
    Plan

    """
    if not (extra > 0 and rate > 0):
        raise InputError('rate and extra must be positive')
    n = len(pos_a)
    check_plan_memory(n, extra, f'a plan of {n} pairs with candidates {extra:g} longer',
                      '--extra or the recording')

    def predict(p, q):
        try:
            return predict_accuracy(model, p0, q0, markers, p, q, cov_a, cov_b, len(p) / rate,
                                    workspace=(pos_a, quat_a))
        except InputError:
            return None

    base = predict(pos_a, quat_a)
    baseline = PlannedAddition('baseline', f'the motion as given ({n / rate:.0f} s, {n} pairs)',
                               base, 1.0 if base is not None else 0.0)
    out = []
    for name, (text, p, q) in planned_motions(pos_a, quat_a, rate, extra).items():
        pred = predict(p, q)
        if pred is None:
            gain = 0.0
        elif base is None:
            gain = float('inf')
        else:
            gain = float(base.registration_rms[0] / pred.registration_rms[0])
        out.append(PlannedAddition(name, text, pred, gain))
    out.sort(key=lambda c: (-c.gain, np.inf if c.prediction is None
                            else c.prediction.registration_rms[0]))
    spread, axes = observability.rotation_spread(np.asarray(quat_a, dtype=float))
    return Plan(baseline=baseline, candidates=tuple(out), weakest_axis=axes[-1],
                rotation_spread=spread[::-1].copy())

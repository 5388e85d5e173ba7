"""The guidance result and its incremental accumulator (what the node updates at 1 Hz)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

from coreg_ros.core.calibration import observability
from coreg_ros.core.calibration.observability import (
    refuse_if_nothing_moved,
    undetermined_in_tangent,
)
from coreg_ros.core.errors import InputError, UnobservableError
from coreg_ros.core.live.guidance.feed import PairBatch
from coreg_ros.core.live.guidance.fisher import (
    _weak_prior,
    device_covariances,
    Estimate,
    information,
    sigma_groups,
)
from coreg_ros.core.live.guidance.keys import (
    AXES,
    GROUP_TITLES,
    is_rotation_group,
    KEY_DURATION,
    KEY_NEXT,
    KEY_NEXT_RATIO,
    KEY_NEXT_TEXT,
    KEY_PAIRS,
    KEY_READY,
    KEY_SIGMA_PREFIX,
    KEY_SUMMARY,
    KEY_TARGET_POSITION,
    KEY_TARGET_ROTATION,
    KEY_TARGET_TIME,
    KEY_WORST,
    KEY_WORST_RATIO,
)
from coreg_ros.core.live.guidance.motions import candidate_motions
from coreg_ros.core.models import SPECS
from coreg_ros.core.noise_model import largest_sigmas
from coreg_ros.core.planning.crlb import CRLB_DIMENSION
from coreg_ros.core.types import MODELS
import numpy as np

#: Pairs kept for re-linearising (evenly decimated beyond this).
MAX_STORED_PAIRS = 50_000
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
        The motion determines every parameter the rig can determine: nothing is left
        undetermined by the pairs so far (``observability.undetermined_in_tangent``), or,
        for a rig that cannot move in every direction, only what it cannot show (``held``),
        and no σ is near the weak prior's.
    reason : str
        Why not determined (empty when determined).
    held : tuple of str
        What a restricted rig cannot determine (``motion_limits``), in words: left out of
        the σ, the targets and the suggestions.
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
    held: tuple = ()

    @property
    def suggestion(self) -> Optional[MotionOption]:
        """Return the motion that would reduce the worst σ / target most (None when ready)."""
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


#: What a rig can do (``GuidanceAccumulator.motion_limits``).
MOTION_LIMITS = ('free', 'auto', 'restricted')
#: With ``motion_limits='auto'``, a direction still undetermined after this much recording (s)
#: is taken as one the rig cannot show.
AUTO_RESTRICTED_S = 60.0
#: A candidate motion whose information along a held direction exceeds this share of the
#: largest (unit-diagonal scale, as ``observability``) would determine it: the rig cannot
#: make it.
CANNOT_MAKE_SHARE = 10.0 * observability.WEAK_SHARE

# --------------------------------------------------------------------------- accumulator


class GuidanceAccumulator:
    """
    Incremental guidance from pairs as they arrive.

    Parameters
    ----------
    model : str
    sigma_a, sigma_b : (float, float) or DeviceNoise
        Device noise (position m, rotation rad, or full covariances in each device's base
        frame), as the calibration states it.
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
    motion_limits : {'free', 'auto', 'restricted'}
        What the rig can do. ``'free'`` (the default): it can move and turn in every
        direction, so a direction the pairs leave undetermined is motion still to make (not
        ready; the suggestions ask for it). ``'restricted'`` (a SCARA arm, a mobile robot, a
        gantry, a turntable): the motions it has shown are all it can do; what they leave
        undetermined is held, as the calibration holds it, ready means the rest meets the
        targets, and a motion that would determine a held direction (one the rig cannot
        make) is never suggested. ``'auto'``: free until ``AUTO_RESTRICTED_S`` of recording
        has left a direction undetermined, then restricted.

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
                 max_stored: int = MAX_STORED_PAIRS, motion_limits: str = 'free'):
        if model not in MODELS:
            raise InputError(f'model {model!r} is unknown; use one of {", ".join(MODELS)}')
        if motion_limits not in MOTION_LIMITS:
            raise InputError(f'motion_limits {motion_limits!r} is unknown; use one of '
                             f'{", ".join(MOTION_LIMITS)}')
        self.motion_limits = motion_limits
        if not (target_sigma_position > 0 and target_sigma_rotation > 0):
            raise InputError('target_sigma_position and target_sigma_rotation must be > 0')
        if target_sigma_time is not None and not target_sigma_time > 0:
            raise InputError('target_sigma_time must be > 0 (or None)')
        self.model = model
        self.cov_a, self.cov_b = device_covariances(model, sigma_a, sigma_b)
        self.sigma_pos_a, self.sigma_rot_a = largest_sigmas(sigma_a)
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

    def _covariance(self, info: np.ndarray, held: Optional[np.ndarray] = None) -> np.ndarray:
        """(info + weak prior)⁻¹; with ``held`` directions (ψ, D×k) projected out of it."""
        cov = np.linalg.inv(info + _weak_prior(self.model, self.with_time))
        if held is None or not held.shape[1]:
            return cov
        proj = np.eye(len(cov))
        proj[:len(held), :len(held)] -= held @ held.T
        return proj @ cov @ proj

    def _undetermined(self, duration: float):
        """Find what the pairs so far leave undetermined; tell whether the rig is restricted."""
        D = CRLB_DIMENSION[self.model]
        found = undetermined_in_tangent(self.info[:D, :D], None, self.sigma_rot_a)
        restricted = not found.empty and (
            self.motion_limits == 'restricted'
            or (self.motion_limits == 'auto' and duration >= AUTO_RESTRICTED_S))
        return found, restricted

    def _cannot_make(self, add: np.ndarray, found) -> bool:
        """Whether a candidate's information ``add`` would determine a held direction."""
        D = CRLB_DIMENSION[self.model]
        scale = np.where(found.scale > 0, found.scale, 1.0)
        v = found.held * scale[:, None]
        v /= np.linalg.norm(v, axis=0)
        along = v.T @ (add[:D, :D] / np.outer(scale, scale)) @ v
        top = np.linalg.eigvalsh(self.info[:D, :D] / np.outer(scale, scale))[-1]
        return bool(np.linalg.eigvalsh(along)[-1] > CANNOT_MAKE_SHARE * top)

    def _words(self, u: np.ndarray) -> str:
        """Say a ψ direction in words (``observability.describe_direction``)."""
        u12, _ = observability.pose_layout(u, SPECS[self.model])
        return observability.describe_direction(u12 / (np.linalg.norm(u12) or 1.0))[0]

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
        duration = 0.0 if self.first_stamp is None else (
            (self.last_stamp - self.first_stamp) * 1e-9)
        found, restricted = self._undetermined(duration)
        held = found.held if restricted else None
        cov = self._covariance(self.info, held)
        sigma = sigma_groups(self.model, cov, self.with_time)
        ratios = _ratios(sigma, self.targets)
        worst, worst_ratio = _worst(ratios)
        ready = worst_ratio <= 1.0
        prior_sd = np.sqrt(np.diag(np.linalg.inv(_weak_prior(self.model, self.with_time))))
        sd = np.sqrt(np.diag(cov))
        determined = bool(np.all((sd < 0.1 * prior_sd) | (sd == 0.0)))
        reason = '' if determined else 'some σ are still at the weak prior'
        if not found.empty and not restricted:
            determined = False
            reason = f'{self._words(found.held[:, 0])} (the motion so far cannot show it)'
        if self._n_store and not self._motion_ok:
            try:
                # the store is an even sample of the motion: enough to judge whether it moved
                stored = np.concatenate(self._store)
                refuse_if_nothing_moved(stored[:, 0:3], stored[:, 3:7],
                                        (self.sigma_pos_a, self.sigma_rot_a))
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
                if restricted and self._cannot_make(add, found):
                    continue  # a motion the rig cannot make: it would determine a held one
                c_sigma = sigma_groups(self.model, self._covariance(self.info + add, held),
                                       self.with_time)
                c_worst, c_ratio = _worst(_ratios(c_sigma, self.targets))
                options.append(MotionOption(cand.name, cand.description, c_ratio, c_worst))
            options.sort(key=lambda o: o.worst_ratio)
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
        words = tuple(self._words(found.held[:, k]) for k in range(found.held.shape[1])
                      ) if restricted else ()
        if words:
            summary += f'; held (the rig cannot show it): {"; ".join(words)}'
        return Guidance(self.model, self.n_pairs, duration, sigma, cov, self.targets, worst,
                        worst_ratio, ready, determined, tuple(options), summary, reason, words)

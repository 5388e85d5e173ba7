"""
A device's noise measured where it stands still: 3×3 covariances, their uncertainty, Allan.

``measure_device`` takes one device's stream and its still segments (``still``, or a window
given by the user) and measures, per channel (position m, rotation rad, both about the
device's base axes, the rotation as ``δθ`` with ``R = Exp(δθ) · R̄``, ``R̄`` the segment's
mean orientation):

- the covariance, pooled within blocks as long as the Allan deviation says one may average
  (``allan.AllanCurve.tau_limit``; the whole segment when no drift shows), so that a slow
  random walk or drift of a still device does not pass for noise;
- its standard error by batch means (batches of ``SE_BATCH`` samples at least: correlated noise
  widens it as it should), hence the effective number of samples and the uncertainty of the
  per-axis σ, of the principal σ and of the principal axes' directions (the eigenvector
  perturbation of a sample covariance, ``σ²(angle_jk) = λ_j λ_k / (n (λ_j - λ_k)²)``);
- the Allan deviation (``allan``), and how the noise grows with the distance from the base's
  origin when the segments lie at several (``distance``);
- the sampling within the segments: effective rate, dropped, repeated stamps and samples; a
  segment of identical samples (a frozen stream) is set apart and not measured.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional

from coreg_ros.core import quaternion as quat
from coreg_ros.core.errors import InputError
from coreg_ros.core.noise.allan import allan_curve, AllanCurve
from coreg_ros.core.noise.distance import distance_law, DistanceLaw
from coreg_ros.core.noise.still import FROZEN_SHARE, MIN_STILL_S, repeated_share
from coreg_ros.core.noise_model import checked_covariance, DeviceNoise, principal_axes
from coreg_ros.core.types import PoseStream
import numpy as np

#: Fewest samples of a batch for the standard errors and of a block for the covariance.
SE_BATCH = 10
MIN_BLOCK = 20
#: Fewest batches for a batch-means standard error (else the white-noise value).
MIN_BATCHES = 8
#: Precision of σ a recording is asked to reach when none is stated (relative, 1σ).
DEFAULT_PRECISION = 0.05


@dataclass(frozen=True)
class ChannelNoise:
    """
    One channel's measured noise (position m or rotation rad) about the device's base axes.

    Attributes
    ----------
    name : {'position', 'rotation'}
    covariance, covariance_se : ndarray, shape (3, 3)
        The covariance (m² or rad²) and the standard error of each entry.
    sigma_axes, sigma_axes_se : ndarray, shape (3,)
        σ along the base axes x, y, z, and its standard error.
    principal_sigma, principal_sigma_se : ndarray, shape (3,)
        Principal σ, largest first, and its standard error.
    principal_axes : ndarray, shape (3, 3)
        Their unit axes as rows, in the base frame.
    axis_angle_se : ndarray, shape (3,)
        Standard error of each axis' direction, rad (large when two σ are nearly equal: the
        axes are then not defined).
    n_effective : float
        Independent samples the covariance is worth (batch means).
    allan : AllanCurve
    distance : DistanceLaw or None
        σ against the distance from the base's origin (None: the segments do not span
        distances).

    """

    name: str
    covariance: np.ndarray
    covariance_se: np.ndarray
    sigma_axes: np.ndarray
    sigma_axes_se: np.ndarray
    principal_sigma: np.ndarray
    principal_sigma_se: np.ndarray
    principal_axes: np.ndarray
    axis_angle_se: np.ndarray
    n_effective: float
    allan: AllanCurve
    distance: Optional[DistanceLaw] = None

    def as_dict(self) -> dict:
        """JSON form (m, m², rad, rad²; axes as rows in the base frame)."""
        unit = 'm' if self.name == 'position' else 'rad'
        return {'covariance': self.covariance.tolist(),
                'covariance_se': self.covariance_se.tolist(),
                f'sigma_axes_{unit}': self.sigma_axes.tolist(),
                'sigma_axes_se': self.sigma_axes_se.tolist(),
                f'sigma_{unit}': self.principal_sigma.tolist(),
                'sigma_se': self.principal_sigma_se.tolist(),
                'principal_axes': self.principal_axes.tolist(),
                'axis_angle_se_rad': self.axis_angle_se.tolist(),
                'n_effective': self.n_effective, 'allan': self.allan.as_dict(),
                'distance': None if self.distance is None else self.distance.as_dict()}


@dataclass(frozen=True)
class Sampling:
    """
    The sampling within the still segments.

    Attributes
    ----------
    rate_hz : float
        Effective rate: samples per second of still time.
    nominal_hz : float
        1 / the median interval.
    n_samples : int
    duration_s : float
    dropped : int
        Samples missing at the nominal rate (gaps longer than 1.5 intervals).
    repeated_stamps : int
        Samples stamped as their predecessor.
    repeated_samples : int
        Samples identical to their predecessor (pose bit for bit).

    """

    rate_hz: float
    nominal_hz: float
    n_samples: int
    duration_s: float
    dropped: int
    repeated_stamps: int
    repeated_samples: int


@dataclass(frozen=True)
class DeviceMeasurement:
    """
    A device's noise measured in its still segments.

    Attributes
    ----------
    device : {'a', 'b'}
    topic, frame_id : str
    segments : list of Segment
        The still segments measured.
    frozen : list of Segment
        Still segments set apart: identical samples (a frozen stream).
    channels : dict of str to ChannelNoise
        ``position`` and, where the device reports a meaningful orientation, ``rotation``.
    sampling : Sampling
    origin_ns : int
        The stamp the segments' times are given from.

    """

    device: str
    topic: str
    frame_id: str
    segments: list
    frozen: list
    channels: dict
    sampling: Sampling
    origin_ns: int = 0
    warnings: list = field(default_factory=list)

    def device_noise(self, fallback) -> DeviceNoise:
        """Return the measured noise; a channel not measured from ``fallback`` (DeviceNoise)."""
        pos = self.channels['position'].covariance if 'position' in self.channels \
            else fallback.position_cov
        rot = self.channels['rotation'].covariance if 'rotation' in self.channels \
            else fallback.rotation_cov
        return DeviceNoise.from_covariances(pos, rot, self.device.upper())

    def segment_times(self, which: Optional[list] = None) -> list:
        """(start s, end s, samples) of the segments, from ``origin_ns``."""
        return [((s.t0_ns - self.origin_ns) * 1e-9, (s.t1_ns - self.origin_ns) * 1e-9, s.n)
                for s in (self.segments if which is None else which)]


def rotation_deviations(quat_wxyz: np.ndarray) -> np.ndarray:
    """
    Rotation vectors ``δθ`` (N, 3) of ``q = Exp(δθ) ⊗ q̄`` about the chordal mean ``q̄``.

    About the fixed axes of the device's base frame (the estimator's convention).
    """
    q = np.asarray(quat_wxyz, dtype=float)
    mean = quat.chordal_mean(q)
    return quat.log(quat.multiply(q, quat.conjugate(mean)[None, :]))


def _blocks(n: int, length: int) -> list:
    """Slices of about ``length`` covering n samples (the remainder joins the last)."""
    k = max(1, n // max(1, length))
    edges = np.linspace(0, n, k + 1).round().astype(int)
    return [slice(a, b) for a, b in zip(edges[:-1], edges[1:], strict=True)]


def pooled_covariance(x: np.ndarray, block: int) -> tuple[np.ndarray, int]:
    """
    Return one segment's covariance pooled within blocks of ``block`` samples.

    Each block about its own mean; returns the covariance and its degrees of freedom (samples
    less blocks).
    """
    scatter, dof = np.zeros((3, 3)), 0
    for sl in _blocks(len(x), block):
        d = x[sl] - x[sl].mean(axis=0)
        scatter += d.T @ d
        dof += len(d) - 1
    return scatter / max(dof, 1), dof


def _batch_se(x: np.ndarray, cov: np.ndarray, dof: int, batch: int) -> np.ndarray:
    """
    Return the standard error of a segment's covariance entries, by batch means of ``batch``.

    With fewer than ``MIN_BATCHES`` batches, the white-noise (Wishart) value
    ``√((Σ_ii Σ_jj + Σ_ij²) / dof)``.
    """
    covs = []
    for sl in _blocks(len(x), batch):
        d = x[sl] - x[sl].mean(axis=0)
        if len(d) >= 2:
            covs.append(d.T @ d / (len(d) - 1))
    if len(covs) < MIN_BATCHES:
        v = np.diag(cov)
        return np.sqrt((np.outer(v, v) + cov ** 2) / max(dof, 1))
    covs = np.array(covs)
    return covs.std(axis=0, ddof=1) / np.sqrt(len(covs))


def _effective_samples(cov: np.ndarray, se: np.ndarray, most: float) -> float:
    """Return the samples a white noise needs for these standard errors (at most ``most``)."""
    v = np.diag(cov)
    n = float(np.mean(2.0 * v ** 2 / np.maximum(np.diag(se) ** 2, 1e-300)))
    return min(n, float(most)) if np.isfinite(n) and n > 0 else float(most)


def channel_noise(name: str, parts: list, tau0: float,
                  distances: Optional[np.ndarray] = None) -> ChannelNoise:
    """
    Measure one channel from its samples in each still segment.

    Parameters
    ----------
    name : {'position', 'rotation'}
        The channel.
    parts : list of ndarray, each shape (N_k, 3)
        The channel's samples per segment (positions m, or rotation deviations rad).
    tau0 : float
        The sample interval, s.
    distances : ndarray, shape (K,), optional
        Each segment's distance from the base's origin, m (the distance law).

    """
    curve = allan_curve(parts, tau0)
    total = sum(len(x) for x in parts)
    block = total if not np.isfinite(curve.tau_limit) else max(
        MIN_BLOCK, int(round(curve.tau_limit / tau0)))
    per = [pooled_covariance(x, block) for x in parts]
    dofs = np.array([d for _, d in per], dtype=float)
    w = dofs / max(dofs.sum(), 1.0)
    cov = sum(wk * c for wk, (c, _) in zip(w, per, strict=True))
    batch = max(SE_BATCH, min(block, total // 30))
    ses = [_batch_se(x, c, d, batch) for x, (c, d) in zip(parts, per, strict=True)]
    se = np.sqrt(sum((wk * sk) ** 2 for wk, sk in zip(w, ses, strict=True)))
    n_eff = _effective_samples(cov, se, total)
    sig, axes = principal_axes(cov)
    lam = sig ** 2
    angle_se = np.zeros(3)
    for j in range(3):
        gaps = [(lam[j] - lam[k]) ** 2 for k in range(3) if k != j]
        others = [lam[k] for k in range(3) if k != j]
        acc = sum(lam[j] * o / (n_eff * g) if g > 0 else np.inf
                  for o, g in zip(others, gaps, strict=True))
        angle_se[j] = min(np.sqrt(acc), np.pi / 2)
    sd = np.sqrt(np.maximum(np.diag(cov), 0.0))
    law = None
    if distances is not None and len(parts) >= 2:
        law = distance_law(distances, np.array([np.sqrt(np.trace(c) / 3.0) for c, _ in per]),
                           np.array([3.0 * _effective_samples(c, s, len(x)) for x, (c, _), s
                                     in zip(parts, per, ses, strict=True)]))
    return ChannelNoise(name, cov, se, sd, np.diag(se) / np.maximum(2.0 * sd, 1e-300),
                        sig, sig / np.sqrt(2.0 * n_eff), axes, angle_se, n_eff, curve, law)


def sampling_of(stream: PoseStream, segments: list, rotation: bool) -> Sampling:
    """Return the sampling within ``segments`` (rate, drops, repeats)."""
    dts, n, span, rep_stamps, rep_samples = [], 0, 0.0, 0, 0
    for s in segments:
        st = stream.stamps[s.start:s.stop]
        dts.append(np.diff(st))
        n += s.n
        span += s.duration
        rep_stamps += int(np.sum(np.diff(st) == 0))
        q = stream.quat_wxyz[s.start:s.stop] if rotation else None
        rep_samples += int(round(repeated_share(stream.position[s.start:s.stop], q)
                                 * max(s.n - 1, 0)))
    dt = np.concatenate(dts) if dts else np.zeros(0, dtype=np.int64)
    step = float(np.median(dt[dt > 0])) if np.any(dt > 0) else float('nan')
    gaps = dt[dt > 1.5 * step] if np.isfinite(step) else dt[:0]
    dropped = int(np.sum(np.round(gaps / step) - 1)) if len(gaps) else 0
    return Sampling(rate_hz=(n - len(segments)) / span if span > 0 else float('nan'),
                    nominal_hz=1e9 / step if np.isfinite(step) else float('nan'),
                    n_samples=n, duration_s=span, dropped=dropped,
                    repeated_stamps=rep_stamps, repeated_samples=rep_samples)


def needed_still_seconds(rate_hz: float, precision: float = DEFAULT_PRECISION) -> float:
    """
    Still time for σ within ``precision`` (relative, 1σ) at ``rate_hz``, white noise, s.

    ``σ(σ̂)/σ = 1/√(2n)`` needs ``n = 1/(2 p²)`` samples; never less than ``MIN_STILL_S``
    (the still test's own windows and the Allan deviation need it).
    """
    n = 1.0 / (2.0 * precision ** 2)
    return max(MIN_STILL_S, n / max(rate_hz, 1e-9))


def measure_device(stream: PoseStream, segments: list, device: str, topic: str = '',
                   rotation: bool = True, origin_ns: Optional[int] = None,
                   precision: float = DEFAULT_PRECISION, longest: float = 0.0
                   ) -> DeviceMeasurement:
    """
    Measure a device's noise in its still segments.

    Parameters
    ----------
    stream : PoseStream
        The device's samples (pose in its base frame).
    segments : list of Segment
        Its still segments (``still.segments_of`` or a given window).
    device : {'a', 'b'}
        Which device it is.
    topic : str
        For the messages and the report.
    rotation : bool
        Measure the rotation too (False for a position-only tracker).
    origin_ns : int, optional
        Stamp the segments' times are given from (default the stream's first).
    precision : float
        The relative precision of σ a refusal asks to record for.
    longest : float
        The longest still stretch found, s (what a refusal says).

    Raises
    ------
    InputError
        No still segment, or only frozen ones: one line with the still time needed.

    """
    name = f'device {device.upper()} ({topic})' if topic else f'device {device.upper()}'
    origin = int(stream.stamps[0]) if origin_ns is None else int(origin_ns)
    step = float(np.median(np.diff(stream.stamps))) * 1e-9 if len(stream) > 1 else 0.0
    rate = 1.0 / step if step > 0 else float('nan')
    need = needed_still_seconds(rate, precision)
    if not segments:
        raise InputError(
            f'{name}: no still segment of at least {MIN_STILL_S:g} s (the longest still stretch '
            f'is {longest:.1f} s); hold the device still for at least {need:.0f} s (σ within '
            f'{precision:.0%} at {rate:.0f} Hz), or give --window T0 T1 of a still part')
    used, frozen = [], []
    for s in segments:
        q = stream.quat_wxyz[s.start:s.stop] if rotation else None
        share = repeated_share(stream.position[s.start:s.stop], q)
        (frozen if share > FROZEN_SHARE else used).append(s)
    warnings = [f'{name}: the still part {(s.t0_ns - origin) * 1e-9:.1f}-'
                f'{(s.t1_ns - origin) * 1e-9:.1f} s is a frozen stream ({s.n} samples, mostly '
                f'identical): the device repeats a pose (lost tracking?); not measured there'
                for s in frozen]
    if not used:
        raise InputError(
            f'{name}: every still part is a frozen stream (identical samples): the device '
            f'repeats its last pose instead of measuring; its noise cannot be measured from '
            f'it (check its tracking), or give --window T0 T1 of a still part it measured')
    parts_p = [np.asarray(stream.position[s.start:s.stop], dtype=float) for s in used]
    distances = np.array([float(np.linalg.norm(p.mean(axis=0))) for p in parts_p])
    channels = {'position': channel_noise('position', parts_p, step, distances)}
    if rotation:
        parts_r = [rotation_deviations(stream.quat_wxyz[s.start:s.stop]) for s in used]
        channels['rotation'] = channel_noise('rotation', parts_r, step, distances)
    for ch in channels.values():
        try:  # a singular covariance (a stream quantised coarser than its noise), mm for m
            checked_covariance(ch.covariance, f'{name} {ch.name}', ch.name)
        except ValueError as e:
            raise InputError(f'{e} (as measured in the still parts)') from e
    return DeviceMeasurement(device, topic, stream.frame_id, used, frozen, channels,
                             sampling_of(stream, used, rotation), origin, warnings)

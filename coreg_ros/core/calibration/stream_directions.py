"""
Which way round are the streams? Detect a device that reports the inverse transform.

Exported pose streams rarely say whether a row is the tracked frame in the base frame
(``T_base_tool``) or the base in the tracked frame (``T_tool_base``). The model
``T_B = T0 · T_A · T1`` (docs/design.md §1) only fits one way: a stream given the other way round
must be inverted (``T → T⁻¹``) first. ``check_directions`` fits every combination with OLS on
a subsample and says which fits best, and by how much.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Optional, Union

from coreg_ros.core import quaternion as quat
from coreg_ros.core.calibration.calibrate import calibrate
from coreg_ros.core.calibration.pairing import pair_for, validated_streams
from coreg_ros.core.clock.coarse import coarse_offsets
from coreg_ros.core.errors import CoregError
from coreg_ros.core.settings import Settings
from coreg_ros.core.so3 import invert_poses
from coreg_ros.core.types import Pairs, PoseStream, TimeOffset
import numpy as np

#: Largest number of pairs each trial fit uses (evenly spread over the recording).
MAX_PAIRS = 3000
#: Iteration limit of each trial fit: a right combination converges in a few iterations, a
#: wrong one is far off either way (its chi2 is then an upper bound, which only widens the gap).
MAX_ITERATIONS = 20
#: Offsets of the coarse search tried with every direction.
OFFSET_CANDIDATES = 3
#: A combination must fit this many times better (chi2/dof) than the data as given to be
#: reported as the right direction.
DEFAULT_THRESHOLD = 10.0
#: The calibration pipeline checks the directions after a fit whose p-value is below this (or
#: not a number), and when the data are refused as a whole; good data pay nothing.
CHECK_BELOW_P = 1e-3


@dataclass(frozen=True)
class DirectionFit:
    """
    One trial fit of the directions.

    Attributes
    ----------
    invert_a, invert_b : bool
        Whether device A's / device B's stream was inverted for this fit.
    chi2_dof : float
        Chi-square per degree of freedom of the OLS fit (inf if the fit failed).
    rms_position_m : float
        RMS distance between B's measured and predicted positions, m (inf if it failed).
    n_pairs : int
        Pairs used.
    error : str
        Why the fit failed ('' if it did not).

    """

    invert_a: bool
    invert_b: bool
    chi2_dof: float
    rms_position_m: float
    n_pairs: int
    error: str = ''

    @property
    def label(self) -> str:
        """E.g. ``'as given'``, ``'B inverted'``, ``'A and B inverted'``."""
        inverted = [d for d, inv in (('A', self.invert_a), ('B', self.invert_b)) if inv]
        return ' and '.join(inverted) + ' inverted' if inverted else 'as given'

    @property
    def flags(self) -> str:
        """Return the ``coreg convert`` flags giving these directions, e.g. ``'--invert-b'``."""
        return ' '.join(f for f, inv in (('--invert-a', self.invert_a),
                                         ('--invert-b', self.invert_b)) if inv)

    def as_dict(self) -> dict:
        """JSON-friendly form (inf as None)."""
        def finite(x):
            return float(x) if np.isfinite(x) else None
        return {'invert_a': self.invert_a, 'invert_b': self.invert_b, 'label': self.label,
                'chi2_dof': finite(self.chi2_dof), 'rms_position_m': finite(self.rms_position_m),
                'n_pairs': self.n_pairs, 'error': self.error}


def _times(ratio: float) -> str:
    if not np.isfinite(ratio):
        return 'infinitely'
    return f'{ratio:.0f}×' if ratio >= 100 else f'{ratio:.3g}×'


def _device(fit: DirectionFit) -> str:
    return {'A': 'device A', 'B': 'device B', 'A and B': 'devices A and B'}[
        fit.label.replace(' inverted', '')]


@dataclass(frozen=True)
class DirectionReport:
    """
    Which combination of stream directions fits best.

    Attributes
    ----------
    fits : tuple of DirectionFit
        Every combination tried, the data as given first (four for ``full_pose``; two for
        the position-only models, whose B stream has no orientation to invert).
    threshold : float
        Factor by which another combination must beat the data as given to be ``flagged``.

    """

    fits: tuple
    threshold: float = DEFAULT_THRESHOLD

    @property
    def as_given(self) -> DirectionFit:
        """Return the fit of the data as given."""
        return self.fits[0]

    @property
    def best(self) -> DirectionFit:
        """Return the fit with the smallest chi2/dof (the data as given on a tie)."""
        return min(self.fits, key=lambda f: (f.chi2_dof, f.invert_a or f.invert_b))

    @property
    def ratio(self) -> float:
        """chi2/dof as given divided by the best chi2/dof (>= 1; inf if only others fit)."""
        given, best = self.as_given.chi2_dof, self.best.chi2_dof
        if not np.isfinite(best):
            return 1.0
        return float(given / best) if best > 0 else float('inf')

    @property
    def flagged(self) -> bool:
        """Whether the data fit more than ``threshold`` times better with an inversion."""
        return self.best is not self.as_given and self.ratio > self.threshold

    @property
    def message(self) -> str:
        """One line for a person."""
        best, given = self.best, self.as_given
        if best is given or not np.isfinite(best.chi2_dof):
            return (f'the data as given fit best (chi2/dof {given.chi2_dof:.4g}); no stream '
                    f'needs inverting')
        times = _times(self.ratio)
        device = _device(best)
        both = (' (inverting both is the same model with T0 and T1 swapped and inverted: '
                'only the noise weighting differs)' if best.invert_a and best.invert_b else '')
        if not self.flagged:
            return (f'the data fit {times} better with {device} inverted (chi2/dof '
                    f'{best.chi2_dof:.4g} vs {given.chi2_dof:.4g} as given), below the '
                    f'{self.threshold:g}× needed to call the directions wrong{both}')
        alt = self.alternative
        if alt is None:
            return (f'the data fit {times} better with {device} inverted (chi2/dof '
                    f'{best.chi2_dof:.4g} vs {given.chi2_dof:.4g} as given){both}: re-run coreg '
                    f'convert with {best.flags}')
        alt_times = _times(given.chi2_dof / alt.chi2_dof)
        return (f'the data fit {times} better with {device} inverted (chi2/dof '
                f'{best.chi2_dof:.4g} vs {given.chi2_dof:.4g} as given), and {alt_times} better '
                f'with {_device(alt)} inverted (the same model with T0 '
                f'and T1 swapped and inverted; only the noise weighting differs): re-run coreg '
                f'convert with {best.flags} (or {alt.flags}), toggling the flags this '
                f'recording was converted with')

    @property
    def alternative(self) -> Optional[DirectionFit]:
        """
        Return the best fit's partner (both directions toggled) if it also beats the threshold.

        Only when ``flagged``, else None. Toggling both streams gives the same model with T0
        and T1 swapped and inverted, so the two fit the geometry equally and differ only
        through the noise weighting.
        """
        if not self.flagged:
            return None
        best = self.best
        for f in self.fits:
            if (f.invert_a, f.invert_b) == (not best.invert_a, not best.invert_b):
                if f is not self.as_given and np.isfinite(f.chi2_dof) and f.chi2_dof > 0 and (
                        self.as_given.chi2_dof / f.chi2_dof > self.threshold):
                    return f
        return None

    def as_dict(self) -> dict:
        """JSON-friendly form: the fits, the best, the ratio, the flags and the message."""
        ratio = self.ratio
        alt = self.alternative
        return {'fits': [f.as_dict() for f in self.fits], 'best': self.best.label,
                'ratio': float(ratio) if np.isfinite(ratio) else None,
                'threshold': self.threshold, 'flagged': self.flagged,
                'flags': self.best.flags if self.flagged else '',
                'alternative_flags': alt.flags if alt is not None else '',
                'message': self.message}


def subsample(pairs: Pairs, max_pairs: int) -> Pairs:
    """At most ``max_pairs`` pairs evenly spread over ``pairs`` (all of them if fewer)."""
    n = len(pairs)
    if n <= max_pairs:
        return pairs
    idx = np.unique(np.linspace(0, n - 1, max_pairs).round().astype(int))

    def pick(a):
        return None if a is None else np.asarray(a)[idx]

    return Pairs(stamps=pick(pairs.stamps), pos_a=pick(pairs.pos_a), quat_a=pick(pairs.quat_a),
                 pos_b=pick(pairs.pos_b), quat_b=pick(pairs.quat_b),
                 a_var_scale=pick(pairs.a_var_scale))


def _inverted(pairs: Pairs, invert_a: bool, invert_b: bool) -> Pairs:
    pos_a, quat_a, pos_b, quat_b = pairs.pos_a, pairs.quat_a, pairs.pos_b, pairs.quat_b
    if invert_a:
        pos_a, quat_a = invert_poses(pos_a, quat_a)
    if invert_b:
        pos_b, quat_b = invert_poses(pos_b, quat_b)
    return Pairs(stamps=pairs.stamps, pos_a=pos_a, quat_a=quat_a, pos_b=pos_b, quat_b=quat_b,
                 a_var_scale=pairs.a_var_scale)


def _rms_position(result, pairs: Pairs) -> float:
    """RMS of |p_B - (p0 + R0 (p_A + R_A p_j))| over pairs and markers, m."""
    t0 = result.base_to_base
    r0 = quat.to_matrix(np.asarray(t0.quat_wxyz, dtype=float))
    ra = quat.to_matrix(np.asarray(pairs.quat_a, dtype=float))
    in_a = pairs.pos_a[:, None, :] + np.einsum('nij,kj->nki', ra, result.markers)
    pred = t0.position + np.einsum('ij,nkj->nki', r0, in_a)
    meas = np.asarray(pairs.pos_b, dtype=float).reshape(pred.shape)
    return float(np.sqrt(np.mean(np.sum((meas - pred) ** 2, axis=-1))))


def check_pair_directions(pairs: Pairs, settings: Settings, *, max_pairs: int = MAX_PAIRS,
                          threshold: float = DEFAULT_THRESHOLD) -> DirectionReport:
    """
    Fit every combination of stream directions to paired samples (see ``check_directions``).

    Parameters
    ----------
    pairs : Pairs
        Paired samples as given (A in A's base frame, B in B's base frame, by assumption).
    settings : Settings
        Model and noise; the fits use OLS whatever ``settings.method`` says, at most
        ``MAX_ITERATIONS`` iterations each.
    max_pairs : int
        Largest number of pairs per fit, evenly spread.
    threshold : float
        Factor for ``DirectionReport.flagged``.

    Returns
    -------
    DirectionReport

    """
    pairs = subsample(pairs, int(max_pairs))
    ols = settings.updated(method='ols', robust=False,
                           max_iterations=min(int(settings.max_iterations), MAX_ITERATIONS))
    combos = [(False, False), (True, False)]
    if settings.model == 'full_pose':
        combos += [(False, True), (True, True)]
    fits = []
    for invert_a, invert_b in combos:
        trial = _inverted(pairs, invert_a, invert_b)
        try:
            result = calibrate(trial, ols)
            chi2_dof = result.reduced_chi2 if result.dof > 0 else float('inf')
            fit = DirectionFit(invert_a, invert_b, float(chi2_dof), _rms_position(result, trial),
                               len(trial))
        except CoregError as e:
            fit = DirectionFit(invert_a, invert_b, float('inf'), float('inf'), len(trial),
                               str(e))
        fits.append(fit)
    return DirectionReport(fits=tuple(fits), threshold=float(threshold))


def check_directions(stream_a: PoseStream, streams_b: Union[PoseStream, Sequence[PoseStream]],
                     settings: Settings, *, max_pairs: int = MAX_PAIRS,
                     threshold: float = DEFAULT_THRESHOLD,
                     pairs: Optional[Pairs] = None) -> DirectionReport:
    """
    Calibrate with each stream as given or inverted and report which fits best.

    Inverting both streams gives ``T_B⁻¹ = T1⁻¹ · T_A⁻¹ · T0⁻¹``, the same model with the two
    unknown transforms swapped and inverted: it fits the geometry equally well, and only the
    noise weighting (noise is isotropic in a device's base frame, not in the inverted frame)
    tells it from the data as given; expect modest ratios for it.

    The streams are paired once with ``settings`` (gap, time offset, model); the inversions
    are applied to the pairs (A interpolated at B's stamps then inverted: the same to well
    below the noise for smooth motion). Each combination — A as given or inverted × B as given
    or inverted for ``full_pose``; A only for ``position_only`` and ``three_marker``, whose B
    has no orientation — is fitted by OLS on at most ``max_pairs`` pairs, and compared by
    chi-square per degree of freedom.

    Parameters
    ----------
    stream_a : PoseStream
        Device A, supposedly its tool pose in its base frame.
    streams_b : PoseStream or sequence of PoseStream
        Device B, supposedly its marker pose(s) in its base frame.
    settings : Settings
        The configuration of the fits (model, method, noise).
    max_pairs : int
        Largest number of pairs per fit (3000: about a second for the four fits).
    threshold : float
        A combination must fit ``threshold`` times better than the data as given to be
        ``flagged``.
    pairs : Pairs, optional
        Already paired samples, to skip the pairing.

    Returns
    -------
    DirectionReport

    Raises
    ------
    InputError
        If the streams cannot be paired (as ``calibrate_streams``).

    """
    if pairs is not None or not settings.estimate_time_offset:
        if pairs is None:
            pairs, _ = pair_for(stream_a, streams_b, settings)
        return check_pair_directions(pairs, settings, max_pairs=max_pairs, threshold=threshold)
    # Offsets and directions together: the speeds the coarse search correlates do not change
    # when a stream is inverted, so its candidates serve every direction; each direction is
    # judged at its best candidate (a wrong direction may fit better than the right one at a
    # wrong offset).
    markers = [streams_b] if isinstance(streams_b, PoseStream) else list(streams_b)
    a, bs = validated_streams(stream_a, markers, settings.model == 'full_pose')
    offsets = [float(settings.time_offset)] + [
        tau for tau, _ in coarse_offsets(a, bs, angular=settings.model != 'position_only')]
    reports, error = [], None
    for tau in offsets[:1 + OFFSET_CANDIDATES]:
        try:
            pairs, _ = pair_for(a, bs, settings, TimeOffset(tau), validated=True)
            reports.append(check_pair_directions(pairs, settings, max_pairs=max_pairs,
                                                 threshold=threshold))
        except CoregError as e:
            error = e
    if not reports:
        raise error
    fits = tuple(min((r.fits[i] for r in reports), key=lambda f: f.chi2_dof)
                 for i in range(len(reports[0].fits)))
    return DirectionReport(fits=fits, threshold=float(threshold))

"""
Watchdog of a published calibration: does every new pair still fit it, and if not, what changed.

1. **Per pair**, the residual of B's measurement against the calibration's prediction from A,
   in the ROS tangents of ``crlb`` (position m, small rotation ``R_meas = Exp(r) R_pred``),
   ``r = y ⊖ f(x, ψ̂)``, is normalised by its covariance at the stated noise with the
   calibration's own uncertainty included:
   ``S = Σ_b + s F_x Σ_a F_xᵀ + F C Fᵀ`` with ``F = [F_ψ, c]`` (``c = -F_x ẋ_A``, the clock
   offset's column) and C the joint covariance of (ψ, τ). ``d² = rᵀ S⁻¹ r ~ χ²_m`` while the
   calibration holds.
2. **Sequential test**: a CUSUM of the log-likelihood ratio of "the residuals' covariance is
   inflated by ``DESIGN_INFLATION``" against "as stated", per pair
   ``ℓ = ½ (1 - 1/λ) min(d², c) - ½ m ln λ``. A change of T0, T1 or the clock adds a mean
   to r, a noise or field change scales it: both raise d² and the CUSUM detects either. d² is
   clipped at the χ²_m ``1 - CLIP_TAIL`` quantile, so an isolated outlier cannot raise an
   alarm alone. The threshold h is set from the CUSUM's in-control run length computed exactly
   for χ²_m residuals (Brook & Evans' Markov chain): the mean number of pairs between false
   alarms is ``TARGET_RUN_LENGTH`` (10⁹ pairs: one per 116 days at 100 Hz, per 11.6 days at
   1 kHz).
3. **Attribution**: after an alarm, the pairs since the CUSUM last stood at zero (the change
   point estimate) are fitted with each alternative, linear in its own parameters: T0 moved
   (δp0, δθ0: the base was bumped), T1 moved (δp1[, δθ1]; the marker set as a rigid body for
   three markers: the marker slipped), the clock offset changed (δτ), or the noise or field
   changed (residual covariance × λ, no mean). The alternatives are compared by their
   -2 log-likelihood (clipped per pair, so outliers do not decide) plus ``k ln n`` (BIC); the
   winner is decided when it beats the runner-up by ``DECISIVE``. Its size is reported with σ
   (fit covariance plus the calibration's own uncertainty of that part).
4. **States**: OK; WARN from the alarm until the attribution is decided (or, if the window
   fits the calibration after all, back to OK: a transient); ERROR once decided, kept until
   the watchdog is reset with a new calibration. ERROR means the calibration is stale.

Units SI (m, rad, s); stamps int64 ns; quaternions (w, x, y, z).
"""

from __future__ import annotations

from dataclasses import dataclass
import functools
from typing import Optional

import numpy as np
from scipy import stats

from coreg_ros.core import quaternion as quat
from coreg_ros.core.covariance import Prior
from coreg_ros.core.crlb import CRLB_DIMENSION
from coreg_ros.core.errors import InputError
from coreg_ros.core.guidance import (
    CHUNK,
    Estimate,
    PairBatch,
    device_covariances,
    effective_covariance,
    jacobians,
)
from coreg_ros.core.models import S0, S1, SPECS, Parameters, tangent_of_chart
from coreg_ros.core.so3 import skew
from coreg_ros.core.types import CalibrationResult

#: Residual covariance inflation the CUSUM is tuned to (λ: d² ≈ λ χ²_m under the change).
DESIGN_INFLATION = 2.0
#: d² is clipped at the χ²_m quantile 1 - CLIP_TAIL in the CUSUM.
CLIP_TAIL = 1e-3
#: Mean pairs between false alarms the threshold is set for (χ²_m residuals).
TARGET_RUN_LENGTH = 1e9
#: Cells of the Brook-Evans Markov chain.
CHAIN_CELLS = 500
#: In the attribution fits, a pair's -2 log-likelihood is clipped at the χ²_m quantile
#: 1 - FIT_CLIP_TAIL (and such pairs are left out of the refit): outliers do not decide.
FIT_CLIP_TAIL = 1e-4
#: The winning alternative must beat the runner-up by this much (-2 log-likelihood + BIC).
DECISIVE = 12.0
#: Fewest pairs after the change point before the attribution is trusted, and the fewest
#: seconds (whichever takes longer).
MIN_WINDOW_PAIRS = 100
MIN_WINDOW_S = 0.5
#: Undecided after this long (s) since the change point: ERROR with the ambiguity said.
MAX_UNDECIDED_S = 30.0
#: Pairs the attribution fits at most (evenly decimated beyond).
MAX_FIT_PAIRS = 6000
#: Seconds of recent pairs kept for the attribution.
KEEP_S = 60.0
#: Once ERROR, the size of the change is refined with the growing window for this long (s).
REFINE_S = 10.0

OK, WARN, ERROR = 0, 1, 2
LEVEL_NAMES = ('OK', 'WARN', 'ERROR')
#: The alternatives of the attribution.
KINDS = ('none', 't0', 't1', 'clock', 'noise')
KIND_TEXT = {'none': 'no change', 't0': 'T0 moved (base bumped)',
             't1': 'T1 moved (marker slipped on the tool)', 'clock': 'clock offset changed',
             'noise': 'noise or field changed'}

#: Name of the watchdog status in /diagnostics (``<node>: watchdog``).
STATUS_NAME = 'watchdog'
#: /diagnostics keys of the watchdog status (the node publishes exactly
#: ``WatchState.diagnostic_values()``; ``coreg watch`` reads these).
KEY_STATE = 'state'
KEY_MESSAGE = 'message'
KEY_STALE = 'calibration stale'
KEY_CHECKED = 'pairs checked'
KEY_STATISTIC = 'cusum'
KEY_THRESHOLD = 'cusum threshold'
KEY_MEAN_D2 = 'mean normalised residual'
KEY_CHANGE = 'change'
KEY_CHANGE_STAMP = 'change stamp ns'
KEY_ALARM_STAMP = 'alarm stamp ns'
KEY_TRANSLATION = 'translation mm'
KEY_ROTATION = 'rotation deg'
KEY_CLOCK = 'clock step ms'
KEY_NOISE = 'noise factor'


# --------------------------------------------------------------------------- the threshold


def _llr_constants(m: int, inflation: float) -> tuple[float, float, float]:
    """Return (a, b, clip) of ``ℓ = a min(d², clip) - b``."""
    a = 0.5 * (1.0 - 1.0 / inflation)
    b = 0.5 * m * np.log(inflation)
    return a, b, float(stats.chi2.isf(CLIP_TAIL, m))


def run_length(threshold: float, m: int, inflation: float = DESIGN_INFLATION,
               noncentrality: float = 0.0, cells: int = CHAIN_CELLS) -> float:
    """
    Mean pairs to an alarm of the CUSUM from zero (Brook & Evans' Markov chain).

    Parameters
    ----------
    threshold : float
        h.
    m : int
        Residuals per pair (χ²_m).
    inflation : float
        λ of the CUSUM's likelihood ratio.
    noncentrality : float
        d² ~ χ²_m(noncentrality) (0: in control, the false-alarm run length; > 0: the
        detection delay of a mean change of that size in σ²).
    cells : int
        States of the chain.

    """
    a, b, clip = _llr_constants(m, inflation)
    width = threshold / cells
    values = np.arange(cells) * width
    edges = (np.arange(cells) + 0.5) * width
    edges[-1] = threshold

    def cdf(y):
        x = (y + b) / a
        inner = (stats.ncx2.cdf(np.maximum(x, 0.0), m, noncentrality) if noncentrality > 0
                 else stats.chi2.cdf(np.maximum(x, 0.0), m))
        return np.where(x >= clip, 1.0, np.where(x < 0.0, 0.0, inner))

    upto = cdf(edges[None, :] - values[:, None])
    P = np.diff(np.concatenate([np.zeros((cells, 1)), upto], axis=1), axis=1)
    return float(np.linalg.solve(np.eye(cells) - P, np.ones(cells))[0])


@functools.lru_cache(maxsize=16)
def cusum_threshold(m: int, target: float = TARGET_RUN_LENGTH,
                    inflation: float = DESIGN_INFLATION) -> float:
    """Return the threshold h whose in-control mean run length is ``target`` pairs."""
    lo, hi = 5.0, 25.0
    f_lo = np.log(run_length(lo, m, inflation)) - np.log(target)
    f_hi = np.log(run_length(hi, m, inflation)) - np.log(target)
    h = hi
    for _ in range(30):
        # ln ARL is nearly linear in h: regula falsi converges in a few steps
        h = hi - f_hi * (hi - lo) / (f_hi - f_lo)
        f = np.log(run_length(h, m, inflation)) - np.log(target)
        if abs(f) < 1e-3:
            break
        if f > 0:
            hi, f_hi = h, f
        else:
            lo, f_lo = h, f
    return float(h)


# --------------------------------------------------------------------------- the calibration


def _psi_map(params: Parameters) -> np.ndarray:
    """Linear map from δφ (estimator coordinates) to δψ (``crlb`` coordinates), (d, P)."""
    spec = params.spec
    d = CRLB_DIMENSION[spec.name]
    T = np.zeros((d, spec.n_params))
    T[0:3, 0:3] = np.eye(3)
    T[3:6, S0] = tangent_of_chart(params.q0, params.dq0)
    T[6:9, spec.marker_slice(0)] = np.eye(3)
    if spec.has_q1:
        T[9:12, S1] = tangent_of_chart(params.q1, params.dq1)
    elif spec.n_markers == 3:
        T[9:12, spec.marker_slice(1)] = np.eye(3)
        T[12:15, spec.marker_slice(2)] = np.eye(3)
    return T


@dataclass(frozen=True)
class Calibration:
    """
    What the watchdog checks the pairs against.

    Attributes
    ----------
    estimate : Estimate
        T0, T1 (markers).
    cov : ndarray, shape (d + 1, d + 1)
        Joint covariance of (ψ, τ) in the ``crlb`` coordinates (τ last, s²; zero where τ was
        given rather than estimated).
    time_offset_s : float
        The offset the pairs are made with (B's clock minus A's), s.

    """

    estimate: Estimate
    cov: np.ndarray
    time_offset_s: float = 0.0

    @property
    def model(self) -> str:
        """The measurement model."""
        return self.estimate.model

    @classmethod
    def from_result(cls, result: CalibrationResult) -> Calibration:
        """From a calibration result (its posterior covariance and time offset)."""
        spec = SPECS[result.model]
        d = CRLB_DIMENSION[result.model]
        cov = np.zeros((d + 1, d + 1))
        if result.param_cov is not None:
            params = Parameters(spec, result.params, list(result.charts))
            T = _psi_map(params)
            cov[:d, :d] = T @ result.param_cov @ T.T
        elif result.cov_joint is not None:
            k = min(d, 12)
            cov[:k, :k] = np.where(np.asarray(result.cov_joint)[:k, :k] < 0, 0.0,
                                   result.cov_joint[:k, :k])
        timing = result.time_offset
        tau = 0.0 if timing is None else float(timing.value_s)
        if timing is not None and timing.estimated and timing.cov is not None:
            cov[d, d] = float(np.asarray(timing.cov)[0, 0])
            if timing.cross_cov is not None:
                cross = np.asarray(timing.cross_cov)[:, 0]
                rows = 12 if spec.has_q1 else 9  # T1's rotation rows are empty otherwise
                cov[:rows, d] = cross[:rows]
                cov[d, :rows] = cross[:rows]
        return cls(Estimate.from_result(result), 0.5 * (cov + cov.T), tau)


# --------------------------------------------------------------------------- residuals


def residuals(estimate: Estimate, batch: PairBatch) -> np.ndarray:
    """
    Return the residuals ``r = y ⊖ f(x, ψ̂)`` per pair, shape (n, m).

    B's measured marker position(s) minus the predicted (m), and for full pose the rotation
    vector of ``R_meas R_predᵀ`` (rad).
    """
    R0 = quat.to_matrix(estimate.q0)
    Ra = quat.to_matrix(np.asarray(batch.quat_a, dtype=float))
    v = np.asarray(batch.pos_a, dtype=float)[:, None, :] + np.einsum(
        'nab,kb->nka', Ra, estimate.markers)
    pred = estimate.p0 + v @ R0.T  # (n, k, 3)
    pos_b = np.asarray(batch.pos_b, dtype=float)
    pos_b = pos_b if pos_b.ndim == 3 else pos_b[:, None, :]
    out = (pos_b - pred).reshape(len(pred), -1)
    if estimate.model == 'full_pose':
        q_pred = quat.multiply(estimate.q0, quat.multiply(np.asarray(batch.quat_a, dtype=float),
                                                          estimate.q1))
        rot = quat.log(quat.multiply(np.asarray(batch.quat_b, dtype=float),
                                     quat.conjugate(q_pred)))
        out = np.concatenate([out, rot], axis=1)
    return out


@dataclass(frozen=True)
class Linearised:
    """
    Pairs linearised at the calibration, whitened by their noise (not the calibration's).

    Attributes
    ----------
    r : ndarray, shape (n, m)
        Whitened residuals ``L⁻¹ r`` (``L Lᵀ = Σ_b + s F_x Σ_a F_xᵀ``).
    f : ndarray, shape (n, m, d + 1)
        Whitened ``[F_ψ, c]``.

    """

    r: np.ndarray
    f: np.ndarray


def linearise(calibration: Calibration, batch: PairBatch, cov_a, cov_b, tls: bool,
              noise_scale: float = 1.0) -> tuple[np.ndarray, Linearised]:
    """
    Normalised squared residuals (calibration's covariance included) and the whitened system.

    Returns
    -------
    d2 : ndarray, shape (n,)
        ``rᵀ S⁻¹ r`` with ``S = noise + F C Fᵀ``: χ²_m while the calibration holds.
    lin : Linearised

    """
    n = len(batch)
    est = calibration.estimate
    d2 = np.empty(n)
    rs, fs = [], []
    for start in range(0, n, CHUNK):
        sl = slice(start, min(n, start + CHUNK))
        sub = batch.take(sl)
        r = residuals(est, sub)
        f, f_x = jacobians(est, sub.pos_a, sub.quat_a, sub.velocity)
        noise = effective_covariance(f_x, cov_a, cov_b, sub.a_var_scale, tls) * noise_scale
        full = noise + f @ calibration.cov @ np.swapaxes(f, 1, 2)
        d2[sl] = np.einsum('ni,ni->n', r, np.linalg.solve(full, r[:, :, None])[:, :, 0])
        L = np.linalg.cholesky(noise)
        rs.append(np.linalg.solve(L, r[:, :, None])[:, :, 0])
        fs.append(np.linalg.solve(L, f))
    return d2, Linearised(np.concatenate(rs), np.concatenate(fs))


# --------------------------------------------------------------------------- attribution


@dataclass(frozen=True)
class Attribution:
    """
    Which alternative explains the pairs since the change point, and by how much.

    Attributes
    ----------
    kind : str
        One of ``KINDS`` (``none``: the window fits the calibration).
    decided : bool
        The winner beats the runner-up by ``DECISIVE``.
    runner_up : str
    margin : float
        Runner-up's score minus the winner's.
    scores : dict of str to float
        -2 log-likelihood (clipped) + k ln n per alternative.
    n_pairs : int
        Pairs fitted.
    translation : ndarray, shape (3,) or None
        δp of the moved transform, m (T0: B's base axes; T1: A's tool axes).
    translation_sigma : float
        σ of |δp|, m.
    rotation : ndarray, shape (3,) or None
        δθ of the moved transform, rad (left perturbation, same axes).
    rotation_sigma : float
        σ of |δθ|, rad.
    time_step : float or None
        δτ (s): B's clock minus A's grew by this much.
    time_sigma : float
    noise_factor : float or None
        Residual σ over the stated σ (√λ) for ``noise``.
    text : str
        One line for a person.

    """

    kind: str
    decided: bool
    runner_up: str
    margin: float
    scores: dict
    n_pairs: int
    translation: Optional[np.ndarray] = None
    translation_sigma: float = float('nan')
    rotation: Optional[np.ndarray] = None
    rotation_sigma: float = float('nan')
    time_step: Optional[float] = None
    time_sigma: float = float('nan')
    noise_factor: Optional[float] = None
    text: str = ''


def _norm_sigma(x: np.ndarray, cov: np.ndarray) -> tuple[float, float]:
    size = float(np.linalg.norm(x))
    if size == 0.0:
        return 0.0, float(np.sqrt(np.trace(cov) / len(x)))
    u = x / size
    return size, float(np.sqrt(max(u @ cov @ u, 0.0)))


def _columns(model: str, estimate: Estimate, kind: str, d: int) -> np.ndarray:
    """Map from an alternative's parameters to (ψ, τ) coordinates, shape (d + 1, k)."""
    if kind == 't0':
        G = np.zeros((d + 1, 6))
        G[0:6, 0:6] = np.eye(6)
    elif kind == 't1' and model == 'full_pose':
        G = np.zeros((d + 1, 6))
        G[6:12, 0:6] = np.eye(6)
    elif kind == 't1' and model == 'position_only':
        G = np.zeros((d + 1, 3))
        G[6:9, 0:3] = np.eye(3)
    elif kind == 't1':
        # the marker set as a rigid body in the tool frame: δp_j = δp + δθ × (p_j - p1)
        G = np.zeros((d + 1, 6))
        for j in range(3):
            G[6 + 3 * j:9 + 3 * j, 0:3] = np.eye(3)
            G[6 + 3 * j:9 + 3 * j, 3:6] = -skew(estimate.markers[j] - estimate.markers[0])
    else:  # clock
        G = np.zeros((d + 1, 1))
        G[d, 0] = 1.0
    return G


def attribute(calibration: Calibration, lin: Linearised) -> Attribution:
    """
    Fit the alternatives on linearised pairs and say which explains them, and by how much.

    Parameters
    ----------
    calibration : Calibration
    lin : Linearised
        The pairs since the change point.

    Returns
    -------
    Attribution

    """
    r, f = lin.r, lin.f
    n, m = r.shape
    d = f.shape[2] - 1
    model = calibration.model
    clip = float(stats.chi2.isf(FIT_CLIP_TAIL, m))
    log_n = float(np.log(max(n, 2)))
    d2_0 = np.einsum('ni,ni->n', r, r)
    scores = {'none': float(np.minimum(d2_0, clip).sum())}
    fits = {}
    for kind in ('t0', 't1', 'clock'):
        G = _columns(model, calibration.estimate, kind, d)
        J = f @ G  # (n, m, k)
        keep = np.ones(n, dtype=bool)
        delta = np.zeros(G.shape[1])
        cov = None
        for _ in range(2):
            # plain least squares, then again without the pairs it leaves far outside the noise
            Jk, rk = J[keep].reshape(-1, G.shape[1]), r[keep].reshape(-1)
            A = Jk.T @ Jk
            try:
                cov = np.linalg.inv(A)
            except np.linalg.LinAlgError:
                cov = np.linalg.pinv(A)
            delta = cov @ (Jk.T @ rk)
            e = r - J @ delta
            d2 = np.einsum('ni,ni->n', e, e)
            keep = d2 < clip
            if keep.sum() < G.shape[1] + 1:
                keep = np.ones(n, dtype=bool)
                break
        scores[kind] = float(np.minimum(d2, clip).sum() + G.shape[1] * log_n)
        fits[kind] = (G, delta, cov)
    # noise (or field) changed: residual covariance λ times the stated, no mean; λ from the
    # median so that a few outliers do not make it
    lam = max(float(np.median(d2_0) / stats.chi2.median(m)), 1e-6)
    scores['noise'] = float(np.minimum(d2_0 / lam, clip).sum() + n * m * np.log(lam) + log_n)
    order = sorted(scores, key=scores.get)
    kind, runner = order[0], order[1]
    margin = scores[runner] - scores[kind]
    out = dict(kind=kind, decided=bool(margin >= DECISIVE), runner_up=runner, margin=margin,
               scores=scores, n_pairs=n)
    C = calibration.cov
    if kind in fits:
        G, delta, cov = fits[kind]
        total = cov + G.T @ C @ G if kind != 't1' or model != 'three_marker' else cov
        if kind == 'clock':
            out.update(time_step=float(delta[0]), time_sigma=float(np.sqrt(total[0, 0])))
        else:
            size, sd = _norm_sigma(delta[0:3], total[0:3, 0:3])
            out.update(translation=delta[0:3].copy(), translation_sigma=sd)
            if len(delta) == 6:
                rsize, rsd = _norm_sigma(delta[3:6], total[3:6, 3:6])
                out.update(rotation=delta[3:6].copy(), rotation_sigma=rsd)
    elif kind == 'noise':
        out['noise_factor'] = float(np.sqrt(lam))
    att = Attribution(**out)
    return Attribution(**{**out, 'text': describe(att)})


def describe(att: Attribution) -> str:
    """One line for a person: what changed and by how much (mm, degrees, ms) with σ."""
    head = KIND_TEXT[att.kind]
    if att.kind in ('t0', 't1'):
        size = float(np.linalg.norm(att.translation)) * 1e3
        text = f'{head}: {size:.3g} ± {att.translation_sigma * 1e3:.2g} mm'
        if att.rotation is not None:
            deg = float(np.degrees(np.linalg.norm(att.rotation)))
            text += f', {deg:.3g} ± {np.degrees(att.rotation_sigma):.2g}°'
        frame = "B's base" if att.kind == 't0' else "A's tool"
        text += f" (δp [{', '.join(f'{v * 1e3:+.2f}' for v in att.translation)}] mm in {frame}"
        text += ' axes)'
    elif att.kind == 'clock':
        text = (f"{head}: B's clock minus A's by {att.time_step * 1e3:+.3g} ± "
                f'{att.time_sigma * 1e3:.2g} ms')
    elif att.kind == 'noise':
        text = (f'{head}: residuals {att.noise_factor:.2g}× the stated noise, not a rigid move '
                f'of T0 or T1 nor a clock step')
    else:
        text = head
    if not att.decided:
        text += f' (or {KIND_TEXT[att.runner_up]}: not yet decided)'
    return text


def recalibration_prior(result: CalibrationResult, kind: str) -> Optional[Prior]:
    """
    Return the prior for recalibrating after a change: the parts of ``result`` still valid.

    After ``t0`` (the base moved) T1 still holds, after ``t1`` T0 does, after ``clock`` both
    do (only τ changed; the recalibration estimates it again). After ``noise`` (or no
    decided change) there is nothing to recalibrate: None.

    Parameters
    ----------
    result : CalibrationResult
        The calibration the watchdog found stale (its poses carry their covariance).
    kind : str
        ``Attribution.kind``.

    """
    if kind not in ('t0', 't1', 'clock'):
        return None
    keep_t0 = kind != 't0' and result.base_to_base.covariance is not None
    keep_t1 = kind != 't1' and result.tool_to_marker.covariance is not None
    if not (keep_t0 or keep_t1):
        return None
    return Prior(result.base_to_base if keep_t0 else None,
                 result.tool_to_marker if keep_t1 else None)


# --------------------------------------------------------------------------- the watchdog


@dataclass(frozen=True)
class WatchState:
    """
    The watchdog's state after an update.

    Attributes
    ----------
    level : int
        ``OK`` (0), ``WARN`` (1) or ``ERROR`` (2), as diagnostic_msgs' levels.
    message : str
        One line for a person.
    n_checked : int
        Pairs checked since the calibration.
    statistic : float
        The CUSUM now.
    threshold : float
        Its alarm threshold h.
    mean_d2 : float
        Mean normalised squared residual per residual component over the last update
        (≈ 1 while the calibration holds).
    change_stamp : int or None
        Estimated change point (B stamp, ns).
    alarm_stamp : int or None
        Stamp of the pair that raised the alarm, ns.
    attribution : Attribution or None

    """

    level: int
    message: str
    n_checked: int
    statistic: float
    threshold: float
    mean_d2: float
    change_stamp: Optional[int] = None
    alarm_stamp: Optional[int] = None
    attribution: Optional[Attribution] = None

    @property
    def level_name(self) -> str:
        """``OK``, ``WARN`` or ``ERROR``."""
        return LEVEL_NAMES[self.level]

    @property
    def stale(self) -> bool:
        """The calibration no longer describes the devices (ERROR)."""
        return self.level == ERROR

    def diagnostic_values(self) -> list:
        """(key, value) string pairs for the watchdog status of /diagnostics."""
        att = self.attribution

        def num(v, scale=1.0, fmt='.4g'):
            return 'n/a' if v is None or not np.isfinite(v) else format(v * scale, fmt)

        out = [(KEY_STATE, self.level_name), (KEY_MESSAGE, self.message),
               (KEY_STALE, 'true' if self.stale else 'false'),
               (KEY_CHECKED, str(self.n_checked)), (KEY_STATISTIC, f'{self.statistic:.4g}'),
               (KEY_THRESHOLD, f'{self.threshold:.4g}'), (KEY_MEAN_D2, num(self.mean_d2)),
               (KEY_CHANGE, 'none' if att is None else att.kind),
               (KEY_CHANGE_STAMP, 'n/a' if self.change_stamp is None else str(self.change_stamp)),
               (KEY_ALARM_STAMP, 'n/a' if self.alarm_stamp is None else str(self.alarm_stamp))]
        trans = rot = clock = noise = 'n/a'
        if att is not None and att.translation is not None:
            trans = (f'{np.linalg.norm(att.translation) * 1e3:.4g} ± '
                     f'{att.translation_sigma * 1e3:.2g}')
        if att is not None and att.rotation is not None:
            rot = (f'{np.degrees(np.linalg.norm(att.rotation)):.4g} ± '
                   f'{np.degrees(att.rotation_sigma):.2g}')
        if att is not None and att.time_step is not None:
            clock = f'{att.time_step * 1e3:+.4g} ± {att.time_sigma * 1e3:.2g}'
        if att is not None and att.noise_factor is not None:
            noise = f'{att.noise_factor:.3g}'
        out += [(KEY_TRANSLATION, trans), (KEY_ROTATION, rot), (KEY_CLOCK, clock),
                (KEY_NOISE, noise)]
        return out


class Watchdog:
    """
    Check pairs against a calibration as they arrive; detect and attribute a change.

    Parameters
    ----------
    calibration : Calibration or CalibrationResult
    sigma_a, sigma_b : (float, float)
        The stated device noise (position m, rotation rad).
    tls : bool
        Errors in both devices (as the calibration's method).
    noise_scale : float
        Factor on the stated noise variance (e.g. the calibration's χ²/dof when above 1, so
        that a noise slightly above the stated one does not raise false alarms).
    target_run_length : float
        Mean pairs between false alarms (sets the CUSUM threshold).

    Notes
    -----
    Feed ``update`` with ``PairBatch`` es (``guidance.PairFeed``) of pairs made at the
    calibration's time offset. The pairs are checked in order; a batch may be any size.

    """

    def __init__(self, calibration, sigma_a, sigma_b, tls: bool = True,
                 noise_scale: float = 1.0, target_run_length: float = TARGET_RUN_LENGTH):
        if isinstance(calibration, CalibrationResult):
            calibration = Calibration.from_result(calibration)
        if not noise_scale > 0:
            raise InputError('noise_scale must be > 0')
        self.calibration = calibration
        self._settings = (sigma_a, sigma_b, tls, noise_scale, target_run_length)
        self.cov_a, self.cov_b = device_covariances(calibration.model, sigma_a, sigma_b)
        self.tls = bool(tls)
        self.noise_scale = float(noise_scale)
        self.m = self.cov_b.shape[0]
        self.threshold = cusum_threshold(self.m, float(target_run_length))
        self._a, self._b, self._clip = _llr_constants(self.m, DESIGN_INFLATION)
        self._recent: list = []  # PairBatch es of the last KEEP_S seconds
        self.statistic = 0.0
        self.n_checked = 0
        self.level = OK
        self.message = 'watching: no pairs yet'
        self.zero_stamp: Optional[int] = None  # last stamp at which the CUSUM stood at zero
        self.change_stamp: Optional[int] = None
        self.alarm_stamp: Optional[int] = None
        self.attribution: Optional[Attribution] = None
        self.transients = 0
        self._mean_d2 = float('nan')
        #: d² of the pairs of the last update (normalised squared residuals, χ²_m in control)
        self.last_d2 = np.zeros(0)

    def reset(self, calibration=None) -> None:
        """Start over (with a new calibration, if given): OK, CUSUM at zero."""
        self.__init__(calibration or self.calibration, *self._settings)

    def _restart(self) -> None:
        self.statistic = 0.0
        self.level = OK
        self.change_stamp = self.alarm_stamp = None
        self.attribution = None

    def state(self) -> WatchState:
        """Return the current state."""
        return WatchState(self.level, self.message, self.n_checked, self.statistic,
                          self.threshold, self._mean_d2, self.change_stamp, self.alarm_stamp,
                          self.attribution)

    def update(self, batch: Optional[PairBatch]) -> WatchState:
        """Check new pairs; detect, attribute; return the state."""
        if batch is None or not len(batch):
            return self.state()
        self._remember(batch)
        d2, _ = linearise(self.calibration, batch, self.cov_a, self.cov_b, self.tls,
                          self.noise_scale)
        self.n_checked += len(batch)
        self.last_d2 = d2
        self._mean_d2 = float(np.mean(d2) / self.m)
        if self.level == OK:
            self._cusum(batch, d2)
        if self.level != OK:
            self._attribute(batch)
        elif self.n_checked == len(batch) or self.message.startswith('watching'):
            self.message = f'watching: the pairs fit the calibration ({self.n_checked} checked)'
        return self.state()

    def _remember(self, batch: PairBatch) -> None:
        self._recent.append(batch)
        last = int(batch.stamps[-1])
        while self._recent and int(self._recent[0].stamps[-1]) < last - int(KEEP_S * 1e9):
            self._recent.pop(0)

    def _cusum(self, batch: PairBatch, d2: np.ndarray) -> None:
        ell = self._a * np.minimum(d2, self._clip) - self._b
        c = np.cumsum(ell)
        # S_k = max(0, S_{k-1} + ℓ_k) in closed form: C_k minus the running minimum of
        # (-S_0, C_1, .., C_k)
        low = np.minimum.accumulate(np.concatenate([[-self.statistic], c]))[1:]
        s = c - low
        zero = np.flatnonzero(s <= 0.0)
        over = np.flatnonzero(s >= self.threshold)
        if over.size == 0:
            self.statistic = float(s[-1])
            if zero.size:
                self.zero_stamp = int(batch.stamps[zero[-1]])
            return
        k = int(over[0])
        before = zero[zero < k]
        if before.size:
            self.zero_stamp = int(batch.stamps[before[-1]])
        self.statistic = float(s[k])
        self.alarm_stamp = int(batch.stamps[k])
        # the change came after the CUSUM last stood at zero
        self.change_stamp = (self.zero_stamp + 1 if self.zero_stamp is not None
                             else int(self._recent[0].stamps[0]))
        self.level = WARN
        self.message = 'the pairs no longer fit the calibration; attributing the change'

    def _window(self) -> Optional[PairBatch]:
        batch = PairBatch.concatenate(self._recent)
        if batch is None:
            return None
        keep = batch.stamps >= self.change_stamp
        if keep.sum() > MAX_FIT_PAIRS:
            idx = np.flatnonzero(keep)
            keep = idx[np.linspace(0, len(idx) - 1, MAX_FIT_PAIRS).round().astype(int)]
        return batch.take(keep)

    def _attribute(self, batch: PairBatch) -> None:
        if (self.level == ERROR
                and (int(batch.stamps[-1]) - self.change_stamp) * 1e-9 > REFINE_S):
            return  # the size is known well enough: no more fits on a stale calibration
        window = self._window()
        if window is None or not len(window):
            return
        span = (int(window.stamps[-1]) - int(window.stamps[0])) * 1e-9
        if len(window) < MIN_WINDOW_PAIRS or span < MIN_WINDOW_S:
            return
        _, lin = linearise(self.calibration, window, self.cov_a, self.cov_b, self.tls,
                           self.noise_scale)
        att = attribute(self.calibration, lin)
        since = (int(batch.stamps[-1]) - self.change_stamp) * 1e-9
        if self.level == ERROR:
            # latched: keep refining the size while the window grows, not the verdict
            if att.kind == self.attribution.kind:
                self.attribution = att
                self.message = f'calibration stale: {att.text}; recalibrate'
            return
        if att.kind == 'none' and att.decided:
            self.transients += 1
            self._restart()
            self.message = ('watching: a transient departure (outliers?) passed; the pairs fit '
                            'the calibration again')
            return
        self.attribution = att
        if att.decided and att.kind != 'none':
            self.level = ERROR
            self.message = f'calibration stale: {att.text}; recalibrate'
        elif since >= MAX_UNDECIDED_S:
            self.level = ERROR
            self.message = (f'calibration stale: the pairs no longer fit; {att.text} '
                            f'after {since:.0f} s; recalibrate')
        else:
            self.message = f'the pairs no longer fit the calibration: {att.text}'

"""After an alarm: which change (T0, T1, clock, noise) explains the window, and how large."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

from coreg_ros.core.distributions import chi2_isf, chi2_ppf
from coreg_ros.core.estimator.priors import Prior
from coreg_ros.core.live.guidance import (
    Estimate,
)
from coreg_ros.core.live.watchdog.keys import KIND_TEXT
from coreg_ros.core.live.watchdog.residuals import Calibration, Linearised
from coreg_ros.core.so3 import skew
from coreg_ros.core.types import CalibrationResult
import numpy as np

#: In the attribution fits, a pair's -2 log-likelihood is clipped at the χ²_m quantile
#: 1 - FIT_CLIP_TAIL (and such pairs are left out of the refit): outliers do not decide.
FIT_CLIP_TAIL = 1e-4
#: The winning alternative must beat the runner-up by this much (-2 log-likelihood + BIC).
DECISIVE = 12.0
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
    size_in : str
        Whose terms ``translation`` and ``rotation`` are in: the kind, or for ``t0_or_t1``
        the one of the two that fitted best.
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
    size_in: str = ''
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
        The calibration in use.
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
    clip = float(chi2_isf(FIT_CLIP_TAIL, m))
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
    lam = max(float(np.median(d2_0) / chi2_ppf(0.5, m)), 1e-6)
    scores['noise'] = float(np.minimum(d2_0 / lam, clip).sum() + n * m * np.log(lam) + log_n)
    order = sorted(scores, key=scores.get)
    kind, runner = order[0], order[1]
    margin = scores[runner] - scores[kind]
    size_in = kind
    other = {'t0': 't1', 't1': 't0'}.get(kind)
    if other is not None and _same_change(fits, f, kind, other):
        # a restricted rig (a gantry): no window will ever tell them apart (the margin
        # between them is only their parameter count); the calibration is stale either way
        runner = min((k for k in scores if k not in ('t0', 't1')), key=scores.get)
        margin = scores[runner] - scores[kind]
        fits['t0_or_t1'] = fits[kind]
        kind = 't0_or_t1'
    out = {'kind': kind, 'decided': bool(margin >= DECISIVE), 'runner_up': runner,
           'margin': margin, 'scores': scores, 'n_pairs': n, 'size_in': size_in}
    C = calibration.cov
    if kind in fits:
        G, delta, cov = fits[kind]
        total = cov + G.T @ C @ G if size_in != 't1' or model != 'three_marker' else cov
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


#: T0's and T1's fits are the same change when the winner's predicted residual change is
#: reproduced by the other's columns to within this share of its squared norm.
SAME_CHANGE_SHARE = 1e-3


def _same_change(fits: dict, f: np.ndarray, kind: str, other: str) -> bool:
    """
    Tell whether the other alternative's columns reproduce the winner's fitted change.

    On a motion that never turns the tool (a gantry), a translation of T0 and one of T1
    change every prediction alike: the two alternatives then fit the same change.
    """
    G, delta, _ = fits[kind]
    change = (f @ G @ delta).reshape(-1)  # the winner's change of the whitened residuals
    J = (f @ fits[other][0]).reshape(len(change), -1)
    rest = change - J @ np.linalg.lstsq(J, change, rcond=None)[0]
    total = float(change @ change)
    return total > 0 and float(rest @ rest) <= SAME_CHANGE_SHARE * total


def describe(att: Attribution) -> str:
    """One line for a person: what changed and by how much (mm, degrees, ms) with σ."""
    head = KIND_TEXT[att.kind]
    if att.kind in ('t0', 't1', 't0_or_t1'):
        size = float(np.linalg.norm(att.translation)) * 1e3
        text = f'{head}: {size:.3g} ± {att.translation_sigma * 1e3:.2g} mm'
        if att.rotation is not None:
            deg = float(np.degrees(np.linalg.norm(att.rotation)))
            text += f', {deg:.3g} ± {np.degrees(att.rotation_sigma):.2g}°'
        frame = "B's base" if att.size_in == 't0' else "A's tool"
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
    do (only τ changed; the recalibration estimates it again); after ``t0_or_t1`` (a motion
    that cannot tell which) neither is kept (an empty prior). After ``noise`` (or no decided
    change) there is nothing to recalibrate: None.

    Parameters
    ----------
    result : CalibrationResult
        The calibration the watchdog found stale (its poses carry their covariance).
    kind : str
        ``Attribution.kind``.

    """
    if kind == 't0_or_t1':
        return Prior()  # neither still holds for sure: recalibrate on the new pairs alone
    if kind not in ('t0', 't1', 'clock'):
        return None
    keep_t0 = kind != 't0' and result.base_to_base.covariance is not None
    keep_t1 = kind != 't1' and result.tool_to_marker.covariance is not None
    if not (keep_t0 or keep_t1):
        return None
    return Prior(result.base_to_base if keep_t0 else None,
                 result.tool_to_marker if keep_t1 else None)

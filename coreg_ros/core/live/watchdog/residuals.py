"""The calibration being watched and each pair's normalised residual against it."""

from __future__ import annotations

from dataclasses import dataclass

from coreg_ros.core import quaternion as quat
from coreg_ros.core.live.guidance import (
    CHUNK,
    effective_covariance,
    Estimate,
    jacobians,
    PairBatch,
)
from coreg_ros.core.models import Parameters, S0, S1, SPECS, tangent_of_chart
from coreg_ros.core.planning.crlb import CRLB_DIMENSION
from coreg_ros.core.types import CalibrationResult
import numpy as np

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
        """Return the measurement model."""
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

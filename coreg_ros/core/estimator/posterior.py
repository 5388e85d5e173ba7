"""
The solution and its posterior covariance (Ikits B.4.2, eq. 58).

At the minimum the covariance of φ is the inverse of the information: JᵀJ for OLS, the Schur
complement S of the TLS normal equations (the φ block of the inverse of the whole normal
matrix) for TLS, priors included in both. The chi-square ``Σ r²`` and its degrees of freedom
(``n_rows - P``) give the goodness of fit (B.4.1).

Published covariances follow ``geometry_msgs/PoseWithCovariance``: 6×6 over
(x, y, z, δθx, δθy, δθz) with ``R_true = Exp(δθ) R_est`` about the fixed axes of the header frame
(docs/design.md §3). A chart step δs moves q to ``Exp(G δs) ⊗ q`` with
``G = 2 vec(R(q*)) dq/ds`` (``models.tangent_of_chart``), so the conversion from φ's coordinates
(positions and reduced quaternions s) is the linear map T: ``C_ros = T C_φ Tᵀ`` (Hoff & Vincent
eq. 6): ``tangent_map``, ``joint_pose_covariance``, ``result_poses``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

from coreg_ros.core import quaternion as quat
from coreg_ros.core.estimator.state import Resume
from coreg_ros.core.models import Parameters, S0, S1, tangent_of_chart
from coreg_ros.core.types import UncertainPose
import numpy as np


def covariance(info: np.ndarray) -> Optional[np.ndarray]:
    """
    Inverse of a symmetric information matrix, None if it is singular.

    Parameters
    ----------
    info : ndarray, shape (P, P)
        JᵀJ (OLS) or the Schur complement S (TLS).

    """
    try:
        cov = np.linalg.inv(info)
    except np.linalg.LinAlgError:
        return None
    if not np.isfinite(cov).all() or (np.diag(cov) <= 0).any():
        return None
    return 0.5 * (cov + cov.T)


@dataclass(frozen=True)
class Solution:
    """
    Outcome of a solver run.

    Attributes
    ----------
    params : Parameters
    cov : ndarray, shape (P, P) or None
        Posterior covariance of φ (eq. 58; TLS: inverse Schur complement).
    info : ndarray, shape (P, P)
        Information matrix JᵀJ (OLS) or Schur complement S (TLS) at the solution.
    chi2 : float
    n_rows : int
        Residual rows beyond the input blocks: N·m plus prior rows.
    residuals : ndarray, shape (N, m), or None
        Whitened output residuals (None for a paused fit, whose refit gives them).
    input_residuals : ndarray, shape (N, 6) or None
        Whitened input residuals (TLS; None for a paused fit).
    iterations : int
    status : int
        How the iterations ended (``lm.MESSAGES``): 1 step small, 2 cost change small,
        0 iteration limit, -1 no acceptable step; ``lm.PAUSED`` (3) a fit stopped before
        its step (``TlsResume.step``), to be continued by the caller.
    message : str
    resume : NormalEquations or TlsResume
        How to go on from this fit (``state.Resume``, ``refit``): OLS, the normal equations
        at the solution; TLS, the estimated inputs and the last linearisation.

    """

    params: Parameters
    cov: Optional[np.ndarray]
    info: np.ndarray
    chi2: float
    n_rows: int
    residuals: Optional[np.ndarray]
    input_residuals: Optional[np.ndarray]
    iterations: int
    status: int
    message: str
    resume: Resume


#: Diagonal value that marks a component as not estimated (sensor_msgs' "unknown" convention).
UNKNOWN = -1.0


def tangent_map(params: Parameters) -> tuple[np.ndarray, np.ndarray]:
    """
    Linear map from δφ to (δp0, δθ0, δp1, δθ1).

    Returns
    -------
    T : ndarray, shape (12, P)
        Rows of T1's rotation are zero where q1 is not estimated.
    known : ndarray of bool, shape (12,)
        Which of the 12 pose components are estimated.

    """
    spec = params.spec
    T = np.zeros((12, spec.n_params))
    T[0:3, 0:3] = np.eye(3)
    T[3:6, S0] = tangent_of_chart(params.q0, params.dq0)
    T[6:9, spec.marker_slice(0)] = np.eye(3)
    known = np.ones(12, dtype=bool)
    if spec.has_q1:
        T[9:12, S1] = tangent_of_chart(params.q1, params.dq1)
    else:
        known[9:12] = False
    return T, known


def joint_pose_covariance(params: Parameters, param_cov: np.ndarray) -> np.ndarray:
    """
    Joint 12×12 covariance of (T0, T1) in the ROS layout, UNKNOWN on unestimated diagonals.

    Parameters
    ----------
    params : Parameters
        The estimated parameters φ.
    param_cov : ndarray, shape (P, P)
        Covariance of φ in its reduced coordinates.

    """
    T, known = tangent_map(params)
    C = T @ param_cov @ T.T
    C = 0.5 * (C + C.T)
    unknown = ~known
    C[unknown, :] = 0.0
    C[:, unknown] = 0.0
    C[unknown, unknown] = UNKNOWN
    return C


def result_poses(params: Parameters, param_cov: Optional[np.ndarray]):
    """
    T0 and T1 as UncertainPose, plus the joint 12×12 covariance (or None).

    T1's orientation is the identity (with UNKNOWN covariance) where it is not estimated.
    """
    joint = None if param_cov is None else joint_pose_covariance(params, param_cov)
    cov0 = None if joint is None else joint[0:6, 0:6]
    cov1 = None if joint is None else joint[6:12, 6:12]
    t0 = UncertainPose(params.p0.copy(), quat.canonical(params.q0), cov0)
    t1 = UncertainPose(params.markers[0].copy(), quat.canonical(params.q1), cov1)
    return t0, t1, joint

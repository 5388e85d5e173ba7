"""
Plain data containers shared by the core, the simulator, the bag layer and the node.

Conventions (DESIGN.md §3): stamps are int64 nanoseconds of the device's clock (header stamp);
positions in metres; quaternions (w, x, y, z); covariances 6×6 over (x, y, z, δθx, δθy, δθz)
with the rotation part the small rotation vector δθ of ``R_true = Exp(δθ) · R_estimate`` about
the fixed axes of the frame the pose is expressed in (``geometry_msgs/PoseWithCovariance``).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional

import numpy as np

#: Names of the measurement models (Ikits eqs. 16, 18, 19).
MODELS = ('full_pose', 'position_only', 'three_marker')
#: Names of the estimators (Ikits appendix B.1, B.2).
METHODS = ('ols', 'tls')


@dataclass(frozen=True)
class PoseStream:
    """
    One device's stream of stamped poses.

    Attributes
    ----------
    stamps : ndarray of int64, shape (N,)
        Header stamps, nanoseconds of the device's clock.
    position : ndarray, shape (N, 3)
        Position of the tracked frame in the device's base frame, metres.
    quat_wxyz : ndarray, shape (N, 4)
        Orientation of the tracked frame in the base frame, (w, x, y, z).
    frame_id : str
        ``header.frame_id`` of the messages (the base frame).
    receive_stamps : ndarray of int64, shape (N,), optional
        Receive or record time, nanoseconds; kept apart from the header stamps.

    """

    stamps: np.ndarray
    position: np.ndarray
    quat_wxyz: np.ndarray
    frame_id: str = ''
    receive_stamps: Optional[np.ndarray] = None

    def __len__(self) -> int:
        return int(self.stamps.shape[0])


@dataclass(frozen=True)
class Pairs:
    """
    Simultaneous samples of device A (input) and device B (output), one row per pair.

    Attributes
    ----------
    stamps : ndarray of int64, shape (N,)
        B's stamps (A is interpolated at them), nanoseconds.
    pos_a : ndarray, shape (N, 3)
        Device A tool position in A's base frame, m.
    quat_a : ndarray, shape (N, 4)
        Device A tool orientation in A's base frame, (w, x, y, z).
    pos_b : ndarray, shape (N, 3) or (N, 3, 3)
        Device B marker position(s) in B's base frame, m. For ``three_marker`` the second axis
        is the marker index 1..3.
    quat_b : ndarray, shape (N, 4), optional
        Device B marker orientation; None for position-only models.
    a_var_scale : ndarray, shape (N,), optional
        Factor on A's noise variance per pair: interpolating between two samples at fraction α
        averages their noise, with variance (α² + (1 - α)²) σ². None means 1.

    """

    stamps: np.ndarray
    pos_a: np.ndarray
    quat_a: np.ndarray
    pos_b: np.ndarray
    quat_b: Optional[np.ndarray] = None
    a_var_scale: Optional[np.ndarray] = None

    def __len__(self) -> int:
        return int(self.pos_a.shape[0])


@dataclass(frozen=True)
class PairingReport:
    """
    What pairing did: counts of B samples paired and not paired, by reason.

    Attributes
    ----------
    n_a, n_b : int
        Samples of A and B offered.
    n_paired : int
        Pairs produced.
    unpaired : dict of str to int
        B samples not paired, by reason (e.g. ``'before_first_a'``, ``'after_last_a'``,
        ``'gap_too_large'``, ``'duplicate_stamp'``, ``'marker_missing'``).
    n_a_unused : int
        A samples that bracket no paired B sample.

    """

    n_a: int
    n_b: int
    n_paired: int
    unpaired: dict = field(default_factory=dict)
    n_a_unused: int = 0

    def summary(self) -> str:
        """One line for a person."""
        why = ', '.join(f'{k}: {v}' for k, v in self.unpaired.items() if v) or 'none'
        return (f'{self.n_paired} pairs from {self.n_a} A and {self.n_b} B samples; '
                f'unpaired B: {why}')


@dataclass(frozen=True)
class UncertainPose:
    """
    A pose with its covariance.

    Attributes
    ----------
    position : ndarray, shape (3,)
        Metres.
    quat_wxyz : ndarray, shape (4,)
        (w, x, y, z), w >= 0.
    covariance : ndarray, shape (6, 6), optional
        ROS ``PoseWithCovariance`` layout (module docstring). A negative diagonal entry marks
        a component that was not estimated (the ``sensor_msgs`` convention for "unknown");
        None when no covariance could be computed.

    """

    position: np.ndarray
    quat_wxyz: np.ndarray
    covariance: Optional[np.ndarray] = None


@dataclass(frozen=True)
class CalibrationResult:
    """
    Result of a calibration, in the manner of ``scipy.optimize.OptimizeResult``.

    Attributes
    ----------
    success : bool
    status : int
        1 converged (step small), 2 converged (cost change small), 0 iteration limit.
    message : str
    model, method : str
    n_pairs : int
    base_to_base : UncertainPose
        T0 = T_bbase_abase: pose of device A's base frame in device B's base frame.
    tool_to_marker : UncertainPose
        T1 = T_atool_bmarker: pose of B's marker frame in A's tool frame (marker 1 for
        ``three_marker``).
    markers : ndarray, shape (k, 3)
        Marker positions in A's tool frame (p1 for full/position-only; p1, p2, p3 for three
        markers), m.
    params : ndarray, shape (P,)
        Parameter vector φ in the final chart (Ikits eq. 17/20).
    param_cov : ndarray, shape (P, P), optional
        Posterior covariance of φ (Ikits eq. 58; for TLS the φ block of the inverse).
    chi2 : float
        Weighted sum of squared residuals S* (Ikits eq. 57).
    dof : int
        Degrees of freedom N·m + prior rows - P.
    p_value : float
        P(χ²_dof >= chi2).
    residuals : ndarray, shape (N, m)
        Whitened output residuals at the solution (unitless, N(0, 1) if the model holds).
    iterations : int
    cov_joint : ndarray, shape (12, 12), optional
        Joint covariance of (T0, T1) in the ROS layout, for propagation.
    input_residuals : ndarray, shape (N, 6), optional
        Whitened input residuals (TLS only): adjusted minus measured A, (position, rotation).

    """

    success: bool
    status: int
    message: str
    model: str
    method: str
    n_pairs: int
    base_to_base: UncertainPose
    tool_to_marker: UncertainPose
    markers: np.ndarray
    params: np.ndarray
    param_cov: Optional[np.ndarray]
    chi2: float
    dof: int
    p_value: float
    residuals: np.ndarray
    iterations: int
    cov_joint: Optional[np.ndarray] = None
    input_residuals: Optional[np.ndarray] = None

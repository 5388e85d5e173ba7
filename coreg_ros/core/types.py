# noqa: A005 (coreg_ros.core.types: imported as a package module, never as `types`)
"""
Plain data containers shared by the core, the simulator, the bag layer and the node.

Conventions (docs/design.md §3): stamps are int64 nanoseconds of the device's clock (header stamp);
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

    def take(self, keep) -> PoseStream:
        """
        Return the samples ``keep`` of the stream, receive stamps included.

        Parameters
        ----------
        keep : ndarray of int or bool, or slice
            Indices, a mask of shape (N,), or a slice of the samples to keep, in that order.

        """
        return PoseStream(stamps=self.stamps[keep], position=self.position[keep],
                          quat_wxyz=self.quat_wxyz[keep], frame_id=self.frame_id,
                          receive_stamps=(None if self.receive_stamps is None
                                          else self.receive_stamps[keep]))


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
class TimeOffset:
    """
    B's clock minus A's clock as used for the pairs of a calibration.

    Attributes
    ----------
    value_s : float
        τ0, s (at ``reference_ns`` when a drift is estimated).
    sigma_s : float or None
        Posterior σ of τ0, s (None when not estimated).
    estimated : bool
        False when τ was given (``--time-offset S``) or the motion could not determine it.
    drift_ppm, drift_sigma_ppm : float or None
        κ and its σ, parts per million (only when the drift was estimated).
    reference_ns : int
        t_mid, the B stamp at which τ(t) = τ0 (ns, B's clock).
    message : str
        Why τ was not estimated, or how it was found.
    cross_cov : ndarray, shape (12, k), optional
        Covariance of (T0, T1) in the ROS layout with (τ0[, κ]) (s, dimensionless).
    cov : ndarray, shape (k, k), optional
        Covariance of (τ0[, κ]).

    """

    value_s: float
    sigma_s: Optional[float] = None
    estimated: bool = False
    drift_ppm: Optional[float] = None
    drift_sigma_ppm: Optional[float] = None
    reference_ns: int = 0
    message: str = ''
    cross_cov: Optional[np.ndarray] = None
    cov: Optional[np.ndarray] = None

    @property
    def drift(self) -> float:
        """κ, dimensionless (0 when not estimated)."""
        return 0.0 if self.drift_ppm is None else self.drift_ppm * 1e-6

    def offset_ns(self) -> int:
        """τ0 in integer nanoseconds (for pairing)."""
        return int(round(self.value_s * 1e9))

    def offset_ns_at(self, stamp_b: int) -> int:
        """τ(t) in integer nanoseconds at B stamp ``stamp_b`` (drift included)."""
        return self.offset_ns() + int(round(self.drift * (int(stamp_b) - self.reference_ns)))

    @classmethod
    def from_dict(cls, offset: Optional[dict], drift: Optional[dict] = None
                  ) -> Optional[TimeOffset]:
        """Inverse of ``as_dict`` / ``drift_dict`` (None when ``offset`` is None)."""
        if not offset:
            return None
        drift = drift or {}
        return cls(float(offset.get('value_s', 0.0)), offset.get('sigma_s'),
                   bool(offset.get('estimated', False)), drift.get('value_ppm'),
                   drift.get('sigma_ppm'), int(drift.get('reference_ns', 0)),
                   str(offset.get('message', '')))

    def as_dict(self) -> dict:
        """``{"value_s", "sigma_s", "estimated", "message"}``."""
        return {'value_s': float(self.value_s),
                'sigma_s': None if self.sigma_s is None else float(self.sigma_s),
                'estimated': bool(self.estimated), 'message': self.message}

    def drift_dict(self) -> Optional[dict]:
        """``{"value_ppm", "sigma_ppm", "reference_ns"}`` or None when no drift was estimated."""
        if self.drift_ppm is None:
            return None
        return {'value_ppm': float(self.drift_ppm),
                'sigma_ppm': None if self.drift_sigma_ppm is None else float(
                    self.drift_sigma_ppm),
                'reference_ns': int(self.reference_ns)}


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
class Unobservable:
    """
    A direction of (T0, T1) the recorded motion does not determine (a restricted rig).

    Attributes
    ----------
    direction : ndarray, shape (12,)
        Unit vector in the layout of ``CalibrationResult.cov_joint``: T0's position (B's base
        frame, m), its rotation (about B's base axes, rad), T1's position (A's tool frame, m),
        its rotation (about A's tool axes, rad); its largest component positive.
    description : str
        The direction in words ("T1's position along z (A's tool frame) together with T0's
        translation along ... (B's base frame)").
    by : str
        ``'held'``: nothing determines it; the fit holds it (``held_at``) and every published
        covariance carries ``observability.UNKNOWN_VARIANCE`` along it. ``'prior'``: the
        prior determines it, with the prior's variance.
    held_at : dict
        ``{"component", "value", "unit", "from"}``: the component that holds it and its value
        (the closed-form start's, or the prior's).
    determine : str
        What would determine it: a partial prior (a measured lever, a known orientation) or
        the motion that shows it.
    markers : ndarray, shape (9,), optional
        Three markers: the direction's part on the three marker positions (A's tool frame).

    """

    direction: np.ndarray
    description: str
    by: str
    held_at: dict
    determine: str
    markers: Optional[np.ndarray] = None

    def as_dict(self) -> dict:
        """JSON form: ``{"direction", "description", "held_at", "by", "determine"}``."""
        out = {'direction': [float(v) for v in self.direction],
               'description': self.description, 'held_at': dict(self.held_at), 'by': self.by,
               'determine': self.determine}
        if self.markers is not None:
            out['markers_direction'] = [float(v) for v in self.markers]
        return out


#: The ``status`` values of a calibration and what each means.
STATUS = {
    1: 'converged: every step component below xtol posterior standard deviations',
    2: 'converged: the cost no longer decreases by more than ftol (relative)',
    0: 'stopped at the iteration limit before converging',
    -1: 'no damping reduced the cost although the step was not small: the model does not fit',
}


@dataclass(frozen=True)
class CalibrationResult:
    """
    Result of a calibration, in the manner of ``scipy.optimize.OptimizeResult``.

    Attributes
    ----------
    success : bool
    status : int
        How the Levenberg-Marquardt iterations ended (``STATUS`` holds this table):

        ====  =====================================================================
         1    converged: every step component below ``xtol`` posterior σ
         2    converged: the cost no longer decreases by more than ``ftol``
         0    stopped at the iteration limit before converging
        -1    no damping reduced the cost although the step was not small: the
              model does not fit the data (stream directions, units)
        ====  =====================================================================

        ``success`` also needs a posterior covariance and a consistent fit.
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
    charts : tuple of (int, float)
        Charts of the reduced quaternions of ``params`` (``models.Parameters``).
    inliers : ndarray of bool, shape (N_pairs,), optional
        Which of the pairs given the fit used (all unless the robust fit rejected some);
        ``residuals`` and ``input_residuals`` are those of the inliers.
    rejected_stamps : ndarray of int64, optional
        B stamps (ns) of the rejected pairs.
    time_offset : TimeOffset, optional
        The clock offset the pairs were made with (estimated or given).
    fit_consistent : bool, optional
        False when the fit does not match the stated noise (p below
        ``verdict.CONSISTENT_P``); None until judged.
    verdict : str
        Why the fit is inconsistent and what to do (empty when consistent).
    prior_check : dict, optional
        ``{"chi2", "dof", "p_value", "consistent"}`` of the prior's own residual rows.
    direction_check : calibration.stream_directions.DirectionReport, optional
        Which way round the streams fit best, when the pipeline checked it (after a fit the
        data contradict); a flagged report makes the result not a success.
    unobservable : tuple of Unobservable
        The directions the motion does not determine (a restricted rig: a SCARA arm, a mobile
        robot, a gantry, a turntable), held or determined by the prior; empty when the motion
        determines everything. The published covariances (``cov_joint``, the poses') carry
        ``observability.UNKNOWN_VARIANCE`` along the held ones; ``param_cov`` is the fit's,
        the held directions pinned in it.
    cov_determined : ndarray, shape (12, 12), optional
        With directions held: the joint covariance of the part the motion determines (the
        published one less what it says along them). What propagates through the model
        (``cov_for_propagation``), which a held direction does not change.
    refusals : tuple of str
        Checks that refuse a converged fit whatever its chi-square, by name:
        ``'devices_swapped'`` when the messages' frame ids say that A and B are swapped and
        the user has not confirmed the roles. Empty when none refuses.
    noise : calibration.noise_verdict.NoiseEstimate, optional
        Each device's noise estimated jointly with the calibration (``noise: auto``), which
        the fit then used; None when the noise was stated.

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
    charts: tuple = ()
    inliers: Optional[np.ndarray] = None
    rejected_stamps: Optional[np.ndarray] = None
    time_offset: Optional[TimeOffset] = None
    fit_consistent: Optional[bool] = None
    verdict: str = ''
    prior_check: Optional[dict] = None
    direction_check: Optional[object] = None
    unobservable: tuple = ()
    cov_determined: Optional[np.ndarray] = None
    noise: Optional[object] = None
    refusals: tuple = ()

    @property
    def flagged(self) -> bool:
        """
        Tell whether the fit converged but is not to be used as it stands.

        The data contradict it (``fit_consistent`` False: a bad chi-square or a disagreeing
        prior) or a check refuses it (``refusals``): ``coreg calibrate`` exits 3 and the node
        does not publish it.
        """
        return self.status > 0 and (self.fit_consistent is False or bool(self.refusals))

    @property
    def reduced_chi2(self) -> float:
        """chi2 / dof (≈ 1 when the stated noise is right; nan without degrees of freedom)."""
        return self.chi2 / self.dof if self.dof > 0 else float('nan')

    def summary(self, pairing: Optional[PairingReport] = None) -> str:
        """Return the text ``coreg calibrate`` prints (with the pairing report, if given)."""
        from coreg_ros.core.result_text import format_result
        return format_result(self, pairing)

    @property
    def cov_for_propagation(self) -> Optional[np.ndarray]:
        """
        Return the joint covariance to carry through the model (``T0 · T_A · T1``).

        ``cov_determined`` when directions are held (a held direction does not change any
        prediction, and its unknown variance must not leak into them), else ``cov_joint``.
        """
        return self.cov_joint if self.cov_determined is None else self.cov_determined

    @property
    def held(self) -> tuple:
        """Return the held directions: those of ``unobservable`` that no prior determines."""
        return tuple(u for u in self.unobservable if u.by == 'held')

    @property
    def n_rejected(self) -> int:
        """Pairs the robust fit rejected."""
        return 0 if self.rejected_stamps is None else int(len(self.rejected_stamps))

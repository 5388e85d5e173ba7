"""
What a rig's calibration gives: every device's transforms in the rig, and their joint covariance.

``RigResult.devices`` holds, per device B_k, its ``CalibrationResult`` in the rig (T0_k, T1_k,
τ_k with the marginals of the joint posterior, its own residuals, its share of χ²) beside the
device calibrated with A alone (``alone``: today's two-device result), so the gain of the joint
fit is there to see (``sigma_ratio``). ``cov_joint`` is the covariance of every device's T0, T1
(ROS layout, 12 each) and τ, cross terms included: what ``loops`` propagates to the pose of any
device's base in any other's.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

from coreg_ros.core.types import CalibrationResult, PairingReport, UncertainPose
import numpy as np


@dataclass(frozen=True)
class DeviceResult:
    """
    One device B_k of a rig.

    Attributes
    ----------
    name : str
    topics : tuple of str
        Its topic(s) (three for ``three_marker``), or empty for arrays.
    base : str
        Its base: devices with the same base are sensors of one device (one T0, one clock).
    result : CalibrationResult
        Its calibration in the rig: T0_k (``base_to_base``), T1_k, τ_k, their covariance (the
        joint posterior's marginal), its residuals and χ² share (``chi2``, ``dof``).
    alone : CalibrationResult
        The device calibrated with A alone (the two-device calibration).
    pairing : PairingReport
        Its pairs with A in the rig.
    chi2_share : float
        Its share of the rig's χ².
    sigma_ratio : ndarray, shape (12,)
        σ in the rig over σ alone per component of (T0, T1) in the ROS layout (NaN where a
        component is not estimated): below 1 where the other devices inform this one.

    """

    name: str
    topics: tuple
    base: str
    result: CalibrationResult
    alone: CalibrationResult
    pairing: PairingReport
    chi2_share: float
    sigma_ratio: np.ndarray


@dataclass(frozen=True)
class RigResult:
    """
    A rig's joint calibration (device A and K devices B_k).

    Attributes
    ----------
    success : bool
        Converged, a covariance, and the fit (and every device's share) matches the stated noise.
    status : int
        How the joint iterations ended (``types.STATUS``).
    message : str
    method : str
    devices : tuple of DeviceResult
    chi2 : float
    dof : int
    p_value : float
    fit_consistent : bool
    verdict : str
        Which device's fit does not match its stated noise, and what to do (empty when
        consistent).
    cov_joint : ndarray, shape (13K, 13K) or None
        Covariance of (T0_1, T1_1, ..., T0_K, T1_K, τ_1, ..., τ_K): T0_k and T1_k in the ROS
        layout at rows 12k..12k+12, τ_k (s) at row 12K + k. Devices that share a base repeat
        its T0 (and clock); UNKNOWN (-1) on the diagonal of components not estimated.
    shared_instants : tuple of tuple of str
        Groups of devices that measure the body at the same instants (one input pose each).
    iterations : int
    loops : LoopReport, optional
        The rig against its pairwise calibrations (``loops.loop_report``).

    """

    success: bool
    status: int
    message: str
    method: str
    devices: tuple
    chi2: float
    dof: int
    p_value: float
    fit_consistent: bool
    verdict: str
    cov_joint: Optional[np.ndarray]
    shared_instants: tuple = ()
    iterations: int = 0
    loops: Optional[object] = None

    @property
    def names(self) -> tuple:
        """Return the devices' names, in order."""
        return tuple(d.name for d in self.devices)

    def index(self, name: str) -> int:
        """Return the index of the device called ``name`` (a ValueError names the others)."""
        if name not in self.names:
            raise ValueError(f'no device {name!r} in the rig; its devices: '
                             f'{", ".join(self.names)}')
        return self.names.index(name)

    def base_to_base(self, k: int) -> UncertainPose:
        """T0_k: the pose of A's base in device k's base, with its rig covariance."""
        return self.devices[k].result.base_to_base

    def block(self, rows: list) -> Optional[np.ndarray]:
        """Return the joint covariance of the given rows of ``cov_joint`` (None without one)."""
        if self.cov_joint is None:
            return None
        idx = np.asarray(rows, dtype=int)
        return self.cov_joint[np.ix_(idx, idx)]

    def summary(self) -> str:
        """Return the text ``coreg calibrate`` prints for a rig."""
        from coreg_ros.core.rig.text import format_rig
        return format_rig(self)

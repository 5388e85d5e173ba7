"""
Live fusion of the two devices once a calibration exists: the ROS-free part of ``~/fused_pose``.

For every pair (A interpolated at B's stamp by the one pairing rule, ``pairing.pair_streams``),
device A's tool pose is carried into B's base frame through the calibration,
``T0 · T_A · T1`` with the joint covariance of (T0, T1) and A's noise (Hoff eq. 7), and fused
with device B's own measurement by inverse-covariance weighting on the tangent space (Hoff
§3.4): the result is a pose of B's marker in B's base frame better than either device's.

Models
    ``full_pose``: the whole pose is fused (6 × 6).
    ``position_only`` and ``three_marker``: B reports positions only and T1's rotation is not
    estimated, so only the positions are fused (B's marker 1 for ``three_marker``); the
    orientation is A's through the calibration with T1's nominal rotation and is marked
    unknown (rotation block of the covariance zero, diagonal -1, the ``sensor_msgs``
    convention), so nobody mistakes it for a measurement.

``pending_pairs`` pairs only the samples that arrived since the last call, on short windows of
the newest samples, so a node can fuse a live stream at a fixed rate without re-pairing its
whole buffer; every B sample is fused at most once and, with long enough windows, exactly the
pairs ``pair_streams`` finds on the whole streams come out.

Covariances follow docs/design.md §3: 6×6 over (x, y, z, δθx, δθy, δθz) about B's base axes, with
``p_true = p + δp`` and ``R_true = Exp(δθ) · R``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Optional, Union

from coreg_ros.core.calibration.pairing import pair_streams
from coreg_ros.core.noise_model import noise_covariance
from coreg_ros.core.types import CalibrationResult, Pairs, PoseStream, UncertainPose
from coreg_ros.core.uncertainty import fuse_arrays, through_calibration_arrays, UNKNOWN
import numpy as np

#: Models whose B measurement carries an orientation that can be fused.
ORIENTED_MODELS = ('full_pose',)


@dataclass(frozen=True)
class FusionCalibration:
    """
    What fusion needs of a calibration: T0, T1, their joint covariance and the model.

    Attributes
    ----------
    base_to_base : UncertainPose
        T0 = T_bbase_abase, pose of A's base frame in B's base frame.
    tool_to_marker : UncertainPose
        T1 = T_atool_bmarker, pose of B's marker (marker 1) in A's tool frame.
    cov_joint : ndarray, shape (12, 12)
        Joint covariance of (T0, T1), ROS layout each; negative diagonal = not estimated.
    model : str
        ``full_pose``, ``position_only`` or ``three_marker``.

    """

    base_to_base: UncertainPose
    tool_to_marker: UncertainPose
    cov_joint: np.ndarray
    model: str

    @classmethod
    def from_result(cls, result: CalibrationResult) -> FusionCalibration:
        """Take T0, T1 and their joint covariance (cross terms included) from a result."""
        joint = result.cov_for_propagation  # held directions (restricted rigs) change no pose
        if joint is None:
            joint = block_joint_covariance(result.base_to_base, result.tool_to_marker)
        return cls(result.base_to_base, result.tool_to_marker,
                   np.asarray(joint, dtype=float).reshape(12, 12), result.model)

    @classmethod
    def from_poses(cls, base_to_base: UncertainPose, tool_to_marker: UncertainPose,
                   model: str, cov_joint=None) -> FusionCalibration:
        """
        Build from the two poses, e.g. a stored result.

        Without ``cov_joint`` the cross-covariance of T0 and T1 is taken as zero (block
        diagonal from the poses' own covariances): with a few thousand pairs that changes the
        predicted σ of A-through-calibration by about 1 %.
        """
        if cov_joint is None:
            cov_joint = block_joint_covariance(base_to_base, tool_to_marker)
        return cls(base_to_base, tool_to_marker,
                   np.asarray(cov_joint, dtype=float).reshape(12, 12), str(model))

    @property
    def orientation_fused(self) -> bool:
        """Whether the model fuses orientations (``full_pose``) or positions only."""
        return self.model in ORIENTED_MODELS


def block_joint_covariance(base_to_base: UncertainPose,
                           tool_to_marker: UncertainPose) -> np.ndarray:
    """
    Return the 12×12 covariance of (T0, T1) from their own 6×6 covariances, cross terms zero.

    A pose without covariance counts as exactly known (zeros).
    """
    joint = np.zeros((12, 12))
    for k, pose in enumerate((base_to_base, tool_to_marker)):
        if pose.covariance is not None:
            joint[6 * k:6 * k + 6, 6 * k:6 * k + 6] = np.asarray(pose.covariance,
                                                                 dtype=float).reshape(6, 6)
    return joint


@dataclass(frozen=True)
class FusedPoses:
    """
    Fused poses of B's marker in B's base frame, one per pair.

    Attributes
    ----------
    stamps : ndarray of int64, shape (N,)
        B's stamps of the pairs (B's clock), ns.
    position : ndarray, shape (N, 3)
        m, in B's base frame.
    quat_wxyz : ndarray, shape (N, 4)
        (w, x, y, z), w >= 0. For position-only models A's prediction, not fused.
    covariance : ndarray, shape (N, 6, 6)
        ROS layout about B's base axes; rotation UNKNOWN (-1 diagonal) for position-only models.
    orientation_fused : bool
        True for ``full_pose``.

    """

    stamps: np.ndarray
    position: np.ndarray
    quat_wxyz: np.ndarray
    covariance: np.ndarray
    orientation_fused: bool

    def __len__(self) -> int:
        return int(self.stamps.shape[0])

    def pose(self, i: int = -1) -> UncertainPose:
        """Return pair ``i`` (default the newest) as an UncertainPose."""
        return UncertainPose(self.position[i].copy(), self.quat_wxyz[i].copy(),
                             self.covariance[i].copy())


def fused_stream(calibration: Union[FusionCalibration, CalibrationResult], pairs: Pairs,
                 sigma_a, sigma_b) -> FusedPoses:
    """
    Fuse each pair's A-through-calibration pose with B's measurement (Hoff eq. 7, §3.4).

    Parameters
    ----------
    calibration : FusionCalibration or CalibrationResult
        T0, T1 and their joint covariance.
    pairs : Pairs
        ``pos_a`` (N, 3) m and ``quat_a`` (N, 4) A's tool pose in A's base frame; ``pos_b``
        (N, 3), or (N, 3, 3) for three markers (marker 1 is used), m in B's base frame;
        ``quat_b`` (N, 4) or None; ``a_var_scale`` (N,) factor on A's noise variance from the
        interpolation (None: 1).
    sigma_a, sigma_b : array_like
        Device noise as ``(position m, rotation rad)`` or a 6×6 ROS-layout covariance (A's
        about A's base axes, B's about B's base axes).

    Returns
    -------
    FusedPoses
        The whole pose fused for ``full_pose`` (when B's orientations are given); the
        positions only otherwise (module docstring).

    """
    if isinstance(calibration, CalibrationResult):
        calibration = FusionCalibration.from_result(calibration)
    n = len(pairs)
    cov_a = np.broadcast_to(noise_covariance(sigma_a), (n, 6, 6))
    if pairs.a_var_scale is not None:
        cov_a = cov_a * np.asarray(pairs.a_var_scale, dtype=float)[:, None, None]
    cov_b = noise_covariance(sigma_b)
    stamps = np.asarray(pairs.stamps, dtype=np.int64)
    if n == 0:
        return FusedPoses(stamps, np.zeros((0, 3)), np.zeros((0, 4)), np.zeros((0, 6, 6)),
                          calibration.orientation_fused)
    p_a, q_a, c_a = through_calibration_arrays(calibration, pairs.pos_a, pairs.quat_a, cov_a)
    pos_b = np.asarray(pairs.pos_b, dtype=float)
    if pos_b.ndim == 3:  # three markers: marker 1 is the one T1 locates
        pos_b = pos_b[:, 0, :]
    if calibration.orientation_fused and pairs.quat_b is not None:
        p, q, c, _ = fuse_arrays(p_a, q_a, c_a, pos_b, pairs.quat_b,
                                 np.broadcast_to(cov_b, (n, 6, 6)))
        return FusedPoses(stamps, p, q, c, True)
    p, c_p = fuse_positions(p_a, c_a[:, 0:3, 0:3], pos_b, cov_b[0:3, 0:3])
    cov = np.zeros((n, 6, 6))
    cov[:, 0:3, 0:3] = c_p
    cov[:, 3, 3] = cov[:, 4, 4] = cov[:, 5, 5] = UNKNOWN
    return FusedPoses(stamps, p, q_a, cov, False)


def fuse_positions(p1, cov1, p2, cov2) -> tuple[np.ndarray, np.ndarray]:
    """
    Fuse two estimates of positions: ``C = (C1⁻¹ + C2⁻¹)⁻¹``, ``p = C (C1⁻¹ p1 + C2⁻¹ p2)``.

    Parameters
    ----------
    p1, p2 : array_like, shape (..., 3)
        m.
    cov1, cov2 : array_like, shape (..., 3, 3)
        Positive definite, m².

    Returns
    -------
    p : ndarray, shape (..., 3)
    cov : ndarray, shape (..., 3, 3)

    """
    i1 = np.linalg.inv(np.asarray(cov1, dtype=float))
    i2 = np.linalg.inv(np.asarray(cov2, dtype=float))
    cov = np.linalg.inv(i1 + i2)
    cov = 0.5 * (cov + np.swapaxes(cov, -1, -2))
    eta = (np.einsum('...ij,...j->...i', i1, np.asarray(p1, dtype=float))
           + np.einsum('...ij,...j->...i', i2, np.asarray(p2, dtype=float)))
    return np.einsum('...ij,...j->...i', cov, eta), cov


# --------------------------------------------------------------------------- incremental pairing

def pending_pairs(stream_a: PoseStream, streams_b: Union[PoseStream, Sequence[PoseStream]],
                  after_ns: Optional[int], *, max_gap_ns: int, offset_ns: int = 0,
                  with_orientation_b: bool = True) -> tuple[Pairs, Optional[int]]:
    """
    Pair the B samples stamped after ``after_ns`` that can be decided now, on recent windows.

    ``pair_streams`` (the one pairing rule) runs on the given windows, restricted to B samples
    later than ``after_ns``. A B sample whose interpolation time lies after A's newest sample
    (or, for three markers, after another marker's newest sample) is not decided yet: it is
    left for a later call, when the next A sample has arrived. The others are paired or
    dropped for good (gap too large, before the A window), and the returned cursor moves past
    them, so each B sample is fused at most once.

    Parameters
    ----------
    stream_a : PoseStream
        The newest samples of device A (a window of its buffer), stamps increasing.
    streams_b : PoseStream or sequence of PoseStream
        The newest samples of device B (one stream, or three marker streams), stamps
        increasing.
    after_ns : int or None
        Cursor: B stamps up to it are done (None: none are). If B's newest stamp is earlier
        than the cursor, the buffers were reset (or B's clock jumped back) and the cursor is
        ignored.
    max_gap_ns, offset_ns, with_orientation_b
        As ``pair_streams``.

    Returns
    -------
    pairs : Pairs
        Possibly empty, oldest first.
    cursor : int or None
        The new ``after_ns``: the newest B stamp decided (the old cursor if none).

    """
    markers = [streams_b] if isinstance(streams_b, PoseStream) else list(streams_b)
    b = markers[0]
    stamps_b = np.asarray(b.stamps, dtype=np.int64)
    empty = _empty_pairs(len(markers) == 3, with_orientation_b)
    if len(stamps_b) == 0 or len(stream_a) == 0 or any(len(m) == 0 for m in markers):
        return empty, after_ns
    if after_ns is not None and stamps_b[-1] < after_ns:
        after_ns = None  # reset: start again from the windows
    start = 0 if after_ns is None else int(np.searchsorted(stamps_b, after_ns, side='right'))
    # decided: A's newest sample (and each other marker's) is at or after the B stamp
    limit = int(np.asarray(stream_a.stamps)[-1]) + int(offset_ns)
    for m in markers[1:]:
        limit = min(limit, int(np.asarray(m.stamps)[-1]))
    stop = int(np.searchsorted(stamps_b, limit, side='right'))
    if stop <= start:
        return empty, after_ns
    # marker 1 restricted to the pending samples; markers 2, 3 are interpolated at its stamps
    window = [b.take(slice(start, stop)), *markers[1:]]
    # A samples older than max_gap before the first pending stamp can bracket no pair (the
    # pair would be refused for its gap either way): leave them out, pairing costs O(window)
    first_a = int(np.searchsorted(np.asarray(stream_a.stamps, dtype=np.int64),
                                  int(stamps_b[start]) - int(offset_ns) - int(max_gap_ns),
                                  side='left'))
    stream_a = stream_a.take(slice(first_a, None))
    pairs, _ = pair_streams(stream_a, window if len(window) == 3 else window[0],
                            max_gap_ns=int(max_gap_ns), offset_ns=int(offset_ns),
                            with_orientation_b=with_orientation_b)
    return pairs, int(stamps_b[stop - 1])


def _empty_pairs(three: bool, with_orientation_b: bool) -> Pairs:
    return Pairs(stamps=np.zeros(0, np.int64), pos_a=np.zeros((0, 3)), quat_a=np.zeros((0, 4)),
                 pos_b=np.zeros((0, 3, 3)) if three else np.zeros((0, 3)),
                 quat_b=np.zeros((0, 4)) if with_orientation_b and not three else None,
                 a_var_scale=np.zeros(0))


__all__ = ['FusedPoses', 'FusionCalibration', 'ORIENTED_MODELS', 'block_joint_covariance',
           'fuse_positions', 'fused_stream', 'pending_pairs']

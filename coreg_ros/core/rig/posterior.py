"""
The rig's joint posterior over every device's T0, T1 and clock offset (Ikits B.4.2).

At fixed clock offsets the joint fit's information is the sum of the devices' (``joint``).
Each clock's offset τ_g (and drift) enters through the devices it stamps: per device the
offset's column ``c = -F_x ẋ_A`` (``clock.timing``) gives ``h_ττ = Σ cᵀ W c`` and
``h_φτ = Σ F_φᵀ W c`` at the joint solution, placed at the device's columns of φ. The joint
information over (φ, τ) is

    [[S, h_φτ], [h_φτᵀ, h_ττ]]

and its inverse the joint covariance with every cross term: for one device it is exactly the
two-device result's ``H⁻¹ + (dφ/dτ) S_τ⁻¹ (dφ/dτ)ᵀ`` (``offset_search``). ``ros_covariance``
maps it to the ROS layout of each device's (T0, T1) and τ (Hoff & Vincent eq. 6).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

from coreg_ros.core.clock.timing import query_seconds, velocity_step
from coreg_ros.core.clock.trajectory import Trajectory, VELOCITY_HALF_WINDOW
from coreg_ros.core.estimator.linearized import PairData
from coreg_ros.core.estimator.posterior import covariance, tangent_map, UNKNOWN
from coreg_ros.core.estimator.problem import Problem
from coreg_ros.core.models import Parameters
from coreg_ros.core.rig.layout import RigParameters
from coreg_ros.core.types import PoseStream, TimeOffset
import numpy as np


@dataclass(frozen=True)
class Clock:
    """
    One clock of the rig (a device's, shared by the sensors of one base).

    Attributes
    ----------
    devices : tuple of int
        The devices that stamp with it.
    timing : TimeOffset
        Its offset (and drift) the pairs are made with.
    n_time : int
        Parameters of the clock in the joint posterior: 0 (given), 1 (τ), 2 (τ, κ).
    sigma : tuple of float
        The σ of those parameters from the devices' own fits (τ s, κ dimensionless): their
        information where the joint fit's motion does not determine them.

    """

    devices: tuple
    timing: TimeOffset
    n_time: int
    sigma: tuple = ()


class ATrajectory:
    """A's tool motion on A's clock, to evaluate its velocity at any device's pairs."""

    def __init__(self, stream_a: PoseStream):
        self.origin_ns = int(stream_a.stamps[0])
        t = (stream_a.stamps - np.int64(self.origin_ns)).astype(float) * 1e-9
        step = float(np.median(np.diff(t))) if len(t) > 1 else 0.0
        self.half = max(VELOCITY_HALF_WINDOW, 1.5 * step)
        self.trajectory = Trajectory(t, stream_a.position, stream_a.quat_wxyz)


def time_information(motion: ATrajectory, problem: Problem, stamps: np.ndarray,
                     params: Parameters, param_cov: np.ndarray, clock: Clock, cov_a: np.ndarray,
                     cov_b_metric: np.ndarray, tls: bool, max_gap: float):
    """
    Compute the information of a device's pairs on its clock's parameters at the joint fit.

    Parameters
    ----------
    motion : ATrajectory
        A's motion.
    problem : Problem
        The device's pairs (inliers).
    stamps : ndarray of int64, shape (N,)
        Their B stamps, ns.
    params : Parameters
        φ_k at the joint solution.
    param_cov : ndarray, shape (P_k, P_k)
        φ_k's covariance at fixed offsets (any positive definite inverse information: the
        information below does not depend on it).
    clock : Clock
        The device's clock (its offset, what is estimated).
    cov_a : ndarray, shape (6, 6)
        A's noise, ROS layout.
    cov_b_metric : ndarray, shape (m, m)
        B's noise in the error metric (``estimator.output_covariance``).
    tls : bool
        Whether A's noise enters (TLS).
    max_gap : float
        s, as pairing.

    Returns
    -------
    info : (h_φτ, h_ττ, g_τ) of shapes (P_k, n), (n, n), (n,), or None
        The information and the gradient of ½χ² on the clock's parameters (φ at its
        optimum); None when the motion does not determine the offset at the joint solution.
    half : float
        The half window (s) of A's velocity that shows the motion (``velocity_step``).

    """
    timing = clock.timing
    kappa = timing.drift if clock.n_time == 2 else 0.0
    t_a = query_seconds(stamps, timing.value_s, kappa, timing.reference_ns, motion.origin_ns)
    since = None if clock.n_time < 2 else (
        (stamps - np.int64(timing.reference_ns)).astype(float) * 1e-9)
    data = PairData(problem.pos_a, problem.quat_a, problem.pos_b, problem.quat_b, cov_a,
                    cov_b_metric, problem.a_scale, tls)
    step, half = velocity_step(motion.trajectory, t_a, motion.half, max_gap, params, data,
                               since, param_cov, cov_a)
    if step.cov is None or not step.determined()[0]:
        return None, half
    # the step's own elimination of φ undone: h_φτ = -H dφ/dτ, h_ττ = S_τ + h_φτᵀ H⁻¹ h_φτ
    H = np.linalg.inv(param_cov)
    h_pt = -H @ step.dphi
    S_t = np.linalg.inv(step.cov)
    return (h_pt, S_t + step.dphi.T @ H @ step.dphi, -S_t @ step.delta), half


def input_shift(motion: ATrajectory, instants_ns: np.ndarray, clock: Clock, half: float,
                max_gap: float) -> np.ndarray:
    """
    How A's measured inputs move with the clock's parameters: (n, 6, n_time).

    A is interpolated at ``t_B - τ(t_B)``: a change of τ shifts it by ``-ẋ_A δτ``, so the
    input error ``x - x̃`` moves by ``+ẋ_A δτ`` (and by ``ẋ_A (t_B - t_ref) δκ``).
    """
    t = (np.asarray(instants_ns, dtype=np.int64) - np.int64(motion.origin_ns)).astype(
        float) * 1e-9
    v, w = motion.trajectory.velocity(t, half, max_gap=max_gap)
    shift = np.hstack([v, w])[:, :, None]
    if clock.n_time == 2:
        stamps = np.asarray(instants_ns, dtype=np.int64) + np.int64(clock.timing.offset_ns())
        since = (stamps - np.int64(clock.timing.reference_ns)).astype(float) * 1e-9
        shift = np.concatenate([shift, shift * since[:, None, None]], axis=2)
    return shift


def joint_covariance(info: np.ndarray, clocks: list, contributions: list
                     ) -> tuple[Optional[np.ndarray], list, np.ndarray]:
    """
    Invert the joint information of (φ, every clock's parameters).

    Parameters
    ----------
    info : ndarray, shape (P, P)
        The joint fit's information at fixed offsets.
    clocks : list of Clock
        The rig's clocks.
    contributions : list of (ndarray, int, ndarray, ndarray, ndarray)
        (columns of φ, clock, h_φτ over those columns, h_ττ, g_τ): a device's pairs'
        (``time_information``) or a group's sharing instants.

    Returns
    -------
    cov : ndarray, shape (P + T, P + T) or None
        T = Σ n_time; None when singular.
    time_columns : list of ndarray
        Each clock's rows of ``cov`` (empty for a given offset).
    step : ndarray, shape (P + T,)
        The Gauss-Newton step of (φ, the clocks) from the clocks' gradients (φ at its
        optimum at the given offsets): the offsets' joint optimum, and φ's move with them.

    """
    P = info.shape[0]
    time_columns, cursor = [], P
    for clock in clocks:
        time_columns.append(cursor + np.arange(clock.n_time))
        cursor += clock.n_time
    J, grad = np.zeros((cursor, cursor)), np.zeros(cursor)
    J[:P, :P] = info
    informed = [False] * len(clocks)
    for cols, g, h_pt, h_tt, g_t in contributions:
        tc = time_columns[g]
        J[np.ix_(cols, tc)] += h_pt
        J[np.ix_(tc, cols)] += h_pt.T
        J[np.ix_(tc, tc)] += h_tt
        grad[tc] += g_t
        informed[g] = True
    for g, clock in enumerate(clocks):
        if clock.n_time and not informed[g]:
            # the motion does not pin it at the joint solution: the devices' own σ (e.g. the
            # coarse estimate's), independent of the transforms
            tc = time_columns[g]
            J[tc, tc] += 1.0 / np.square(np.asarray(clock.sigma[:clock.n_time], dtype=float))
    cov = covariance(J)
    return cov, time_columns, np.zeros(cursor) if cov is None else -cov @ grad


def ros_covariance(cov: np.ndarray, params: RigParameters, device_clock: list,
                   time_columns: list) -> np.ndarray:
    """
    ``cov`` in the ROS layout: every device's (T0, T1), then every device's τ (13K × 13K).

    UNKNOWN on the diagonal (and zero off it) where a component is not estimated: T1's
    orientation without a full pose, τ where it was given.
    """
    layout = params.layout
    K, n = len(params.devices), cov.shape[0]
    M = np.zeros((13 * K, n))
    known = np.ones(13 * K, dtype=bool)
    for k, (p, cols) in enumerate(zip(params.devices, layout.columns, strict=True)):
        T, known_k = tangent_map(p)
        M[12 * k:12 * k + 12, cols] = T
        known[12 * k:12 * k + 12] = known_k
        tc = time_columns[device_clock[k]]
        if len(tc):
            M[12 * K + k, tc[0]] = 1.0
        else:
            known[12 * K + k] = False
    C = M @ cov @ M.T
    C = 0.5 * (C + C.T)
    C[~known, :] = 0.0
    C[:, ~known] = 0.0
    C[~known, ~known] = UNKNOWN
    return C

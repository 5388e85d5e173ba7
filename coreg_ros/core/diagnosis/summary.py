"""
Numbers a person reads: the gap on held-out data, the calibration's transforms.

All gaps are measured on held-out blocks (each block predicted by the fit on the others); each
effect's size with its uncertainty is its class's ``size`` (``effects/``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

from coreg_ros.core import quaternion as quat
from coreg_ros.core.diagnosis import variance as vm
from coreg_ros.core.diagnosis.record import optional, Record
import numpy as np


@dataclass(frozen=True, kw_only=True)
class HeldOutGap(Record):
    """
    The gap of a fitted model on held-out blocks, under its own noise model (inliers).

    Attributes
    ----------
    chi2_per_dof : float
        Under the fitted noise model.
    chi2_per_dof_stated_noise : float
        Under the stated noise.
    position_rms_m : float
        Per axis, m.
    noise_floor_position_m, stated_noise_floor_position_m : float
        The RMS the fitted (the stated) noise model expects, m.
    position_rms_to_floor : float
        The RMS over the fitted noise model's floor.
    log_likelihood_per_residual : float
    outlier_pairs : int
        Pairs more likely outliers than not.
    n_pairs : int
    rotation_rms_rad, noise_floor_rotation_rad, stated_noise_floor_rotation_rad : float, optional
        The same for rotation, rad (full pose).
    rotation_rms_to_floor : float, optional

    """

    chi2_per_dof: float
    chi2_per_dof_stated_noise: float
    position_rms_m: float
    noise_floor_position_m: float
    stated_noise_floor_position_m: float
    position_rms_to_floor: float
    log_likelihood_per_residual: float
    outlier_pairs: int
    n_pairs: int
    rotation_rms_rad: Optional[float] = optional()
    noise_floor_rotation_rad: Optional[float] = optional()
    stated_noise_floor_rotation_rad: Optional[float] = optional()
    rotation_rms_to_floor: Optional[float] = optional()


def gap_measures(data, fit, heldout) -> HeldOutGap:
    """Measure the gap of a fitted model on held-out blocks (``heldout.Heldout``)."""
    m = data.m
    inl = heldout.p_in > 0.5
    if not inl.any():
        inl = np.ones_like(inl)
    model = fit.model
    idx = np.arange(data.n)
    sd = np.concatenate([model._decorrelation(ch, None)[2] if _cached(model, ch)
                         else model.evaluate(fit.state, ch, jac=False).sd
                         for ch in model.chunks(idx)])
    var = fit.state.var
    st = fit.stats if len(fit.stats.z) == data.n else None
    if st is not None:
        _, _, D, _ = vm.components(var, st)
        ez = D + var.beta * st.u ** 2
        ratio = float(np.mean(np.sum(ez / (1.0 + st.lam), axis=1)) / m)
    else:
        ratio = float(np.exp(var.log_s2 + var.log_c))
    k = data.spec.n_markers
    pos_rows = list(range(3 * k)) if not data.spec.has_q1 else [0, 1, 2]
    e = heldout.e[inl]
    pos_rms = float(np.sqrt(np.mean(e[:, pos_rows] ** 2)))
    floor_pos_stated = float(np.sqrt(np.mean(sd[:, pos_rows] ** 2)))
    rotation = {}
    if data.spec.has_q1:
        rot_rms = float(2.0 * np.sqrt(np.mean(e[:, 3:6] ** 2)))
        floor_rot = float(2.0 * np.sqrt(np.mean(sd[:, 3:6] ** 2)))
        rotation = {'rotation_rms_rad': rot_rms,
                    'noise_floor_rotation_rad': floor_rot * np.sqrt(ratio),
                    'stated_noise_floor_rotation_rad': floor_rot,
                    'rotation_rms_to_floor': rot_rms / (floor_rot * np.sqrt(ratio))}
    return HeldOutGap(
        chi2_per_dof=float(np.mean(heldout.quad[inl]) / m),
        chi2_per_dof_stated_noise=float(np.mean(heldout.quad_stated[inl]) / m),
        position_rms_m=pos_rms,
        noise_floor_position_m=floor_pos_stated * np.sqrt(ratio),
        stated_noise_floor_position_m=floor_pos_stated,
        position_rms_to_floor=pos_rms / (floor_pos_stated * np.sqrt(ratio)),
        log_likelihood_per_residual=float(np.mean(heldout.ll) / m),
        outlier_pairs=int(np.sum(~inl)),
        n_pairs=int(len(heldout.ll)),
        **rotation)


def _cached(model, ch) -> bool:
    key = (int(ch[0]), int(ch[-1]), len(ch))
    return key in model.data.cache.get('decorrelation', {})


@dataclass(frozen=True)
class FrameEstimate(Record):
    """
    A transform of a fit.

    Attributes
    ----------
    position, sigma_position : list of float
        Its translation and the standard deviations, m.
    quat_wxyz : list of float
        Its rotation (w, x, y, z).

    """

    position: list
    sigma_position: list
    quat_wxyz: list


@dataclass(frozen=True, kw_only=True)
class Transforms(Record):
    """
    The calibration of a fit: T0, T1 and, with several markers, every marker's position.

    Attributes
    ----------
    base_to_base, tool_to_marker : FrameEstimate
        T0 (A's base in B's) and T1 (the first marker on A's tool).
    markers : list of list of float, optional
        The markers' positions on the tool, m (more than one marker).

    """

    base_to_base: FrameEstimate
    tool_to_marker: FrameEstimate
    markers: Optional[list] = optional()


def transforms(fit) -> Transforms:
    """
    T0 and T1 of a fit: positions (m) with standard deviations, quaternions (w, x, y, z).

    The standard deviations are of the fit with its effects modelled (φ's posterior, inflated
    by any chi-square per dof left above one).
    """
    p = fit.state.params
    cov = fit.mean_cov()
    sd0 = sd1 = [float('nan')] * 3
    if cov is not None:
        infl = vm.inflation(fit.state.var, fit.stats)
        sd0 = np.sqrt(np.clip(np.diag(cov)[0:3], 0, None) * infl).tolist()
        sd1 = np.sqrt(np.clip(np.diag(cov)[6:9], 0, None) * infl).tolist()
    return Transforms(
        base_to_base=FrameEstimate(p.p0.tolist(), sd0, quat.canonical(p.q0).tolist()),
        tool_to_marker=FrameEstimate(p.markers[0].tolist(), sd1,
                                     quat.canonical(p.q1).tolist()),
        markers=p.markers.tolist() if p.spec.n_markers > 1 else None)

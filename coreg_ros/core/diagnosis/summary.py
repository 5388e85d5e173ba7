"""
Numbers a person reads: the gap on held-out data, the calibration's transforms.

All gaps are measured on held-out blocks (each block predicted by the fit on the others); each
effect's size with its uncertainty is its class's ``size`` (``effects/``).
"""

from __future__ import annotations

from coreg_ros.core import quaternion as quat
from coreg_ros.core.diagnosis import variance as vm
import numpy as np


def gap_measures(data, fit, heldout) -> dict:
    """
    Measure the gap of a fitted model on held-out blocks.

    Returns
    -------
    dict
        ``chi2_per_dof`` (under the fitted noise model, inliers), ``chi2_per_dof_stated_noise``,
        ``position_rms_m`` (per axis, inliers), ``rotation_rms_rad`` (full pose),
        ``noise_floor_position_m`` / ``noise_floor_rotation_rad`` (RMS expected from the noise
        model), their ratios, ``log_likelihood_per_residual``, ``outlier_pairs``.

    """
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
    out = {
        'chi2_per_dof': float(np.mean(heldout.quad[inl]) / m),
        'chi2_per_dof_stated_noise': float(np.mean(heldout.quad_stated[inl]) / m),
        'position_rms_m': pos_rms,
        'noise_floor_position_m': floor_pos_stated * np.sqrt(ratio),
        'stated_noise_floor_position_m': floor_pos_stated,
        'position_rms_to_floor': pos_rms / (floor_pos_stated * np.sqrt(ratio)),
        'log_likelihood_per_residual': float(np.mean(heldout.ll) / m),
        'outlier_pairs': int(np.sum(~inl)),
        'n_pairs': int(len(heldout.ll)),
    }
    if data.spec.has_q1:
        rot_rms = float(2.0 * np.sqrt(np.mean(e[:, 3:6] ** 2)))
        floor_rot = float(2.0 * np.sqrt(np.mean(sd[:, 3:6] ** 2)))
        out.update({'rotation_rms_rad': rot_rms,
                    'noise_floor_rotation_rad': floor_rot * np.sqrt(ratio),
                    'stated_noise_floor_rotation_rad': floor_rot,
                    'rotation_rms_to_floor': rot_rms / (floor_rot * np.sqrt(ratio))})
    return out


def _cached(model, ch) -> bool:
    key = (int(ch[0]), int(ch[-1]), len(ch))
    return key in model.data.cache.get('decorrelation', {})


def transforms(fit) -> dict:
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
    out = {'base_to_base': {'position': p.p0.tolist(), 'sigma_position': sd0,
                            'quat_wxyz': quat.canonical(p.q0).tolist()},
           'tool_to_marker': {'position': p.markers[0].tolist(), 'sigma_position': sd1,
                              'quat_wxyz': quat.canonical(p.q1).tolist()}}
    if p.spec.n_markers > 1:
        out['markers'] = p.markers.tolist()
    return out
